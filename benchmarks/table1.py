"""The paper's Table 1, reproduced: render time by number of global photons.

Cornell box at 512² (the paper's scale), global photons 10k…50k as in the paper plus
100k and 1M; ``photon_map`` with 500 photons per estimate (as in the paper),
``irradiance_cache`` and ``pmic`` (the paper's first-hit estimator) with max error 1.0
(as in the paper), and ``pmic`` at its defaults, first-hit and final-gather. For each: total time (every stage, after a warm-up), time per stage,
record count and relMSE against the path-traced reference.

    python benchmarks/table1.py                 # 512², ~15 minutes on 2 cores
    python benchmarks/table1.py --quick         # 128², 10k and 20k photons

Each cell is the fastest of ``--repeat`` runs (default 3; each a fresh integrator with
the same seed, so the images are the same), made in rounds over all cells (every other
round backwards), not back to back: on this 2-core machine one run's time varies by up
to 10 %, and the machine's speed drifts over minutes by more, both more than the
differences between the caches. Runs slower than ``REPEAT_BELOW_S`` (photon_map) are
not repeated.

Writes benchmarks/results/table1_<res>.json and .md.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import pmic_integrator  # noqa: F401
import mitsuba as mi

import common

#: Cells whose first run takes longer are measured once (their noise is small beside
#: their time, and repeating photon_map would triple the benchmark).
REPEAT_BELOW_S = 10.0
PHOTONS = {"full": [10_000, 20_000, 30_000, 40_000, 50_000, 100_000, 1_000_000],
           "quick": [10_000, 20_000]}
METHODS = [
    ("photon_map (500/estimate)", {"method": "photon_map", "lookup_size": 500}),
    ("irradiance_cache (a = 1.0)", {"method": "irradiance_cache", "max_error": 1.0}),
    # The paper's method: interpolation at the first diffuse hit, as irradiance_cache.
    ("pmic (a = 1.0)", {"method": "pmic", "estimator": "first_hit", "max_error": 1.0}),
    ("pmic first_hit (defaults)", {"method": "pmic", "estimator": "first_hit"}),
    ("pmic (defaults: final gather)", {"method": "pmic"}),
]
PAPER = {  # seconds, Table 1 of Gu & Wang (2010), Core Duo E8400
    "photon_map (500/estimate)": [398.3, 555.1, 725.3, 888.1, 1028.6],
    "irradiance_cache (a = 1.0)": [144.2, 162.8, 182.7, 193.5, 201.3],
    "pmic (a = 1.0)": [94.3, 163.5, 234.2, 301.5, 357.7],
}


def main(argv=None):
    from pmic_integrator import compare, scenes

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--spp", type=int, default=16, help="camera samples per pixel (all methods)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs per cell, the fastest kept (default 3)")
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error(f"--repeat must be at least 1; got {args.repeat}")
    mode = "quick" if args.quick else "full"
    resolution = 128 if args.quick else args.resolution
    mi.set_variant(common.VARIANT)
    reference = scenes.load_reference("cornell_box", resolution)
    scene = scenes.load_scene("cornell_box", resolution=resolution, spp=args.spp)
    # Rounds over every cell, not a cell's runs back to back: the machine's speed drifts
    # over minutes (±10-25 % here), and a cell measured during one slow minute lost to
    # its neighbours by as much as the differences between the caches. Every other
    # round walks the cells backwards.
    cells = [(label, params, photons) for label, params in METHODS for photons in PHOTONS[mode]]
    best, runs = {}, {}
    for round_index in range(args.repeat):
        order = cells if round_index % 2 == 0 else cells[::-1]
        for label, params, photons in order:
            key = (label, photons)
            if round_index and best[key].seconds >= REPEAT_BELOW_S:
                continue
            spec = {"type": "pmic", "global_photons": photons, **params}
            r = compare.render_measured(scene, spec, args.spp, reference, label=label)
            runs.setdefault(key, []).append(r.seconds)
            if key not in best or r.seconds < best[key].seconds:
                best[key] = r
    rows = []
    for label, params, photons in cells:
        r = best[(label, photons)]
        s = r.stats
        row = {"method": label, "global_photons": photons, "total_s": r.seconds,
               "runs_s": [round(t, 3) for t in runs[(label, photons)]],
               "compile_s": r.compile_s, "rel_mse": r.rel_mse, "luminance": r.luminance_ratio,
               "records": s.get("records", 0) + s.get("records_fallback", 0),
               "records_probes": s.get("records_probes", 0),
               **{k: s.get(k, 0.0) for k in ("time_photons", "time_precompute", "time_cache",
                                             "time_cache_view", "time_render")}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    stem = f"table1_{resolution}" + ("_quick" if args.quick else "")
    command = common.command(__file__, argv)
    photons = PHOTONS[mode]
    md = [f"# Table 1 at {resolution}², {args.spp} spp", "", f"`{command}`", "",
          f"Total time in seconds (every stage, after a warm-up; the fastest of up to "
          f"{args.repeat} runs); relMSE in brackets.", "",
          "| method | " + " | ".join(f"{p // 1000}k" for p in photons) + " |",
          "|---|" + "---|" * len(photons)]
    for label, _ in METHODS:
        cells = [f"{r['total_s']:.2f} ({r['rel_mse']:.1e})" for r in rows if r["method"] == label]
        md.append(f"| {label} | " + " | ".join(cells) + " |")
    for label, times in PAPER.items():
        md.append(f"| paper: {label} | " + " | ".join(f"{t}" for t in times) +
                  " | —" * (len(photons) - len(times)) + " |")
    md += ["", "Per stage (seconds): photons / precompute / cache / camera records (per view) / render; records (of which placed at surface probes).", "",
           "| method | photons | stages | records |", "|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['method']} | {r['global_photons']} | {r['time_photons']:.2f} / "
                  f"{r['time_precompute']:.2f} / {r['time_cache']:.2f} / {r['time_cache_view']:.2f} / "
                  f"{r['time_render']:.2f} | {r['records']} ({r['records_probes']}) |")
    common.write_results(args.out, stem, {"command": command, "spp": args.spp, "resolution": resolution,
                                          "rows": rows}, md)
    print("\n".join(md))


if __name__ == "__main__":
    main()
