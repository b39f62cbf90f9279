#!/usr/bin/env python
"""What the caustic map buys, scene by scene: pmic with its caustic map against pmic
without one (``caustic_photons=0``: gather rays and camera paths trace caustic light
instead), raw and through OIDN, at the same spp.

For each scene it reports, from the default global photon map (no caustic pass):

* the *caustic share*: the power of the global map's caustic photons (light -> one or
  more delta or glossy bounces -> a diffuse surface) over theirs plus the direct
  photons';
* the *caustic standout* (:func:`pmic_integrator.irradiance.caustic_standout`): at up
  to 400 of those caustic photons, the caustic share of the global map's irradiance
  estimate there, averaged with the photons' power as weights. A focused caustic (a
  glass sphere's spot) stands out from the light around it (near 1); light that glass
  or a glossy floor spreads through a room does not (near its share). A render for a
  denoiser goes without the map below ``pipeline.CAUSTIC_MIN_STANDOUT``...
* ...where tracing finds them readily, too: the *traced moment*
  (:func:`pmic_integrator.pipeline.traced_caustics_moment`), the relative second
  moment of the caustic light one cosine ray finds by tracing from those photons, at
  most ``pipeline.CAUSTIC_MAX_TRACED_MOMENT``.

Then, for each configuration and render seed, relMSE (less the reference's own noise),
seconds (every stage, the denoiser's time included) and mean luminance over the
reference; and *efficiency*: relMSE × seconds with the map over the same product
without it (above 1: the map costs more than it saves; for raw images the equal-time
ratio of errors, since a path tracer's relMSE falls as 1/t; after OIDN an indication
only). "With the map" keeps it for a denoiser too (``CAUSTIC_MIN_STANDOUT`` set to 0
for those renders).

    python benchmarks/caustic_map.py
    python benchmarks/caustic_map.py --scenes --kinds tall_stairwell --kind-scale 3

Writes ``benchmarks/results/caustic_map.{json,md}`` (``--stem`` names another).
"""
from __future__ import annotations

import argparse

import pmic_integrator  # noqa: F401  (registers pmic; before drjit/mitsuba)
import drjit as dr
import mitsuba as mi
import numpy as np

import common
import public_scenes

from pmic_integrator import compare, metrics, pipeline
from pmic_integrator.settings import Settings

CONFIGS = {"with the map": {}, "without": {"caustic_photons": 0}}


def caustic_figures(scene: mi.Scene) -> dict:
    """The caustic share, standout and traced moment of the scene's default global map
    (the last only where the standout is under ``pipeline.CAUSTIC_MIN_STANDOUT``), and
    what a render for a denoiser does with them."""
    settings = Settings(aovs="albedo,normal")
    info = pipeline.SceneInfo.of(scene)
    photons, _ = pipeline.trace_maps(scene, settings, info, True, False, [], pipeline.Progress())
    figures = {"share": 0.0, "caustic_photons": 0, "caustic_standout": 0.0, "for_denoiser": "with the map"}
    if photons.count == 0:
        return figures
    power = mi.luminance(photons.power)
    caustic = photons.caustic
    caustic_power = dr.sum(dr.select(caustic, power, 0.0))[0]
    direct_power = dr.sum(dr.select(photons.depth == 1, power, 0.0))[0]
    figures["share"] = float(caustic_power / max(caustic_power + direct_power, 1e-30))
    figures["caustic_photons"] = int(dr.count(caustic)[0])
    traced = pipeline.caustics_traced_for_denoiser(scene, settings, info, photons, figures)
    if traced and pipeline.leaves_caustics_to_denoiser(settings, info):
        figures["for_denoiser"] = "without"
    return figures


def render(scene, spec: dict, spp: int, ref, seed: int, denoised: bool):
    """``compare.render_measured`` of pmic with ``spec``; with the map (``spec``
    empty), kept for a denoiser too."""
    keep = pipeline.CAUSTIC_MIN_STANDOUT
    if not spec:
        pipeline.CAUSTIC_MIN_STANDOUT = 0.0
    try:
        return compare.render_measured(scene, {"type": "pmic", **spec}, spp, ref, seed=seed,
                                       denoised=denoised)
    finally:
        pipeline.CAUSTIC_MIN_STANDOUT = keep


def measure(name: str, scene: mi.Scene, found, spp: int, seeds: int, log) -> dict:
    ref, noise, origin = found
    figures = caustic_figures(scene)
    moment = figures.get("caustic_traced_moment")
    log(f"{name}: caustic share {figures['share']:.3f}, standout {figures['caustic_standout']:.3f}, "
        f"traced moment {moment if moment is None else round(moment, 1)} "
        f"({figures['caustic_photons']} caustic photons); for a denoiser: {figures['for_denoiser']}")
    row = {"scene": name, "reference": origin, "noise": noise, **figures, "runs": {}}
    for label, spec in CONFIGS.items():
        for denoised in (False, True):
            key = f"{label}, {'OIDN' if denoised else 'raw'}"
            runs = []
            for seed in range(seeds):
                r = render(scene, spec, spp, ref, seed, denoised)
                runs.append({"seed": seed, "rel_mse": r.rel_mse - noise, "seconds": r.seconds,
                             "luminance": metrics.luminance_ratio(r.image, ref)})
                log(f"  {key} seed {seed}: relMSE {runs[-1]['rel_mse']:.3e}, {r.seconds:.2f} s, "
                    f"luminance {runs[-1]['luminance']:.4f}")
            row["runs"][key] = runs
    return row


def _mean(runs, field):
    return float(np.mean([r[field] for r in runs]))


def markdown(rows, spp: int, seeds: int, command: str) -> list[str]:
    lines = ["# The caustic map, with and without", "",
             f"`{command}` ({common.machine_summary()}); pmic at {spp} spp, render seeds "
             f"0-{seeds - 1} (means), with the caustic map and without it (`caustic_photons=0`). "
             "Efficiency: relMSE × seconds with the map over the same without it (above 1: "
             "the map costs more than it saves). *Traced moment*: the relative second moment of "
             "traced caustic samples (measured where the standout is under "
             f"`pipeline.CAUSTIC_MIN_STANDOUT` {pipeline.CAUSTIC_MIN_STANDOUT}). *For a denoiser*: "
             "what pmic's defaults do in a render with the denoiser's guides (without the map "
             f"where the moment is at most `CAUSTIC_MAX_TRACED_MOMENT` {pipeline.CAUSTIC_MAX_TRACED_MOMENT:.0f} "
             "too); raw renders keep the map.", "",
             "| scene | caustic share | standout | traced moment | for a denoiser | mode | relMSE with map | s | "
             "luminance | relMSE without | s | luminance | efficiency of going without |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for mode in ("raw", "OIDN"):
            on, off = row["runs"][f"with the map, {mode}"], row["runs"][f"without, {mode}"]
            ratio = (_mean(on, "rel_mse") * _mean(on, "seconds")) / \
                max(_mean(off, "rel_mse") * _mean(off, "seconds"), 1e-30)
            moment = row.get("caustic_traced_moment")
            lines.append(f"| {row['scene']} | {row['share']:.3f} | {row['caustic_standout']:.3f} | "
                         f"{'—' if moment is None else f'{moment:.3g}'} | {row['for_denoiser']} | {mode} | "
                         f"{_mean(on, 'rel_mse'):.2e} | {_mean(on, 'seconds'):.2f} | "
                         f"{_mean(on, 'luminance'):.4f} | {_mean(off, 'rel_mse'):.2e} | "
                         f"{_mean(off, 'seconds'):.2f} | {_mean(off, 'luminance'):.4f} | {ratio:.2f}× |")
    lines += ["", "Per seed: the `.json` file's `runs`."]
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    public_scenes.add_study_arguments(parser, ["veach_bidir", "white_room", "cornell_glossy", "torus"], [], 1)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--stem", default="caustic_map")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be an integer >= 1, got {args.seeds}")
    mi.set_variant(common.VARIANT)
    rows = public_scenes.study_rows(args, measure, args.spp)
    lines = markdown(rows, args.spp, args.seeds, common.command(__file__, argv))
    md = common.write_results(common.RESULTS, args.stem, rows, lines)
    print(f"written {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
