#!/usr/bin/env python
"""How much the light that photons carry into a room on a vast sunlit ground moves from
one photon seed to the next, for several ways of shooting a sky's and a sun's rays.

The classroom kind (``pmic_integrator.kinds.sunlit_classroom``: an 8 × 3 × 6 m room on
a ground 220 m wide, lit by a sun and a sky through its windows) is lit indoors mostly
by photons that the ground sends in through the windows. Its sky and sun shoot
``emission.FOCUS_SHARE`` of their rays across the building's box (the *focus*), and the
rest across rings round it and the whole ground (``emission.focus_rings``). For each
``--config`` (``share:widening[:growth]``: ``FOCUS_SHARE``, ``FOCUS_RING_WIDENING``
(0: no rings, the rest across the whole ground) and ``FOCUS_RING_GROWTH``, by default
1 / widening) this traces the default 200 000 global photons for ``--seeds`` photon seeds and
reports the spread of the photon power landing in the room (its standard deviation
over its mean) and the largest share of it one photon carried. With ``--images N`` it
also renders N images (96×54, 32 spp, photon seeds 0..N-1, render seeds 10..) against
the kind's kept `path` reference (``public_scenes.load_kind``) and reports their mean
luminance ratio, its spread, the mean relMSE, the lookup radius and the records.

    python benchmarks/focus_spread.py --seeds 128
    python benchmarks/focus_spread.py --config 0.75:0 0.5:4 --seeds 16 --images 16

Writes ``benchmarks/results/focus_spread.{json,md}`` (``--stem`` names another).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import mitsuba as mi

RESULTS = Path(__file__).parent / "results"
CONFIGS = ["0.75:0", "0.5:4", "0.45:4", "0.55:4", "0.5:3", "0.5:6", "0.6:4", "0.4:4", "0.3:4"]


def _room(photons):
    """Green photon power of the photons inside the room, as a numpy array."""
    from pmic_integrator import kinds
    p = np.array(photons.position)
    x, y, z = p if p.shape[0] == 3 else p.T
    power = np.array(photons.power)
    green = (power if power.shape[0] == 3 else power.T)[1]
    return green[kinds.inside_sunlit_classroom(x, y, z)]


def _configure(config: str) -> None:
    from pmic_integrator import emission
    share, widening, *growth = (float(v) for v in config.split(":"))
    emission.FOCUS_SHARE = share
    emission.FOCUS_RING_GROWTH = growth[0] if growth else 1.0 / widening if widening > 0 else 1.0
    emission.FOCUS_RING_WIDENING = widening if widening > 0 else 4.0
    emission.FOCUS_RING_MAX_RATIO = 0.5 if widening > 0 else 0.0


def photon_spread(seeds: int) -> dict:
    from pmic_integrator import kinds
    from pmic_integrator.photons import GLOBAL, trace_photons
    scene = mi.load_dict(kinds.sunlit_classroom())
    sums, largest, counts = [], [], []
    for seed in range(seeds):
        room = _room(trace_photons(scene, GLOBAL, 200_000, -1, seed, 1 << 24, warn=False))
        sums.append(float(room.sum()))
        largest.append(float(room.max() / room.sum()))
        counts.append(len(room))
    return {"room_power_mean": float(np.mean(sums)),
            "room_power_spread": float(np.std(sums, ddof=1) / np.mean(sums)),
            "largest_photon_share": max(largest), "room_photons": float(np.mean(counts))}


def image_spread(images: int) -> dict:
    import public_scenes
    from pmic_integrator.metrics import luminance_ratio, rel_mse
    scene, (ref, noise, _) = public_scenes.load_kind("sunlit_classroom", 60)
    ratios, errors, radii, records = [], [], [], []
    for seed in range(images):
        integrator = mi.load_dict({"type": "pmic", "seed": seed})
        image = np.array(mi.render(scene, integrator=integrator, spp=32, seed=10 + seed))[..., :3]
        ratios.append(luminance_ratio(image, ref))
        errors.append(rel_mse(image, ref) - noise)
        radii.append(float(integrator.prepared.global_radius))
        records.append(integrator.prepared.index.records.count)
    return {"image_mean": float(np.mean(ratios)), "image_spread": float(np.std(ratios, ddof=1)),
            "image_ratios": [round(float(r), 4) for r in ratios], "rel_mse": float(np.mean(errors)),
            "lookup_radius": float(np.mean(radii)), "records": float(np.mean(records))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", nargs="+", default=CONFIGS, help="share:widening[:growth] (widening 0: no rings)")
    parser.add_argument("--seeds", type=int, default=128, help="photon seeds per config")
    parser.add_argument("--images", type=int, default=0, help="images per config (0: none)")
    parser.add_argument("--stem", default="focus_spread", help="results file name")
    args = parser.parse_args()
    mi.set_variant("llvm_ad_rgb")
    rows = {}
    for config in args.config:
        _configure(config)
        start = time.perf_counter()
        rows[config] = photon_spread(args.seeds)
        if args.images:
            rows[config].update(image_spread(args.images))
        rows[config]["seconds"] = time.perf_counter() - start
        print(config, json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                                  for k, v in rows[config].items()}), flush=True)
    command = "python benchmarks/focus_spread.py " + " ".join(
        ["--config", *args.config, "--seeds", str(args.seeds)] + (["--images", str(args.images)] if args.images else []) +
        (["--stem", args.stem] if args.stem != "focus_spread" else []))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.stem}.json").write_text(json.dumps({"command": command, "rows": rows}, indent=1))
    lines = ["# Photon power carried into the classroom kind's room, by emission focus", "",
             f"`{command}`: over photon seeds 0-{args.seeds - 1}, 200 000 global photons; spread = "
             "standard deviation over mean of the power landing in the room; largest = the largest "
             "share of it one photon carried.", "",
             "| share:widening[:growth] | room photons | spread | largest | image mean | image sd | relMSE | radius | records |",
             "|---|---|---|---|---|---|---|---|---|"]
    for config, r in rows.items():
        image = [f"{r['image_mean']:.4f}", f"{r['image_spread']:.4f}", f"{r['rel_mse']:.2e}",
                 f"{r['lookup_radius']:.3f}", f"{r['records']:.0f}"] if "image_mean" in r else ["-"] * 5
        lines.append(f"| {config} | {r['room_photons']:.0f} | {r['room_power_spread']:.3f} | "
                     f"{r['largest_photon_share']:.3f} | " + " | ".join(image) + " |")
    (RESULTS / f"{args.stem}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
