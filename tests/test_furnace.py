"""A closed furnace with an analytic answer.

Inside a closed sphere whose inner surface emits radiance Le and reflects diffusely
with albedo ρ, radiance is Le / (1 − ρ) everywhere and irradiance is π Le / (1 − ρ).
The test runs at three scene scales: nothing may depend on the scene's units.
"""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator.hashgrid import PointGrid
from pmic_integrator.irradiance import estimate_irradiance, lookup_radius

RHO = 0.5
LE = 1.0
RADIANCE = LE / (1 - RHO)


def furnace(scale=1.0, resolution=16):
    return mi.load_dict({
        "type": "scene",
        "sphere": {
            "type": "sphere", "radius": scale, "flip_normals": True,
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [RHO] * 3}},
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [LE] * 3}},
        },
        "sensor": {
            "type": "perspective", "fov": 60, "near_clip": 1e-3 * scale,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                     "rfilter": {"type": "box"}},
        },
    })


def test_photon_density_estimate_gives_analytic_irradiance():
    scene = furnace()
    integrator = mi.load_dict({"type": "pmic", "global_photons": 200_000, "method": "photon_map"})
    mi.render(scene, integrator=integrator, spp=1)
    photons = integrator._prepared.global_map
    assert 200_000 <= photons.count < 200_000 + 64  # whole paths
    radius = lookup_radius(4 * math.pi, photons.count, 64)
    grid = PointGrid.build(photons.position, radius)
    # Query at points that are not photons (an estimate at a photon counts itself).
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    e = np.array(estimate_irradiance(photons, grid, mi.Point3f(d.T), mi.Vector3f(-d.T), radius))
    assert abs(e.mean() / (math.pi * RADIANCE) - 1) < 0.02


@pytest.mark.parametrize("method", ["pmic", "photon_map", "irradiance_cache"])
@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_furnace_radiance_is_exact_at_any_scale(method, scale):
    integrator = mi.load_dict({"type": "pmic", "method": method, "global_photons": 100_000,
                               "gather_rays": 128})
    image = np.array(mi.render(furnace(scale), integrator=integrator, spp=4))
    assert np.isfinite(image).all()
    assert abs(image.mean() / RADIANCE - 1) < 0.02
    # Radiance is uniform: no pixel may stray far (noise only). (In a spectral variant
    # each pixel's colour comes from 16 wavelengths, a noise of its own: 0.8.)
    if not mi.is_spectral:
        assert np.abs(image / RADIANCE - 1).max() < 0.25


@pytest.mark.rgb_only("traces rays built without wavelengths")
@pytest.mark.parametrize("traced", [True, False])
def test_lookups_no_photon_answers_are_answered_by_a_traced_bounce(monkeypatch, traced):
    """A record's gather ray whose hit no photon answers (none near, or the nearest
    hidden across a wall) traces one more bounce (gather.TRACE_UNANSWERED): E = π L
    from one cosine ray that counts the emission it meets and reads the photons where
    it lands. Here every lookup of the batch on the x > 0 half of the furnace is
    hidden (the traced bounces' own lookups are not): the rays must still carry
    ρ L = 1, as every photon answered; reading 0 there they carried 0.5."""
    from pmic_integrator import _jit, gather, pipeline
    from pmic_integrator.settings import Settings

    scene = furnace()
    props = mi.Properties()
    props["global_photons"] = 100_000
    source = pipeline.prepare(scene, Settings.parse(props)).gather_source
    original = gather.GatherSource._visible

    def half_hidden(self, scene, p, n, position, found):
        seen = original(self, scene, p, n, position, found)
        return seen if dr.flag(dr.JitFlag.SymbolicScope) else seen & (p.x <= 0)

    monkeypatch.setattr(gather.GatherSource, "_visible", half_hidden)
    monkeypatch.setattr(gather, "TRACE_UNANSWERED", traced)
    count = 1 << 16
    rng = np.random.default_rng(3)
    origin = mi.Point3f(*(rng.uniform(-0.3, 0.3, (3, count)).astype(np.float32)))
    direction = mi.warp.square_to_uniform_sphere(mi.Point2f(*(rng.random((2, count)).astype(np.float32))))
    radiance, _ = gather.gather_radiance(scene, source, mi.Ray3f(origin, direction), _jit.rng(count, 1))
    mean = float(np.mean(np.array(radiance)))
    if traced:
        assert mean == pytest.approx(RHO * RADIANCE, rel=0.02)
    else:
        assert mean == pytest.approx(0.5 * RHO * RADIANCE, rel=0.05)  # (what it was)
