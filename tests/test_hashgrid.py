"""Hash grids against brute force: exact agreement on random and adversarial inputs."""
import drjit as dr
import mitsuba as mi
import math

import numpy as np
import pytest

from pmic_integrator.hashgrid import BallGrid, PointGrid


def _neighbors_by_grid(points, queries, radius, cell_size=None, octant=False, packed=False):
    """Sorted neighbour index lists (and squared distances) found through a PointGrid
    (``packed``: its entries read as packets, PointGrid.pack)."""
    grid = PointGrid.build(mi.Point3f(points.T), cell_size or (2 * radius if octant else radius))
    if packed:
        grid.pack()
    lanes = len(queries)
    # Record up to 64 neighbours per query as a bit-exact checksum: count, sum of
    # indices and sum of squared indices identify the set for these small inputs.
    def visit(state, index, dist2, valid):
        count, s1, s2 = state
        i = mi.UInt32(index)
        return (count + dr.select(valid, 1, 0), s1 + dr.select(valid, i, 0),
                s2 + dr.select(valid, i * i, 0))

    init = (dr.zeros(mi.UInt32, lanes), dr.zeros(mi.UInt32, lanes), dr.zeros(mi.UInt32, lanes))
    count, s1, s2 = grid.for_each_neighbor(mi.Point3f(queries.T), radius, init, visit, octant=octant)
    return np.array(count), np.array(s1), np.array(s2)


def _neighbors_brute(points, queries, radius):
    with np.errstate(over="ignore"):
        d = queries[:, None, :].astype(np.float32) - points[None, :, :].astype(np.float32)
        # Same float32 arithmetic and order as the kernel: fma(x, x, fma(y, y, z*z)).
        dist2 = (d[..., 0] * d[..., 0] + (d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]))
    inside = dist2 < np.float32(radius) ** 2
    idx = np.arange(len(points), dtype=np.uint64)
    return (inside.sum(1), (inside * idx).sum(1) % 2**32, (inside * idx * idx).sum(1) % 2**32)


def _check_exact(points, queries, radius, cell_size=None, octant=False, packed=False):
    got = _neighbors_by_grid(points, queries, radius, cell_size, octant, packed)
    want = _neighbors_brute(points, queries, radius)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w.astype(np.uint32))
    return got[0]


@pytest.mark.parametrize("packed", [False, True])
def test_random_points_match_brute_force(packed):
    rng = np.random.default_rng(1)
    points = rng.random((3000, 3), dtype=np.float32)
    queries = rng.random((700, 3), dtype=np.float32)
    counts = _check_exact(points, queries, 0.08, packed=packed)
    assert counts.mean() > 3  # the test exercises real neighbourhoods


@pytest.mark.parametrize("packed", [False, True])
@pytest.mark.parametrize("seed", [11, 12])
def test_octant_queries_match_brute_force(seed, packed):
    rng = np.random.default_rng(seed)
    points = rng.random((3000, 3), dtype=np.float32)
    queries = np.concatenate([rng.random((700, 3), dtype=np.float32), points[:100]], 0)
    counts = _check_exact(points, queries, 0.06, octant=True, packed=packed)
    assert counts.mean() > 1


def test_points_on_cell_boundaries_and_exact_radius():
    # Integer lattice with cell size 1: every point sits on a cell corner, and many
    # lie exactly at distance 1 = radius (excluded: the query is strict, d < r).
    g = np.arange(-3, 4, dtype=np.float32)
    points = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    queries = np.concatenate([points[::7], points[::11] + 0.5], 0)
    counts = _check_exact(points, queries, 1.0)
    assert counts.min() >= 1
    # A lattice point's only neighbour strictly within 1 is itself.
    assert (counts[: len(points[::7])] == 1).all()


def test_many_points_in_one_cell():
    rng = np.random.default_rng(2)
    points = (rng.random((2000, 3), dtype=np.float32) * 1e-3).astype(np.float32)
    queries = rng.random((50, 3), dtype=np.float32) * 1e-3
    counts = _check_exact(points, queries, 0.5)
    assert (counts == 2000).all()


def test_hash_collisions():
    # 40 points spread over a 100^3-cell grid: the table has only 64 buckets, so
    # many distinct cells share a bucket and must not be double counted.
    rng = np.random.default_rng(3)
    points = rng.integers(0, 100, (40, 3)).astype(np.float32)
    points = np.concatenate([points, points + 0.25, points - 0.3], 0)
    queries = np.concatenate([points, rng.random((300, 3), dtype=np.float32) * 100], 0)
    _check_exact(points, queries, 1.0)


def test_queries_far_outside_and_empty_grid():
    points = np.zeros((5, 3), np.float32)
    queries = np.array([[1e30, 0, 0], [-1e30, 1e30, 0], [0, 0, 0]], np.float32)
    counts = _check_exact(points, queries, 0.1)
    assert list(counts) == [0, 0, 5]
    empty = PointGrid.build(mi.Point3f(), 1.0)
    out = empty.for_each_neighbor(mi.Point3f(queries.T), 1.0, dr.zeros(mi.UInt32, 3),
                                  lambda s, i, d, v: s + dr.select(v, 1, 0))
    assert list(np.array(out)) == [0, 0, 0]


def test_bad_cell_size_is_rejected():
    with pytest.raises(ValueError, match="cell_size"):
        PointGrid.build(mi.Point3f([0.0], [0.0], [0.0]), 0.0)


@pytest.mark.parametrize("packed", [False, True])
@pytest.mark.parametrize("seed", [4, 5])
def test_ball_grid_matches_brute_force(seed, packed):
    rng = np.random.default_rng(seed)
    centers = rng.random((400, 3), dtype=np.float32)
    radii = (rng.random(400, dtype=np.float32) ** 3 * 0.3 + 1e-3).astype(np.float32)
    queries = np.concatenate([rng.random((600, 3), dtype=np.float32), centers[:50]], 0)
    grid = BallGrid.build(mi.Point3f(centers.T), mi.Float(radii))
    if packed:  # (entries read as packets, as the records' lookup grids are at render)
        assert grid.pack().packed is not None
    c, r, q = mi.Point3f(centers.T), mi.Float(radii), mi.Point3f(queries.T)

    def visit(state, index, valid):
        count, s1 = state
        cc = dr.gather(mi.Point3f, c, index, valid)
        rr = dr.gather(mi.Float, r, index, valid)
        inside = valid & (dr.squared_norm(cc - q) < rr * rr)
        return count + dr.select(inside, 1, 0), s1 + dr.select(inside, index, 0)

    count, s1 = grid.for_each_ball(q, (dr.zeros(mi.UInt32, len(queries)), dr.zeros(mi.UInt32, len(queries))), visit)
    d2 = ((queries[:, None] - centers[None]) ** 2).sum(-1)
    inside = d2 < radii[None] ** 2
    np.testing.assert_array_equal(np.array(count), inside.sum(1))
    np.testing.assert_array_equal(np.array(s1), (inside * np.arange(400)).sum(1))
    assert inside.sum() > 100


@pytest.mark.parametrize("one_loop", [True, False])
def test_pyramid_finds_exactly_the_points_within_each_querys_own_radius(one_loop):
    """A dense cluster inside sparse points: queries in the cluster use finer levels
    (smaller radii); every query must find exactly the points within its radius, in
    one loop over the 27 cells or in a loop per cell (density estimates), which skips
    the cells a query's ball cannot reach (hashgrid._reaches_neighbour)."""
    from pmic_integrator.hashgrid import PointGridPyramid

    rng = np.random.default_rng(3)
    sparse = rng.uniform(-1, 1, (3000, 3)).astype(np.float32)
    cluster = (rng.normal(0, 0.02, (6000, 3)) + 0.3).astype(np.float32)
    points = np.concatenate([sparse, cluster])
    queries = np.concatenate([rng.uniform(-1, 1, (200, 3)), rng.normal(0, 0.02, (200, 3)) + 0.3]).astype(np.float32)
    pyramid, order = PointGridPyramid.build(mi.Point3f(points.T), 0.2, per_estimate=16)
    level, radius = pyramid.level_of(mi.Point3f(queries.T))
    level_np, radius_np = np.array(level), np.array(radius)
    # The cluster goes finer; sparse queries with no cluster cell in their scan do not.
    far = np.linalg.norm(queries[:200] - 0.3, axis=1) > 0.2 * 3 * math.sqrt(3)
    assert far.sum() > 100
    assert level_np[:200][far].max() <= 1 and level_np[200:].min() >= 2
    sorted_points = points[np.array(order)]

    def visit(state, index, dist2, valid):
        count, s1 = state
        return count + dr.select(valid, 1, 0), s1 + dr.select(valid, mi.UInt32(index), 0)

    lanes = len(queries)
    count, s1 = pyramid.for_each_neighbor(mi.Point3f(queries.T), level,
                                          (dr.zeros(mi.UInt32, lanes), dr.zeros(mi.UInt32, lanes)), visit,
                                          one_loop=one_loop)
    d = queries[:, None, :] - sorted_points[None, :, :]
    dist2 = d[..., 0] * d[..., 0] + (d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2])
    inside = dist2 < radius_np[:, None] ** 2
    # Points right on a radius can differ by float rounding: compare away from it.
    near_edge = np.abs(dist2 - radius_np[:, None] ** 2) < 1e-5 * radius_np[:, None] ** 2
    ok = ~near_edge.any(1)
    assert ok.mean() > 0.95
    idx = np.arange(len(points), dtype=np.uint64)
    np.testing.assert_array_equal(np.array(count)[ok], inside.sum(1)[ok])
    np.testing.assert_array_equal(np.array(s1)[ok], ((inside * idx).sum(1) % 2**32)[ok])


def test_pyramid_queries_beside_a_cluster_do_not_scan_it_at_the_coarse_level():
    """A query in a sparse cell whose disc reaches a dense cluster in the next cell
    must go finer too. Choosing by its own cell's count, it scanned the whole cluster
    and its kernel smeared the cluster over the disc (a caustic's focus came out 5 %
    too bright around it, and such lanes held up their SIMD packets)."""
    from pmic_integrator.hashgrid import PointGridPyramid

    rng = np.random.default_rng(4)
    sparse = rng.uniform(-1, 1, (3000, 3)).astype(np.float32)
    cluster = (rng.normal(0, 0.01, (6000, 3)) + 0.3).astype(np.float32)
    pyramid, _ = PointGridPyramid.build(mi.Point3f(np.concatenate([sparse, cluster]).T), 0.2,
                                        per_estimate=16)
    direction = rng.normal(size=(300, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    beside = (0.3 + direction * rng.uniform(0.08, 0.14, (300, 1))).astype(np.float32)
    level, radius = pyramid.level_of(mi.Point3f(beside.T))
    # Every such query's level-0 disc (0.2) holds most of the cluster...
    assert np.all(np.linalg.norm(beside - 0.3, axis=1) < 0.2 - 0.05)  # cluster σ 0.01
    # ...so each goes to a level whose disc excludes it: the densest level.
    assert np.array(level).min() >= 2
    assert np.array(radius).max() <= 0.05 + 1e-6


@pytest.mark.parametrize("octant", [False, True])
def test_one_loop_and_a_loop_per_cell_visit_in_the_same_order(octant):
    """The two ways of walking the cells must give bit-identical float sums (the order
    of visits decides them) and the same early stops."""
    rng = np.random.default_rng(5)
    points = rng.random((3000, 3)).astype(np.float32)
    queries = mi.Point3f(rng.random((500, 3)).astype(np.float32).T)
    weights = mi.Float(rng.random(3000).astype(np.float32))
    grid = PointGrid.build(mi.Point3f(points.T), 0.2 if octant else 0.1)

    def visit(state, index, dist2, valid):
        total, seen = state
        w = dr.gather(mi.Float, weights, index, valid)
        # Order-sensitive: a running sum of products, rounded at every step.
        return dr.select(valid, total * 0.75 + w * dist2, total), seen + dr.select(valid, 1, 0)

    def stop(state):
        return state[1] >= 5

    out = {}
    for one_loop in (True, False):
        for finished in (None, stop):
            init = (dr.zeros(mi.Float, 500), dr.zeros(mi.UInt32, 500))
            total, seen = grid.for_each_neighbor(queries, 0.1, init, visit, finished=finished,
                                                 octant=octant, one_loop=one_loop)
            out[one_loop, finished is None] = (np.array(total), np.array(seen))
    for full in (True, False):
        np.testing.assert_array_equal(out[True, full][0], out[False, full][0])
        np.testing.assert_array_equal(out[True, full][1], out[False, full][1])
    assert out[True, True][1].max() > 5 and out[True, False][1].max() == 5


def _photons_on_a_box(count=20000, seed=3):
    """Photons on the six faces of a unit box (inward normals), with powers, depths 1-3,
    specular and delta flags: everything a density estimate filters on."""
    from pmic_integrator.photons import PhotonMap
    rng = np.random.default_rng(seed)
    face = rng.integers(0, 6, count)
    axis, side = face // 2, face % 2
    p = rng.random((count, 3)).astype(np.float32)
    p[np.arange(count), axis] = side
    n = np.zeros((count, 3), np.float32)
    n[np.arange(count), axis] = np.where(side == 1, -1.0, 1.0)
    power = (rng.random((count, 3)) * 1e-3).astype(np.float32)
    depth = rng.integers(1, 4, count).astype(np.uint32)
    return PhotonMap(mi.Point3f(p.T), mi.Vector3f(n.T), mi.Color3f(power.T), mi.UInt32(depth),
                     mi.Bool(rng.random(count) < 0.3), mi.UInt32(np.arange(count, dtype=np.uint32)),
                     count, delta_light=mi.Bool(rng.random(count) < 0.5))


def test_packed_photons_and_entries_give_the_same_estimates_and_nearest_photons():
    """Density estimates and nearest-photon searches read the photons and grid entries
    packed (PhotonMap.pack, PackedEntries: packet loads) or field by field: the very
    same numbers, with every filter of the estimate in play."""
    import dataclasses
    from pmic_integrator.gather import GatherSource
    from pmic_integrator.irradiance import estimate_irradiance, nearest_photon, sort_into_grid
    photons, grid = sort_into_grid(_photons_on_a_box(), 0.08, 32)
    assert photons.packed is not None and grid.packed is not None
    plain_photons = dataclasses.replace(photons, packed=None)
    plain_grid = dataclasses.replace(grid, packed=None)
    rng = np.random.default_rng(9)
    q = rng.random((3000, 3)).astype(np.float32)
    q[:, 1] = 0.0  # on the floor (normal +y)
    qp, qn = mi.Point3f(q.T), mi.Vector3f(0.0, 1.0, 0.0)
    for kwargs in ({}, {"min_depth": 2, "skip_specular_paths": True},
                   {"without_delta_direct": True, "max_depth": 2},
                   {"delta_scale": 0.5, "nodelta_too": True}):
        packed = estimate_irradiance(photons, grid, qp, qn, **kwargs)
        plain = estimate_irradiance(plain_photons, plain_grid, qp, qn, **kwargs)
        for a, b in zip(packed if isinstance(packed, tuple) else (packed,),
                        plain if isinstance(plain, tuple) else (plain,)):
            assert float(dr.mean(mi.luminance(a))[0]) > 0
            np.testing.assert_array_equal(np.array(a), np.array(b))
    photons.irradiance = dr.zeros(mi.Color3f, photons.count)
    source = GatherSource.build(photons, 0.05)
    assert source.near_grid.packed is not None and source.near_grid.packed.has_normals
    for steps in ((source.near_photons, source.near_grid, 0.025, True),
                  (source.mid_photons, source.mid_grid, 0.1, False)):
        photons_s, grid_s, reach, octant = steps
        packed = nearest_photon(photons_s, grid_s, qp, qn, reach, octant=octant)
        plain = nearest_photon(photons_s, dataclasses.replace(grid_s, packed=None), qp, qn, reach,
                               octant=octant)
        assert np.array(packed[1]).mean() > 0.5
        np.testing.assert_array_equal(np.array(packed[0]), np.array(plain[0]))
        np.testing.assert_array_equal(np.array(packed[1]), np.array(plain[1]))


def test_a_photon_on_a_curved_surface_is_seen_from_beside_it():
    """Gather lookups on a sphere read their nearest photon on it: every query finds
    one and none is hidden. The chord between two points of a convex surface runs
    under it; with both ends lifted by a fixed height only, the sphere hid the photon
    from 54 % of the queries, which read 0 (the white room's mouldings and sofas, and
    Sponza's columns, came out dark: 26 % / 8 % of their records' lookups hidden)."""
    from pmic_integrator.gather import GatherSource
    from pmic_integrator.photons import PhotonMap

    def on_sphere(count, seed):
        d = np.random.default_rng(seed).normal(size=(count, 3))
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "radius": 1.0}})
    spots = on_sphere(300, 0)  # ~0.2 apart: each query's nearest photon 0.05-0.15 off
    photons = PhotonMap(mi.Point3f(spots.T), mi.Vector3f(spots.T), dr.full(mi.Color3f, 1e-3, 300),
                        dr.full(mi.UInt32, 2, 300), dr.zeros(mi.Bool, 300),
                        mi.UInt32(np.arange(300, dtype=np.uint32)), 300)
    photons.irradiance = dr.full(mi.Color3f, 1.0, 300)
    source = GatherSource.build(photons, 0.05)
    queries = on_sphere(4000, 1)
    read = np.array(source.irradiance_of(scene, mi.Point3f(queries.T), mi.Vector3f(queries.T)))
    assert (read[0] == 1.0).mean() == 1.0, f"{(read[0] == 0).mean():.1%} of the queries read 0"


def test_a_photon_far_off_the_plane_stays_hidden_behind_what_lies_between():
    """The extra lift is capped: a floor lookup under a table whose nearest accepted
    photon lies on the table top (a wide search step's plane test lets such photons
    through where photons are sparse) must see the table between them. Lifted by the
    photon's whole height, both ends passed over the table: the lamp room at 30k
    photons read the inside of its shade through the shade's base, 1.17 of path."""
    from pmic_integrator.gather import GatherSource
    from pmic_integrator.photons import PhotonMap

    scene = mi.load_dict({"type": "scene",
                          "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(2.0)},
                          "table": {"type": "rectangle", "to_world":
                                    mi.ScalarTransform4f().translate([0, 0, 0.7]).scale(0.25)}})
    top = mi.Point3f(0.15, 0.0, 0.7)
    photons = PhotonMap(top, mi.Vector3f(0, 0, 1), mi.Color3f(1e-3), mi.UInt32(2), mi.Bool(False),
                        mi.UInt32(0), 1)
    photons.irradiance = mi.Color3f(1.0)
    source = GatherSource.build(photons, 0.05)
    up = mi.Vector3f(0, 0, 1)
    # One query on the floor under the table, one on the table top beside the photon.
    queries = mi.Point3f([0.1, 0.1], [0.0, 0.1], [0.0, 0.7])
    assert np.array(source._visible(scene, queries, up, top, mi.Bool(True))).tolist() == [False, True]
