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
    python benchmarks/seed_spread.py --scenes --public torus --seeds 4 --spp 128 --render-seeds

``--public`` adds scenes of ``../shared/scenes`` scored against their references
(``public_scenes.reference_of``). ``--render-seeds`` gives each image its own render
seed too (100 + its scene seed), so that the spread holds the camera samples' noise as
well and the mean over the images, with its standard error (sd / √seeds), tells a bias
from one image's luck: where a few pixels hold very bright light (a sun's glint in a
mirror), one 16-spp image's mean moves by a percent from one render seed to the next.

Writes ``benchmarks/results/seed_spread_<res>.{json,md}`` (``seed_spread_public`` with
``--public``). The luminance ratio is
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


def kind_scene(name: str, size, ref_spp: int):
    """(scene, reference) of the scene kind ``name`` (scene_kinds.py)."""
    scene = mi.load_dict(scene_kinds.scene_dict(name, size))
    return scene, scene_kinds.reference(name, size, ref_spp, scene)


def public_scene(name: str):
    """(scene, reference) of the public scene ``name``."""
    import public_scenes

    found = public_scenes.reference_of(name)
    if found is None:
        raise SystemExit(f"--public {name}: no reference (benchmarks/public_references.py makes one)")
    return common.load_public(name), found[0]


def spread(name: str, scene, reference, spp: int, seeds: int, render_seeds: bool = False) -> dict:
    ratios, errors = [], []
    for seed in range(seeds):
        render_seed = 100 + seed if render_seeds else 0
        image, _ = timed_render(scene, mi.load_dict({"type": "pmic", "seed": seed}), spp, render_seed)
        ratios.append(luminance_ratio(image, reference))
        errors.append(rel_mse(image, reference))
    ratios = np.array(ratios)
    sd = float(ratios.std(ddof=1)) if seeds > 1 else 0.0
    return {"scene": name, "seeds": seeds, "spp": spp, "render_seeds": render_seeds,
            "luminance_mean": float(ratios.mean()), "luminance_sd": sd,
            "luminance_standard_error": sd / np.sqrt(seeds),
            "luminance_min": float(ratios.min()), "luminance_max": float(ratios.max()),
            "outside_1_percent": int(np.sum(np.abs(ratios - 1.0) > 0.01)),
            "relmse_mean": float(np.mean(errors)), "ratios": [round(r, 5) for r in ratios]}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="*", default=list(DEFAULT_SCENES), choices=scene_kinds.SCENES)
    parser.add_argument("--public", nargs="*", default=[], help="public scenes (../shared/scenes) with a reference")
    parser.add_argument("--render-seeds", action="store_true",
                        help="each image its own render seed too (the spread then holds the render's noise)")
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--resolution", type=int, default=320, help="width; height is 3/4 of it")
    parser.add_argument("--ref-spp", type=int, default=2048)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    if not args.scenes and not args.public:
        parser.error("no scene: give --scenes and/or --public")
    if args.seeds < 2 or args.spp < 1:
        parser.error(f"--seeds must be at least 2 and --spp at least 1; got {args.seeds}, {args.spp}")
    mi.set_variant(common.VARIANT)
    size = (args.resolution, args.resolution * 3 // 4)
    rows = []
    scenes = [(name, lambda name=name: kind_scene(name, size, args.ref_spp)) for name in args.scenes]
    scenes += [(name, lambda name=name: public_scene(name)) for name in args.public]
    for name, load in scenes:
        row = spread(name, *load(), args.spp, args.seeds, args.render_seeds)
        rows.append(row)
        print(f"{name:20s} luminance {row['luminance_mean']:.4f} ± {row['luminance_standard_error']:.4f} "
              f"sd {row['luminance_sd']:.4f} "
              f"[{row['luminance_min']:.4f}, {row['luminance_max']:.4f}] "
              f"outside 1 %: {row['outside_1_percent']}/{row['seeds']}  relMSE {row['relmse_mean']:.3e}",
              flush=True)
    command = common.command(__file__, argv)
    references = ", ".join(([f"scene kinds {size[0]}×{size[1]} path {args.ref_spp} spp"] if args.scenes else []) +
                           (["public scenes their own"] if args.public else []))
    render = "render seed 100 + scene seed" if args.render_seeds else "render seed 0"
    lines = ["# One image's mean luminance over path's, scene seed by scene seed",
             "", f"`{command}` (pmic {args.spp} spp, {render}; references: {references})", "",
             "| scene | seeds | mean | standard error | sd | min | max | outside ±1 % | mean relMSE |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['seeds']} | {r['luminance_mean']:.4f} | "
                     f"{r['luminance_standard_error']:.4f} | {r['luminance_sd']:.4f} | "
                     f"{r['luminance_min']:.4f} | {r['luminance_max']:.4f} | {r['outside_1_percent']} | "
                     f"{r['relmse_mean']:.3e} |")
    stem = f"seed_spread_{size[0]}" if not args.public else "seed_spread_public"
    md = common.write_results(args.out, stem, {"command": command, "rows": rows}, lines)
    print(f"wrote {md.with_suffix('')}.json/.md")


if __name__ == "__main__":
    main()
