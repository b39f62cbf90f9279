"""pmic in every JIT variant this machine has: RGB and spectral, on LLVM, CUDA and Metal.
A variant that is not built into this Mitsuba, or cannot be set here (no CUDA driver or
device, not a Mac), is skipped with the reason; the rest of the run keeps its own
variant (``PMIC_TEST_VARIANT``, see conftest.py).

Each renders the Cornell box with pmic and with ``path`` in that variant: finite, and
pmic's mean luminance within 3 % of ``path``'s (a 32² image at 64 spp: the spread of
pmic's own seeds there is 0.985-1.004)."""
import numpy as np
import pytest

import mitsuba as mi

import pmic_integrator  # noqa: F401
from pmic_integrator import kinds
from pmic_integrator.metrics import mean_luminance

#: Every variant pmic accepts, whether or not this Mitsuba or machine has it.
JIT_VARIANTS = ["llvm_ad_rgb", "llvm_ad_spectral", "cuda_ad_rgb", "cuda_ad_spectral",
                "metal_ad_rgb", "metal_ad_spectral"]


@pytest.fixture(params=JIT_VARIANTS)
def variant(request):
    name = request.param
    if name not in mi.variants():
        pytest.skip(f"{name} is not built into this Mitsuba")
    before = mi.variant()
    try:
        mi.set_variant(name)
    except Exception as error:  # no CUDA driver or device, no Metal
        mi.set_variant(before)
        pytest.skip(f"{name} cannot be set here: {error}")
    yield name
    mi.set_variant(before)


def test_pmic_renders_the_cornell_box_like_path(variant):
    scene = mi.load_dict(kinds.cornell(32))
    reference = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": -1}),
                                   spp=1024))[..., :3]
    image = np.array(mi.render(scene, integrator=mi.load_dict(kinds.pmic_cornell(32)["integrator"]),
                               spp=64))[..., :3]
    assert np.isfinite(image).all()
    assert mean_luminance(image) / mean_luminance(reference) == pytest.approx(1.0, abs=0.03)
