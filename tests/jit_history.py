"""Which JIT kernels a piece of code made Dr.Jit compile: for the tests that a second
run with other counts (records, photons, rays) compiles nothing anew."""
from __future__ import annotations

import contextlib

import drjit as dr


@contextlib.contextmanager
def new_kernels():
    """Yields a list that, after the ``with`` block, holds ``(size, operation count)``
    of each JIT kernel the block launched that was new to the process: compiled, or
    loaded from Dr.Jit's disk cache (a kernel whose code is already in memory is
    neither). A count written into a kernel's code shows as one more such kernel."""
    found = []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # (clears what came before)
    try:
        yield found
        found.extend((k["size"], k["operation_count"]) for k in dr.kernel_history()
                     if k["type"] == dr.KernelType.JIT and (not k["cache_hit"] or k["cache_disk"]))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
