"""What the records' gathers read at their hits: the share of photon lookups whose
nearest photon was found and seen, found but hidden by the visibility test
(``GatherSource._visible``: the lookup reads 0), or not found at all; and the image's
mean luminance against the reference, with the test as it is and, for comparison,
with no test at all (which leaks through thin walls: an upper bound, not a setting),
and with the lookups that find no photon reading the mean of the seen ones (a probe
of what those lookups are worth, not a setting).

    python benchmarks/gather_visibility.py                       # white room, Sponza
    python benchmarks/gather_visibility.py --scenes veach_bidir --spp 16

The counts come from wrapping ``GatherSource._visible`` for the evaluated batches of
the records' gathers (``GatherSource.irradiance_of``); camera paths' lookups run
inside symbolic loops and are not counted. Results go to
``benchmarks/results/gather_visibility.md``.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import drjit as dr
import mitsuba as mi

import common
from public_scenes import reference_of
from pmic_integrator import gather, metrics


#: What each mode's row is called in the table.
MODES = {"on": "on; unanswered: traced", "zero": "on; unanswered: 0", "off": "off (leaks); none found: 0",
         "fill": "on; none found: batch mean, hidden: 0",
         "near": "on; unanswered: traced, near hits bounced on"}


def render_counting(scene, spp: int, mode: str) -> tuple[np.ndarray, dict]:
    """pmic's image at defaults, and the records' lookups counted by outcome. ``mode``:
    "on" (as pmic runs: lookups no photon answers, hidden or not found, are answered by
    a traced bounce, ``gather.TRACE_UNANSWERED``), "zero" (they read 0, as before),
    "off" (every found photon is read: no visibility test; none found: 0), "fill"
    (lookups that find no photon read the mean irradiance of the batch's seen ones,
    hidden ones 0: a probe of what those lookups are worth), or "near" (traced, and a
    traced ray's near hit bounced on as a gather ray's: ``gather.TRACED_NEAR_HITS``)."""
    counts = {"seen": 0, "hidden": 0, "not found": 0}
    original, original_of = gather.GatherSource._visible, gather.GatherSource.irradiance_of
    last = {}

    def counted(self, scene, p, n, position, found):
        if dr.flag(dr.JitFlag.SymbolicScope):  # a camera path's lookup: left as it is
            return original(self, scene, p, n, position, found)
        seen = mi.Bool(found) if mode == "off" else original(self, scene, p, n, position, found)
        counts["seen"] += int(dr.count(seen)[0])
        counts["hidden"] += int(dr.count(found & ~seen)[0])
        counts["not found"] += int(dr.count(~found)[0])
        last.update(found=found, seen=seen)
        return seen

    def filled(self, scene, p, n, without_delta=False, caustic=None, with_seen=False):
        last.clear()
        value, seen = original_of(self, scene, p, n, without_delta, caustic, with_seen=True)
        if last:
            count = max(int(dr.count(seen)[0]), 1)
            mean = mi.Color3f(*(float(dr.sum(dr.select(seen, value[i], 0.0))[0]) / count for i in range(3)))
            value = dr.select(last["found"], value, mean)
        return (value, seen) if with_seen else value

    traced, near = gather.TRACE_UNANSWERED, gather.TRACED_NEAR_HITS
    gather.GatherSource._visible = counted
    gather.TRACE_UNANSWERED = mode in ("on", "near")
    gather.TRACED_NEAR_HITS = mode == "near"
    if mode == "fill":
        gather.GatherSource.irradiance_of = filled
    try:
        image = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "pmic"}), spp=spp))
    finally:
        gather.GatherSource._visible, gather.GatherSource.irradiance_of = original, original_of
        gather.TRACE_UNANSWERED, gather.TRACED_NEAR_HITS = traced, near
    return image[..., :3], counts


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["white_room", "sponza"])
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--stem", default="gather_visibility")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    rows = []
    for name in args.scenes:
        reference = reference_of(name)
        if reference is None:
            print(f"{name}: no reference (benchmarks/public_references.py), skipped")
            continue
        ref, noise, _ = reference
        for mode in args.modes:
            image, counts = render_counting(common.load_public(name), args.spp, mode)
            total = max(sum(counts.values()), 1)
            row = {"scene": name, "visibility test": MODES[mode],
                   "lookups": total, **{k: v / total for k, v in counts.items()},
                   "luminance": metrics.luminance_ratio(image, ref),
                   "relMSE": metrics.rel_mse(image, ref) - noise}
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = [f"# The records' photon lookups: seen, hidden, not found ({args.spp} spp)", "",
             f"`{common.command(__file__, argv)}` ({common.machine_summary()})",
             "", "| scene | visibility test | lookups | seen | hidden | not found | luminance | relMSE |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['visibility test']} | {r['lookups']:,} | {r['seen']:.3f} | "
                     f"{r['hidden']:.3f} | {r['not found']:.3f} | {r['luminance']:.4f} | {r['relMSE']:.3e} |")
    print(f"written {common.write_results(common.RESULTS, args.stem, rows, lines)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
