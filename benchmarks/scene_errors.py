"""Every bundled scene with every method at default settings, and path at equal time.

For each scene: ``pmic``, ``irradiance_cache`` and ``photon_map`` (each timed after a
warm-up, every stage included), then Mitsuba's ``path`` given pmic's wall time; relMSE,
luminance ratio and time against the path-traced reference.

    python benchmarks/scene_errors.py                     # 128², 64 spp, all scenes
    python benchmarks/scene_errors.py --resolution 512 --spp 32 --scenes cornell_box indirect_room

Writes benchmarks/results/scene_errors_<res>.json and .md.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import pmic_integrator  # noqa: F401
import mitsuba as mi

import common

METHODS = ("pmic", "irradiance_cache", "photon_map")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=None)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    from pmic_integrator import compare, scenes

    names = args.scenes or list(scenes.SCENES)
    command = common.command(__file__, argv)
    rows = []
    for name in names:
        reference = scenes.load_reference(name, args.resolution)
        scene = scenes.load_scene(name, resolution=args.resolution, spp=args.spp)
        pmic_seconds = None
        for method in METHODS:
            r = compare.render_measured(scene, {"type": "pmic", "method": method}, args.spp, reference,
                                        label=method)
            pmic_seconds = pmic_seconds or r.seconds
            rows.append({"scene": name, **{k: v for k, v in r.row().items() if k != "stats"},
                         "records": r.stats.get("records", 0) + r.stats.get("records_fallback", 0)})
            print(json.dumps(rows[-1]), flush=True)
        p = compare.path_at_equal_time(scene, pmic_seconds, reference)
        rows.append({"scene": name, **{k: v for k, v in p.row().items() if k != "stats"}, "records": 0})
        print(json.dumps(rows[-1]), flush=True)
    md = [f"# Bundled scenes at {args.resolution}², defaults, {args.spp} spp (path: pmic's time)", "",
          f"`{command}`", "", "| scene | integrator | spp | time [s] | relMSE | luminance | records |",
          "|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['scene']} | {r['label']} | {r['spp']} | {r['seconds']:.2f} | {r['rel_mse']:.2e} | "
                  f"{r['luminance_ratio']:.4f} | {r['records']} |")
    common.write_results(args.out, f"scene_errors_{args.resolution}", {"command": command, "rows": rows}, md)
    print("\n".join(md))


if __name__ == "__main__":
    main()
