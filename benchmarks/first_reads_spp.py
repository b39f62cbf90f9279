#!/usr/bin/env python
"""First reads at high sample counts: the adaptive estimator against itself reading
every record the survey passes at every sample count, and against the final gather.

A read at a camera path's first hit swaps the traced bounce's noise, which falls as
1/spp, for the record's error, which does not. Up to
``render.reads.FIRST_READ_ANY_SPP`` samples per pixel every record the survey passes
is read; above it, a record only up to its own count (its bounce variance over
``FIRST_READ_ERROR_SCALE`` times its left-out error: ``reads.survey_first_reads``).
*Every spp* is the estimator without that limit (``FIRST_READ_ANY_SPP`` set to
infinity for those renders: a benchmark's switch, not a parameter).

For each configuration, sample count and render seed: relMSE (less the reference's own
noise), seconds (every stage) and mean luminance over the reference.

    python benchmarks/first_reads_spp.py
    python benchmarks/first_reads_spp.py --scenes matpreview --kinds door_ajar --kind-scale 3

Writes ``benchmarks/results/first_reads_spp.{json,md}`` (``--stem`` names another).
"""
from __future__ import annotations

import argparse
import math

import pmic_integrator  # noqa: F401  (registers pmic; before drjit/mitsuba)
import mitsuba as mi
import numpy as np

import common
import public_scenes

from pmic_integrator import compare, metrics
from pmic_integrator.render import reads

CONFIGS = {"adaptive": {}, "adaptive, every spp": {}, "final_gather": {"estimator": "final_gather"}}


def render(scene, label: str, spp: int, ref, seed: int):
    """``compare.render_measured`` of pmic in configuration ``label``."""
    keep = reads.FIRST_READ_ANY_SPP
    if label == "adaptive, every spp":
        reads.FIRST_READ_ANY_SPP = math.inf
    try:
        return compare.render_measured(scene, {"type": "pmic", **CONFIGS[label]}, spp, ref, seed=seed)
    finally:
        reads.FIRST_READ_ANY_SPP = keep


def measure(name: str, scene: mi.Scene, found, counts, seeds: int, log) -> dict:
    ref, noise, origin = found
    row = {"scene": name, "reference": origin, "noise": noise, "runs": {}}
    for spp in counts:
        for label in CONFIGS:
            runs = []
            for seed in range(seeds):
                r = render(scene, label, spp, ref, seed)
                runs.append({"seed": seed, "rel_mse": r.rel_mse - noise, "seconds": r.seconds,
                             "luminance": metrics.luminance_ratio(r.image, ref)})
                log(f"{name} {spp} spp, {label}, seed {seed}: relMSE {runs[-1]['rel_mse']:.3e}, "
                    f"{r.seconds:.2f} s, luminance {runs[-1]['luminance']:.4f}")
            row["runs"][f"{spp} {label}"] = runs
    return row


def _mean(runs, field):
    return float(np.mean([r[field] for r in runs]))


def markdown(rows, counts, seeds: int, command: str) -> list[str]:
    lines = ["# First reads at high sample counts", "",
             f"`{command}` ({common.machine_summary()}); render seeds 0-{seeds - 1} (means). "
             f"*adaptive*: the default (every record the survey passes read up to "
             f"`FIRST_READ_ANY_SPP` {reads.FIRST_READ_ANY_SPP} spp, above it each up to its own count); "
             "*adaptive, every spp*: without that limit; *final_gather*: no first reads. "
             "relMSE is less the reference's own noise; seconds are every stage's.", "",
             "| scene | spp | " + " | ".join(f"{c}: relMSE, s, luminance" for c in CONFIGS) + " |",
             "|---|---|" + "---|" * len(CONFIGS)]
    for row in rows:
        for spp in counts:
            cells = []
            for label in CONFIGS:
                runs = row["runs"][f"{spp} {label}"]
                cells.append(f"{_mean(runs, 'rel_mse'):.2e}, {_mean(runs, 'seconds'):.1f}, "
                             f"{_mean(runs, 'luminance'):.4f}")
            lines.append(f"| {row['scene']} | {spp} | " + " | ".join(cells) + " |")
    lines += ["", "Per seed: the `.json` file's `runs`."]
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    public_scenes.add_study_arguments(parser, ["matpreview", "white_room", "sponza"], ["door_ajar"], 3)
    parser.add_argument("--spp", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--stem", default="first_reads_spp")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be an integer >= 1, got {args.seeds}")
    if min(args.spp) < 1:
        parser.error(f"--spp must be integers >= 1, got {args.spp}")
    mi.set_variant(common.VARIANT)
    rows = public_scenes.study_rows(args, measure, args.spp)
    lines = markdown(rows, args.spp, args.seeds, common.command(__file__, argv))
    md = common.write_results(common.RESULTS, args.stem, rows, lines)
    print(f"written {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
