"""Images of the bundled scenes against their path-traced references (128², see
scenes/references/README.md for how they were made).

Thresholds (relMSE = mean((img − ref)² / (ref² + 1e-2))) were set from measured values
with a margin for other seeds; the measured figures are in the README.
"""
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import metrics, scenes

SPP = 64  # the scenes' own default sample count

#: The configurations tested: pmic's default (final gather), the paper's first-hit
#: interpolation, and the two baselines.
CONFIGS = {
    "pmic": {"method": "pmic", "estimator": "final_gather"},
    "pmic_first_hit": {"method": "pmic", "estimator": "first_hit"},
    "irradiance_cache": {"method": "irradiance_cache"},
    "photon_map": {"method": "photon_map"},
}
#: Largest relMSE allowed per (configuration, scene) at default settings and 64 spp.
#: The final gather's error is noise (it falls as 1/spp), first-hit's is mostly a
#: floor of blotches. With guiding the final gather measured 1.5e-3 on cornell_box and
#: 5.4e-3 on indirect_room (2.6e-3 and 1.7e-2 without: those thresholds fail then).
#: exterior_envmap's is mostly fireflies: the sun's caustic off the plastic ball onto
#: the ground, path-traced (too few caustic photons for a map). Which seed draws them
#: decides: 3.0-4.7e-3 over render seeds 0-2; 1.1-2.1e-2 at 16 spp over seeds 0-7,
#: mean 1.42e-2 with coat rays and 1.47e-2 without.
THRESHOLDS = {
    "pmic": {"cornell_box": 2.2e-3, "cornell_caustics": 4e-3, "indirect_room": 8e-3,
             "exterior_envmap": 5.5e-3, "interior_window": 1.2e-2},
    "pmic_first_hit": {"cornell_box": 2e-3, "cornell_caustics": 2e-3, "indirect_room": 2e-3,
                       "exterior_envmap": 5e-3, "interior_window": 1.2e-2},
    "irradiance_cache": {"cornell_box": 3e-3, "cornell_caustics": 3e-3, "indirect_room": 4e-3,
                         "exterior_envmap": 5e-3, "interior_window": 1.2e-2},
    "photon_map": {"cornell_box": 8e-3, "cornell_caustics": 8e-3, "indirect_room": 2e-2,
                   "exterior_envmap": 7e-3, "interior_window": 0.12},
}
#: Mean luminance must be within this of the reference's: 1 % for pmic on the exterior
#: (measured 0.9993 final gather), 2 % otherwise, and 2.5 % on interior_window, whose
#: photon maps decide the whole room's bounced light. Over cache seeds 0-5 the final
#: gather measured 1.009, 1.003, 0.987, 0.995, 0.996, 0.995 and first-hit 1.006, 1.009,
#: 1.001, 1.005, 0.999, 0.995 (before photons on the dark side of its one-sided walls
#: were left out, 95 % of the map lay outside the room: seeds 0-2 gave 0.999, 1.014,
#: 0.985 and 1.026, 0.991, 0.988); and the sun shines through a glass sphere, a caustic
#: that path (so the reference) cannot carry and the caustic map does.
LUMINANCE_TOLERANCE = {("pmic", "exterior_envmap"): 0.01, ("pmic", "interior_window"): 0.025,
                       ("pmic_first_hit", "exterior_envmap"): 0.01,
                       ("pmic_first_hit", "interior_window"): 0.025,
                       ("irradiance_cache", "interior_window"): 0.025}


def render(name, spp=SPP, seed=0, **params):
    scene = scenes.load_scene(name, resolution=128, spp=spp)
    integrator = mi.load_dict({"type": "pmic", **params})
    image = np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed))
    return image, integrator


@pytest.mark.rgb_only('the references were rendered with path in llvm_ad_rgb (spectral path renders other colours)')
@pytest.mark.parametrize("config", list(THRESHOLDS))
@pytest.mark.parametrize("name", scenes.SCENES)
def test_image_matches_reference(name, config):
    image, integrator = render(name, **CONFIGS[config])
    reference = scenes.load_reference(name)
    assert np.isfinite(image).all()
    error = metrics.rel_mse(image, reference)
    assert error <= THRESHOLDS[config][name], f"{config} on {name}: relMSE {error:.2e}"
    tolerance = LUMINANCE_TOLERANCE.get((config, name), 0.02)
    assert abs(metrics.luminance_ratio(image, reference) - 1) < tolerance
    if config.startswith("pmic"):
        assert integrator.stats["records"] > 0
        if name == "cornell_caustics":
            assert integrator.stats["photons_caustic"] > 0


@pytest.mark.parametrize("param,coarse,fine", [
    ("global_photons", 20_000, 400_000),
    ("gather_rays", 32, 1024),
    pytest.param("max_error", 1.0, 0.1, marks=pytest.mark.slow),  # 60 s: many records at a = 0.1
])
def test_error_falls_as_quality_grows(param, coarse, fine):
    # The same render seed gives both images the same camera samples (the same
    # direct-light noise), so the difference comes from the cache alone.
    reference = scenes.load_reference("cornell_box")
    # First-hit interpolation: the cache's error is seen directly, not behind a gather.
    errors = [metrics.rel_mse(render("cornell_box", spp=32, estimator="first_hit",
                                     **{param: value})[0], reference)
              for value in (coarse, fine)]
    # max_error 1.0 -> 0.1 measured 8.5e-4 -> 7.9e-4: at 32 spp the direct light's
    # noise, the same in both, is most of the error, so the cache's gain shows as 7 %.
    factor = 0.95 if param == "max_error" else 0.9
    assert errors[1] < factor * errors[0], f"{param}: {errors}"
