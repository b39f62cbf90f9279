"""Stages 1-3 on their own (pipeline.prepare, no camera), the surface probes, the
nearest-photon search steps of gather rays, and the named random streams."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import cache, gather, photons, pipeline, streams
from pmic_integrator.settings import Settings

from pmic_integrator.kinds import SMALL_PMIC, cornell, courtyard
from jit_history import new_kernels


def settings(**params):
    props = mi.Properties()
    for key, value in {**SMALL_PMIC, **params}.items():
        props[key] = value
    return Settings.parse(props)


def test_prepare_needs_no_camera_and_covers_every_photon():
    scene_dict = cornell(16)
    scene_dict.pop("sensor")
    scene = mi.load_dict(scene_dict)
    prepared = pipeline.prepare(scene, settings(estimator="first_hit"))
    assert 0 <= prepared.global_map.count - SMALL_PMIC["global_photons"] < 64  # whole paths
    assert prepared.index is not None and prepared.stats["records"] == prepared.index.records.count
    assert 0 < prepared.stats["records_probes"] < prepared.stats["records"]
    covered = prepared.index.covered(prepared.global_map.position, prepared.global_map.normal)
    assert bool(dr.all(covered))
    # Same scene, settings and seed: the same cache, bit for bit (final gather; two
    # first_hit builds are not always identical yet, see the README's limits).
    once = pipeline.prepare(scene, settings())
    again = pipeline.prepare(scene, settings())
    np.testing.assert_array_equal(np.array(again.index.records.irradiance),
                                  np.array(once.index.records.irradiance))


def test_failed_stage_publishes_nothing(monkeypatch):
    scene = mi.load_dict(cornell(16))
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        raise RuntimeError("simulated failure in stage 3")

    monkeypatch.setattr(pipeline.CacheBuilder, "build_records", failing)
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    with pytest.raises(RuntimeError, match="simulated"):
        integrator.build_cache(scene)
    assert calls and integrator.prepared is None


def _probe_scene(twosided: bool, reverse: bool = False):
    bsdf = {"type": "diffuse"}
    shapes = {
        # A 2x2 square (area 4) facing +z, and a 1x1 one (area 1) at z = 1.
        "big": {"type": "rectangle", "bsdf": {"type": "twosided", "b": bsdf} if twosided else bsdf},
        # (Another BSDF, so that Mitsuba does not merge the two meshes into one.)
        "small": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.3},
                  "to_world": mi.ScalarTransform4f().translate([0, 0, 1]).scale(0.5)},
        "mirror": {"type": "sphere", "center": [5, 0, 0], "radius": 0.5,
                   "bsdf": {"type": "conductor"}},
    }
    order = reversed(shapes) if reverse else shapes
    return mi.load_dict({"type": "scene", **{k: shapes[k] for k in order}}, parallel=False)


@pytest.mark.parametrize("twosided", [False, True])
def test_surface_probes_follow_area_and_sides(twosided):
    p, n = pipeline.surface_probes(_probe_scene(twosided), 5000, seed=0)
    p, n = np.array(p).T, np.array(n).T
    big = np.abs(p[:, 2]) < 1e-5
    small = np.abs(p[:, 2] - 1) < 1e-5
    assert big.sum() + small.sum() == len(p), p[~big & ~small][:5]  # none on the sphere
    assert np.all(np.abs(p[big, :2]) <= 1) and np.all(np.abs(p[small, :2]) <= 0.5)
    # 4000 + 1000 points by area; the twosided square gets each point on both sides.
    assert small.sum() == 1000 and big.sum() == (8000 if twosided else 4000)
    assert np.all(n[small] == [0, 0, 1])
    assert (n[big, 2] < 0).sum() == (4000 if twosided else 0)
    # Deterministic in the seed, different across seeds.
    again = np.array(pipeline.surface_probes(_probe_scene(twosided), 5000, seed=0)[0]).T
    other = np.array(pipeline.surface_probes(_probe_scene(twosided), 5000, seed=1)[0]).T
    np.testing.assert_array_equal(again, p)
    assert not np.array_equal(other, p)


def test_surface_probes_ignore_shape_order():
    """Mitsuba's parallel loading lists a scene's shapes in a varying order (1 load in
    8 for the test Cornell box): the probes, and with them a first_hit cache, changed
    from build to build. They must depend on the shapes, not on their order."""
    a = pipeline.surface_probes(_probe_scene(False), 5000, seed=0)
    reordered = _probe_scene(False, reverse=True)
    assert [s.id() for s in reordered.shapes()] != [s.id() for s in _probe_scene(False).shapes()]
    b = pipeline.surface_probes(reordered, 5000, seed=0)
    np.testing.assert_array_equal(np.array(a[0]), np.array(b[0]))
    np.testing.assert_array_equal(np.array(a[1]), np.array(b[1]))


def test_gather_search_steps_lose_no_photon():
    """The first search step visits 2x2x2 cells only: it must find exactly what a
    search of all 27 cells within the same reach finds; and the two steps together
    find a photon wherever one search over the full reach does."""
    from pmic_integrator.irradiance import nearest_photon

    scene = mi.load_dict(cornell(16))
    prepared = pipeline.prepare(scene, settings(method="photon_map", final_gather=True))
    source = prepared.gather_source
    rng = np.random.default_rng(1)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(0.0, 0.3, 0.0), mi.Vector3f(d.T))
    si = scene.ray_intersect(ray)
    n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
    photons, grid, reach, octant = source._steps()[0]
    assert octant and reach == 0.5 * grid.cell_size
    fast = nearest_photon(photons, grid, si.p, n, reach, si.is_valid(), octant=True)
    full = nearest_photon(photons, grid, si.p, n, reach, si.is_valid(), octant=False)
    found = np.array(full[1])
    assert found.mean() > 0.8
    np.testing.assert_array_equal(np.array(fast[1]), found)
    np.testing.assert_array_equal(np.array(fast[0])[found], np.array(full[0])[found])
    stepped = np.array(source.irradiance_at(scene, si.p, n, si.is_valid()))
    wide = gather.GatherSource(source.photons, source.grid, source.radius)
    single = np.array(wide.irradiance_at(scene, si.p, n, si.is_valid()))
    np.testing.assert_array_equal(stepped.sum(0) > 0, single.sum(0) > 0)


def _rough_plastic(rgb):
    return {"type": "roughplastic", "alpha": 0.3, "diffuse_reflectance": {"type": "rgb", "value": rgb}}


@pytest.mark.parametrize("scene_dict", [
    # caustic map from the coats, glossy bounces, near hits reading caustic irradiance
    lambda: cornell(16, white=_rough_plastic([0.7, 0.7, 0.7]), red=_rough_plastic([0.6, 0.1, 0.1])),
    # delta bounces through glass
    lambda: cornell(16, glass={"type": "sphere", "center": [0.3, -0.6, 0.2], "radius": 0.35,
                               "bsdf": {"type": "dielectric"}}),
    # a sun: its direct light sampled at the hits, the photons' without it
    lambda: courtyard((16, 12)),
], ids=["coated box", "glass sphere", "sunlit courtyard"])
def test_records_split_gather_equals_one_loop(scene_dict, monkeypatch):
    """gather_radiance (first vertex apart, its lookups answered together, the rest in
    one loop) gives trace_gather_rays' radiance up to float rounding, the same
    distances, and its compacted search the same photons' irradiance. (With the
    lookups no photon answers read as 0 in both: the one loop, which camera paths use,
    does not trace them; the records' gathers always take the split path.)"""
    monkeypatch.setattr(gather, "TRACE_UNANSWERED", False)
    scene = mi.load_dict(scene_dict())
    prepared = pipeline.prepare(scene, settings(estimator="first_hit"))
    source, records = prepared.gather_source, prepared.index.records
    delta = source.photons.irradiance_nodelta is not None
    assert delta == ("sun" in scene_dict())

    def rays():
        return cache._stratified_rays(records.position, records.normal, (8, 16), 7,
                                      streams.RECORD_GATHER, prepared.ray_offset)

    ray, *_, rng = rays()
    assert dr.width(ray.o) >= gather.SPLIT_GATHER_MIN_RAYS
    loop_radiance, loop_distance = gather.trace_gather_rays(scene, source, ray, rng, mi.Bool(True), delta)
    ray, *_, rng = rays()
    split_radiance, split_distance = gather.gather_radiance(scene, source, ray, rng, delta)
    loop_radiance = np.array(loop_radiance)
    assert loop_radiance.sum() > 0
    np.testing.assert_array_equal(np.array(split_distance), np.array(loop_distance))
    np.testing.assert_allclose(np.array(split_radiance), loop_radiance, rtol=1e-5, atol=1e-7)

    si = scene.ray_intersect(ray)
    hit = dr.compress(si.is_valid())
    p = dr.gather(mi.Point3f, si.p, hit)
    n = dr.gather(mi.Vector3f, mi.Vector3f(dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)), hit)
    at = np.array(source.irradiance_at(scene, p, n, True, without_delta=delta))
    assert (at.sum(0) > 0).mean() > 0.5
    np.testing.assert_array_equal(np.array(source.irradiance_of(scene, p, n, without_delta=delta)), at)


def test_one_walk_gives_both_estimates_of_a_sunlit_scene():
    """estimate_irradiance(nodelta_too=True): the whole estimate and the one without the
    sun's direct photons from one walk, bit-identical to two walks."""
    from pmic_integrator import irradiance

    scene = mi.load_dict(courtyard((16, 12)))
    prepared = pipeline.prepare(scene, settings())
    half_a, half_b = prepared.global_map.split_by_path()
    grid, order = irradiance.PointGridPyramid.build(half_b.position, prepared.global_radius, 32)
    half_b = half_b.select(order)
    args = (half_b, grid, half_a.position, half_a.normal)
    whole = np.array(irradiance.estimate_irradiance(*args))
    without = np.array(irradiance.estimate_irradiance(*args, without_delta_direct=True))
    both = [np.array(x) for x in irradiance.estimate_irradiance(*args, nodelta_too=True)]
    assert (whole.sum(0) > without.sum(0)).mean() > 0.3  # the sun's photons are apart
    np.testing.assert_array_equal(both[0], whole)
    np.testing.assert_array_equal(both[1], without)


def test_render_rng_follows_the_sampler_seed():
    def numbers(seed):
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(seed, 64)
        return np.array(streams.render_rng(sampler, 64).next_float32())

    np.testing.assert_array_equal(numbers(3), numbers(3))
    assert not np.array_equal(numbers(3), numbers(4))
    assert len(np.unique(numbers(3))) == 64


def test_photon_seeds_keep_maps_and_batches_apart():
    seeds = {streams.photon_batch_seed(seed, batch, caustic)
             for seed in range(3) for batch in range(100) for caustic in (False, True)}
    assert len(seeds) == 600


def test_no_photon_is_stored_on_the_dark_side_of_a_one_sided_surface():
    """Two plates lit from below by a point light: the one-sided plate's underside
    reflects nothing, the twosided one's does. Photons used to be stored on both (in a
    room of thin walls lit through a window, 95 % of the map lay outside it)."""
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}
    plate = lambda x, bsdf: {"type": "rectangle", "bsdf": bsdf,  # noqa: E731 (facing +z)
                             "to_world": mi.ScalarTransform4f().translate([x, 0, 0])}
    scene = mi.load_dict({"type": "scene",
                          "one_sided": plate(-1.5, grey),
                          "two_sided": plate(1.5, {"type": "twosided", "bsdf": grey}),
                          "light": {"type": "point", "position": [0, 0, -1],
                                    "intensity": {"type": "rgb", "value": 1.0}}})
    stored = photons.trace_photons(scene, photons.GLOBAL, 2000, -1, 0, 1 << 20, warn=False)
    x = np.array(stored.position.x)
    assert 2000 <= stored.count < 2000 + 64  # whole paths: the last may add a few
    assert (x > 0).all(), f"{int((x < 0).sum())} photons under the one-sided plate"


def test_progress_bars_end_at_100_percent_with_the_stage_detail():
    """The photon tracer reporting its last batch stays under 100 %: the stage's end
    (done) closes the bar at 100 % with the stored count."""
    import io

    log = io.StringIO()
    progress = pipeline.Progress(enabled=True, stream=log, delay=0)
    progress.photons("global", 500, 1000, 800)
    progress.photons("global", 1000, 1000, 1600)
    lines = [line for line in log.getvalue().replace("\r", "\n").split("\n") if line.strip()]
    assert not [line for line in lines if "100%" in line], lines
    progress.done("photons (global)", "1000 stored")
    lines = [line for line in log.getvalue().replace("\r", "\n").split("\n") if line.strip()]
    assert lines[-1].startswith("photons (global)") and "100%" in lines[-1] and "1000 stored" in lines[-1]


def test_progress_shows_nothing_for_a_short_stage_or_when_off():
    import io

    for progress in (pipeline.Progress(enabled=True, stream=io.StringIO()),  # under its delay
                     pipeline.Progress(enabled=False, stream=io.StringIO(), delay=0)):
        progress.update("cache", 0.5, "half")
        progress.done("cache", "done")
        assert progress.stream.getvalue() == ""


@pytest.mark.parametrize("max_depth, holds", [(-1, True), (6, False), (63, False), (65, True)])
def test_final_gather_records_hold_caustics_only_at_unbounded_depth(max_depth, holds):
    """Final-gather records add the caustic map's irradiance (camera paths then skip
    the caustic read where they read the cache); with a bounded max_depth the read
    stays per vertex, where its depth is known. A max_depth of 64 or more is unbounded
    (settings.UNBOUNDED_FROM)."""
    from pmic_integrator import scenes

    scene = scenes.load_scene("cornell_caustics", resolution=16, spp=1)
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC, "max_depth": max_depth})
    integrator.build_cache(scene)
    index = integrator.prepared.index
    assert integrator.prepared.caustic_map.count > 0
    assert index.holds_caustics is holds


@pytest.mark.parametrize("max_depth", [64, 65, 1024])
def test_a_deep_max_depth_renders_as_unbounded(max_depth):
    """Scenes often ask for a max_depth of 65 (Bitterli's do) to mean "unbounded".
    Read as a bound, camera paths read the cache at one depth only and path-traced
    deeper vertices (the lamp room's relMSE 2.1 instead of 0.22); now the image is the
    unbounded one, bit for bit (photon paths stop at 64 bounces either way)."""
    from pmic_integrator import scenes

    scene = scenes.load_scene("cornell_caustics", resolution=16, spp=4)

    def image(depth):
        spec = {"type": "pmic", **SMALL_PMIC, "max_depth": depth}
        return np.array(mi.render(scene, integrator=mi.load_dict(spec), spp=4, seed=0))

    assert Settings.parse({"max_depth": max_depth}).bounded is False
    assert Settings.parse({"max_depth": 63}).bounded is True
    np.testing.assert_array_equal(image(max_depth), image(-1))


def test_materials_held_in_instances_count():
    """An instance reports a default diffuse BSDF of its own, not those of the shapes
    its shapegroup holds: a glass sphere and a rough plastic cube held in instances
    must still give the scene a caustic map and rough-plastic handling."""
    T = mi.ScalarTransform4f
    d = cornell(16, **{"large-box": None, "small-box": None})
    d["group"] = {"type": "shapegroup",
                  "cube": {"type": "cube", "to_world": T().scale(0.15),
                           "bsdf": {"type": "roughplastic", "alpha": 0.2}},
                  "ball": {"type": "sphere", "center": [0, 0.3, 0], "radius": 0.12,
                           "bsdf": {"type": "dielectric"}}}
    d["instance"] = {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                     "to_world": T().translate([0, -0.85, 0])}
    scene = mi.load_dict(d)
    info = pipeline.SceneInfo.of(scene)
    assert info.has_specular and info.has_glossy_coat
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    integrator.build_cache(scene)
    assert integrator.prepared.caustic_map.paths_emitted > 0  # traced (if then dropped)
    assert not any("no delta or glossy" in reason for reason in integrator.prepared.skipped)
    # Scenes without instances: only the shapes' own BSDFs (an unused one adds nothing).
    plain = cornell(16, unused={"type": "dielectric", "id": "spare"})
    assert not pipeline.SceneInfo.of(mi.load_dict(plain)).has_specular


@pytest.mark.parametrize("name,pays", [("indirect_room", True), ("exterior_envmap", False)])
def test_guiding_is_used_where_bounced_light_matters(name, pays):
    """Guiding's record lookups are spent where records owe much of their light to
    bounces (a room lit through its ceiling), not under an open sky, where direct light
    is nearly all of it; and every record of the room has a distribution to draw from."""
    from pmic_integrator import scenes

    scene = scenes.load_scene(name, resolution=16)
    prepared = pipeline.prepare(scene, settings())
    assert prepared.index.guiding_pays() is pays
    guide = np.array(prepared.index.records.guide).reshape(prepared.index.records.count, -1)
    assert np.all(np.diff(guide, axis=1) >= 0) and np.all(np.isin(guide[:, -1], [0.0, 1.0]))
    if pays:
        assert np.mean(guide[:, -1] == 1.0) > 0.95


@pytest.mark.parametrize("target, stride", [(20_000, 1), (200_000, 6)])
def test_irradiance_is_precomputed_at_whole_even_paths_one_in_stride(target, stride):
    """Of the even light paths, one in ``precompute_stride`` gets the estimates (6 for
    a 200k map, where 8 would leave under 2**14 photons; 1 for a 20k map), and, where
    even photons are sparse (irradiance.SPARSE_CELL_RADII), the other even ones there:
    in a lit Cornell box, few."""
    from pmic_integrator import irradiance

    scene = mi.load_dict(cornell())
    stored = photons.trace_photons(scene, photons.GLOBAL, target, -1, 0, 1 << 24, warn=False)
    even = int(dr.count((stored.path & 1) == 0)[0])
    assert irradiance.precompute_stride(even) == stride
    out = irradiance.precompute_irradiance(stored, 0.1, 64)  # (the box is 2 wide)
    path = np.array(out.path)
    assert (path % 2 == 0).all()
    strided = int(((np.array(stored.path) % (2 * stride)) == 0).sum())
    assert int((path % (2 * stride) == 0).sum()) == strided
    assert strided <= out.count <= 1.1 * strided
    assert np.isfinite(np.array(out.irradiance)).all() and np.array(out.irradiance).max() > 0


def test_precomputed_irradiance_counts_every_photon_of_the_other_paths():
    """On a plane of 140k photons, one per path, precomputed at one in 4 even paths (A,
    1/8 of the map: 2**14 photons must remain): the estimates count the 7/8 of the
    photons of other paths, not the odd half alone. Unbiased (mean within 1 % of the plane's irradiance, n·p / area) and
    with the noise of that many photons: relative sd sqrt(9 / (5 λ π r²)) for λ photons
    per unit area in the disc of radius r (Simpson kernel), 0.087 against the odd half's
    0.115."""
    from pmic_integrator import irradiance

    rng = np.random.default_rng(3)
    n, r, power = 140_000, 0.05, 1e-3
    xy = rng.uniform(-1.0, 1.0, (2, n)).astype(np.float32)
    plane = photons.PhotonMap(
        mi.Point3f(mi.Float(xy[0]), mi.Float(xy[1]), 0.0), mi.Vector3f(0.0, 0.0, 1.0) + dr.zeros(mi.Vector3f, n),
        mi.Color3f(power) + dr.zeros(mi.Color3f, n), dr.ones(mi.UInt32, n), dr.zeros(mi.Bool, n),
        dr.arange(mi.UInt32, n), n, delta_light=dr.zeros(mi.Bool, n))
    assert irradiance.precompute_stride(n // 2) == 4
    # A huge per_estimate keeps every disc at the base radius (no finer level).
    out = irradiance.precompute_irradiance(plane, r, 1e6)
    path = np.array(out.path)
    assert out.count == n // 8 and (path % 8 == 0).all()
    p = np.array(out.position)
    inside = (np.abs(p[0]) < 1 - 2 * r) & (np.abs(p[1]) < 1 - 2 * r)
    e = np.array(out.irradiance)[0][inside]
    truth = n * power / 4.0
    assert e.mean() == pytest.approx(truth, rel=0.01)
    density = (n - n // 8) / 4.0
    expected_sd = np.sqrt(9.0 / (5.0 * density * np.pi * r * r))
    assert e.std() / e.mean() == pytest.approx(expected_sd, rel=0.1)
    # From the odd half only (what open scenes use: pipeline.OTHER_PATHS_MIN_BOUNCED):
    # the same photons precomputed, half the photons counted.
    odd = irradiance.precompute_irradiance(plane, r, 1e6, other_paths=False)
    assert (np.array(odd.path) == path).all()
    e_odd = np.array(odd.irradiance)[0][inside]
    assert e_odd.mean() == pytest.approx(truth, rel=0.015)
    assert e_odd.std() / e_odd.mean() == pytest.approx(np.sqrt(9.0 / (5.0 * n / 8.0 * np.pi * r * r)), rel=0.1)


def test_the_last_batch_keeps_the_path_that_reaches_the_target(monkeypatch):
    """Whole paths are kept, and the last one may run past the target: keeping only
    paths that fit entirely could keep none when a few photons were left, and in the
    indirectly lit room (long paths) seed 0 then traced ten more 1024-path batches
    (0.4 s) before one began with a path short enough."""
    from pmic_integrator import scenes

    scene = scenes.load_scene("indirect_room", resolution=32, spp=1)
    calls = []
    trace_batch = photons._trace_batch
    monkeypatch.setattr(photons, "_trace_batch", lambda *a, **k: calls.append(a[3]) or trace_batch(*a, **k))
    for seed in range(3):
        calls.clear()
        stored = photons.trace_photons(scene, photons.GLOBAL, 50_000, -1, seed, 1 << 24, warn=False)
        assert 50_000 <= stored.count < 50_000 + photons.MAX_PHOTON_BOUNCES
        assert len(calls) <= 2, f"seed {seed}: batches of {calls} paths"


def test_a_lone_photon_is_traced_as_in_company():
    """When one photon of a batch is left it goes on beside a dead twin (Dr.Jit
    compiles one-element arrays as scalars: a lone photon made a whole bounce's kernels
    of its own, compiled anew whenever a seed left one). Its photons are those it has
    in a batch of two (each lane has its own random stream), and the twin stores none."""
    scene = mi.load_dict(cornell(8))
    bounds = photons.emission_bounds(scene)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        alone = photons._trace_batch(scene, photons.GLOBAL, 0, 1, 5, 12, bounds)
        history = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    # A batch of one path is one element wide at its first bounce only (before: 4).
    assert sum(1 for k in history if k["size"] == 1 and k["operation_count"] > 100) <= 2
    pair = photons._trace_batch(scene, photons.GLOBAL, 0, 2, 5, 12, bounds)
    mine = np.array(pair[5]) == 0
    assert len(np.array(alone[3])) == mine.sum() > 1
    assert (np.array(alone[5]) == 0).all()
    order = np.argsort(np.array(pair[3])[mine], kind="stable")
    for got, want in zip(alone[:4], pair[:4]):
        got = np.array(got).reshape(-1, len(np.array(alone[3]))) if np.array(got).ndim > 1 else np.array(got)
        want = np.array(want)
        want = want[..., mine] if want.ndim > 1 else want[mine]
        assert np.array_equal(got, want[..., order] if want.ndim > 1 else want[order])


@pytest.mark.parametrize("kind", [photons.GLOBAL, photons.CAUSTIC])
@pytest.mark.parametrize("max_store_depth", [64, 5])
def test_the_photon_tail_loop_stores_what_the_wavefront_stores(monkeypatch, kind, max_store_depth):
    """photons._trace_tail: a batch's last paths, traced in one symbolic loop (in
    chunks of bounces that fill its slots), store the wavefront's photons, bit for bit
    and in its order (by bounce, then by path), up to the same depth limit. A room lit
    through a pane over a rough plastic floor: caustic paths, lobes sampled apart."""
    d = _pane_room()
    d["floor"]["bsdf"] = {"type": "roughplastic", "alpha": 0.2}
    scene = mi.load_dict(d)
    bounds = photons.emission_bounds(scene)

    def batch(tail_paths, tail_slots):
        monkeypatch.setattr(photons, "TAIL_LOOP_PATHS", tail_paths)
        monkeypatch.setattr(photons, "TAIL_LOOP_SLOTS", tail_slots)
        return [np.array(a) for a in photons._trace_batch(scene, kind, 0, paths, 3, max_store_depth, bounds)]

    paths = 100_000
    wavefront = batch(0, 1)
    assert len(wavefront[3]) > 500 and wavefront[3].max() >= min(max_store_depth, 3)
    for tail_paths, tail_slots in ((1 << 17, 1 << 21), (1 << 17, paths * 3), (500, 1 << 21)):
        looped = batch(tail_paths, tail_slots)
        for got, want in zip(looped, wavefront):
            assert np.array_equal(got, want), (tail_paths, tail_slots)


def test_guiding_is_judged_by_the_area_records_cover():
    """Guiding pays where records covering an eighth of the surface (records weighted
    by R²) owe a quarter of their light to bounces. Counted record by record (a quarter
    of them), the bundled exterior's answer flipped with the seed (0.251 of its records
    at seed 0, 0.244 at seed 1: a second render kernel to compile), and an object's
    concave corners, where small records crowd, turned guiding on under an open sky.
    By area the exterior scores 0.09, a room lit through its ceiling 0.98."""
    from pmic_integrator import scenes

    scene = scenes.load_scene("exterior_envmap", resolution=16)
    answers = []
    for seed in (0, 1):
        integrator = mi.load_dict({"type": "pmic", "seed": seed})
        mi.render(scene, integrator=integrator, spp=1)
        answers.append(integrator.prepared.index.guiding_pays())
    assert answers == [False, False]


@pytest.mark.parametrize("name, rounds", [("exterior_envmap", "quarter"), ("cornell_box", "whole"),
                                          ("courtyard", "completed")])
def test_open_scenes_gather_a_quarter_of_the_rays(name, rounds, monkeypatch):
    """Final gather: in open scenes (little of the photons' power bounced) records
    gather a quarter of gather_rays, and the rest only where bounced light matters
    (RecordIndex.guiding_pays: not under the exterior's open sky, but in a courtyard);
    rooms gather all of their rays at once (pipeline.FIRST_GATHER_SHARE)."""
    from pmic_integrator import cache, scenes
    from pmic_integrator.settings import rays_strata
    from pmic_integrator import kinds as sb

    used = []
    compute = cache.compute_records
    monkeypatch.setattr(cache, "compute_records",
                        lambda *a, **k: used.append(a[5]) or compute(*a, **k))
    scene = mi.load_dict(sb.courtyard(size=(16, 12))) if name == "courtyard" else \
        scenes.load_scene(name, resolution=16, spp=1)
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC, "gather_rays": 256})
    integrator.build_cache(scene)
    assert used
    quarter, rest = rays_strata(64), rays_strata(256 - 60)
    expected = {"quarter": {quarter}, "whole": {rays_strata(256)}, "completed": {quarter, rest}}[rounds]
    assert set(used) == expected
    if rounds == "completed":
        assert used[-1] == rest  # once, at the end, over every record
        assert integrator.prepared.index.guiding_pays()


def test_a_caustic_map_that_holds_a_rooms_light_through_glass_is_kept():
    """A room lit by a sky through a thin glass pane: all of its light is caustic, and
    under a fifth of the caustic pass's paths store a photon (the window is small). Such
    a map is kept (pipeline.CAUSTIC_MIN_YIELD): gathered instead, that light was 18×
    noisier per second. A map of a few dozen photons is still dropped (an open sky)."""
    from pmic_integrator import kinds as sb

    d = sb.window_room(size=(16, 12))
    d["pane"] = {"type": "rectangle", "bsdf": {"type": "thindielectric"},
                 "to_world": mi.ScalarTransform4f().translate([0, 1.4, 1.99]).scale([0.6, 0.4, 1])}
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    stats = integrator.build_cache(mi.load_dict(d))
    prepared = integrator.prepared
    caustic = prepared.caustic_map
    assert caustic.count > 0
    # The caustic pass's own photons (the global pass's come after them: numbered past
    # its paths) are the case the rule is for.
    own = int(dr.count(caustic.path < caustic.paths_emitted)[0])
    assert own < 0.25 * SMALL_PMIC["caustic_photons"]
    assert stats["photons_caustic_from_global"] == caustic.count - own > 0
    assert not any(reason.startswith("caustic map") for reason in prepared.skipped)


def _pane_room():
    from pmic_integrator import kinds as sb

    d = sb.window_room(size=(16, 12))
    d["pane"] = {"type": "rectangle", "bsdf": {"type": "thindielectric"},
                 "to_world": mi.ScalarTransform4f().translate([0, 1.4, 1.99]).scale([0.6, 0.4, 1])}
    return d


@pytest.mark.parametrize("floor", ["diffuse", "roughplastic"])
def test_the_global_passs_caustic_photons_join_the_caustic_map(floor):
    """photons.merge_caustic_photons: the global pass's L S+ D photons of odd paths are
    added, and every photon of a path both passes sample alike is weighed by the paths
    of both (N_c + N_g / 2). Photons whose path the caustic pass sampled otherwise
    (lobes apart, off a rough plastic floor) keep their power."""
    d = _pane_room()
    if floor == "roughplastic":
        d["floor"]["bsdf"] = {"type": "roughplastic", "alpha": 0.2}
    scene = mi.load_dict(d)
    glob = photons.trace_photons(scene, photons.GLOBAL, 20_000, -1, 0, 1 << 22, warn=False)
    caustic = photons.trace_photons(scene, photons.CAUSTIC, 4_000, -1, 0, 1 << 22, warn=False)
    merged = photons.merge_caustic_photons(caustic, glob)
    n_c, n_g = caustic.paths_emitted, glob.paths_emitted
    total = n_c + n_g // 2
    joins = np.array(glob.specular_path & glob.shared_path & (glob.depth >= 2) & ((glob.path & 1) == 1))
    assert joins.sum() > caustic.count / 2  # most of this room's light is caustic
    assert merged.count == caustic.count + joins.sum()
    assert merged.shared_path is None and merged.paths_emitted == n_c
    power = np.array(merged.power).T if np.array(merged.power).shape[0] == 3 else np.array(merged.power)
    own_power = np.array(caustic.power).T
    shared = np.array(caustic.shared_path)
    scale = np.where(shared, n_c / total, 1.0)[:, None]
    assert np.allclose(power[:caustic.count], own_power * scale, rtol=1e-6, atol=0)
    assert np.allclose(power[caustic.count:], np.array(glob.power).T[joins] * (n_g / total), rtol=1e-6, atol=0)
    path = np.array(merged.path)
    assert np.all(path[caustic.count:] >= n_c) and np.all((path[caustic.count:] - n_c) % 2 == 1)
    if floor == "roughplastic":
        assert not shared.all()  # photons bounced off the floor's glossy lobe
        assert not np.array(glob.shared_path).all()
    else:
        assert shared.all()
    # Both estimate the same light: the caustic photons' power per path, merged or the
    # global pass's alone, agree within their noise (photon counts ~ Poisson).
    floor_power = lambda m, p: float(p[np.abs(np.array(m.position.y)) < 1e-3].sum())
    g_all = np.array(glob.specular_path & glob.shared_path & (glob.depth >= 2))
    g_pos_y = np.array(glob.position.y)[g_all]
    g_floor = float(np.array(glob.power).T[g_all][np.abs(g_pos_y) < 1e-3].sum())
    m_floor = floor_power(merged, power)
    if floor == "diffuse":
        n = (np.abs(np.array(merged.position.y)) < 1e-3).sum()
        assert abs(m_floor / g_floor - 1) < 4 / np.sqrt(n)


def test_caustic_maps_of_rooms_lit_through_glass_hold_the_global_passs_photons():
    """In the pipeline: the pane room's caustic map holds the global pass's caustic
    photons (more than its own there), and the global map carries no merge flags on."""
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    stats = integrator.build_cache(mi.load_dict(_pane_room()))
    prepared = integrator.prepared
    assert stats["photons_caustic_from_global"] > stats["photons_caustic"] / 2
    assert prepared.caustic_map.shared_path is None and prepared.global_map.shared_path is None


def test_normal_bins_rule_out_only_estimates_that_are_zero():
    """irradiance.may_count_photons: wherever a caustic estimate is not 0 it says
    "may" (checked at points spread over a room's surfaces and just off them, with
    their normals and random ones), and it rules out the far side of a 4 cm wall whose
    other side holds the photons (the rough floor's caustic in the lit room)."""
    from pmic_integrator import kinds as sb
    from pmic_integrator import irradiance

    d = sb.two_rooms(size=(16, 12), floor_bsdf={"type": "roughconductor", "alpha": 0.25, "material": "Al"})
    scene = mi.load_dict(d)
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    integrator.build_cache(scene)
    prepared = integrator.prepared
    caustic = prepared.caustic_map
    assert caustic.count > 1000
    bins = irradiance.NormalBins.build(caustic, prepared.caustic_grid)
    rng = np.random.default_rng(5)
    # Queries at photons, moved up to two radii, with the photon's normal or a random one.
    pick = mi.UInt32(rng.integers(0, caustic.count, 20_000).astype(np.uint32))
    p = dr.gather(mi.Point3f, caustic.position, pick)
    shift = rng.normal(size=(3, 20_000)).astype(np.float32) * prepared.caustic_radius
    p = p + mi.Vector3f(shift)
    n = dr.gather(mi.Vector3f, caustic.normal, pick)
    random_n = rng.normal(size=(3, 20_000)).astype(np.float32)
    random_n /= np.linalg.norm(random_n, axis=0)
    use_random = mi.Bool(rng.random(20_000) < 0.3)
    n = dr.select(use_random, mi.Vector3f(random_n), n)
    estimate = np.array(mi.luminance(irradiance.estimate_irradiance(
        caustic, prepared.caustic_grid, p, n, prepared.caustic_radius)))
    may = np.array(irradiance.may_count_photons(bins, p, n))
    assert (estimate > 0).sum() > 1500
    assert np.all(may[estimate > 0])
    assert not may.all()  # it does rule some out
    # A closed box split by a 2 cm wall, lit on the left, whose rough metal floor puts
    # caustic photons on the wall's left face: on its right face (dark) no estimate
    # can count them, and the bins say so.
    d = sb.thin_wall_room(thickness=0.02)
    d["shell_floor"]["bsdf"] = {"type": "roughconductor", "alpha": 0.25, "material": "Al"}
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    integrator.build_cache(mi.load_dict(d))
    prepared = integrator.prepared
    bins = irradiance.NormalBins.build(prepared.caustic_map, prepared.caustic_grid)
    y, z = np.meshgrid(np.linspace(-0.4, 0.4, 9), np.linspace(-0.4, 0.4, 9))
    left = mi.Point3f(mi.Float(np.full(81, -0.0101, np.float32)), mi.Float(y.ravel().astype(np.float32)),
                      mi.Float(z.ravel().astype(np.float32)))
    lit = np.array(mi.luminance(irradiance.estimate_irradiance(
        prepared.caustic_map, prepared.caustic_grid, left, mi.Vector3f(-1, 0, 0), prepared.caustic_radius)))
    assert (lit > 0).mean() > 0.5  # the lit face has caustic light
    right = mi.Point3f(-left.x, left.y, left.z)
    assert not np.array(irradiance.may_count_photons(bins, right, mi.Vector3f(1, 0, 0))).any()
    assert np.array(irradiance.may_count_photons(bins, left, mi.Vector3f(-1, 0, 0)))[lit > 0].all()


def test_caustic_estimates_use_more_photons_where_caustics_light_the_room():
    """pipeline.caustic_lookup_size: in the room lit by a sky through a glass pane the
    caustic photons carry 98 % of the first-bounce light, and a caustic estimate, read
    at every first diffuse vertex, is the image: its noise shows as blotches. It uses
    up to CAUSTIC_LOOKUP_GROWTH times the photons there, and the usual count where
    caustics are a glass sphere's focus (Cornell box)."""
    from pmic_integrator import scenes

    base = int(64 * pipeline.CAUSTIC_LOOKUP_FRACTION)
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    integrator.build_cache(mi.load_dict(_pane_room()))
    prepared = integrator.prepared
    assert pipeline.caustic_share(prepared.global_map, prepared.caustic_map) > 0.9
    grown = pipeline.caustic_lookup_size(64, pipeline.caustic_share(prepared.global_map, prepared.caustic_map))
    assert 3.5 * base < grown <= base * pipeline.CAUSTIC_LOOKUP_GROWTH
    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC})
    integrator.build_cache(scenes.load_scene("cornell_caustics", 16, 1))
    prepared = integrator.prepared
    assert prepared.caustic_map.count > 0
    assert pipeline.caustic_share(prepared.global_map, prepared.caustic_map) < 0.1
    assert pipeline.caustic_lookup_size(64, pipeline.caustic_share(prepared.global_map, prepared.caustic_map)) == base


def test_walls_lit_through_a_pane_beside_a_sun_patch_read_enough_caustic_photons():
    """A sun and a sky through a glass pane: most caustic photons crowd into the sun's
    patch on the floor. The caustic map's radius is set over the surfaces' area where
    caustics light the room (pipeline.CAUSTIC_ROOM_PYRAMID_LEVELS), so the walls, lit
    by the sky through the pane, read enough photons: against the light traced through
    the pane at 600 wall points, relative RMS 37-42 % and no point at 0, where a radius
    fitted to the photons gave 78-81 % and 7-12 % of the points at 0; the same mean."""
    import math

    from pmic_integrator import irradiance

    d = _pane_room()
    d["sun"] = {"type": "directional", "direction": [-0.3, -0.5, -1.0],
                "irradiance": {"type": "rgb", "value": [3.0, 2.8, 2.5]}}
    scene = mi.load_dict(d)
    rng = np.random.default_rng(1)
    m, rays = 600, 2048
    back = rng.random(m) < 0.5
    u, v = rng.uniform(-1.9, 1.9, m), rng.uniform(0.1, 2.4, m)
    points = np.where(back[:, None], np.stack([u, v, np.full(m, -2 + 1e-4)], 1),
                      np.stack([np.full(m, -2 + 1e-4), v, u], 1)).astype(np.float32)
    normals = np.where(back[:, None], [0, 0, 1], [1, 0, 0]).astype(np.float32)
    p, n = mi.Point3f(points.T), mi.Vector3f(normals.T)
    # The sky's light through the pane, traced (the sun's reaches the floor only).
    owner = dr.arange(mi.UInt32, m * rays) // rays
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(3, m * rays)
    origin, normal = dr.gather(mi.Point3f, p, owner), dr.gather(mi.Vector3f, n, owner)
    direction = mi.Frame3f(normal).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d()))
    si = scene.ray_intersect(mi.Ray3f(origin + normal * 1e-3, direction))
    flags = si.bsdf().flags()
    pane = si.is_valid() & (mi.has_flag(flags, mi.BSDFFlags.Null) | mi.has_flag(flags, mi.BSDFFlags.DeltaTransmission))
    beyond = scene.ray_intersect(si.spawn_ray(direction), pane)
    bs, weight = si.bsdf().sample(mi.BSDFContext(), si, mi.Float(0.9999999), mi.Point2f(0.5, 0.5), pane)
    through = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null) | mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaTransmission)
    sky = mi.Color3f(0.5, 0.6, 0.8)
    light = dr.select(pane & ~beyond.is_valid() & through, weight * bs.pdf * sky, 0.0)
    truth = np.array(mi.luminance(mi.Color3f(light))).reshape(m, rays).mean(1) * math.pi
    for seed in range(2):
        integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC, "seed": seed})
        integrator.build_cache(scene)
        prepared = integrator.prepared
        estimate = np.array(mi.luminance(irradiance.estimate_irradiance(
            prepared.caustic_map, prepared.caustic_grid, p, n, prepared.caustic_radius)))
        assert abs(estimate.sum() / truth.sum() - 1) < 0.08
        assert np.sqrt(np.mean((estimate - truth) ** 2)) / truth.mean() < 0.6
        assert np.mean(estimate == 0) < 0.02


def test_a_sun_patch_through_a_pane_keeps_its_edge():
    """Where caustics light the room, caustic estimates take more photons, but a delta
    light's photons count with a kernel narrower by the square root of that growth
    (PreparedScene.caustic_delta_scale): a sun's patch through the pane keeps the base
    count of photons per estimate and its edge. Across the patch's edge, the light
    10-30 cm outside it is under 5 % of the inside's (2.3-2.6 %; 8.5 % with the sun's
    photons read with the grown kernel)."""
    from pmic_integrator import irradiance

    d = _pane_room()
    d["sun"] = {"type": "directional", "direction": [-0.3, -0.5, -1.0],
                "irradiance": {"type": "rgb", "value": [3.0, 2.8, 2.5]}}
    scene = mi.load_dict(d)
    # The patch: the window (y 1-1.8) along the sun onto the floor; at z = -0.8 it
    # spans x in [-1.44, -0.24].
    xs = np.linspace(-0.6, 0.1, 141).astype(np.float32)
    line = mi.Point3f(mi.Float(xs), mi.Float(np.full(141, 1e-4, np.float32)), mi.Float(np.full(141, -0.8, np.float32)))
    for seed in range(2):
        integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC, "seed": seed})
        integrator.build_cache(scene)
        prepared = integrator.prepared
        assert 0.45 < prepared.caustic_delta_scale < 0.55
        e = np.array(mi.luminance(irradiance.estimate_irradiance(
            prepared.caustic_map, prepared.caustic_grid, line, mi.Vector3f(0, 1, 0), prepared.caustic_radius,
            delta_scale=prepared.caustic_delta_scale)))
        inside, outside = np.median(e[:30]), np.median(e[-30:])
        assert outside < 0.05 * inside


def test_a_caustic_pass_that_will_be_dropped_stops_early():
    """A Cornell box with a rough plastic floor stores under a tenth of the requested
    caustic photons, so its caustic map is dropped. The pass went on until the
    projected count fell under half of that tenth, so it traced all of its 2 M paths
    (0.25 s of a 1.2 s render at 256²) for a map it then dropped; it now stops once a
    generous estimate (3 Poisson deviations up) stays under the tenth: after its first
    batch here, and with the same image."""
    d = cornell(16)
    d["floor"]["bsdf"] = {"type": "roughplastic", "alpha": 0.2,
                          "diffuse_reflectance": {"type": "rgb", "value": [0.7, 0.7, 0.7]}}
    stats = mi.load_dict({"type": "pmic"}).build_cache(mi.load_dict(d))
    assert stats["photons_caustic"] == 0  # dropped
    assert stats["paths_emitted_caustic"] <= photons.FIRST_BATCH_PATHS  # (before: 2 M)


def test_a_room_on_a_large_sunlit_ground_receives_photons_through_its_windows():
    """The public classroom's kind (kinds.sunlit_classroom): an 8 × 3 × 6 m room whose
    windows face a sun and a sky, on a ground square 220 m wide. Its indirect light
    comes from the photons that enter through the windows. Shot across the whole ground,
    5 of the map's 50,000 landed inside (on a 10 m ground 1607 do). The sky and the sun
    now shoot half of their rays at the building and the ground beside it
    (emission.focus_box, FOCUS_SHARE), most of the rest at rings round it
    (emission.focus_rings): 415 (647 with three quarters at the focus, no rings)."""
    from pmic_integrator import kinds
    scene = mi.load_dict(kinds.sunlit_classroom(size=(16, 9), ground_half=110.0))
    integrator = mi.load_dict({"type": "pmic", "global_photons": 50_000})
    integrator.build_cache(scene)
    position = np.array(integrator.prepared.global_map.position)
    x, y, z = position if position.shape[0] == 3 else position.T
    inside = (np.abs(x) < 4) & (np.abs(z) < 3) & (y > -0.005) & (y < 3)
    assert inside.sum() >= 300  # 415


def test_the_renders_cache_decisions_are_made_once_in_the_cache_stage(monkeypatch):
    """Whether guiding pays (and whether a sky is seen, first reads may pay) is read
    back from the device once, when the cache is built (RecordIndex.remembered): each
    render then starts its camera pass without a host read, which on a GPU is a
    synchronisation (benchmarks/kernel_report.py: the render stage's element reads 3 -> 1)."""
    from pmic_integrator import kinds
    from pmic_integrator.cache import RecordIndex

    scene = mi.load_dict(kinds.pmic_cornell(16))
    first = np.array(mi.render(scene, spp=2))
    index = scene.integrator().prepared.index
    assert any(key[0] == "guiding_pays" for key in index.__dict__["_remembered"])

    def recomputed(self):
        raise AssertionError("guiding_pays computed again at a render")

    monkeypatch.setattr(RecordIndex, "_guiding_pays", recomputed)
    assert np.array_equal(np.array(mi.render(scene, spp=2)), first)


def test_the_records_gathers_of_another_count_compile_nothing_anew():
    """gather_radiance sums each ray's lookups into its radiance. Dr.Jit's default
    scatter-add on the CPU reduces into a copy per thread and writes the target's size
    (the rays' count) into the kernel: compiled anew for every count of records, so
    for every scene, seed and photon count. Now atomic adds, one per ray and sum
    (_jit.scatter_min has the same story). (A kernel loaded from Dr.Jit's disk cache
    counts as new to the process too.)"""
    scene = mi.load_dict(cornell(16, white=_rough_plastic([0.7, 0.7, 0.7])))
    prepared = pipeline.prepare(scene, settings(estimator="first_hit"))
    source, records = prepared.gather_source, prepared.index.records
    assert records.count >= 150

    def run(count):
        chosen = dr.arange(mi.UInt32, count)
        ray, *_, rng = cache._stratified_rays(dr.gather(mi.Point3f, records.position, chosen),
                                              dr.gather(mi.Vector3f, records.normal, chosen), (8, 16), 7,
                                              streams.RECORD_GATHER, prepared.ray_offset)
        assert dr.width(ray.o) >= gather.SPLIT_GATHER_MIN_RAYS
        radiance, _ = gather.gather_radiance(scene, source, ray, rng)
        dr.eval(radiance)
        return radiance

    # (Read back outside the history: a colour copied to NumPy writes its width into
    # a kernel of its own, the test's.)
    assert np.array(run(130)).sum() > 0
    with new_kernels() as compiled:
        run(150)
    assert compiled == []


def _layered_photons(layers, spots: int = 3000):
    """Photons on a 1 m square (z = 0, normals +z) at ``spots`` random spots; at each
    spot one photon per ``(depth, specular_path, power)`` of ``layers``: every estimate
    holds the layers in the same proportions as their powers."""
    xy = np.random.default_rng(1).random((spots, 2))
    p = np.concatenate([np.column_stack([xy, np.zeros(spots)])] * len(layers))
    depth = np.concatenate([np.full(spots, d, np.uint32) for d, _, _ in layers])
    specular = np.concatenate([np.full(spots, s) for _, s, _ in layers])
    power = np.concatenate([np.full(spots, w, np.float32) for _, _, w in layers])
    count = spots * len(layers)
    up = np.tile([0.0, 0.0, 1.0], (count, 1))
    return photons.PhotonMap(mi.Point3f(p.T), mi.Vector3f(up.T),
                             mi.Color3f(power, power, power), mi.UInt32(depth), mi.Bool(specular),
                             dr.arange(mi.UInt32, count), count)


@pytest.mark.parametrize("layers, share", [
    ([(1, True, 1.0), (2, True, 1.0)], 0.5),  # direct and caustic alike
    ([(1, True, 1.0), (3, True, 2.0), (2, False, 1.0)], 0.5),  # a bounce off a diffuse surface is not caustic
    ([(1, True, 1.0), (2, True, 3.0)], 0.75),
    ([(1, True, 1.0), (2, False, 1.0)], 0.0),  # no caustic photon
])
def test_caustic_standout_is_the_caustic_share_of_the_estimates_at_caustic_photons(layers, share):
    from pmic_integrator.irradiance import caustic_standout

    assert caustic_standout(_layered_photons(layers), 0.05, 32) == pytest.approx(share, abs=1e-5)


@pytest.mark.parametrize("aovs, caustic_map", [("albedo,normal", False), ("", True),
                                               ("albedo,normal,direct", False)])
def test_a_render_for_a_denoiser_traces_caustics_that_neither_stand_out_nor_hide(aovs, caustic_map):
    """A fifth of a wide ceiling panel behind glass (the white room's kind: caustic
    standout ~0.2, traced moment ~33): a render that outputs the denoiser's guides
    skips the caustic pass (pipeline.CAUSTIC_MIN_STANDOUT, CAUSTIC_MAX_TRACED_MOMENT),
    whose map cost more than it saved after OIDN, and its gathers trace the caustics;
    a raw render keeps the map, and does not measure."""
    from pmic_integrator import kinds

    integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC, "aovs": aovs})
    stats = integrator.build_cache(mi.load_dict(kinds.glass_covered_panel()))
    prepared = integrator.prepared
    assert (prepared.caustic_map.count > 0) == caustic_map
    assert prepared.gather_source.caustics_by_gathering != caustic_map
    if caustic_map:
        assert "caustic_standout" not in stats
    else:
        assert stats["caustic_standout"] < pipeline.CAUSTIC_MIN_STANDOUT
        assert 1.0 <= stats["caustic_traced_moment"] <= pipeline.CAUSTIC_MAX_TRACED_MOMENT
        assert stats["caustics_left_to_denoiser"] is True
        assert any("for a denoiser" in reason for reason in prepared.skipped)


def test_a_render_for_a_denoiser_maps_caustics_that_stand_out_or_that_tracing_hardly_finds():
    """A glass sphere's caustic spot stands out from the light round it (~0.5); the
    stairwell kind's glass drop spreads a 4 cm lamp's light down the shaft (standout
    ~0.08), but a traced ray meets the lamp through the drop about once in 10^5 (its
    samples' relative moment above CAUSTIC_MAX_TRACED_MOMENT): both keep their maps."""
    from pmic_integrator import kinds, scenes

    for scene, measured in ((scenes.load_scene("cornell_caustics", resolution=16, spp=1), "standout"),
                            (mi.load_dict(kinds.tall_stairwell(size=(12, 20))), "moment")):
        integrator = mi.load_dict({"type": "pmic", **SMALL_PMIC, "aovs": "albedo,normal"})
        stats = integrator.build_cache(scene)
        assert integrator.prepared.caustic_map.count > 0
        assert "caustics_left_to_denoiser" not in stats
        if measured == "standout":
            assert stats["caustic_standout"] >= pipeline.CAUSTIC_MIN_STANDOUT
        else:
            assert stats["caustic_standout"] < pipeline.CAUSTIC_MIN_STANDOUT
            assert stats["caustic_traced_moment"] > pipeline.CAUSTIC_MAX_TRACED_MOMENT


def test_a_raw_render_of_a_denoisers_cache_file_without_caustics_is_warned(tmp_path, caplog):
    """Read by a render that is not for a denoiser, a cache file built for one without a
    caustic map is used (its records gathered the caustics) with a warning."""
    from pmic_integrator import kinds

    path = str(tmp_path / "for_denoiser.npz")
    scene = mi.load_dict(kinds.glass_covered_panel())
    writer = mi.load_dict({"type": "pmic", **SMALL_PMIC, "aovs": "albedo,normal", "cache_file": path})
    writer.build_cache(scene)
    for aovs, warned in (("albedo,normal", False), ("", True)):
        caplog.clear()
        reader = mi.load_dict({"type": "pmic", **SMALL_PMIC, "aovs": aovs, "cache_file": path})
        with caplog.at_level("WARNING", logger="pmic"):
            reader.build_cache(scene)
        assert reader.prepared.caustic_map.count == 0
        assert any("built for a denoiser" in r.getMessage() for r in caplog.records) == warned


def test_gather_hits_in_a_dim_room_find_a_precomputed_photon_near():
    """Irradiance is precomputed at one in eight of the even paths' photons; in a room
    lit through a door those are so sparse that a gather hit read the nearest one
    several lookup radii off, towards the light (the door-ajar kind 1-11 % bright in
    its dim room). Where even photons are sparse every one is precomputed too, from the
    odd half (irradiance.SPARSE_CELL_RADII): 65 % of the dim room's photons had a
    precomputed photon within two lookup radii before, 99 % now."""
    from pmic_integrator import irradiance, kinds

    prepared = pipeline.prepare(mi.load_dict(kinds.two_rooms(size=(16, 12))), Settings())
    photons, source = prepared.global_map, prepared.gather_source
    assert irradiance.precompute_stride(photons.count // 2) > 1  # (the case at hand)
    dim = dr.compress(photons.position.x > 0.05)  # the room lit through the door
    assert dr.width(dim) > 1000
    _, found = irradiance.nearest_photon(source.near_photons, source.near_grid,
                                         dr.gather(mi.Point3f, photons.position, dim),
                                         dr.gather(mi.Vector3f, photons.normal, dim),
                                         2 * source.lookup_radius, True)
    assert dr.count(found)[0] >= 0.95 * dr.width(dim)
    # Every precomputed photon holds an estimate (the sparse ones' from the odd half).
    assert bool(dr.all(dr.isfinite(mi.luminance(source.photons.irradiance))))
    assert dr.count(mi.luminance(source.photons.irradiance) > 0)[0] > 0.9 * source.photons.count
