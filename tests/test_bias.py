"""Sources of bias found on real scenes, each isolated in a small scene and compared
with Mitsuba's ``path`` (mean luminance). Every test here failed before its fix; the
figure it had then is in its docstring.

Path means use 512-1024 spp at these tiny sizes: their own noise is ~0.3-0.5 %, well
under the thresholds (2-3 %).
"""
import math
import threading

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import kinds as sb

#: Default photon counts (at 50k the edge bias of density estimates alone is ~2 %).
SMALL = {"global_photons": 200_000, "caustic_photons": 50_000, "gather_rays": 128}
from pmic_integrator.metrics import REC709_LUMINANCE as LUMINANCE  # noqa: E402
#: Pixels brighter than this in path's image see an emitter (the scenes' surfaces stay
#: below 1): they and their neighbours (partly covered by the emitter: at 16 spp their
#: sampling moved the whole mean by ±5 % with the sampler's seed, for path as for pmic)
#: are left out of mean comparisons.
EMITTER_LUMINANCE = 1.0


def luminance(image):
    return float(np.mean(np.asarray(image)[..., :3] @ LUMINANCE))


def render(scene, spp, seed=0, **params):
    """pmic's image; ``seed`` is both the scene seed (photons, cache) and the render's."""
    integrator = mi.load_dict({"type": "pmic", **SMALL, "seed": seed, **params})
    image = np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed))
    assert np.isfinite(image).all()
    return image, integrator


def path_image(scene, spp=1024, **params):
    return np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "path", **params}), spp=spp))


def path_mean(scene, spp=1024, **params):
    return luminance(mi.render(scene, integrator=mi.load_dict({"type": "path", **params}), spp=spp))


#: What the spectral variants' sRGB store adds to a tolerance here (coloured walls'
#: bounced light rebuilt as a smooth spectrum: measured -0.5 % on a plastic Cornell box,
#: 0.982 against 0.987 in llvm_ad_rgb; a principled quadrant 0.976).
SPECTRAL_STORE = 0.01 if mi.is_spectral else 0.0


def ratio_to_path(scene_dict, spp=16, path_spp=1024, seeds=(0,), **params):
    """pmic's mean luminance over path's, on the pixels that do not see an emitter:
    at these sizes a light covers a few pixels whose anti-aliased edges, at 16 spp,
    move the whole image's mean by ~3 % (direct light alone did). With several
    ``seeds`` (each pmic's scene and render seed, see :func:`render`), the mean of
    their ratios to one path reference."""
    scene = mi.load_dict(scene_dict)
    lum_ref = path_image(scene, path_spp)[..., :3] @ LUMINANCE
    return float(np.mean([masked_ratio(render(scene, spp, seed=seed, **params)[0][..., :3] @ LUMINANCE,
                                       lum_ref) for seed in seeds]))


def masked_ratio(lum_img, lum_ref):
    """Mean over mean, leaving out pixels within one pixel of an emitter's image."""
    emitter = lum_ref > EMITTER_LUMINANCE
    near = emitter.copy()
    near[1:] |= emitter[:-1]
    near[:-1] |= emitter[1:]
    near[:, 1:] |= near[:, :-1].copy()
    near[:, :-1] |= near[:, 1:].copy()
    return float(lum_img[~near].mean() / lum_ref[~near].mean())


def test_back_face_of_a_twosided_floor_gets_indirect_light():
    """The diffuse response was evaluated with the outgoing direction at +z, which a
    ``twosided`` BSDF seen from its back returns as 0 (before: 0.043 vs path 0.070 on
    an upside-down floor)."""
    floor = {"type": "rectangle",
             "to_world": mi.ScalarTransform4f().translate([0, -1, 0]).rotate([1, 0, 0], 90),
             "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse",
                                                   "reflectance": {"type": "rgb", "value": [0.8] * 3}}}}
    assert ratio_to_path(sb.cornell(floor=floor)) == pytest.approx(1.0, abs=0.02)


def test_principled_is_not_counted_twice():
    """Mitsuba 3.9's ``principled`` ignores the lobe mask of its BSDFContext in eval
    and sample, so diffuse + non-diffuse counted it twice (before: +20 %)."""
    def principled(rgb, roughness):
        return {"type": "principled", "base_color": {"type": "rgb", "value": rgb}, "roughness": roughness}

    scene = sb.cornell(**{"large-box": {"bsdf": principled([0.8, 0.8, 0.8], 0.5)},
                          "small-box": {"bsdf": principled([0.8, 0.3, 0.3], 0.3)}})
    assert ratio_to_path(scene) == pytest.approx(1.0, abs=0.025)


@pytest.mark.parametrize("estimator", ["first_hit", "final_gather"])
def test_light_through_a_thin_principled_leaf_reaches_the_cache(estimator):
    """A ``principledthin`` leaf (diffuse transmission) hangs under the light. Gather
    rays that met it took its reflection only (its response to the irradiance on
    their side; the principled BSDFs ignore lobe masks, so the lobes cannot be taken
    apart) and lost what it transmits from the light above: the floor and the boxes
    under it came out 13-28 % dark (before: 0.84 of path with first_hit, 0.93 with
    final_gather).

    At 40 pixels a handful of records make the first-hit image, and its mean moves
    with the seed (0.972-1.038 over seeds 0-8, sd 0.025, mean 1.000; on an AVX-512
    machine seed 0 alone gave 0.99, on an AVX2 one 0.975): the mean over six seeds is
    tested (sd ~0.01) within 3 % of path; the final gather's within 1.5 % at one."""
    leaf = {"type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([0, 0.5, 0]).rotate([1, 0, 0], 90).scale(0.6),
            "bsdf": {"type": "principledthin", "base_color": {"type": "rgb", "value": [0.6, 0.8, 0.4]},
                     "diff_trans": 1.0, "roughness": 0.6}}
    seeds, tolerance = (range(6), 0.03) if estimator == "first_hit" else (range(1), 0.015)
    assert ratio_to_path(sb.cornell(size=40, leaf=leaf), spp=64, seeds=seeds, estimator=estimator) == \
        pytest.approx(1.0, abs=tolerance)


@pytest.mark.parametrize("roughness, metallic", [(0.5, 0.0), (0.3, 0.5)])
def test_a_principled_cornell_box_reads_the_cache_where_it_is_nearly_diffuse(roughness, metallic):
    """Mitsuba's ``principled`` ignores lobe masks, so its lobes cannot be taken apart
    and every vertex on it was traced whole: in a Cornell box all of principled (what
    Blender exports) no camera path read the cache (coverage 0 everywhere) and pmic
    was a path tracer at twice the cost per sample (0.30x path's speed). Behind a
    traced vertex, where the BSDF is nearly diffuse for the incident direction, it now
    reads the cache with its whole response; glossy metal stays traced. Each quadrant
    must stay within 2 % of path (reading everywhere: 3-8 % off at roughness 0.5,
    10-20 % with metallic 0.5)."""
    materials = {k: {"type": "principled", "roughness": roughness, "metallic": metallic,
                     "base_color": {"type": "rgb", "value": v}}
                 for k, v in (("white", [0.8] * 3), ("green", [0.1, 0.6, 0.1]), ("red", [0.6, 0.1, 0.1]))}
    scene = mi.load_dict(sb.cornell(size=32, **materials))
    image, _ = render(scene, 256, aovs="coverage")
    reference = path_image(scene, spp=8192)
    reads = image[..., 3].mean()
    if metallic == 0.0:
        assert reads > 0.05  # (before: 0)
    else:
        assert reads == 0.0
    lum_img, lum_ref = image[..., :3] @ LUMINANCE, reference[..., :3] @ LUMINANCE
    for rows in (slice(0, 16), slice(16, 32)):
        for cols in (slice(0, 16), slice(16, 32)):
            assert masked_ratio(lum_img[rows, cols], lum_ref[rows, cols]) == \
                pytest.approx(1.0, abs=0.02 + SPECTRAL_STORE)


@pytest.mark.parametrize("material", ["roughplastic", "plastic"])
def test_coated_walls_reflect_the_cosine_weighted_average(material):
    """The diffuse lobe of a coated material falls towards grazing angles (Fresnel);
    evaluated at the normal alone it overstated indirect light (before: +3 %)."""
    coat = {"type": material, "diffuse_reflectance": {"type": "rgb", "value": [0.8, 0.8, 0.8]}}
    scene = sb.cornell(floor={"bsdf": coat}, back={"bsdf": coat}, **{"large-box": {"bsdf": coat}})
    assert ratio_to_path(scene) == pytest.approx(1.0, abs=0.02 + SPECTRAL_STORE)


def test_sparse_photons_in_a_room_lit_through_a_door():
    """Precomputed irradiance counted the photon it sits on: +3/k with k photons per
    disc, large where photons are sparse (before: +23 % at lookup_size 8). At 8 photons
    per estimate one photon map's image moves by ~1.5 % from one photon seed to the
    next (over 10 seeds 1.002-1.009 of path's on average): the mean of four."""
    assert ratio_to_path(sb.two_rooms(size=(32, 24)), seeds=range(4), lookup_size=8) == \
        pytest.approx(1.0, abs=0.025 + SPECTRAL_STORE)  # (spectral: 1.028 measured)


def test_scene_size_counts_merged_meshes():
    """Mitsuba merges the lamp room's walls into a mesh whose bounding box is invalid,
    and ``scene.bbox()`` leaves it out: the scene was taken for 0.10 across instead of
    5.6, which capped records at 8 mm (60 000 of them, a 44 s cache stage, and the
    first-hit image 39 % dark)."""
    from pmic_integrator.pipeline import SceneInfo

    info = SceneInfo.of(mi.load_dict(sb.lamp_room()))
    assert info.diagonal == pytest.approx(float(np.linalg.norm([4.0, 3.0, 2.5])), rel=1e-4)


@pytest.mark.parametrize("estimator, spp", [
    ("first_hit", 32),
    # The final gather's camera bounce meets the bright shade: at 32 spp its mean
    # moved by ±5 % with the seed (0.90-1.05), at 128 spp 0.99.
    pytest.param("final_gather", 128, marks=pytest.mark.slow)])
def test_lamp_room_where_photons_cluster_in_the_shade(estimator, spp):
    """The lookup radius fits the 3/4 of the photons inside the lampshade; in the rest
    of the room gather hits found no photon within the search's reach and read zero
    (before: 0.936 of path, first-hit; see GatherSource). After: 0.980-0.991 over
    render seeds (its cache does not depend on them). The final gather, which reads
    the cache one bounce later, passed before too: it guards that estimator here.

    The shade's fireflies make both sides noisy: path at 1024 spp was 1.1 % brighter
    than at 16384, and over seeds 0-5 (against 16384 spp) the first-hit image ranged
    0.955-1.040 (mean 0.993), the final gather's 0.980-1.004 (mean 0.989); on an
    AVX2 machine seed 0 alone failed where it passed on an AVX-512 one. So: path at
    8192 spp, and the mean over a few seeds (sd of the mean ~0.013 and ~0.005)."""
    seeds = range(4) if estimator == "first_hit" else range(3)
    ratio = ratio_to_path(sb.lamp_room(size=(32, 24)), spp=spp, path_spp=8192, seeds=seeds,
                          estimator=estimator)
    assert ratio == pytest.approx(1.0, abs=0.025)


def test_sun_lights_all_of_a_merged_ground():
    """Mitsuba merges the ground and two boxes of one material into a mesh whose
    bbox() covers the boxes only; the sun's photons came from a disk round that box
    (before: first hit 0.904 of path, indirect light half of path's). After: 0.990."""
    from pmic_integrator.emission import emission_sphere

    scene = mi.load_dict(sb.sun_shelter())
    assert emission_sphere(scene)[1] >= float(np.linalg.norm([8.0, 1.1, 8.0])) / 2
    assert ratio_to_path(sb.sun_shelter(), spp=32, path_spp=1024, estimator="first_hit") == \
        pytest.approx(1.0, abs=0.025)


@pytest.mark.parametrize("estimator", ["first_hit", "final_gather"])
def test_shading_normals_weigh_light_as_path_does(estimator):
    """A floor whose vertex normals lean 50° towards a grazing strip light. Mitsuba's
    BSDFs weigh light by the cosine to the shading normal; photon flux lands by the
    geometric one. Before: photons stored the bare flux (first hit 0.63, final gather
    0.64 of path); with the photons corrected but records still gathered about the
    geometric normal, the final gather read 0.78 (its records hold direct light by
    the geometric cosine). After: 1.007 / 1.010."""
    ratio = ratio_to_path(sb.bent_normal_room(), spp=32, path_spp=1024, estimator=estimator)
    assert ratio == pytest.approx(1.0, abs=0.025)


def test_shading_normal_factors_are_the_cosine_ratios():
    """Exact values on one hit: a plane z = 0 whose shading normal leans 60° towards
    +x, light arriving from 80° off the geometric normal (in the x-z plane), leaving
    straight up along the geometric normal."""
    from pmic_integrator.photons import shading_normal_factors

    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.n = mi.Vector3f(0, 0, 1)
    tilt, incidence = np.radians(60.0), np.radians(80.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(float(np.sin(tilt)), 0.0, float(np.cos(tilt))))
    to_light = mi.Vector3f(float(np.sin(incidence)), 0.0, float(np.cos(incidence)))
    wo_local = si.to_local(mi.Vector3f(0, 0, 1))
    arrival, scattering = shading_normal_factors(si, mi.Vector3f(0, 0, 1), to_light, wo_local)
    cos_s_in, cos_g_in = np.cos(incidence - tilt), np.cos(incidence)
    assert arrival[0] == pytest.approx(cos_s_in / cos_g_in, rel=1e-5)
    assert scattering[0] == pytest.approx(cos_s_in / cos_g_in * 1.0 / np.cos(tilt), rel=1e-5)
    # Light below the shading hemisphere is not reflected at all; flat: exactly 1.
    below = mi.Vector3f(-float(np.sin(incidence)), 0.0, float(np.cos(incidence)))
    assert shading_normal_factors(si, mi.Vector3f(0, 0, 1), below)[0] == 0.0
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    assert shading_normal_factors(si, mi.Vector3f(0, 0, 1), to_light)[0] == 1.0


def test_thin_wall_keeps_the_dark_side_dark():
    """A 2 mm wall closes the room; the light is on the other side, so path is black.
    Gather rays read the lit side's photons and the lit side's records reached across
    (before: mean 0.010, brightest pixel 0.22, against a lit side of ~1.4)."""
    scene = mi.load_dict(sb.thin_wall_room())
    image, _ = render(scene, 8)
    assert path_mean(scene, 64) == 0.0
    assert image.max() < 1e-3, image.max()


def test_closed_box_standing_on_a_floor_stays_dark_inside():
    """The camera inside a closed box standing on a floor under a sky, where path is
    black. A photon stored at the foot of the box's wall lies on the wall's plane (within
    rounding of either side), and the shadow ray to it from inside, stopped just short
    of it, passed: its light was read inside (before: mean 7.1e-5, brightest pixel
    0.014 at scene seed 0; 3.7e-4 in the random room where it was found)."""
    scene = mi.load_dict(sb.closed_box_on_floor())
    assert path_mean(scene, 64) == 0.0
    image = mi.render(scene, integrator=mi.load_dict({"type": "pmic", "seed": 0}), spp=16, seed=0)
    assert np.array(image).max() < 1e-3, np.array(image).max()


@pytest.mark.rgb_only('traces rays built without wavelengths')
def test_gather_rays_meeting_a_glossy_metal_principled_floor_follow_its_reflection():
    """Gather rays from a wall that meet a glossy metallic principled floor carry what
    Mitsuba's path carries along the same rays, within 10 %. Such a floor (its lobes
    cannot be taken apart) reflected the photons' irradiance there as if lit evenly:
    18 % too bright here, 76 % in the random room where it was found (whose first-hit
    image came out 12 % bright over 12 seeds). Now a ray goes on through a sample of
    the whole BSDF where it is far from diffuse (gather.GATHER_WHOLE_PEAK_RATIO)."""
    from pmic_integrator import _jit, gather, pipeline
    from pmic_integrator.settings import Settings

    scene = mi.load_dict(sb.glossy_metal_floor_box())
    props = mi.Properties()
    props["global_photons"] = 100_000
    source = pipeline.prepare(scene, Settings.parse(props)).gather_source
    rng = np.random.default_rng(0)
    count = 1 << 18
    origin = np.stack([rng.uniform(-0.9, 0.9, count), rng.uniform(0.3, 1.7, count),
                       np.full(count, -0.999)]).astype(np.float32)
    u = mi.Point2f(rng.random(count).astype(np.float32), rng.random(count).astype(np.float32))
    ray = mi.Ray3f(mi.Point3f(origin), mi.Frame3f(mi.Vector3f(0, 0, 1)).to_world(
        mi.warp.square_to_cosine_hemisphere(u)))
    hit = scene.ray_intersect(ray)
    on_floor = np.array(hit.is_valid()) & (np.abs(np.array(hit.p.y)) < 1e-3)
    gathered, _ = gather.gather_radiance(scene, source, ray, _jit.rng(count, 6, stream=1))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(6, count)
    traced, _, _ = mi.load_dict({"type": "path"}).sample(scene, sampler, mi.RayDifferential3f(ray),
                                                         None, True)
    ratio = np.array(gathered).mean(0)[on_floor].mean() / np.array(traced).mean(0)[on_floor].mean()
    assert on_floor.mean() > 0.1
    assert ratio == pytest.approx(1.0, abs=0.1)


def test_thin_wall_lit_side_is_right():
    assert ratio_to_path(sb.thin_wall_room(camera_on_lit_side=True), path_spp=512) == \
        pytest.approx(1.0, abs=0.03)


@pytest.mark.parametrize("rotate", [False, True])
def test_envmap_exterior(rotate):
    """Mitsuba 3.9 emits a rotated envmap's photons from a disk tilted against their
    direction (before: indirect light 1.6-1.9x too bright); see emission.py."""
    assert ratio_to_path(sb.envmap_exterior(rotate), path_spp=1024) == pytest.approx(1.0, abs=0.02)


@pytest.mark.rgb_only("Mitsuba refuses a NaN emitter's spectrum in spectral variants ('no probability mass')")
def test_nan_emitter_costs_only_its_own_light():
    """One emitter with NaN radiance beside a normal one: the NaN samples must be
    dropped, not the whole camera sample (before: 16 % of path's image)."""
    nan_light = {"type": "sphere", "center": [0.5, 0.5, 0.3], "radius": 0.1,
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [float("nan")] * 3}}}
    scene_nan = mi.load_dict(sb.cornell(nan_light=nan_light))
    image, _ = render(scene_nan, 16)
    expected = path_image(mi.load_dict(sb.cornell()), 1024)
    assert masked_ratio(image[..., :3] @ LUMINANCE, expected[..., :3] @ LUMINANCE) == \
        pytest.approx(1.0, abs=0.03)


@pytest.mark.rgb_only("Mitsuba refuses Inf texels' spectra in spectral variants")
def test_inf_texels_touch_only_their_samples():
    """A texture with Inf and NaN texels on the back wall: only the samples reading them
    are lost (before: luminance 0.0 for Inf). Compared with path on the same texture
    with those texels set to zero."""
    texels = np.full((16, 16, 3), 0.7, np.float32)
    bad = texels.copy()
    bad[3, 4] = np.inf
    bad[9, 11] = np.nan

    def wall(values):
        return {"bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(values),
                                                            "raw": True, "filter_type": "nearest"}}}

    zeroed = texels.copy()
    zeroed[3, 4] = zeroed[9, 11] = 0.0
    image, _ = render(mi.load_dict(sb.cornell(back=wall(bad))), 16)
    expected = path_image(mi.load_dict(sb.cornell(back=wall(zeroed))), 1024)
    assert masked_ratio(image[..., :3] @ LUMINANCE, expected[..., :3] @ LUMINANCE) == \
        pytest.approx(1.0, abs=0.03)


def test_hidden_emitter_shows_what_is_behind_it():
    """With hide_emitters, a light in front of a red wall must show the wall, as path
    does (before: the light's own black BSDF, blue-black)."""
    light = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -0.5]).scale(0.3),
             "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5, 5, 5]}}}
    scene = mi.load_dict(sb.cornell(front_light=light))
    image, _ = render(scene, 32, hide_emitters=True)
    reference = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "hide_emitters": True}),
                                   spp=512))
    centre = (slice(13, 19), slice(13, 19))  # where the hidden light is
    got, want = image[centre].mean((0, 1)), reference[centre].mean((0, 1))
    np.testing.assert_allclose(got, want, rtol=0.08, atol=0.01)


def test_one_integrator_two_threads():
    """Per-render state lived on the integrator: two threads rendering with one object
    gave different images (largest pixel difference 0.087)."""
    scene = mi.load_dict(sb.cornell(size=24))
    integrator = mi.load_dict({"type": "pmic", **SMALL})
    alone = np.array(mi.render(scene, integrator=integrator, spp=4, seed=3))
    results = [None, None]

    def work(k):
        results[k] = np.array(mi.render(scene, integrator=integrator, spp=4, seed=3))

    threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for image in results:
        np.testing.assert_array_equal(image, alone)


def test_failed_build_is_retried(monkeypatch):
    """A build that fails must leave nothing behind: the next render rebuilds (before:
    0 records and every shading point fell back to the photon map)."""
    from pmic_integrator import pipeline as module

    scene = mi.load_dict(sb.cornell(size=16))
    integrator = mi.load_dict({"type": "pmic", **SMALL})
    real = module.precompute_irradiance
    calls = {"n": 0}

    def failing_once(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("simulated failure")
        return real(*args, **kwargs)

    monkeypatch.setattr(module, "precompute_irradiance", failing_once)
    with pytest.raises(RuntimeError):  # mi.render wraps it: "error while performing ..."
        mi.render(scene, integrator=integrator, spp=2)
    assert calls["n"] == 1
    image = np.array(mi.render(scene, integrator=integrator, spp=2))
    # (A rebuilt cache leaves at most a stray gather hit uncovered, out of 512 camera
    # samples; without the rebuild every one of them fell back.)
    assert integrator.stats["records"] > 0 and integrator.stats["shading_points_fallback"] <= 5
    assert np.isfinite(image).all() and image.mean() > 0.05
    dr.sync_thread()


def test_sun_shadows_are_not_smeared_by_records():
    """The final gather's records held the sun's direct light too, and interpolated it
    across the sharp edges of its shadows: the ground round a shelter's shadow (and a
    sunlit patch's surroundings in a room lit through a window: 11-15 % too bright
    over its floor) read light that is not there. Before: 1.0076, 1.0119, 1.0086 of
    path over cache seeds 0-2. After (records hold no delta light's direct light; the
    camera path samples it where it reads the cache): 0.9992, 0.9998, 0.9993."""
    scene = mi.load_dict(sb.sun_shelter())
    reference = path_image(scene, spp=2048)[..., :3] @ LUMINANCE
    image, _ = render(scene, 32, estimator="final_gather")
    assert masked_ratio(image[..., :3] @ LUMINANCE, reference) == pytest.approx(1.0, abs=0.005)


def test_light_through_a_rough_plastic_is_counted_once_by_the_caustic_map_or_the_path():
    """Sun -> rough plastic floor -> wall: the caustic map holds what came through the
    floor's glossy lobe, the camera path what came through its diffuse lobe. Mitsuba
    samples the whole BSDF and weighs each sample by f_all / p_all whichever lobe it
    took, so photons that took the glossy lobe carried part of the diffuse lobe's light
    and the camera path, leaving out what its glossy samples met, kept part of the
    glossy lobe's: the light bounced once came out 1.36 % dark here (1 % bright in
    the window-lit bundled room). Lobes sampled apart (bsdfs.sample_lobes_apart):
    1.0001. The bounce alone: max_depth 3 minus max_depth 2, each of the two seeds."""
    scene = mi.load_dict(sb.sunlit_rough_floor())

    def bounce(kind, spp, seed):
        spec = {"type": kind, **(SMALL if kind == "pmic" else {})}
        if kind == "pmic":
            spec["seed"] = seed
        means = [np.array(mi.render(scene, integrator=mi.load_dict({**spec, "max_depth": depth}),
                                    spp=spp, seed=seed)).mean() for depth in (3, 2)]
        return means[0] - means[1]

    path = np.mean([bounce("path", 1024, 100 + s) for s in range(2)])
    pmic = np.mean([bounce("pmic", 256, s) for s in range(2)])
    assert pmic / path == pytest.approx(1.0, abs=0.006)


@pytest.mark.parametrize("max_depth", [4, 5])
def test_a_bounded_max_depth_bounds_the_light_read_from_the_cache(max_depth):
    """The records' gather rays read irradiance precomputed at the photons for paths
    read from the camera's first diffuse vertex (max_depth - 2 photon interactions);
    the final gather reads the records one bounce later, where that is one bounce too
    many: Cornell box at max_depth 4 1.029 of path's (5: 1.017; here, on the pixels
    that see no light, 1.053-1.058 and 1.028-1.034), a window-lit room 1.071. Now the records hold what is allowed where they are read
    (Settings.records_read_depth), and deeper vertices are traced on (final gather)
    or read the photon map by depth (first hit)."""
    scene = mi.load_dict(sb.cornell(32))
    image, _ = render(scene, 64, max_depth=max_depth)
    reference = path_image(scene, spp=2048, max_depth=max_depth)
    ratio = masked_ratio(image[..., :3] @ LUMINANCE, reference[..., :3] @ LUMINANCE)
    assert ratio == pytest.approx(1.0, abs=0.015)  # after: 0.993-1.000


def _slot_records_over_path(seed: int) -> float:
    """Irradiance the records between two white blocks 0.1 apart hold (their own and
    their direct light), over what `path` traces there (1024 cosine-distributed rays at
    each record), for photon and render seed ``seed``. (Under an open sky records
    gather a quarter of gather_rays, pipeline.FIRST_GATHER_SHARE: 512 gives them 128.)"""
    scene = mi.load_dict(sb.slot(0.1))
    integrator = mi.load_dict({"type": "pmic", "global_photons": 50_000, "gather_rays": 512,
                               "seed": seed})
    mi.render(scene, integrator=integrator, spp=1)
    index = integrator._prepared.index
    records = index.records
    position = np.array(records.position).T
    inside = np.nonzero((np.abs(position[:, 0]) < 0.051) & (position[:, 2] > 0.02) &
                        (position[:, 2] < 0.98) & (np.abs(position[:, 1]) < 0.45))[0]
    assert len(inside) > 20
    rays_per_record = 1024
    lane = dr.arange(mi.UInt32, len(inside) * rays_per_record)
    owner = dr.gather(mi.UInt32, mi.UInt32(inside.astype(np.uint32)), lane // rays_per_record)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7 + seed, len(inside) * rays_per_record)
    normal = dr.gather(mi.Vector3f, records.shading_normal, owner)
    origin = dr.gather(mi.Point3f, records.position, owner) + normal * 1e-4
    direction = mi.Frame3f(normal).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d()))
    radiance, _, _ = mi.load_dict({"type": "path"}).sample(
        scene, sampler, mi.RayDifferential3f(mi.Ray3f(origin, direction)))
    truth = np.array(mi.luminance(mi.Color3f(radiance))).reshape(len(inside), -1).mean(1) * np.pi
    held = np.array(mi.luminance(mi.Color3f(records.irradiance + index.direct)))[inside]
    return float(held.sum() / truth.sum())


@pytest.mark.rgb_only('traces path.sample on rays built without wavelengths')
def test_records_in_a_narrow_slot_hold_its_light():
    """Records between two white blocks 0.1 apart (a lookup radius is 0.14): their
    gather rays meet the slot's other wall a hand's width off, where the photons'
    estimate, a disc wider than the slot, is far off. Two fixes answer it, either
    enough here: gather hits closer than NEAR_HIT_LOOKUPS lookup radii are bounced on,
    and the photons' estimates are scaled by the part of their disc on the surface
    (boundary.py). Over photon seeds 0-7 the records hold 1.007 of `path`'s irradiance
    (0.996 without the near-hit bounces, 0.990 without the probes, **0.960 without
    both**).

    One seed's ratio moves ±6 % (0.949-1.064: the few photons that enter the slot), so
    the test takes the mean of eight. (It took seeds 0 and 1 alone before, which passed
    or failed by their luck: seed 2 gives 0.949 with both fixes.)"""
    ratios = [_slot_records_over_path(seed) for seed in range(8)]
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.02)  # 1.007


@pytest.mark.parametrize("estimator, tolerance", [("first_hit", 0.025), ("final_gather", 0.035)])
def test_normal_mapped_walls_reflect_the_cache_at_their_tilted_response(estimator, tolerance):
    """Walls, floor and ceiling under a ``normalmap`` that leans their normal 30° along
    the bitangent. Where a path reads the cache, the diffuse response (1/π ∫ f cos dω)
    was a four-direction quadrature with one azimuth per level, which read such a
    leaning lobe as 0.72 of its value (``tests/test_bsdfs.py``), and the irradiance
    was read about the surface's normal: the box came out 12 % dark (0.88 of path with
    either estimator). Now first_hit 0.984-0.990, final_gather 0.975-0.984 (seeds
    0-2; 0.963-0.971 before the records' direct light had a rotational gradient to
    follow the lean). Real normal maps lean both ways (a wavy one: 0.997)."""
    texel = (0.5 * np.array([0.0, math.sin(math.radians(30)), math.cos(math.radians(30))]) + 0.5)
    white = {"type": "normalmap", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8] * 3}},
             "normalmap": {"type": "bitmap", "raw": True,
                           "bitmap": mi.Bitmap(np.tile(texel.astype(np.float32), (4, 4, 1)))}}
    assert ratio_to_path(sb.cornell(size=32, white=white), spp=32, path_spp=2048, seeds=(0, 1),
                         estimator=estimator) == pytest.approx(1.0, abs=tolerance)


def test_a_room_on_a_vast_sunlit_ground_is_as_bright_as_path():
    """The classroom kind (an 8 × 3 × 6 m room lit by a sun and a sky through its
    windows, on a ground 220 m wide), at pmic's default photon counts. Its sky and sun
    shot their photons across the whole ground: a few dozen of 200 000 entered the
    room, the lookup radius was set by the ground's (2.2 m) and so were the records
    (12 in the room, each wider than it). The room came out 1.016 of `path`'s mean
    over photon seeds 0-4 (0.999-1.049 from seed to seed). Three quarters of those rays
    now cross the building and the ground beside it (emission.focus_box): 0.995
    (0.986-1.012). Over seeds 0-15 (path at 16384 spp): 1.014 ± 0.007 before, 1.002 ±
    0.004 after; the seed-to-seed deviation 2.8 % → 1.6 %. Half at that focus and most
    of the rest at rings round it (emission.focus_rings), the lookup radius from the
    focus's photons: 0.994 (0.982-1.006)."""
    from pmic_integrator import kinds

    ratio = ratio_to_path(kinds.sunlit_classroom(size=(32, 18)), spp=32, path_spp=8192,
                          seeds=range(5), global_photons=200_000, caustic_photons=100_000,
                          gather_rays=256)
    assert ratio == pytest.approx(1.0, abs=0.01 + SPECTRAL_STORE)
