"""Shared test setup: a usable libLLVM for Dr.Jit, then the variant the tests run in.

Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` only when ``drjit`` is first imported, so the LLVM
configuration must run before anything imports ``mitsuba`` or ``drjit``; conftest.py is
imported by pytest before any test module.

The variant is ``llvm_ad_rgb`` unless the environment variable ``PMIC_TEST_VARIANT``
names another (``PMIC_TEST_VARIANT=cuda_ad_rgb python -m pytest ...`` on a machine
with an NVIDIA GPU; ``tools/gpu_check.py`` does this). Where that variant cannot be
set (not built into this Mitsuba, or no CUDA driver or device), every test is skipped
with the reason, and ``llvm_ad_rgb`` is set so that the test modules still import.
Tests that start a fresh Python process set their own variant there.

In a spectral variant (``PMIC_TEST_VARIANT=llvm_ad_spectral``), tests marked
``rgb_only(reason)`` are skipped with their reason: they compare with references
rendered in RGB, with Mitsuba's own RGB-only conventions, or build inputs that Mitsuba
refuses in spectral variants.
"""
import os

import pytest

import pmic_integrator._llvm as _llvm

_llvm.configure()

import mitsuba as mi  # noqa: E402

#: The variant the tests run in.
VARIANT = os.environ.get("PMIC_TEST_VARIANT", "").strip() or "llvm_ad_rgb"
#: Why :data:`VARIANT` cannot be used in this process (None: it is set).
UNAVAILABLE = None
try:
    mi.set_variant(VARIANT)
except Exception as error:  # ImportError: not built, or no CUDA driver/device
    UNAVAILABLE = f"PMIC_TEST_VARIANT={VARIANT} is unavailable here: {error}"
    mi.set_variant("llvm_ad_rgb")


def pytest_report_header(config):
    if UNAVAILABLE:
        return f"pmic test variant: {VARIANT} UNAVAILABLE, every test is skipped ({UNAVAILABLE})"
    return f"pmic test variant: {VARIANT}"


def pytest_collection_modifyitems(config, items):
    if UNAVAILABLE:
        skip = pytest.mark.skip(reason=UNAVAILABLE)
        for item in items:
            item.add_marker(skip)
        return
    if mi.is_spectral:
        # Tests that hold in RGB variants only, each with its reason (rgb_only(reason)).
        for item in items:
            marker = item.get_closest_marker("rgb_only")
            if marker is not None:
                item.add_marker(pytest.mark.skip(reason=f"RGB variants only: {marker.args[0]}"))
