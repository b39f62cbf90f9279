"""Error versus time: pmic and pmic + OIDN against Mitsuba's path and path + OIDN, same
scenes, same run.

For each scene, ``path`` runs at a ladder of spp and ``pmic`` at a ladder of settings
(photon counts, max_error, gather_rays, spp); each ladder runs raw and denoised (Intel
OIDN through ``pmic_integrator.denoise``, the same albedo and normal guides for both:
Mitsuba's ``aov`` integrator for path, pmic's own identical AOVs; wall time includes the
denoiser). Every render is timed after a warm-up in the same process (``compile_s``
reports the first run's extra time separately), and scored against the path-traced
reference: relMSE, FLIP, low-frequency relMSE (both images blurred by σ = 4 px),
RMSE, CIEDE2000, luminance ratio.

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
    python benchmarks/error_vs_time.py --repeat 2            # each run's fastest of 2 rounds
"""
from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import mitsuba as mi

import common

TARGETS = (2e-3, 1e-3, 5e-4)

PATH_SPP = {"full": [4, 16, 64, 256], "quick": [4, 16]}
PATH_DENOISED_SPP = {"full": [1, 2, 3, 4, 6, 8, 16, 32], "quick": [1, 4]}
#: A cheap cache: behind a final gather its error is read one bounce away.
CHEAP = {"global_photons": 50_000, "max_error": 1.0, "gather_rays": 64, "direct_samples": 1}
#: pmic settings (default estimator: final gather), cheapest first; each is one point of
#: its curve, raw and denoised.
PMIC_LADDER = {
    "full": [
        {**CHEAP, "spp": 2},
        {**CHEAP, "spp": 3},
        {**CHEAP, "spp": 4},
        {**CHEAP, "global_photons": 100_000, "spp": 2},
        {**CHEAP, "global_photons": 100_000, "spp": 4},
        {**CHEAP, "spp": 8},
        {**CHEAP, "spp": 16},
        {"global_photons": 100_000, "max_error": 0.8, "gather_rays": 128, "direct_samples": 1, "spp": 32},
        {"global_photons": 200_000, "spp": 64},
    ],
    "quick": [
        {"global_photons": 20_000, "max_error": 0.8, "gather_rays": 64, "spp": 4},
        {"global_photons": 50_000, "max_error": 0.6, "gather_rays": 128, "spp": 8},
    ],
}
#: The paper's first-hit interpolation (estimator "first_hit"): its error is mostly
#: the cache's, so the ladder grows the cache with the spp.
FIRST_HIT_LADDER = {
    "full": [
        {"estimator": "first_hit", "global_photons": 100_000, "max_error": 0.6, "gather_rays": 256,
         "spp": 8, "direct_samples": 1},
        {"estimator": "first_hit", "global_photons": 200_000, "max_error": 0.5, "gather_rays": 256, "spp": 16},
        {"estimator": "first_hit", "global_photons": 200_000, "max_error": 0.4, "gather_rays": 512, "spp": 32},
        {"estimator": "first_hit", "global_photons": 400_000, "max_error": 0.3, "gather_rays": 1024, "spp": 64},
    ],
    "quick": [{"estimator": "first_hit", "global_photons": 20_000, "max_error": 0.8, "gather_rays": 64,
               "spp": 4}],
}
#: The curves: (label, integrator, denoised). "pmic" is the default estimator (final
#: gather); the paper's first-hit estimator is shown beside it.
CURVES = (("path", "path", False), ("path+OIDN", "path", True),
          ("pmic", "pmic", False), ("pmic+OIDN", "pmic", True),
          ("pmic-first-hit", "first_hit", False), ("pmic-first-hit+OIDN", "first_hit", True))
#: Crops shown for each method (fractions of the image: y0, y1, x0, x1).
CROPS = {"cornell_box": {"light gap": (0.0, 0.14, 0.33, 0.67),
                         "contact shadow": (0.70, 0.92, 0.18, 0.48)},
         "indirect_room": {"corner": (0.0, 0.3, 0.0, 0.3), "floor": (0.7, 1.0, 0.35, 0.65)}}


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


def run_scene(name, resolution, mode, log, repeat: int = 1):
    """Every curve's ladder on scene ``name``; with ``repeat`` > 1, that many rounds
    over all the runs (every other round backwards), each run keeping its fastest
    time: the machine's speed drifts over minutes (the same render took 2.0-3.3 s
    within minutes on a shared VM), and a run measured in one slow minute would move
    its curve by as much as the differences between the methods."""
    from pmic_integrator import compare, scenes

    reference = scenes.load_reference(name, resolution)
    scene = scenes.load_scene(name, resolution=resolution, spp=4)
    cells = []
    for label, kind, denoised in CURVES:
        if kind == "path":
            spec = dict(compare.PATH_INTEGRATOR)
            ladder = [{"spp": spp} for spp in (PATH_DENOISED_SPP if denoised else PATH_SPP)[mode]]
        elif kind == "first_hit":
            spec, ladder = {"type": "pmic"}, FIRST_HIT_LADDER[mode]
        else:
            spec, ladder = {"type": "pmic"}, PMIC_LADDER[mode]
        for setting in ladder:
            run_spec = {**spec, **{k: v for k, v in setting.items() if k != "spp"}}
            cells.append((label, kind, denoised, setting, run_spec))
    best = {}
    for round_index in range(repeat):
        order = list(enumerate(cells)) if round_index % 2 == 0 else list(enumerate(cells))[::-1]
        for key, (label, kind, denoised, setting, run_spec) in order:
            r = compare.render_measured(scene, run_spec, setting["spp"], reference, label=label,
                                        denoised=denoised)
            if key not in best or r.seconds < best[key].seconds:
                best[key] = r
    rows = []
    for key, (label, kind, denoised, setting, run_spec) in enumerate(cells):
        r = best[key]
        rows.append(r)
        s = r.stats
        stages = (f"  (photons {s.get('time_photons', 0):.2f} precompute {s.get('time_precompute', 0):.2f} "
                  f"cache {s.get('time_cache', 0):.2f} render {s.get('time_render', 0):.2f} s, "
                  f"{s.get('records', 0)} records)") if kind != "path" else ""
        log(f"  {label:9s} {setting}  {r.seconds:7.2f} s  relMSE {r.rel_mse:.2e}  "
            f"FLIP {r.flip:.3f}  low-freq {r.low_frequency:.2e}  lum {r.luminance_ratio:.4f}{stages}")
        save_crops(name, label, r, resolution)
    return rows


CROP_IMAGES: dict = {}


def save_crops(name, label, result, resolution):
    """Keep each method's image nearest in time to the showcase (see write_crops)."""
    CROP_IMAGES.setdefault(name, {}).setdefault(label, []).append((result.seconds, result.rel_mse,
                                                                  result.image))


def write_crops(name, out: Path, stem: str, reference):
    """One PNG per scene: for each method, its run nearest in time to the pmic+OIDN
    run that first reaches 1e-3 (else its fastest), full image and crops."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pmic_integrator import metrics

    runs = CROP_IMAGES.get(name, {})
    if not runs or name not in CROPS:
        return None
    showcase = runs.get("pmic+OIDN") or next(iter(runs.values()))
    reached = [t for t, e, _ in sorted(showcase, key=lambda x: x[0]) if e <= 1e-3]
    t_show = reached[0] if reached else min(t for t, _, _ in showcase)
    crops = CROPS[name]
    labels = list(runs) + ["reference"]
    fig, axes = plt.subplots(len(crops) + 1, len(labels), figsize=(2.4 * len(labels), 2.4 * (len(crops) + 1)))
    for j, label in enumerate(labels):
        if label == "reference":
            image, title = reference, "reference"
        else:
            t, e, image = min(runs[label], key=lambda x: abs(math.log(x[0] / t_show)))
            title = f"{label}\n{t:.1f} s, relMSE {e:.1e}"
        ldr = metrics.tonemap_srgb(image)
        axes[0, j].imshow(ldr)
        axes[0, j].set_title(title, fontsize=7)
        h, w = image.shape[:2]
        for i, (crop_name, (y0, y1, x0, x1)) in enumerate(crops.items(), start=1):
            axes[i, j].imshow(ldr[int(y0 * h):int(y1 * h), int(x0 * w):int(x1 * w)], interpolation="nearest")
            if j == 0:
                axes[i, j].set_ylabel(crop_name, fontsize=8)
        for ax in axes[:, j]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    path = out / f"{stem}_{name}_crops.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def speedups(rows, noise=0.0, ours="pmic", theirs="path"):
    path = [(r.seconds, max(r.rel_mse - noise, 1e-12)) for r in rows if r.label == theirs]
    pmic = [(r.seconds, max(r.rel_mse - noise, 1e-12)) for r in rows if r.label == ours]
    out = {}
    path_best = min(e for _, e in path) if path else math.inf
    for target in TARGETS:
        # A denoised curve is not unbiased Monte Carlo: never extrapolated.
        tp = time_to_reach(path, target, extrapolate="OIDN" not in theirs)
        tq = time_to_reach(pmic, target)
        out[f"{target:.0e}"] = {"path_s": tp, "pmic_s": tq,
                                "path_extrapolated": path_best > target and "OIDN" not in theirs,
                                "speedup": (tp / tq) if tp and tq else None}
    return out


def plot(name, rows, path_png, resolution):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for label, style in (("path", "o-"), ("path+OIDN", "o--"), ("pmic", "s-"), ("pmic+OIDN", "s--"),
                         ("pmic-first-hit", "^-"), ("pmic-first-hit+OIDN", "^--")):
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
        data["speedup_denoised"] = ups_dn = speedups(rows, ours="pmic+OIDN", theirs="path+OIDN")
        data["speedup_first_hit"] = ups_fh = speedups(rows, ours="pmic-first-hit", theirs="path")
        data["speedup_first_hit_denoised"] = ups_fh_dn = speedups(rows, ours="pmic-first-hit+OIDN",
                                                                  theirs="path+OIDN")
        data["speedup_noise_corrected"] = corrected = speedups(rows, noise)
        data["speedup_denoised_noise_corrected"] = corrected_dn = speedups(
            rows, noise, ours="pmic+OIDN", theirs="path+OIDN")
        plot(name, rows, out / f"{stem}_{name}.png", resolution)
        md += [f"## {name}", "", "| method | settings | spp | time [s] | compile [s] | relMSE | FLIP | "
               "low-freq relMSE (σ 4 px) | CIEDE2000 | luminance |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            settings = {k: v for k, v in r.integrator.items() if k != "type"}
            md.append(f"| {r.label} | {settings or ''} | {r.spp} | {r.seconds:.2f} | {r.compile_s:.2f} | "
                      f"{r.rel_mse:.2e} | {getattr(r, 'flip', math.nan):.3f} | "
                      f"{getattr(r, 'low_frequency', math.nan):.2e} | {r.ciede2000:.3f} | {r.luminance_ratio:.4f} |")
        md += ["", f"Reference: `{data['reference']}`; its own noise relMSE {noise:.1e}.", "",
               "| relMSE target | path+OIDN [s] | pmic+OIDN [s] | speed-up | noise-corrected (denoised) "
               "| path [s] | pmic [s] | speed-up | noise-corrected (raw) |", "|---|---|---|---|---|---|---|---|---|"]
        for target, v in ups.items():
            c, d, cd = corrected[target], ups_dn[target], corrected_dn[target]
            md.append(f"| {target} | {fmt(d['path_s'])} | {fmt(d['pmic_s'])} | {sp(d)} | {sp(cd)} | "
                      f"{fmt(v['path_s'], v['path_extrapolated'])} | {fmt(v['pmic_s'])} | {sp(v)} | {sp(c)} |")
        md += ["", "The paper's first-hit estimator (`estimator=first_hit`):", "",
               "| relMSE target | path+OIDN [s] | first-hit+OIDN [s] | speed-up | path [s] | first-hit [s] | speed-up |",
               "|---|---|---|---|---|---|---|"]
        for target, v in ups_fh.items():
            d = ups_fh_dn[target]
            md.append(f"| {target} | {fmt(d['path_s'])} | {fmt(d['pmic_s'])} | {sp(d)} | "
                      f"{fmt(v['path_s'], v['path_extrapolated'])} | {fmt(v['pmic_s'])} | {sp(v)} |")
        md += ["", f"![{name}]({stem}_{name}.png)", ""]
        if (out / f"{stem}_{name}_crops.png").exists():
            md += [f"![{name} crops]({stem}_{name}_crops.png)", ""]
        print(name, "raw", json.dumps(ups), "denoised", json.dumps(ups_dn), "first-hit",
              json.dumps(ups_fh), "first-hit denoised", json.dumps(ups_fh_dn), flush=True)
    common.write_results(out, stem, results, md)
    with open(out / f"{stem}.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene", "integrator", "settings", "spp", "seconds", "compile_s", "rel_mse", "flip",
                    "low_frequency", "rmse", "ciede2000", "luminance_ratio"])
        for name, data in results["scenes"].items():
            for r in data["runs"]:
                w.writerow([name, r["label"], json.dumps({k: v for k, v in r["integrator"].items()
                                                          if k != "type"}),
                            r["spp"], r["seconds"], r["compile_s"], r["rel_mse"], r.get("flip"),
                            r.get("low_frequency"), r["rmse"],
                            r["ciede2000"], r["luminance_ratio"]])
    print(f"wrote {out / stem}.json/.csv/.md and plots")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell_box", "indirect_room"])
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--quick", action="store_true", help="tiny ladders at 128² (smoke test)")
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    parser.add_argument("--variant", default=common.VARIANT)
    parser.add_argument("--repeat", type=int, default=1,
                        help="rounds over all runs, each run keeping its fastest time (a noisy machine)")
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
    results = {"machine": common.machine(), "resolution": resolution, "mode": mode,
               "command": common.command(__file__, argv),
               "scenes": {}}
    for name in args.scenes:
        print(f"{name}:", flush=True)
        meta = bundled.read_exr_metadata(bundled.reference_path(name, resolution))
        rows = run_scene(name, resolution, mode, lambda s: print(s, flush=True), max(1, args.repeat))
        write_crops(name, args.out, stem, bundled.load_reference(name, resolution))
        results["scenes"][name] = {"runs": [r.row() for r in rows],
                                   "reference_noise_rel_mse": float(meta.get("pmic_noise_rel_mse", 0.0)),
                                   "reference": meta.get("pmic_command", "")}
    write_outputs(results, args.out, stem)


if __name__ == "__main__":
    main()
