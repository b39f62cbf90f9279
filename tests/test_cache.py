"""Irradiance-cache placement and interpolation against plain reference implementations."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import cache
from pmic_integrator.cache import CacheRecords, RecordIndex


def _covers_np(x, n, rp, rn, rr, a):
    """Ward's coverage test as in cache.covers, in numpy."""
    err = np.linalg.norm(x - rp, axis=-1) / rr + np.sqrt(np.maximum(0.0, 1.0 - (n * rn).sum(-1)))
    in_front = ((x - rp) * 0.5 * (n + rn)).sum(-1) < -cache.IN_FRONT_TOLERANCE * rr
    return (err < a) & ((n * rn).sum(-1) > 0) & ~in_front


def sequential_placement(p, n, r, a):
    """The paper's Fig. 2 as written: walk the candidates; a candidate that no record
    covers becomes a record. Candidates are walked in the same order as the parallel
    version (cache.placement_priority)."""
    order = np.argsort(np.array(cache.placement_priority(dr.arange(mi.UInt32, len(p)))), kind="stable")
    records = []
    for i in order:
        if records:
            idx = np.array(records)
            if _covers_np(p[i], n[i], p[idx], n[idx], r[idx], a).any():
                continue
        records.append(i)
    return np.sort(np.array(records))


def _candidates(count, seed):
    """Photon-like candidates on the six faces of a unit box, radii varying 10×."""
    rng = np.random.default_rng(seed)
    face = rng.integers(0, 6, count)
    uv = rng.random((count, 2))
    p = np.zeros((count, 3))
    n = np.zeros((count, 3))
    axis = face // 2
    side = face % 2
    for k in range(3):
        sel = axis == k
        others = [j for j in range(3) if j != k]
        p[sel, k] = side[sel]
        p[sel, others[0]] = uv[sel, 0]
        p[sel, others[1]] = uv[sel, 1]
        n[sel, k] = np.where(side[sel] == 1, -1.0, 1.0)
    r = 0.03 + 0.27 * rng.random(count) ** 2
    return p.astype(np.float32), n.astype(np.float32), r.astype(np.float32)


@pytest.mark.parametrize("max_error,seed", [(0.5, 0), (1.0, 1), (0.25, 2)])
def test_parallel_placement_matches_sequential_and_covers_everything(max_error, seed):
    p, n, r = _candidates(1500, seed)
    selected, rounds = cache.place_records(mi.Point3f(p.T), mi.Vector3f(n.T), mi.Float(r), max_error)
    selected = np.array(selected)
    reference = sequential_placement(p.astype(np.float64), n.astype(np.float64), r.astype(np.float64),
                                     max_error)
    # The bound is 25 %; the rounds reproduce the walk exactly, up to float32
    # rounding in borderline coverage tests.
    assert abs(len(selected) - len(reference)) <= 0.25 * len(reference)
    assert len(set(selected) ^ set(reference)) <= max(2, 0.02 * len(reference))
    assert rounds < 40
    # Every candidate is covered by at least one selected record.
    covered = np.zeros(len(p), bool)
    for i in selected:
        covered |= _covers_np(p, n, p[i], n[i], r[i], max_error)
    assert covered.all()


def test_existing_records_are_respected():
    p, n, r = _candidates(800, 3)
    pts, nrm, rad = mi.Point3f(p.T), mi.Vector3f(n.T), mi.Float(r)
    first, _ = cache.place_records(pts, nrm, rad, 0.5)
    z = mi.Vector3f(dr.zeros(mi.Vector3f, dr.width(first)))
    records = CacheRecords(dr.gather(mi.Point3f, pts, first), dr.gather(mi.Vector3f, nrm, first),
                           dr.gather(mi.Float, rad, first), dr.zeros(mi.Color3f, dr.width(first)),
                           (z, z, z), (z, z, z))
    again, _ = cache.place_records(pts, nrm, rad, 0.5, RecordIndex.build(records, 0.5))
    assert dr.width(again) == 0


def _random_records(count, seed):
    rng = np.random.default_rng(seed)
    p = rng.random((count, 3)).astype(np.float32)
    p[:, 2] *= 0.05  # records near the plane z = 0
    nrm = np.tile([0.0, 0.0, 1.0], (count, 1)) + rng.normal(0, 0.15, (count, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    r = (0.03 + 0.1 * rng.random(count)).astype(np.float32)
    e = rng.random((count, 3)).astype(np.float32) + 0.5
    gt = [rng.normal(0, 0.5, (count, 3)).astype(np.float32) for _ in range(3)]
    gr = [rng.normal(0, 0.2, (count, 3)).astype(np.float32) for _ in range(3)]
    return p, nrm.astype(np.float32), r, e, gt, gr


def test_interpolation_matches_brute_force_ward_formula():
    a = 0.6
    p, nrm, r, e, gt, gr = _random_records(120, 7)
    records = CacheRecords(mi.Point3f(p.T), mi.Vector3f(nrm.T), mi.Float(r), mi.Color3f(e.T),
                           tuple(mi.Vector3f(g.T) for g in gt), tuple(mi.Vector3f(g.T) for g in gr))
    index = RecordIndex.build(records, a)
    rng = np.random.default_rng(8)
    x = rng.random((500, 3)).astype(np.float32)
    x[:, 2] *= 0.05
    qn = np.tile([0.0, 0.0, 1.0], (500, 1)) + rng.normal(0, 0.1, (500, 3))
    qn = (qn / np.linalg.norm(qn, axis=1, keepdims=True)).astype(np.float32)
    got, covered = index.interpolate(mi.Point3f(x.T), mi.Vector3f(qn.T))
    got = np.array(got).T
    covered = np.array(covered)

    want = np.zeros((500, 3))
    want_cov = np.zeros(500, bool)
    backup_used = 0
    for q in range(500):
        err = np.linalg.norm(x[q] - p, axis=1) / r + np.sqrt(np.maximum(0, 1 - nrm @ qn[q]))
        inv = 1.0 / np.maximum(err, cache.MIN_ERROR)
        # Ward's weight shifted to zero at the reach; where no record reaches the
        # point, the same with the backup reach.
        for reach in (a, a * cache.BACKUP_REACH):
            w = np.maximum(inv - 1.0 / reach, 0.0) * _covers_np(x[q], qn[q], p, nrm, r, reach)
            if w.sum() > 0:
                break
        if w.sum() <= 0:
            continue
        backup_used += reach != a
        want_cov[q] = True
        rot = np.cross(nrm, qn[q])
        ext = np.stack([e[:, c] + ((x[q] - p) * gt[c]).sum(1) + (rot * gr[c]).sum(1) for c in range(3)], 1)
        ext = np.maximum(ext, 0.0)
        want[q] = (w[:, None] * ext).sum(0) / w.sum()
    assert backup_used > 5  # the backup path is exercised
    np.testing.assert_array_equal(covered, want_cov)
    assert 0.5 < want_cov.mean() < 1.0
    np.testing.assert_allclose(got[want_cov], want[want_cov], rtol=2e-4, atol=2e-5)
    assert (got[~want_cov] == 0).all()


def test_coverage_index_answers_as_the_lookup_index():
    """The cheap index used while building (default cells, no backup grid) must give
    exactly the lookup index's coverage; it cannot interpolate."""
    a = 0.6
    p, nrm, r, e, gt, gr = _random_records(300, 3)
    records = CacheRecords(mi.Point3f(p.T), mi.Vector3f(nrm.T), mi.Float(r), mi.Color3f(e.T),
                           tuple(mi.Vector3f(g.T) for g in gt), tuple(mi.Vector3f(g.T) for g in gr))
    lookup, coverage = RecordIndex.build(records, a), RecordIndex.build(records, a, lookup=False)
    assert coverage.backup_grid is None and coverage.grid.entries < lookup.grid.entries / 4
    rng = np.random.default_rng(4)
    x = rng.random((4000, 3)).astype(np.float32)
    x[:, 2] *= 0.05
    qn = mi.Vector3f(np.tile([0.0, 0.0, 1.0], (4000, 1)).T.astype(np.float32))
    want = np.array(lookup.covered(mi.Point3f(x.T), qn))
    assert 0.3 < want.mean() < 1.0
    np.testing.assert_array_equal(np.array(coverage.covered(mi.Point3f(x.T), qn)), want)
    with pytest.raises(RuntimeError, match="for_lookup"):
        coverage.interpolate(mi.Point3f(x.T), qn)
    again = coverage.for_lookup()
    np.testing.assert_array_equal(np.array(again.interpolate(mi.Point3f(x.T), qn)[0]),
                                  np.array(lookup.interpolate(mi.Point3f(x.T), qn)[0]))


def test_weight_falls_continuously_to_zero_at_the_reach():
    a = 0.5
    err = mi.Float(np.linspace(0.45, 0.55, 101).astype(np.float32))
    w = np.array(cache.interpolation_weight(err, a))
    assert (w[err.numpy() >= a] == 0).all()
    assert w[49] < 0.05  # just inside the reach: nearly zero, no brightness step
    assert (np.diff(w) <= 0).all()
