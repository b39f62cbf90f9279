"""Error versus time: pmic against Mitsuba's path tracer, same scenes, same run.

For each scene, ``path`` runs at a ladder of spp and ``pmic`` at a ladder of settings
(photon counts, max_error, gather_rays, spp). Every render is timed after a warm-up in
the same process (``compile_s`` reports the first run's extra time separately), and
scored against the path-traced reference: relMSE, RMSE, CIEDE2000, luminance ratio.

Writes, into ``--out`` (default ``benchmarks/results/``):
  error_vs_time_<res>.json / .csv   every run, with pmic's per-stage timings
  error_vs_time_<res>.md            tables and the speed-up of pmic over path
  error_vs_time_<res>_<scene>.png   log-log plot, both integrators on the same axes

The speed-up at a target relMSE is t_path(e) / t_pmic(e), each time interpolated
log-linearly along that integrator's lower envelope (the fastest run reaching e). Where
path's longest run did not reach e, its time is extrapolated with relMSE ∝ 1/time
(unbiased Monte Carlo) from that run, and marked "extrapolated"; pmic's never is.
A reference is itself noisy: its own relMSE against the truth (``noise``, estimated by
make_references.py from the spread between its passes) adds to every measured relMSE.
The tables show the measured relMSE; the speed-ups are given both on it and on the
corrected relMSE − noise (an estimate of the error against the noise-free image).

    python benchmarks/error_vs_time.py                       # 512², Cornell box + room
    python benchmarks/error_vs_time.py --resolution 128 --scenes cornell_box cornell_caustics indirect_room
    python benchmarks/error_vs_time.py --quick               # a minute: smoke test
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import platform
import sys
import time
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import mitsuba as mi
import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
TARGETS = (2e-3, 1e-3, 5e-4)

PATH_SPP = {"full": [4, 16, 64, 256, 1024], "quick": [4, 16]}
#: pmic settings, cheapest first; each is one point of its curve.
PMIC_LADDER = {
    "full": [
        {"global_photons": 100_000, "max_error": 0.6, "gather_rays": 256, "spp": 8, "direct_samples": 1},
        {"global_photons": 200_000, "max_error": 0.5, "gather_rays": 256, "spp": 16},
        {"global_photons": 200_000, "max_error": 0.5, "gather_rays": 256, "spp": 32},
        {"global_photons": 200_000, "max_error": 0.4, "gather_rays": 512, "spp": 64},
        {"global_photons": 400_000, "max_error": 0.3, "gather_rays": 1024, "spp": 128},
        {"global_photons": 400_000, "max_error": 0.3, "gather_rays": 1024, "spp": 256},
    ],
    "quick": [
        {"global_photons": 20_000, "max_error": 0.8, "gather_rays": 64, "spp": 4},
        {"global_photons": 50_000, "max_error": 0.6, "gather_rays": 128, "spp": 8},
    ],
}


def envelope(points):
    """Lower envelope of (time, error): runs that no faster run beats in error."""
    best = []
    for t, e in sorted(points):
        if not best or e < best[-1][1]:
            best.append((t, e))
    return best


def time_to_reach(points, target, extrapolate=False):
    """Time at which the envelope first reaches ``target`` (log-log interpolation);
    None if no run reached it. With ``extrapolate`` (for path tracing only: unbiased
    Monte Carlo, whose relMSE falls as 1/time), a target below the last run is reached
    at t_last · e_last / target."""
    env = envelope(points)
    if not env:
        return None
    if env[-1][1] > target:
        return env[-1][0] * env[-1][1] / target if extrapolate else None
    if env[0][1] <= target:
        return env[0][0]  # the cheapest run already reaches it (upper bound)
    for (t0, e0), (t1, e1) in zip(env, env[1:]):
        if e1 <= target <= e0:
            f = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0)))
    return None


def run_scene(name, resolution, mode, log):
    from pmic_integrator import compare, scenes

    reference = scenes.load_reference(name, resolution)
    scene = scenes.load_scene(name, resolution=resolution, spp=4)
    rows = []
    path = mi.load_dict(dict(compare.PATH_INTEGRATOR))
    _, cold = compare.timed_render(scene, path, 1, seed=99)
    _, warm = compare.timed_render(scene, path, 1, seed=98)
    for spp in PATH_SPP[mode]:
        image, seconds = compare.timed_render(scene, path, spp, seed=spp)
        r = compare.score(compare.RenderResult("path", dict(compare.PATH_INTEGRATOR), spp, seconds,
                                               max(0.0, cold - warm), image=image), reference)
        rows.append(r)
        log(f"  path  spp {spp:5d}  {seconds:7.2f} s  relMSE {r.rel_mse:.2e}")
    for setting in PMIC_LADDER[mode]:
        spec = {"type": "pmic", **{k: v for k, v in setting.items() if k != "spp"}}
        r = compare.render_measured(scene, spec, setting["spp"], reference, label="pmic")
        rows.append(r)
        s = r.stats
        log(f"  pmic  {setting}  {r.seconds:7.2f} s  relMSE {r.rel_mse:.2e}  "
            f"(photons {s.get('time_photons', 0):.2f} precompute {s.get('time_precompute', 0):.2f} "
            f"cache {s.get('time_cache', 0):.2f} render {s.get('time_render', 0):.2f} s, "
            f"{s.get('records', 0)} records)")
    return rows


def speedups(rows, noise=0.0):
    path = [(r.seconds, max(r.rel_mse - noise, 1e-12)) for r in rows if r.label == "path"]
    pmic = [(r.seconds, max(r.rel_mse - noise, 1e-12)) for r in rows if r.label == "pmic"]
    out = {}
    path_best = min(e for _, e in path) if path else math.inf
    for target in TARGETS:
        tp, tq = time_to_reach(path, target, extrapolate=True), time_to_reach(pmic, target)
        out[f"{target:.0e}"] = {"path_s": tp, "pmic_s": tq, "path_extrapolated": path_best > target,
                                "speedup": (tp / tq) if tp and tq else None}
    return out


def plot(name, rows, path_png, resolution):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for label, style in (("path", "o-"), ("pmic", "s-")):
        pts = sorted((r.seconds, r.rel_mse) for r in rows if r.label == label)
        ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=label)
    for target in TARGETS:
        ax.axhline(target, color="grey", lw=0.5, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time incl. every stage [s]")
    ax.set_ylabel("relMSE vs path-traced reference")
    ax.set_title(f"{name}, {resolution}²")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path_png, dpi=110)
    plt.close(fig)


def machine():
    import drjit as dr

    return {"python": sys.version.split()[0], "mitsuba": mi.__version__, "drjit": dr.__version__,
            "variant": mi.variant(), "cpu": platform.processor() or platform.machine(),
            "threads": dr.thread_count(), "date": time.strftime("%Y-%m-%d")}


def write_outputs(results, out: Path, stem: str):
    """Speed-ups, Markdown, CSV and plots from ``results`` (as saved in the JSON)."""
    from types import SimpleNamespace

    resolution = results["resolution"]
    md = [f"# Error vs time at {resolution}²", "",
          f"`{results['command']}` — {results['machine']}", ""]
    fmt = lambda x, extra=False: (f"{x:.2f}" + (" (extrapolated)" if extra else "")) if x else "not reached"
    sp = lambda v: (str(round(v["speedup"], 1)) + "×") if v["speedup"] else "—"
    for name, data in results["scenes"].items():
        rows = [SimpleNamespace(**r) for r in data["runs"]]
        noise = data["reference_noise_rel_mse"]
        data["speedup"] = ups = speedups(rows)
        data["speedup_noise_corrected"] = corrected = speedups(rows, noise)
        plot(name, rows, out / f"{stem}_{name}.png", resolution)
        md += [f"## {name}", "", "| integrator | settings | spp | time [s] | compile [s] | relMSE | RMSE | "
               "CIEDE2000 | luminance |", "|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            settings = {k: v for k, v in r.integrator.items() if k != "type"}
            md.append(f"| {r.label} | {settings or ''} | {r.spp} | {r.seconds:.2f} | {r.compile_s:.2f} | "
                      f"{r.rel_mse:.2e} | {r.rmse:.4f} | {r.ciede2000:.3f} | {r.luminance_ratio:.4f} |")
        md += ["", f"Reference: `{data['reference']}`; its own noise relMSE {noise:.1e}.", "",
               "| relMSE target | path [s] | pmic [s] | pmic speed-up | noise-corrected: path [s] | pmic [s] | speed-up |",
               "|---|---|---|---|---|---|---|"]
        for target, v in ups.items():
            c = corrected[target]
            md.append(f"| {target} | {fmt(v['path_s'], v['path_extrapolated'])} | {fmt(v['pmic_s'])} | "
                      f"{sp(v)} | {fmt(c['path_s'], c['path_extrapolated'])} | {fmt(c['pmic_s'])} | {sp(c)} |")
        md += ["", f"![{name}]({stem}_{name}.png)", ""]
        print(name, json.dumps(ups), flush=True)
    (out / f"{stem}.json").write_text(json.dumps(results, indent=2, default=str))
    (out / f"{stem}.md").write_text("\n".join(md) + "\n")
    with open(out / f"{stem}.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene", "integrator", "settings", "spp", "seconds", "compile_s", "rel_mse", "rmse",
                    "ciede2000", "luminance_ratio"])
        for name, data in results["scenes"].items():
            for r in data["runs"]:
                w.writerow([name, r["label"], json.dumps({k: v for k, v in r["integrator"].items()
                                                          if k != "type"}),
                            r["spp"], r["seconds"], r["compile_s"], r["rel_mse"], r["rmse"],
                            r["ciede2000"], r["luminance_ratio"]])
    print(f"wrote {out / stem}.json/.csv/.md and plots")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell_box", "indirect_room"])
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--quick", action="store_true", help="tiny ladders at 128² (smoke test)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--variant", default="llvm_ad_rgb")
    parser.add_argument("--replot", type=Path, default=None,
                        help="recompute speed-ups, tables and plots from a saved JSON (no rendering)")
    args = parser.parse_args(argv)
    if args.replot:
        results = json.loads(args.replot.read_text())
        write_outputs(results, args.replot.parent, args.replot.stem)
        return
    mode = "quick" if args.quick else "full"
    resolution = 128 if args.quick else args.resolution
    mi.set_variant(args.variant)
    from pmic_integrator import scenes as bundled

    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"error_vs_time_{resolution}" + ("_quick" if args.quick else "")
    results = {"machine": machine(), "resolution": resolution, "mode": mode,
               "command": "python benchmarks/error_vs_time.py " + " ".join(argv or sys.argv[1:]),
               "scenes": {}}
    for name in args.scenes:
        print(f"{name}:", flush=True)
        meta = bundled.read_exr_metadata(bundled.reference_path(name, resolution))
        rows = run_scene(name, resolution, mode, lambda s: print(s, flush=True))
        results["scenes"][name] = {"runs": [r.row() for r in rows],
                                   "reference_noise_rel_mse": float(meta.get("pmic_noise_rel_mse", 0.0)),
                                   "reference": meta.get("pmic_command", "")}
    write_outputs(results, args.out, stem)


if __name__ == "__main__":
    main()
