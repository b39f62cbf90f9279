#!/usr/bin/env python
"""What pmic's camera pass alone is worth against ``path``, per public scene: the
ceiling on pmic's speed-up once its fixed stages (photons, precomputed irradiance,
cache) cost nothing.

    python benchmarks/render_stage.py
    python benchmarks/render_stage.py --scenes cornell_glossy matpreview --spp 16 --renders 3

Per scene, after a warm-up render of each (pmic's builds its cache, which later
renders reuse; both compile their kernels), ``--renders`` renders of pmic (its
defaults) and of ``path`` at ``--spp``, render seeds 1, 2, ...: each one's seconds
and relMSE (less the reference's own noise, ``public_scenes.reference_of``). The
*render-stage efficiency* is ``path``'s mean relMSE × seconds over pmic's: how many
times sooner pmic's camera pass reaches an error than ``path`` does (relMSE falling
as 1/t for both). The equal-time speed-up of ``public_scenes.py`` adds pmic's fixed
stages to its time; where they are a large part of it, the efficiency here is what
a longer render tends to. The fixed stages' seconds shown are those of pmic's first
render (its ``stats``), kernel compilation included: ``public_scenes.py`` has them
warm.

Writes ``benchmarks/results/render_stage.{json,md}``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import mitsuba as mi

from pmic_integrator.compare import timed_render
from pmic_integrator.metrics import rel_mse

import common
import public_scenes

STAGES = ("time_photons", "time_precompute", "time_cache")


def measure(name: str, spp: int, renders: int) -> dict:
    """The row of scene ``name``: per method its renders' (seconds, relMSE)."""
    scene = common.load_public(name)
    found = public_scenes.reference_of(name)
    if found is None:
        raise SystemExit(f"{name}: no reference (benchmarks/public_references.py makes one)")
    ref, noise, origin = found
    row = {"scene": name, "reference": origin, "reference_noise": noise, "spp": spp}
    for label, spec in (("path", {"type": "path", "max_depth": -1}), ("pmic", {"type": "pmic"})):
        integrator = mi.load_dict(spec)
        timed_render(scene, integrator, spp, seed=0)
        if label == "pmic":
            row["fixed_seconds"] = {k: integrator.stats[k] for k in STAGES}
        runs = []
        for seed in range(1, renders + 1):
            image, seconds = timed_render(scene, integrator, spp, seed=seed)
            runs.append({"seconds": seconds, "rel_mse": rel_mse(image, ref) - noise})
        row[label] = runs
    cost = {m: _mean(row[m], "seconds") * _mean(row[m], "rel_mse") for m in ("path", "pmic")}
    row["efficiency"] = float(cost["path"] / cost["pmic"])
    return row


def _mean(runs, key: str) -> float:
    """The mean of ``key`` (seconds, rel_mse) over a method's renders."""
    return float(np.mean([r[key] for r in runs]))


def markdown(rows, command: str) -> list[str]:
    lines = ["# pmic's camera pass alone against path", "",
             f"`{command}` ({common.machine_summary()}); means over the renders; efficiency = "
             "path's relMSE × seconds over pmic's render stage's (its cache already built).", "",
             "| scene | spp | path s | path relMSE | pmic render s | pmic relMSE | render-stage efficiency | "
             "pmic fixed stages s, compiling (photons / irradiance / cache) |",
             "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        path, pmic = row["path"], row["pmic"]
        fixed = " / ".join(f"{row['fixed_seconds'][k]:.2f}" for k in STAGES)
        lines.append(f"| {row['scene']} | {row['spp']} | {_mean(path, 'seconds'):.2f} | {_mean(path, 'rel_mse'):.2e} | "
                     f"{_mean(pmic, 'seconds'):.2f} | {_mean(pmic, 'rel_mse'):.2e} | {row['efficiency']:.2f}× | {fixed} |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(public_scenes.ORDER))
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--renders", type=int, default=2)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    rows = []
    for name in args.scenes:
        rows.append(measure(name, args.spp, args.renders))
        print(f"{name}: render-stage efficiency {rows[-1]['efficiency']:.2f}x", flush=True)
    data = {"command": common.command(__file__, argv), "machine": common.machine(), "rows": rows}
    md = common.write_results(args.out, "render_stage", data, markdown(rows, data["command"]))
    print(f"written {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
