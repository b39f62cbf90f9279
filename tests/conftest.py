"""Shared test setup: a usable libLLVM for Dr.Jit, then the ``llvm_ad_rgb`` variant.

Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` only when ``drjit`` is first imported, so the LLVM
configuration must run before anything imports ``mitsuba`` or ``drjit``; conftest.py is
imported by pytest before any test module.
"""
import pmic_integrator._llvm as _llvm

_llvm.configure()

import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")
