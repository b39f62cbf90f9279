"""Bright records as lights (:mod:`pmic_integrator.lights`): which records become lights,
the exactness of the density that the continuation's MIS weights use, and the noise
they remove in a room lit off the inside of a lampshade."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import kinds as sb
from pmic_integrator import cachefile, lights
from pmic_integrator.lights import RecordLights


def records(points, irradiance, reach=0.05):
    """Records at ``points`` (N × 3) with grey ``irradiance`` (N): RecordLights.select's
    arguments."""
    p = np.asarray(points, dtype=np.float32)
    e = np.asarray(irradiance, dtype=np.float32)
    return (mi.Point3f(*[mi.Float(p[:, i]) for i in range(3)]),
            dr.full(mi.Float, reach, len(p)),
            mi.Color3f(mi.Float(e), mi.Float(e), mi.Float(e)))


def floor_with_two_lamps():
    """A 20 × 20 grid of dim records (irradiance 1) and two clusters of 4 bright ones
    (1000 and 500), 2 apart."""
    g = np.linspace(-2, 2, 20)
    floor = np.array([(x, y, 0.0) for x in g for y in g])
    lamp_a = np.array([(0.5, 0.5, 1.0), (0.55, 0.5, 1.0), (0.5, 0.55, 1.0), (0.55, 0.55, 1.0)])
    lamp_b = lamp_a + np.array([-2.0, 0.0, 0.0])
    points = np.concatenate([floor, lamp_a, lamp_b])
    irradiance = np.concatenate([np.ones(len(floor)), np.full(4, 1000.0), np.full(4, 500.0)])
    return records(points, irradiance)


def test_bright_groups_become_spherical_lights():
    found = RecordLights.select(*floor_with_two_lamps())
    assert found.count == 2
    center = np.array(found.center).T
    # Power-weighted centres of the two groups, the brighter first.
    assert center[0] == pytest.approx([0.525, 0.525, 1.0], abs=1e-5)
    assert center[1] == pytest.approx([-1.475, 0.525, 1.0], abs=1e-5)
    # Bounding spheres of the records' disks: half the 0.05·√2 diagonal plus the reach.
    assert np.array(found.radius) == pytest.approx([0.025 * math.sqrt(2) + 0.05] * 2, rel=1e-5)
    assert np.array(found.power) == pytest.approx([4 * 1000 * 0.05 ** 2, 4 * 500 * 0.05 ** 2], rel=1e-5)


def test_no_lights_where_nothing_stands_out_or_holds_little_power():
    g = np.linspace(-2, 2, 20)
    floor = np.array([(x, y, 0.0) for x in g for y in g])
    # Evenly lit: nothing 50× the median.
    assert RecordLights.select(*records(floor, np.linspace(1, 40, len(floor)))) is None
    # One record 100× brighter but holding 100 / (399 + 100) = 20 % of the power
    # (under LIGHTS_MIN_SHARE): guiding's business, not a light.
    irradiance = np.ones(len(floor))
    irradiance[0] = 100.0
    assert RecordLights.select(*records(floor, irradiance)) is None
    assert RecordLights.select(*records(np.zeros((0, 3)), np.zeros(0))) is None


def query(count, x=(0.3, -0.2, 0.0)):
    return (mi.Point3f(*[dr.full(mi.Float, v, count) for v in x]),
            mi.Vector3f(0.0, 0.0, dr.ones(mi.Float, count)))


def lamps_seen_from_floor(count, seed):
    """The two lamps' lights, ``count`` queries at one floor point with their total
    weight, and a sampler of ``count`` lanes."""
    found = RecordLights.select(*floor_with_two_lamps())
    x, n = query(count)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, count)
    return found, x, n, found.total_weight(x, n), sampler


def test_density_integrates_to_one():
    found, x, n, total, sampler = lamps_seen_from_floor(1 << 20, seed=3)
    d = mi.warp.square_to_uniform_sphere(sampler.next_2d())
    integral = 4 * math.pi * float(dr.mean(found.pdf(x, n, total, d))[0])
    # Each cone holds (w_k / W) of the mass; their solid angles are ~0.03 sr of 4π, so
    # 2^20 uniform directions put ~2500 in them: ±2 % at 1σ.
    assert integral == pytest.approx(1.0, abs=0.06)


def test_samples_follow_the_density():
    """Sampled directions fall in each light's cone with probability w_k / W, and the
    density at every sampled direction is the cone's constant (the cones do not
    overlap here), so E[1/pdf] over samples is the solid angle of the cones."""
    found, x, n, total, sampler = lamps_seen_from_floor(1 << 16, seed=4)
    d = found.sample(x, n, total, sampler.next_1d(), sampler.next_2d())
    density = found.pdf(x, n, total, d)
    # Rounding puts ~1e-5 of the samples a hair outside their cone (density 0 there).
    assert float(dr.mean(mi.Float(dr.select(density > 0, 0.0, 1.0)))[0]) < 1e-4
    centers = np.array(found.center).T
    radii = np.array(found.radius)
    xp = np.array([0.3, -0.2, 0.0])
    dist = np.linalg.norm(centers - xp, axis=1)
    cos_max = np.sqrt(1 - (radii / dist) ** 2)
    axis = (centers - xp) / dist[:, None]
    dirs = np.array(d).T
    in_a = dirs @ axis[0] >= cos_max[0] - 1e-6
    # Selection probability of light A: w_A / W from the formula in the class docstring.
    sin_max = radii / dist
    w = np.array(found.power) * np.clip(axis[:, 2] + sin_max, 0, 1) / dist ** 2
    assert in_a.mean() == pytest.approx(w[0] / w.sum(), abs=0.01)
    solid_angle = float(np.sum(2 * math.pi * (1 - cos_max)))
    density = np.array(density)
    assert float(np.mean(1.0 / density[density > 0])) == pytest.approx(solid_angle, rel=1e-3)


def test_no_weight_from_inside_a_light_or_behind_the_surface():
    found = RecordLights.select(*floor_with_two_lamps())
    inside, n = query(1, x=(0.525, 0.525, 1.0))  # the centre of lamp A: only B counts
    to_b = np.array(found.center).T[1] - np.array([0.525, 0.525, 1.0])
    dist = np.linalg.norm(to_b)
    w_b = float(np.array(found.power)[1]) * (to_b[2] / dist + float(np.array(found.radius)[1]) / dist) / dist ** 2
    assert float(found.total_weight(inside, n)[0]) == pytest.approx(w_b, rel=1e-5)
    below, _ = query(1, x=(0.525, 0.525, 0.5))
    assert float(found.total_weight(below, -n)[0]) == 0.0  # facing away from both lamps


LAMP = {"type": "pmic", "global_photons": 200_000, "caustic_photons": 50_000, "gather_rays": 128}


def lamp_room_noise(spp=32, seeds=6):
    """Mean of the per-pixel variance over render seeds, relative to path's image (as
    relMSE: a firefly in a dark pixel counts as the eye sees it)."""
    scene = mi.load_dict(sb.lamp_room(size=(32, 24)))
    reference = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=1024))[..., :3]
    integrator = mi.load_dict(LAMP)
    images = np.stack([np.array(mi.render(scene, integrator=integrator, spp=spp, seed=s))
                       for s in range(seeds)])[..., :3]
    assert np.isfinite(images).all()
    noise = float(np.mean(np.var(images, 0, ddof=1) / (reference ** 2 + 1e-2)))
    return noise, integrator.prepared.index.lights


def test_lamp_shade_lights_cut_the_final_gathers_fireflies(monkeypatch):
    """The lamp room is lit off the inside of a shade (irradiance ~1000× the room's):
    cosine-sampled continuations met it rarely, carrying hundreds of times the pixel.
    Measured: relative noise 0.94 without the light, 0.073 with it (32 spp, 6 seeds)."""
    with_lights, found = lamp_room_noise()
    assert found is not None and found.count >= 1
    monkeypatch.setattr(lights, "LIGHT_CONTRAST", math.inf)
    without, none = lamp_room_noise()
    assert none is None
    assert with_lights < without / 4, (with_lights, without)


def test_lights_survive_a_cache_file(tmp_path):
    scene = mi.load_dict(sb.lamp_room(size=(8, 6)))
    integrator = mi.load_dict(LAMP)
    integrator.build_cache(scene)
    found = integrator.prepared.index.lights
    path = integrator.save_cache(tmp_path / "lamp.npz")
    key = integrator.prepared.key
    loaded = cachefile.load(path, scene, key[2], key[1]).index.lights
    assert loaded.count == found.count
    for name in ("center", "radius", "power"):
        assert np.array_equal(np.array(getattr(loaded, name)), np.array(getattr(found, name)))
