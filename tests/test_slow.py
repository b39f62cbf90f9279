"""Heavier checks at the paper's 512² scale (run with ``pytest -m slow``; the
benchmarks cover the same ground with timings)."""
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import metrics, scenes


@pytest.mark.slow
@pytest.mark.parametrize("name,threshold", [("cornell_box", 4e-3), ("indirect_room", 1.6e-2)])
def test_512_pmic_matches_reference(name, threshold):
    """Defaults (the final gather) at 32 spp. Its error there is noise, which falls as
    spp grows (benchmarks/error_vs_time.py): measured 2.9e-3 (Cornell box) and
    1.1-1.2e-2 (room) over two seeds, luminance within 0.3 %. The thresholds were
    first-hit figures (1.2e-3, 2e-3) from before the final gather became the default,
    and these tests, outside CI, had failed since."""
    reference = scenes.load_reference(name, 512)
    scene = scenes.load_scene(name, resolution=512, spp=32)
    image = np.array(mi.render(scene, integrator=mi.load_dict({"type": "pmic"}), spp=32))
    assert np.isfinite(image).all()
    assert metrics.rel_mse(image, reference) < threshold
    assert abs(metrics.luminance_ratio(image, reference) - 1) < 0.01


@pytest.mark.slow
def test_ten_million_photons_fit_and_render():
    scene = scenes.load_scene("cornell_box", resolution=64, spp=1)
    integrator = mi.load_dict({"type": "pmic", "global_photons": 10_000_000, "caustic_photons": 0})
    image = np.array(mi.render(scene, integrator=integrator, spp=1))
    assert np.isfinite(image).all()
    assert 10_000_000 <= integrator.stats["photons_global"] < 10_000_000 + 64  # whole paths
