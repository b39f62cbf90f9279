"""AOVs from pmic, denoising as a post-process, the final-gather estimator, and the image
metrics that judge them (FLIP, low-frequency error)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import pmic_integrator
from pmic_integrator import metrics, scenes
from pmic_integrator.settings import AOVS

from pmic_integrator.kinds import SMALL_PMIC as SMALL, pmic_cornell as cornell


# -------------------------------------------------------------------------------------
# Parameters
# -------------------------------------------------------------------------------------
def test_aov_names_follow_the_parameter():
    all_names = mi.load_dict({"type": "pmic", "aovs": "all"}).aov_names()
    assert all_names == [c for a in AOVS for c in AOVS[a]] and len(all_names) == 16
    # Order is the table's, whatever order they are asked in.
    some = mi.load_dict({"type": "pmic", "aovs": "normal, albedo"}).aov_names()
    assert some == ["albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z"]
    assert mi.load_dict({"type": "pmic"}).aov_names() == []


@pytest.mark.parametrize("param,value", [("aovs", "albedo,depth"), ("aovs", "ALL"),
                                         ("estimator", "gather"), ("estimator", "")])
def test_bad_aov_or_estimator_is_refused_by_name(param, value):
    with pytest.raises(Exception) as err:
        mi.load_dict({"type": "pmic", param: value})
    text = str(err.value) + str(getattr(err.value, "__cause__", ""))
    assert f"'{param}'" in text and repr(value) in text


# -------------------------------------------------------------------------------------
# AOVs
# -------------------------------------------------------------------------------------
@pytest.mark.rgb_only("Mitsuba's aov integrator projects albedo under illuminant E in spectral variants (a wall of sRGB 0.886, 0.699, 0.666 reads 1.05, 0.66, 0.61); pmic's is under D65, the wall's own sRGB")
def test_guides_equal_mitsubas_aov_integrator():
    """pmic's albedo and normal are exactly what Mitsuba's aov integrator gives path,
    so pmic + denoiser and path + denoiser are compared with the same guides."""
    scene = mi.load_dict(cornell())
    pmic = mi.load_dict({"type": "pmic", **SMALL, "aovs": "albedo,normal"})
    ours = np.array(mi.render(scene, integrator=pmic, spp=4))
    theirs = np.array(mi.render(scene, integrator=mi.load_dict(
        {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal", "integrator": {"type": "path"}}), spp=4))
    assert ours.shape == (32, 32, 9) and theirs.shape == (32, 32, 9)
    assert np.array_equal(ours[..., 3:9], theirs[..., 3:9])
    assert ours[..., 3:6].max() > 0.3  # not trivially zero


def test_radiance_parts_add_up_to_the_image():
    """direct + indirect + caustic is the image, on a scene with all three."""
    integrator = {"type": "pmic", **SMALL, "aovs": "direct,indirect,caustic,coverage"}
    scene = scenes.load_scene("cornell_caustics", 32, 4, integrator)
    image = np.array(mi.render(scene, spp=4))
    parts = pmic_integrator.split_channels(image, scene.integrator())
    assert set(parts) == {"color", "direct", "indirect", "caustic", "coverage"}
    total = parts["direct"] + parts["indirect"] + parts["caustic"]
    assert np.allclose(total, parts["color"], rtol=1e-4, atol=1e-5)
    for name in ("direct", "indirect", "caustic"):
        assert parts[name].mean() > 1e-3, name  # each part is really there
        # (Spectral variants: one pixel's sRGB, from a few wavelengths, may fall outside
        # the gamut, as path's do; its channels' means may not.)
        lowest = parts[name].mean(axis=(0, 1)).min() if mi.is_spectral else parts[name].min()
        assert lowest >= 0.0
    # A fraction of each pixel's samples (averaged by the film).
    assert 0.0 <= parts["coverage"].min() and parts["coverage"].max() <= 1.0
    assert parts["coverage"].mean() > 0.3


@pytest.mark.rgb_only("compares bit for bit with Mitsuba's aov integrator's albedo (see test_guides_equal_mitsubas_aov_integrator)")
def test_aovs_inside_mitsubas_aov_integrator():
    scene = mi.load_dict(cornell())
    nested = mi.load_dict({"type": "aov", "aovs": "albedo:albedo",
                           "integrator": {"type": "pmic", **SMALL, "aovs": "albedo"}})
    image = np.array(mi.render(scene, integrator=nested, spp=4))
    assert np.isfinite(image).all() and image.shape[2] > 6
    # Mitsuba's own albedo is the last 3 channels; pmic's copy is among the others.
    theirs = image[..., -3:]
    assert any(np.array_equal(image[..., c:c + 3], theirs) for c in range(3, image.shape[2] - 3))


# -------------------------------------------------------------------------------------
# Denoising
# -------------------------------------------------------------------------------------
@pytest.mark.rgb_only('its reference was rendered in llvm_ad_rgb')
def test_denoise_reduces_the_error_of_a_noisy_render():
    reference = scenes.load_reference("cornell_box", 128)
    scene = scenes.load_scene("cornell_box", 128, 2)
    guided = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal",
                           "integrator": {"type": "path"}})
    image = np.array(mi.render(scene, integrator=guided, spp=2))
    noisy = image[..., :3]
    clean = pmic_integrator.denoise(noisy, image[..., 3:6], image[..., 6:9])
    assert clean.shape == noisy.shape and clean.dtype == np.float32 and np.isfinite(clean).all()
    assert metrics.rel_mse(clean, reference) < metrics.rel_mse(noisy, reference) / 5
    assert abs(metrics.luminance_ratio(clean, reference) - 1) < 0.05


def test_denoise_checks_its_inputs_and_contains_nan():
    color = np.full((8, 8, 3), 0.5, np.float32)
    with pytest.raises(ValueError, match="'image'"):
        pmic_integrator.denoise(color[..., :2])
    with pytest.raises(ValueError, match="'albedo'"):
        pmic_integrator.denoise(color, np.ones((4, 4, 3)))
    with pytest.raises(ValueError, match="'normal' guide needs an 'albedo'"):
        pmic_integrator.denoise(color, None, np.ones((8, 8, 3)))
    with pytest.raises(ValueError, match="'backend'"):
        pmic_integrator.denoise(color, backend="gpu")
    color[3, 3] = np.nan
    color[4, 4] = np.inf
    out = pmic_integrator.denoise(color)
    assert np.isfinite(out).all() and abs(out.mean() - 0.5) < 0.05


# -------------------------------------------------------------------------------------
# The final-gather estimator
# -------------------------------------------------------------------------------------
@pytest.mark.parametrize("estimator", ["final_gather", "first_hit"])
def test_cache_is_view_independent(estimator):
    """Two sensors: each view's image is bit-identical whatever was rendered before it
    (no per-view records or clamping), and two builds of the cache are bit-identical.
    With first_hit this failed before the surface probes (the camera pass added
    records and shrank others in the shared cache), and then again one build in eight
    until the probes stopped following the order in which Mitsuba listed the shapes."""
    def two_views():
        d = cornell(estimator=estimator)
        d["sensor2"] = dict(d["sensor"])
        d["sensor2"]["to_world"] = mi.ScalarTransform4f().look_at(origin=[0.5, 0.2, 3.5],
                                                                target=[0, 0, 0], up=[0, 1, 0])
        return mi.load_dict(d)

    first = two_views()
    a0 = np.array(mi.render(first, sensor=0, spp=2, seed=3))
    a1 = np.array(mi.render(first, sensor=1, spp=2, seed=4))
    for build in range(2):
        second = two_views()
        pmic = mi.load_dict({"type": "pmic", **SMALL, "estimator": estimator})
        b1 = np.array(mi.render(second, integrator=pmic, sensor=1, spp=2, seed=4))
        b0 = np.array(mi.render(second, integrator=pmic, sensor=0, spp=2, seed=3))
        assert not np.array_equal(a0, a1)
        assert np.array_equal(a0, b0) and np.array_equal(a1, b1), build
    assert "time_cache_view" not in pmic.stats


@pytest.mark.rgb_only('its reference was rendered in llvm_ad_rgb')
def test_final_gather_counts_caustics_once():
    """The caustic map is read at the traced vertex; light reaching it through the glass
    again along the path is not added (it would be +several % on the caustic floor)."""
    reference = scenes.load_reference("cornell_caustics", 128)
    scene = scenes.load_scene("cornell_caustics", 128, 16, {"type": "pmic", "estimator": "final_gather"})
    image = np.array(mi.render(scene, spp=16))
    assert abs(metrics.luminance_ratio(image, reference) - 1) < 0.01


# -------------------------------------------------------------------------------------
# Metrics
# -------------------------------------------------------------------------------------
def test_low_frequency_error_ignores_noise_and_sees_blotches():
    rng = np.random.default_rng(1)
    reference = np.full((64, 64, 3), 0.5)
    noisy = reference * (1 + 0.2 * rng.standard_normal(reference.shape))
    blotchy = reference.copy()
    blotchy[16:32, 16:32] *= 1.1
    assert metrics.rel_mse(noisy, reference) > 10 * metrics.rel_mse(blotchy, reference)
    assert metrics.low_frequency_rel_mse(noisy, reference) < metrics.low_frequency_rel_mse(blotchy, reference)
    assert np.allclose(metrics.gaussian_blur(reference, 4), reference)


def test_flip_is_zero_for_equal_images_and_grows_with_difference():
    rng = np.random.default_rng(2)
    reference = rng.uniform(0, 1, (32, 32, 3))
    assert metrics.flip(reference, reference) == 0.0
    assert 0 < metrics.flip(reference * 0.9, reference) < metrics.flip(reference * 0.5, reference)
