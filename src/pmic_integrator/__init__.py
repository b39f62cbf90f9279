"""pmic: photon mapping with a view-independent irradiance cache, for Mitsuba 3.

Importing this package (1) points Dr.Jit at a usable libLLVM before ``drjit`` is loaded,
and (2) registers the ``pmic`` integrator with Mitsuba for every JIT RGB or spectral variant, now
and whenever ``mi.set_variant`` is called later. After::

    import pmic_integrator
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    integrator = mi.load_dict({"type": "pmic"})

``<integrator type="pmic">`` also works in XML scenes loaded with ``mi.load_file``.
"""
from . import _llvm

_llvm.configure()
if _llvm.problem:
    import warnings

    warnings.warn(_llvm.problem, RuntimeWarning, stacklevel=2)

from .plugins import registration as _registration  # noqa: E402

__version__ = "0.1.0"

register = _registration.register

_registration.install()

from .denoise import denoise, split_channels  # noqa: E402
from .scenes import load_file  # noqa: E402

__all__ = ["register", "denoise", "split_channels", "load_file", "__version__"]
