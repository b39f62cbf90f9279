"""Photon emission from environment maps: the flux reaching a surface must match the
irradiance the map gives it, whatever the map's rotation (Mitsuba 3.9's own
``sample_emitter_ray`` tilts a rotated envmap's emission disk: 1.3-1.8x too bright;
``benchmarks/envmap_emission_check.py`` measures it)."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator.emission import sample_emitter_rays


def _flux_from_above(scene, n=1 << 18, seed=7):
    """Flux that emitted rays carry onto the top face of the unit square at the origin."""
    sampler = mi.PCG32(size=n, initstate=seed)
    u = [sampler.next_float32() for _ in range(5)]
    ray, weight, _ = sample_emitter_rays(scene, mi.Float(0.0), u[0], mi.Point2f(u[1], u[2]),
                                         mi.Point2f(u[3], u[4]))
    si = scene.ray_intersect(ray)
    from_above = si.is_valid() & (ray.d.y < 0)
    return float(dr.sum(dr.select(from_above, weight.x, 0.0))[0]) / n


@pytest.mark.parametrize("rotation", [0.0, 70.0, 135.0])
def test_uniform_envmap_irradiance_is_pi_for_any_rotation(rotation):
    scene = mi.load_dict({
        "type": "scene",
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(np.ones((16, 32, 3), np.float32)),
                "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], rotation)},
        "square": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(0.5)},
    })
    # A uniform sky of radiance 1 gives irradiance π; the square's area is 1. 2^18 rays:
    # ~0.5 % noise, so 2 % is a real error.
    assert _flux_from_above(scene) == pytest.approx(math.pi, rel=0.02)


def test_nan_envmap_gives_no_nan_rays():
    texels = np.ones((16, 32, 3), np.float32)
    texels[3, 5] = np.nan
    scene = mi.load_dict({"type": "scene",
                          "sky": {"type": "envmap", "bitmap": mi.Bitmap(texels)},
                          "square": {"type": "rectangle"}})
    sampler = mi.PCG32(size=4096, initstate=1)
    u = [sampler.next_float32() for _ in range(5)]
    ray, weight, _ = sample_emitter_rays(scene, mi.Float(0.0), u[0], mi.Point2f(u[1], u[2]),
                                         mi.Point2f(u[3], u[4]))
    assert np.isfinite(np.array(weight)).all() and np.isfinite(np.array(ray.o)).all()
