#!/usr/bin/env python
"""Kernel launches, distinct kernels, memory copies and sets, and reads back to the host,
per stage of one pmic render against Mitsuba's ``path`` (issue 43, item 3).

    python benchmarks/kernel_report.py                      # Cornell box 128², 16 spp
    python benchmarks/kernel_report.py --variant cuda_ad_rgb --out /tmp/gpu

One Cornell box render with ``path`` and one with ``pmic`` (default settings), each
twice in the same process: the first ("cold") run says which kernels were not yet in
Dr.Jit's in-memory cache (loaded from the disk cache, or compiled: on a GPU every one of
them is compiled on a fresh machine); the second ("warm") run gives the tables. pmic's
stages are the functions that run them, wrapped while the benchmark runs (nothing in
``src`` changes): ``pipeline.trace_maps`` (1 photons), ``pipeline.precompute`` (2
precomputed irradiance), ``pipeline.build_cache`` (3 cache), and the camera pass
``PMICIntegrator._render_camera_paths`` (4 render); what runs outside them (scene
checks, the scene fingerprint, the sky table, statistics) is "set-up". Inside the
stages, the functions of :data:`LABELS` are wrapped too, for the table of where the
launches come from (each count goes to the innermost wrapped function running).

What is counted, and how:

* **launches**: every entry of Dr.Jit's kernel history (``dr.JitFlag.KernelHistory``,
  ``dr.kernel_history()``): JIT kernels, and Dr.Jit's built-in operations (memcpy,
  memset, reductions, prefix sums, ``compress``, the ``mkperm`` of sorts, aggregates,
  host functions); **JIT**, **distinct** (distinct JIT kernel hashes); **memcpy**,
  **memset**; **other** (the built-in operations but memcpy and memset).
* **host reads**, each of which waits for the queue (on a GPU, a synchronisation):
  *element*: reads of single values (``x[0]``, ``int(x)``, ``float(dr.sum(x)[0])``,
  ``bool(dr.any(m)[0])``), which Dr.Jit's history records as memcpys of at most 8
  bytes (checked on LLVM; larger memcpys are copies between arrays); *array*:
  conversions of whole Dr.Jit arrays to NumPy (``np.array(x)``, ``x.numpy()``,
  DLPack), counted by wrapping ``dr.ArrayBase``'s ``__array__``, ``numpy`` and
  ``__dlpack__`` (Dr.Jit's history does not record them on LLVM); *compress*: each
  ``dr.compress`` (its output size is read on the host); *sync*: explicit
  ``dr.sync_thread()`` calls made through the ``drjit`` module. Reads made inside
  Mitsuba's C++ code are counted only where they show in the history.
* **first run**: JIT kernels of the cold run that were not in the in-memory cache
  (``cache_disk``: loaded from ``~/.drjit``; ``cache_hit`` false: compiled), and the
  milliseconds spent compiling them (``backend_time``).

Timing runs with the history on (each wrapped function reads the history on entry and
exit, which waits for the kernels launched so far): seconds here are not the render's
speed, see ``error_vs_time.py`` for that. Writes
``benchmarks/results/kernel_report.{json,md}``.
"""
from __future__ import annotations

import argparse
import collections
import functools
import importlib
import inspect
import sys
import time
from pathlib import Path

import pmic_integrator  # noqa: F401  (registers pmic, points Dr.Jit at libLLVM)
import drjit as dr
import mitsuba as mi

import common

#: pmic's stages: (module of pmic_integrator, function or Class.method, stage name).
STAGES = (
    ("pipeline", "trace_maps", "1 photons"),
    ("pipeline", "precompute", "2 precomputed irradiance"),
    ("pipeline", "build_cache", "3 cache"),
    ("integrator", "PMICIntegrator._render_camera_paths", "4 render"),
)
#: What runs outside the stages.
SETUP = "set-up"
#: Functions inside the stages whose launches are counted apart (one that does not
#: exist in this version is skipped and listed in the report).
LABELS = (
    ("fingerprint", "scene_fingerprint"),
    ("pipeline", "SceneInfo.of"),
    ("skylight", "SkySampler.build"),
    ("photons", "trace_photons"),
    ("photons", "_emit_batch"),
    ("photons", "_trace_batch"),
    ("photons", "EmissionGuide.learn"),
    ("photons", "merge_caustic_photons"),
    ("pipeline", "caustic_share"),
    ("irradiance", "adapted_lookup_radius"),
    ("irradiance", "sort_into_grid"),
    ("irradiance", "NormalBins.build"),
    ("irradiance", "precompute_irradiance"),
    ("irradiance", "estimate_irradiance"),
    ("hashgrid", "PointGrid.build"),
    ("hashgrid", "PointGridPyramid.build"),
    ("hashgrid", "BallGrid.build"),
    ("gather", "GatherSource.build"),
    ("pipeline", "CacheBuilder.placement_photons"),
    ("pipeline", "CacheBuilder.pilot_radius"),
    ("pipeline", "CacheBuilder.build_records"),
    ("pipeline", "CacheBuilder._place"),
    ("pipeline", "CacheBuilder._gather"),
    ("pipeline", "CacheBuilder.gather_placed"),
    ("pipeline", "CacheBuilder.settle"),
    ("pipeline", "CacheBuilder.complete_gathers"),
    ("pipeline", "CacheBuilder.complete_with_probes"),
    ("cache", "place_records"),
    ("cache", "compute_records"),
    ("cache", "clamp_to_neighbours"),
    ("cache", "guide_cdfs"),
    ("cache", "direct_irradiance_parts"),
    ("cache", "RecordIndex.build"),
    ("cache", "RecordIndex.for_lookup"),
    ("cache", "RecordIndex.pack"),
    ("lights", "RecordLights.select"),
    ("camera", "seeded_sampler"),
    ("camera", "camera_rays"),
    ("camera", "splat"),
    ("integrator", "PMICIntegrator._sample"),
    ("render.config", "PathConfig.of"),
    ("render.config", "PathContext.of"),
    ("render.path", "trace_camera_paths"),
    ("render.caustics", "add_deferred_caustics"),
)
#: Counters kept per label, in the order of the JSON.
COUNTERS = ("launches", "jit", "memcpy", "memset", "other", "element_reads", "array_reads",
            "compress", "syncs", "new_from_disk", "new_compiled")
#: Memcpys of at most this many bytes are reads of single values (see the docstring).
ELEMENT_BYTES = 8

_sync_thread = dr.sync_thread  # the instrument's own, not counted


class Counts:
    """What one label (or stage) launched and read."""

    def __init__(self):
        self.n = dict.fromkeys(COUNTERS, 0)
        self.hashes: set = set()
        self.seconds = 0.0
        self.execution_ms = 0.0
        self.compile_ms = 0.0

    def add_entry(self, e: dict) -> None:
        kind = e["type"]
        self.n["launches"] += 1
        self.execution_ms += float(e.get("execution_time", 0.0) or 0.0)
        if kind == dr.KernelType.JIT:
            self.n["jit"] += 1
            self.hashes.add(e["hash"])
            if not e.get("cache_hit", True):
                self.n["new_compiled"] += 1
                self.compile_ms += float(e.get("backend_time", 0.0) or 0.0)
            elif e.get("cache_disk", False):
                self.n["new_from_disk"] += 1
        elif kind == dr.KernelType.Memcpy:
            self.n["memcpy"] += 1
            if int(e.get("size", 0)) <= ELEMENT_BYTES:
                self.n["element_reads"] += 1
        elif kind == dr.KernelType.Memset:
            self.n["memset"] += 1
        else:
            self.n["other"] += 1
            if kind == dr.KernelType.Compress:
                self.n["compress"] += 1

    def merge(self, other: "Counts") -> None:
        for k in COUNTERS:
            self.n[k] += other.n[k]
        self.hashes |= other.hashes
        self.seconds += other.seconds
        self.execution_ms += other.execution_ms
        self.compile_ms += other.compile_ms

    @property
    def host_reads(self) -> int:
        return sum(self.n[k] for k in ("element_reads", "array_reads", "compress", "syncs"))

    def row(self) -> dict:
        return {**self.n, "distinct": len(self.hashes), "host_reads": self.host_reads,
                "seconds": self.seconds, "execution_ms": self.execution_ms,
                "compile_ms": self.compile_ms}


class Recorder:
    """Wraps the stage and label functions, ``dr.sync_thread`` and ``dr.ArrayBase``'s
    NumPy conversions while active, and files Dr.Jit's kernel history under the
    innermost wrapped function running (a tuple path: stage, label, label, ...)."""

    def __init__(self, stages=STAGES, labels=LABELS, root: str = SETUP):
        self.targets = [(m, q, s) for m, q, s in stages] + [(m, q, q) for m, q in labels]
        self.root = root
        self.stage_names = [s for _, _, s in stages]
        self.stack: list = []
        self.counts: dict = collections.defaultdict(Counts)
        self.missing: list = []
        self._restore: list = []
        self._start = 0.0

    # -- attribution ---------------------------------------------------------------
    def names(self) -> tuple:
        return tuple(name for name, _ in self.stack)

    def path(self) -> tuple:
        return self.names() or (self.root,)

    def flush(self) -> None:
        entries = dr.kernel_history()
        if entries:
            counts = self.counts[self.path()]
            for e in entries:
                counts.add_entry(e)

    def count(self, counter: str) -> None:
        self.counts[self.path()].n[counter] += 1

    def wrap(self, fn, name):
        recorder = self

        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            if dr.flag(dr.JitFlag.SymbolicScope):  # being traced into a loop: no launch
                return fn(*args, **kwargs)
            recorder.flush()
            recorder.stack.append((name, time.perf_counter()))
            try:
                return fn(*args, **kwargs)
            finally:
                recorder.flush()
                _, t0 = recorder.stack.pop()
                recorder.counts[recorder.names() + (name,)].seconds += time.perf_counter() - t0
        return wrapped

    # -- patching --------------------------------------------------------------------
    def _set(self, owner, attr, value):
        self._restore.append((owner, attr, owner.__dict__[attr] if isinstance(owner, type)
                              else getattr(owner, attr)))
        setattr(owner, attr, value)

    def _patch(self, module_name: str, qualname: str, name: str) -> None:
        try:
            module = importlib.import_module(f"pmic_integrator.{module_name}")
        except ImportError:
            self.missing.append(f"{module_name}.{qualname}")
            return
        *owners, attr = qualname.split(".")
        owner = module
        for part in owners:
            owner = getattr(owner, part, None)
        if owner is None or not hasattr(owner, attr):
            self.missing.append(f"{module_name}.{qualname}")
            return
        if isinstance(owner, type):
            raw = inspect.getattr_static(owner, attr)
            if isinstance(raw, staticmethod):
                self._set(owner, attr, staticmethod(self.wrap(raw.__func__, name)))
            elif isinstance(raw, classmethod):
                self._set(owner, attr, classmethod(self.wrap(raw.__func__, name)))
            elif inspect.isfunction(raw):
                self._set(owner, attr, self.wrap(raw, name))
            else:
                self.missing.append(f"{module_name}.{qualname}")
            return
        original = getattr(owner, attr)
        wrapped = self.wrap(original, name)
        # Every module of the package that imported the function by name.
        for mod_name, mod in list(sys.modules.items()):
            if mod is None or not mod_name.startswith("pmic_integrator"):
                continue
            for key, value in list(vars(mod).items()):
                if value is original:
                    self._set(mod, key, wrapped)

    def __enter__(self):
        for module_name, qualname, name in self.targets:
            self._patch(module_name, qualname, name)
        recorder = self

        def sync_thread():
            recorder.count("syncs")
            return _sync_thread()
        self._set(dr, "sync_thread", sync_thread)
        for attr in ("__array__", "numpy", "__dlpack__"):
            original = dr.ArrayBase.__dict__.get(attr)
            if original is None:
                continue

            def converted(self_, *args, _original=original, **kwargs):
                if dr.is_jit_v(self_):
                    recorder.count("array_reads")
                return _original(self_, *args, **kwargs)
            self._set(dr.ArrayBase, attr, converted)
        _sync_thread()
        dr.kernel_history_clear()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        _sync_thread()
        self.flush()
        self.total_seconds = time.perf_counter() - self._start
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        for owner, attr, value in reversed(self._restore):
            setattr(owner, attr, value)
        self._restore.clear()
        return False

    # -- results -----------------------------------------------------------------------
    def stages(self) -> dict:
        """Counts per stage (inclusive of their labels), set-up first, and the total."""
        root = self.root
        out = collections.OrderedDict((name, Counts()) for name in [root] + self.stage_names)
        total = Counts()
        for path, counts in self.counts.items():
            stage = path[0] if path[0] in out else root
            out[stage].merge(counts)
            total.merge(counts)
        # A stage's seconds are those of its outermost call(s); the root's are the rest.
        for name in self.stage_names:
            out[name].seconds = sum(c.seconds for p, c in self.counts.items() if p == (name,))
        out[root].seconds = max(0.0, self.total_seconds - sum(out[s].seconds for s in self.stage_names))
        total.seconds = self.total_seconds
        out = collections.OrderedDict((k, v) for k, v in out.items() if v.n["launches"] or v.host_reads
                                      or v.seconds > 1e-4 or k == root)
        out["total"] = total
        return out

    def labels(self) -> list:
        """Exclusive counts per path (stage / label / ...), most launches first."""
        rows = []
        for path, counts in self.counts.items():
            if counts.n["launches"] or counts.host_reads:
                if path[0] != self.root and path[0] not in self.stage_names:
                    path = (self.root,) + path
                rows.append({"path": " / ".join(path), **counts.row()})
        return sorted(rows, key=lambda r: (-r["launches"], -r["host_reads"]))


def render_recorded(scene, spec: dict, spp: int, seed: int = 0, staged: bool = True) -> Recorder:
    """One render of ``spec`` with a :class:`Recorder` on (``staged``: pmic's stages
    and labels wrapped; else the whole render is one stage, "render")."""
    integrator = mi.load_dict(spec)
    recorder = Recorder() if staged else Recorder(stages=(), labels=(), root="render")
    with recorder:
        image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        dr.eval(image)
    recorder.integrator_stats = dict(getattr(integrator, "stats", {}) or {})
    return recorder


def render_by_line(scene, spec: dict, spp: int, seed: int = 0) -> dict:
    """One render of ``spec`` with a line tracer (``sys.settrace``) that files Dr.Jit's
    kernel history under the line of pmic's source that was running when Dr.Jit
    launched (the evaluation point: kernels queued lazily launch where something is
    evaluated or read, not where they were built). ``{"file.py:line function": Counts}``;
    only what Dr.Jit's history records (no array reads, no sync_thread calls)."""
    root = str(Path(pmic_integrator.__file__).resolve().parent)
    sites: dict = collections.defaultdict(Counts)
    here = ["(outside pmic's code)"]

    def tracer(frame, event, arg):
        entries = dr.kernel_history()
        if entries:
            counts = sites[here[0]]
            for e in entries:
                counts.add_entry(e)
        filename = frame.f_code.co_filename
        if filename.startswith(root):
            here[0] = f"{filename[len(root) + 1:]}:{frame.f_lineno} {frame.f_code.co_name}"
            return tracer
        return None

    integrator = mi.load_dict(spec)
    _sync_thread()
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    sys.settrace(tracer)
    try:
        image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        dr.eval(image)
        _sync_thread()
    finally:
        sys.settrace(None)
        tracer(sys._getframe(), "return", None)
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return dict(sites)


STAGE_HEADER = ["| integrator | stage | s | launches | JIT | distinct | memcpy | memset | other | "
                "host reads (element + array + compress + sync) | first run: from disk / compiled |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]


def stage_lines(name: str, warm: dict, cold: dict) -> list[str]:
    lines = []
    for stage, c in warm.items():
        first = cold.get(stage)
        f = f"{first.n['new_from_disk']} / {first.n['new_compiled']}" if first else "—"
        n = c.n
        label = f"**{stage}**" if stage == "total" else stage
        lines.append(f"| {name} | {label} | {c.seconds:.2f} | {n['launches']} | {n['jit']} | {len(c.hashes)} | "
                     f"{n['memcpy']} | {n['memset']} | {n['other']} | {c.host_reads} ({n['element_reads']} + "
                     f"{n['array_reads']} + {n['compress']} + {n['syncs']}) | {f} |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="cornell_box")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--variant", default=common.VARIANT)
    parser.add_argument("--top", type=int, default=20, help="rows of the tables of functions and lines")
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant(args.variant)
    from pmic_integrator import scenes

    scene = scenes.load_scene(args.scene, resolution=args.resolution, spp=args.spp)
    runs = {}
    for name, spec in (("path", {"type": "path"}), ("pmic", {"type": "pmic"})):
        staged = name == "pmic"
        cold = render_recorded(scene, spec, args.spp, seed=1, staged=staged)
        warm = render_recorded(scene, spec, args.spp, seed=0, staged=staged)
        runs[name] = (cold, warm)
        w = warm.stages()["total"]
        print(f"{name}: {w.n['launches']} launches ({w.n['jit']} JIT, {len(w.hashes)} distinct, "
              f"{w.n['memcpy']} memcpy, {w.n['memset']} memset, {w.n['other']} other), "
              f"{w.host_reads} host reads", flush=True)
    lines_pmic = render_by_line(scene, {"type": "pmic"}, args.spp, seed=0)

    command = common.command(__file__, argv)
    result = {"command": command, "machine": common.machine(), "scene": args.scene,
              "resolution": args.resolution, "spp": args.spp, "element_read_max_bytes": ELEMENT_BYTES,
              "integrators": {}}
    lines = [f"# Kernels and host reads per stage: {args.scene} {args.resolution}², {args.spp} spp",
             "", f"`{command}` ({common.machine_summary()}, {mi.variant()}, Dr.Jit {dr.__version__})", "",
             "The second (warm) run of each integrator in one process. launches: every entry of Dr.Jit's "
             "kernel history; JIT: JIT kernels, distinct: distinct JIT kernels; memcpy, memset; other: "
             "reductions, prefix sums, compress, sort permutations, aggregates. Host reads: single "
             "values read (memcpys of ≤ 8 bytes in the history) + whole arrays converted to NumPy + "
             "`dr.compress` calls + explicit `dr.sync_thread()` calls. First run: JIT kernels of the "
             "first run not yet in memory, loaded from the disk cache / compiled. Seconds with the "
             "history on (not the render's speed).", "", *STAGE_HEADER]
    for name, (cold, warm) in runs.items():
        warm_stages, cold_stages = warm.stages(), cold.stages()
        lines += stage_lines(name, warm_stages, cold_stages)
        result["integrators"][name] = {
            "warm": {k: v.row() for k, v in warm_stages.items()},
            "cold": {k: v.row() for k, v in cold_stages.items()},
            "functions": warm.labels(),
            "not_wrapped": sorted(set(warm.missing)),
            "stats": {k: v for k, v in warm.integrator_stats.items() if isinstance(v, (int, float, str))},
        }
    pmic_warm = runs["pmic"][1]
    lines += ["", f"## Where pmic's launches come from: functions (top {args.top} by launches)", "",
              "Each count goes to the innermost wrapped function running (exclusive); a stage's name "
              "alone is its own code outside the wrapped functions; s: seconds inside the function "
              "(inclusive).", "",
              "| stage / function | launches | JIT | distinct | memcpy | memset | other | host reads | s |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in pmic_warm.labels()[:args.top]:
        lines.append(f"| {r['path']} | {r['launches']} | {r['jit']} | {r['distinct']} | {r['memcpy']} | "
                     f"{r['memset']} | {r['other']} | {r['host_reads']} | {r['seconds']:.3f} |")
    if pmic_warm.missing:
        lines += ["", "Not wrapped (not in this version): " +
                  ", ".join(f"`{m}`" for m in sorted(set(pmic_warm.missing)))]
    line_rows = [{"line": k, **v.row()} for k, v in lines_pmic.items()]
    result["integrators"]["pmic"]["lines"] = sorted(line_rows, key=lambda r: -r["launches"])
    total_lines = sum(r["launches"] for r in line_rows)
    lines += ["", "## Where pmic's launches come from: lines of pmic_integrator", "",
              f"A third pmic run ({total_lines} launches) traced line by line: each launch goes to the "
              "line of pmic's code running when Dr.Jit launched it, which is where something was "
              "evaluated or read (kernels queued by earlier lines launch there too). Reads: single "
              "values + `dr.compress` (the history's; no array reads or `sync_thread` here).", ""]
    header = ["| line | launches | JIT | distinct | memcpy | memset | other | reads |",
              "|---|---|---|---|---|---|---|---|"]
    by_launches = sorted(line_rows, key=lambda r: -r["launches"])[:args.top]
    by_reads = sorted((r for r in line_rows if r["element_reads"] + r["compress"]),
                      key=lambda r: -(r["element_reads"] + r["compress"]))[:args.top]
    for title, rows in ((f"Top {args.top} by launches:", by_launches), (f"Top {args.top} by host reads:", by_reads)):
        lines += [title, "", *header]
        for r in rows:
            lines.append(f"| `{r['line']}` | {r['launches']} | {r['jit']} | {r['distinct']} | {r['memcpy']} | "
                         f"{r['memset']} | {r['other']} | {r['element_reads'] + r['compress']} |")
        lines.append("")
    md = common.write_results(args.out, "kernel_report", result, lines)
    print("\n".join(lines))
    print(f"wrote {md} and .json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
