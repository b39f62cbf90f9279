"""What the benchmark scripts share: where their results go, the command line each
result records, the machine it ran on, timing, the public scenes, and writing a
result's JSON and Markdown.

The scripts import it as ``import common``: run as ``python benchmarks/<script>.py``,
Python puts this folder first on ``sys.path``. Image metrics (relMSE, luminance, FLIP)
come from :mod:`pmic_integrator.metrics` and timed renders from
:func:`pmic_integrator.compare.timed_render`, not from here.
"""
from __future__ import annotations

import json
import platform
import shlex
import sys
import time
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import drjit as dr
import mitsuba as mi

HERE = Path(__file__).resolve().parent
#: Where every script writes its tables and figures unless given ``--out``.
RESULTS = HERE / "results"
#: The public scenes (``../shared/scenes`` beside the checkout): ``scenes/<name>/scene.xml``
#: and, for some, ``refs/<name>.npy``.
SHARED = HERE.parents[1] / "shared" / "scenes"
#: This project's references of the public scenes that came without one
#: (``public_references.py``).
PUBLIC_REFERENCES = HERE / "references" / "public"
#: The variant every benchmark renders with.
VARIANT = "llvm_ad_rgb"


def command(script: str, argv=None) -> str:
    """The command line that runs this again: ``python benchmarks/<script> ARGS``.
    ``script``: the script's ``__file__``; ``argv``: the arguments given to its
    ``main`` (None: those of the command line)."""
    args = sys.argv[1:] if argv is None else argv
    return shlex.join(["python", f"benchmarks/{Path(script).name}", *map(str, args)])


def machine() -> dict:
    """The software and machine a result was measured on."""
    return {"python": sys.version.split()[0], "mitsuba": mi.__version__, "drjit": dr.__version__,
            "variant": mi.variant(), "cpu": platform.processor() or platform.machine(),
            "threads": dr.thread_count(), "date": time.strftime("%Y-%m-%d")}


def machine_summary() -> str:
    """``"<cpu>, <n> threads"``, for a table's heading."""
    return f"{platform.processor() or platform.machine()}, {dr.thread_count()} threads"


def timed(fn):
    """``(fn(), seconds)``, Dr.Jit's queued work included: a Dr.Jit result is evaluated
    and the thread pool drained before the clock stops."""
    dr.sync_thread()
    start = time.perf_counter()
    out = fn()
    if dr.is_array_v(out):
        dr.eval(out)
    dr.sync_thread()
    return out, time.perf_counter() - start


def fastest(fn, repeats: int) -> float:
    """Seconds of the fastest of ``repeats`` calls of ``fn``, after one untimed call
    (which compiles its kernels)."""
    fn()
    return min(timed(fn)[1] for _ in range(repeats))


def load_public(name: str) -> mi.Scene:
    """The public scene ``name``. Mitsuba 3.9 can deadlock loading an envmap with a
    one-thread Dr.Jit pool: it is loaded with at least two threads."""
    threads = dr.thread_count()
    dr.set_thread_count(max(2, threads))
    try:
        return mi.load_file(str(SHARED / "scenes" / name / "scene.xml"))
    finally:
        dr.set_thread_count(threads)


def write_results(out: Path, stem: str, data, lines: list[str]) -> Path:
    """Write ``data`` to ``out/<stem>.json`` and ``lines`` to ``out/<stem>.md`` (the
    folder made if needed); return the Markdown file's path."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(data, indent=1, default=str))
    md = out / f"{stem}.md"
    md.write_text("\n".join(lines) + "\n")
    return md
