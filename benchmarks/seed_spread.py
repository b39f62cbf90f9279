#!/usr/bin/env python
"""How much one pmic image's mean moves from one scene seed to the next.

pmic's photons and cache are one random draw per scene seed (the ``seed`` parameter),
and their error does not average away with more camera samples: a single image's mean
luminance can sit off `path`'s by more than the mean over many seeds does. For each
scene of ``scene_kinds.py``, pmic renders ``--seeds`` images at its defaults and
``--spp`` samples per pixel, each with its own scene seed (the render seed fixed, so
that the spread is the photons' and the cache's), and reports the images' mean
luminance over the ``path`` reference's (``scene_kinds.py``'s, computed once and kept):
their mean, standard deviation and range, and the mean relMSE.

    python benchmarks/seed_spread.py                          # door rooms, 16 seeds
    python benchmarks/seed_spread.py --scenes courtyard_sun --seeds 8

Writes ``benchmarks/results/seed_spread_<res>.{json,md}``. The luminance ratio is
:func:`pmic_integrator.metrics.luminance_ratio` (Rec. 709 weights); the table written
up to commit 3439931 holds the ratio of the plain means of R, G and B.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import mitsuba as mi

from pmic_integrator.compare import timed_render
from pmic_integrator.metrics import luminance_ratio, rel_mse

import common
import scene_kinds

DEFAULT_SCENES = ("door_diffuse", "door_principled")


def spread(name: str, size, spp: int, seeds: int, ref_spp: int) -> dict:
    scene = mi.load_dict(scene_kinds.scene_dict(name, size))
    reference = scene_kinds.reference(name, size, ref_spp, scene)
    ratios, errors = [], []
    for seed in range(seeds):
        image, _ = timed_render(scene, mi.load_dict({"type": "pmic", "seed": seed}), spp, 0)
        ratios.append(luminance_ratio(image, reference))
        errors.append(rel_mse(image, reference))
    ratios = np.array(ratios)
    return {"scene": name, "seeds": seeds, "spp": spp, "luminance_mean": float(ratios.mean()),
            "luminance_sd": float(ratios.std(ddof=1)) if seeds > 1 else 0.0,
            "luminance_min": float(ratios.min()), "luminance_max": float(ratios.max()),
            "outside_1_percent": int(np.sum(np.abs(ratios - 1.0) > 0.01)),
            "relmse_mean": float(np.mean(errors)), "ratios": [round(r, 5) for r in ratios]}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES), choices=scene_kinds.SCENES)
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--resolution", type=int, default=320, help="width; height is 3/4 of it")
    parser.add_argument("--ref-spp", type=int, default=2048)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    if args.seeds < 2 or args.spp < 1:
        parser.error(f"--seeds must be at least 2 and --spp at least 1; got {args.seeds}, {args.spp}")
    mi.set_variant(common.VARIANT)
    size = (args.resolution, args.resolution * 3 // 4)
    rows = []
    for name in args.scenes:
        row = spread(name, size, args.spp, args.seeds, args.ref_spp)
        rows.append(row)
        print(f"{name:20s} luminance {row['luminance_mean']:.4f} sd {row['luminance_sd']:.4f} "
              f"[{row['luminance_min']:.4f}, {row['luminance_max']:.4f}] "
              f"outside 1 %: {row['outside_1_percent']}/{row['seeds']}  relMSE {row['relmse_mean']:.3e}",
              flush=True)
    command = common.command(__file__, argv)
    lines = [f"# One image's mean luminance over path's, scene seed by scene seed, {size[0]}×{size[1]}",
             "", f"`{command}` (pmic {args.spp} spp, render seed 0; reference: path {args.ref_spp} spp)", "",
             "| scene | seeds | mean | sd | min | max | outside ±1 % | mean relMSE |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['seeds']} | {r['luminance_mean']:.4f} | {r['luminance_sd']:.4f} | "
                     f"{r['luminance_min']:.4f} | {r['luminance_max']:.4f} | {r['outside_1_percent']} | "
                     f"{r['relmse_mean']:.3e} |")
    md = common.write_results(args.out, f"seed_spread_{size[0]}", {"command": command, "rows": rows}, lines)
    print(f"wrote {md.with_suffix('')}.json/.md")


if __name__ == "__main__":
    main()
