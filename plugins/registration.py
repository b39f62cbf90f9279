"""Register the ``pmic`` integrator with Mitsuba, for the current and future variants.

Mitsuba's plugin registry is per variant, so registering once is not enough: a user may
``import pmic_integrator`` before or after ``mi.set_variant``. ``install`` registers for
the active variant (if any) and adds a variant callback that registers again whenever
the variant changes.
"""
from __future__ import annotations

import mitsuba as mi

PLUGIN_NAME = "pmic"

_registered: set[str] = set()
_installed = False
#: Dr.Jit's vectorised backends; Mitsuba names its variants after them.
JIT_BACKENDS = ("llvm", "cuda", "metal")


def supported(variant: str | None) -> bool:
    """pmic needs a JIT (vectorised) RGB or spectral variant: ``llvm_*``, ``cuda_*`` or
    ``metal_*``, ending in ``_rgb`` or ``_spectral`` (not polarised, not monochrome)."""
    return (bool(variant) and variant.split("_")[0] in JIT_BACKENDS
            and variant.endswith(("_rgb", "_spectral")))


def register(variant: str | None = None) -> None:
    """Register ``pmic`` for ``variant`` (default: the active one)."""
    variant = variant or mi.variant()
    if variant is None or variant in _registered:
        return
    if supported(variant):
        mi.register_integrator(PLUGIN_NAME, _create)
    else:
        mi.register_integrator(PLUGIN_NAME, lambda props: _unsupported(variant))
    _registered.add(variant)


def _create(props):
    from pmic_integrator import _llvm

    if _llvm.problem and mi.variant().startswith("llvm"):
        raise _llvm.LLVMUnavailableError(_llvm.problem)
    # Imported lazily: the integrator module needs an active variant at import time.
    from pmic_integrator.integrator import integrator_class

    return integrator_class()(props)


def _unsupported(variant: str):
    raise ValueError(
        f"integrator 'pmic': variant must be a JIT RGB or spectral variant (e.g. "
        f"'llvm_ad_rgb', 'llvm_ad_spectral', 'cuda_ad_rgb'), got '{variant}'"
    )


def _on_variant_change(old, new) -> None:
    if new is not None:
        register(new)


def _is_pmic(integrator) -> bool:
    return type(integrator).__module__.startswith("pmic_integrator")


def _render_with_own_errors(scene, params=None, sensor=0, integrator=None, seed=0, seed_grad=0,
                            spp=0, spp_grad=0):
    """Mitsuba's ``mi.render`` (same parameters; see its documentation), except that an
    error raised inside pmic's ``render()`` reaches the caller as itself.

    Mitsuba runs an integrator's ``render()`` inside Dr.Jit's custom operation, which
    replaces any error by ``drjit.custom(<..._RenderOp>): error while performing a
    custom differentiable operation. (see above)``: the user's own error (a cache file
    of another scene, a lookup_radius too large for the scene) would only be its
    ``__cause__``. Other integrators' errors are left as Mitsuba raises them."""
    from mitsuba.python.util import render

    try:
        return render(scene, params, sensor, integrator, seed, seed_grad, spp, spp_grad)
    except RuntimeError as error:
        cause = error.__cause__
        used = integrator if integrator is not None else scene.integrator()
        if cause is None or not _is_pmic(used) or "drjit.custom" not in str(error):
            raise
        raise cause from None


def install() -> None:
    """Register for the active variant and for every variant selected later; make
    ``mi.render`` raise pmic's errors as themselves (:func:`_render_with_own_errors`)."""
    global _installed
    if not _installed:
        mi.detail.add_variant_callback(_on_variant_change)
        mi.render = _render_with_own_errors
        _installed = True
    if mi.variant() is not None:
        register(mi.variant())
