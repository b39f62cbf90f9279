"""Tests of the bundled scenes, their references, EXR input/output and the metrics."""
from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import metrics
from pmic_integrator import scenes as sc

EXPECTED_SCENES = ("cornell_box", "cornell_caustics", "indirect_room", "exterior_envmap", "interior_window")


# --------------------------------------------------------------------------- scenes


def test_scene_names():
    assert sc.SCENES == EXPECTED_SCENES


@pytest.mark.parametrize("name", EXPECTED_SCENES)
def test_scene_loads_with_defaults(name):
    scene = sc.load_scene(name, resolution=16, spp=4)
    film = scene.sensors()[0].film()
    assert tuple(film.size()) == (16, 16)
    assert scene.sensors()[0].sampler().sample_count() == 4
    # The default integrator is the unbounded path tracer the references were made with.
    text = str(scene.integrator())
    assert text.startswith("PathIntegrator")
    assert "max_depth = 4294967295" in text  # -1 stored as an unsigned int
    assert len(scene.emitters()) == (2 if name == "interior_window" else 1)  # sky + sun


@pytest.mark.parametrize("name", EXPECTED_SCENES)
def test_scene_renders_finite(name):
    image = mi.render(sc.load_scene(name, resolution=8, spp=4), seed=0)
    assert np.asarray(image).shape == (8, 8, 3)
    assert metrics.finite(image)


def test_scene_path_is_xml_in_scenes_dir():
    for name in EXPECTED_SCENES:
        path = sc.scene_path(name)
        assert path.name == f"{name}.xml"
        assert path.parent == sc.scenes_dir()


def test_unknown_scene_names_parameter_allowed_values_and_value():
    with pytest.raises(ValueError) as info:
        sc.scene_path("cornell_boxx")
    message = str(info.value)
    assert "scene" in message and "'cornell_boxx'" in message
    for name in EXPECTED_SCENES:
        assert name in message
    with pytest.raises(ValueError, match="scene"):
        sc.load_scene("nope")
    with pytest.raises(ValueError, match="scene"):
        sc.reference_path("nope")


def test_integrator_type_only_goes_through_xml_parameter():
    scene = sc.load_scene("cornell_box", resolution=8, spp=1, integrator={"type": "direct"})
    assert str(scene.integrator()).startswith("DirectIntegrator")


def test_integrator_with_properties_is_swapped_in():
    spec = {"type": "path", "max_depth": 3, "rr_depth": 2}
    scene = sc.load_scene("cornell_caustics", resolution=8, spp=2, integrator=spec)
    text = str(scene.integrator())
    assert "max_depth = 3" in text and "rr_depth = 2" in text
    assert spec == {"type": "path", "max_depth": 3, "rr_depth": 2}  # not consumed
    # The rebuilt scene renders exactly like the original with the same integrator.
    plain = sc.load_scene("cornell_caustics", resolution=8, spp=2)
    a = np.asarray(mi.render(scene, seed=7))
    b = np.asarray(mi.render(plain, integrator=sc.make_integrator(spec), seed=7))
    np.testing.assert_array_equal(a, b)


def test_integrator_instance_is_used_as_is():
    integrator = sc.make_integrator({"type": "path", "max_depth": 2})
    scene = sc.load_scene("indirect_room", resolution=8, spp=1, integrator=integrator)
    assert "max_depth = 2" in str(scene.integrator())


def test_make_integrator_default_and_errors():
    assert "max_depth = 4294967295" in str(sc.make_integrator(None))
    with pytest.raises(ValueError, match="type"):
        sc.make_integrator({"max_depth": 3})


def test_bad_resolution_and_spp():
    with pytest.raises(ValueError, match="resolution"):
        sc.load_scene("cornell_box", resolution=0)
    with pytest.raises(ValueError, match="spp"):
        sc.load_scene("cornell_box", spp=0)


def test_scenes_dir_override(monkeypatch, tmp_path):
    monkeypatch.setenv(sc.SCENES_DIR_ENV, str(tmp_path))
    assert sc.scenes_dir() == tmp_path.resolve()
    with pytest.raises(FileNotFoundError, match=sc.SCENES_DIR_ENV):
        sc.scene_path("cornell_box")


def test_no_variant_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(mi, "variant", lambda: None)
    with pytest.raises(RuntimeError, match="set_variant"):
        sc.load_scene("cornell_box")


# ----------------------------------------------------------------------- references


@pytest.mark.parametrize("name", EXPECTED_SCENES)
def test_reference_exists_and_is_sane(name):
    path = sc.reference_path(name)
    assert path == sc.scenes_dir() / "references" / f"{name}_128.exr"
    assert path.is_file()
    ref = sc.load_reference(name)
    assert ref.shape == (128, 128, 3)
    assert ref.dtype == np.float32
    assert metrics.finite(ref)
    assert ref.min() >= 0.0
    assert 0.05 < metrics.mean_luminance(ref) < 0.6  # interior_window 0.086, exterior_envmap 0.57
    meta = sc.read_exr_metadata(path)
    assert meta["pmic_scene"] == name
    assert int(meta["pmic_spp"]) >= 8192


@pytest.mark.parametrize("name", EXPECTED_SCENES)
def test_reference_matches_current_scene(name):
    """A short path-traced render agrees with the stored reference.

    Catches a reference that went stale after a scene edit: the overall brightness must
    agree within 2 % (the 64-spp estimate of the mean luminance is good to a fraction of
    a percent), and the relMSE must be that of plain Monte Carlo noise.
    """
    image = np.asarray(mi.render(sc.load_scene(name, resolution=128, spp=64), seed=123))
    ref = sc.load_reference(name)
    assert metrics.luminance_ratio(image, ref) == pytest.approx(1.0, abs=0.02)
    assert metrics.rel_mse(image, ref) < 0.2


def test_missing_reference_says_how_to_make_it():
    with pytest.raises(FileNotFoundError, match="make_references.py") as info:
        sc.load_reference("cornell_box", resolution=3)
    assert "--resolution 3" in str(info.value)


def test_exr_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    image = (rng.random((5, 7, 3)) * 10).astype(np.float32)
    path = tmp_path / "sub" / "image.exr"
    sc.write_exr(path, image, metadata={"pmic_note": "hello", "pmic_spp": 12})
    back = sc.read_exr(path)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, image)  # float32 EXR is lossless
    meta = sc.read_exr_metadata(path)
    assert meta["pmic_note"] == "hello" and meta["pmic_spp"] == "12"


def test_write_exr_accepts_tensor_and_rejects_bad_shapes(tmp_path):
    image = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    sc.write_exr(tmp_path / "t.exr", mi.TensorXf(image))
    np.testing.assert_array_equal(sc.read_exr(tmp_path / "t.exr"), image)
    with pytest.raises(ValueError, match=r"\(2, 3\)"):
        sc.write_exr(tmp_path / "bad.exr", np.zeros((2, 3)))


# -------------------------------------------------------------------------- metrics

IMG = np.array([[[1.0, 2.0, 3.0]]])
REF = np.array([[[0.0, 1.0, 1.0]]])


def test_rel_mse_known_values():
    assert metrics.rel_mse(IMG, IMG) == 0.0
    # Squared errors 1, 1, 4 over ref^2 + eps = 0.01, 1.01, 1.01, averaged over 3 values.
    expected = (1 / 0.01 + 1 / 1.01 + 4 / 1.01) / 3
    assert metrics.rel_mse(IMG, REF) == pytest.approx(expected, rel=1e-12)
    assert metrics.rel_mse(IMG, REF, eps=1.0) == pytest.approx((1 / 1 + 1 / 2 + 4 / 2) / 3)


def test_rmse_known_values():
    assert metrics.rmse(IMG, IMG) == 0.0
    assert metrics.rmse(IMG, REF) == pytest.approx(math.sqrt(6 / 3), rel=1e-12)


def test_luminance():
    assert metrics.mean_luminance(np.ones((2, 2, 3))) == pytest.approx(1.0)
    red = np.zeros((1, 2, 3))
    red[..., 0] = 1.0
    assert metrics.mean_luminance(red) == pytest.approx(0.2126)
    assert metrics.mean_luminance(REF) == pytest.approx(0.7152 + 0.0722)
    x = np.random.default_rng(1).random((4, 4, 3))
    assert metrics.luminance_ratio(2 * x, x) == pytest.approx(2.0)


def test_ciede2000_known_values():
    white, black = np.ones((1, 1, 3)), np.zeros((1, 1, 3))
    assert metrics.ciede2000(white, white) == 0.0
    # L* = 100 vs 0 with a* = b* = 0: at mean L* = 50 the lightness weight S_L is 1.
    assert metrics.ciede2000(white, black) == pytest.approx(100.0, abs=1e-2)
    # Everything above 1 clips to display white: HDR highlights compare equal.
    assert metrics.ciede2000(5 * white, white) == 0.0
    # Half of the pixels differ by 100, half not at all.
    assert metrics.ciede2000(np.concatenate([white, white], 1),
                             np.concatenate([white, black], 1)) == pytest.approx(50.0, abs=1e-2)


def test_finite():
    assert metrics.finite(IMG)
    for bad in (np.nan, np.inf, -np.inf):
        img = IMG.copy()
        img[0, 0, 1] = bad
        assert not metrics.finite(img)


def test_metrics_accept_mitsuba_types():
    x = np.random.default_rng(2).random((3, 4, 3)).astype(np.float32)
    assert metrics.rel_mse(mi.TensorXf(x), x) == 0.0
    assert metrics.mean_luminance(mi.Bitmap(x)) == pytest.approx(metrics.mean_luminance(x))


@pytest.mark.parametrize(
    "metric",
    [metrics.rel_mse, metrics.rmse, metrics.luminance_ratio, metrics.ciede2000],
)
def test_shape_mismatch_names_both_shapes(metric):
    with pytest.raises(ValueError) as info:
        metric(np.zeros((2, 3, 3)), np.zeros((3, 2, 3)))
    assert "(2, 3, 3)" in str(info.value) and "(3, 2, 3)" in str(info.value)
