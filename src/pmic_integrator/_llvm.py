"""Point Dr.Jit at a libLLVM it can use, before ``drjit`` is first imported.

Dr.Jit 1.5 emits IR that LLVM 14/15 cannot compile (Debian 12's system ``libLLVM-15``
aborts the process at the first kernel with ``Cannot select: ... fminimum``). Dr.Jit
reads ``DRJIT_LIBLLVM_PATH`` only once, when ``drjit`` is imported, so this module must
run before that import. The project depends on the ``karellen-llvm-core`` wheel, which
installs ``libLLVM.so.<major>`` into the environment's ``lib/`` folder.
"""
from __future__ import annotations

import glob
import os
import re
import sys

#: Oldest LLVM major version that Dr.Jit 1.5 was seen to work with.
MIN_LLVM_MAJOR = 16


class LLVMUnavailableError(RuntimeError):
    """Raised when pmic would run on an LLVM that Dr.Jit cannot use."""


def _llvm_major(path: str) -> int | None:
    match = re.search(r"LLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    if match is None:
        match = re.search(r"libLLVM\.so\.(\d+)", os.path.basename(path))
    return int(match.group(1)) if match else None


def find_wheel_llvm() -> str | None:
    """Return the newest libLLVM shipped into this Python environment, if any."""
    prefixes = {sys.prefix, sys.exec_prefix, getattr(sys, "base_prefix", sys.prefix)}
    candidates = []
    for prefix in prefixes:
        candidates += glob.glob(os.path.join(prefix, "lib", "libLLVM.so.*"))
        candidates += glob.glob(os.path.join(prefix, "lib", "libLLVM-*.so"))
    usable = [(m, p) for p in candidates if (m := _llvm_major(p)) and m >= MIN_LLVM_MAJOR]
    return max(usable)[1] if usable else None


def _loaded_llvm() -> str | None:
    """Path of a libLLVM already mapped into this process (Linux only)."""
    try:
        with open("/proc/self/maps", encoding="utf-8") as maps:
            for line in maps:
                if "libLLVM" in line:
                    return line.split()[-1]
    except OSError:
        pass
    return None


#: Why the LLVM backend cannot be used in this process (None: no known problem).
problem: str | None = None


def configure() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` if it is not set already; return the path in use.

    If ``drjit`` was imported before this call, the LLVM it loaded is checked instead;
    when it is too old to work, :data:`problem` says so in one sentence (the package
    warns at import, and ``pmic`` refuses to run on ``llvm_*`` variants rather than
    letting the first kernel abort the process).
    """
    global problem
    if "drjit" in sys.modules:
        loaded = _loaded_llvm()
        major = _llvm_major(loaded) if loaded else None
        if loaded and major is not None and major < MIN_LLVM_MAJOR:
            problem = (
                f"Dr.Jit was imported before pmic_integrator and loaded {loaded} "
                f"(LLVM {major}), which cannot compile Dr.Jit 1.5 kernels: the next render "
                f"on an llvm_* variant, with any integrator ('path' too), would abort this "
                f"process. Restart the Python process (in Jupyter: restart the kernel) and "
                f"import pmic_integrator before drjit/mitsuba, or set DRJIT_LIBLLVM_PATH to "
                f"an LLVM >= {MIN_LLVM_MAJOR} library before starting Python."
            )
        return loaded
    current = os.environ.get("DRJIT_LIBLLVM_PATH")
    if current and os.path.exists(current):
        return current
    path = find_wheel_llvm()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path
