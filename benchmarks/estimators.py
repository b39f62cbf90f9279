"""pmic's estimators side by side at equal spp, raw and through OIDN, on the public
scenes and on the interior kinds built in code.

For each scene and estimator: two renders (render seeds 0 and 1, after a warm-up that
compiles the kernels), each scored against the reference (relMSE less the reference's
own noise, raw and after OIDN with albedo/normal guides; mean luminance over the
reference's); the table gives the means and the mean render time. The renders ask for
no AOVs; OIDN gets the guides of Mitsuba's ``aov`` integrator. The estimators
share one cache where they can (``adaptive`` and ``final_gather``), so the times
compare their camera passes.

    python benchmarks/estimators.py                                    # every scene
    python benchmarks/estimators.py --scenes door_ajar sponza --estimators final_gather adaptive

References: the public scenes' (``public_scenes.reference_of``), the kinds' kept path
renders (:func:`pmic_integrator.reference.cached_reference`, ``--reference-seconds``).
Writes benchmarks/results/estimators.md and .json.
"""
from __future__ import annotations

import argparse
import time

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import mitsuba as mi
import numpy as np

import common
from common import RESULTS
from public_scenes import ORDER, load_kind, reference_of
from pmic_integrator.kinds import INTERIOR_KINDS


def load(name: str, reference_seconds: float):
    """(scene, reference image, the reference's own relMSE noise)."""
    if name in INTERIOR_KINDS:
        scene, (image, noise, _) = load_kind(name, reference_seconds)
        return scene, image, noise
    found = reference_of(name)
    if found is None:
        raise SystemExit(f"{name}: no reference (benchmarks/public_references.py makes them)")
    return common.load_public(name), found[0], found[1]


def guides_of(scene, spp: int):
    """The denoiser's guides (albedo, shading normal) of ``scene``, as Mitsuba's ``aov``
    integrator computes them: the same for every estimator's raw image."""
    integrator = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,normal:sh_normal"})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=0))


def measure(scene, ref, noise, estimator: str, spp: int, guides=None) -> dict:
    """Raw renders (no AOVs asked for: the image as it is rendered for viewing) at
    render seeds 0 and 1, scored raw and after OIDN with ``guides`` (from
    :func:`guides_of`): what OIDN makes of that raw image. (A render that outputs the
    guides itself is meant for a denoiser: there ``adaptive`` makes no first reads and
    renders ``final_gather``'s image.)"""
    from pmic_integrator import compare, metrics

    integrator = mi.load_dict({"type": "pmic", "estimator": estimator})
    mi.render(scene, integrator=integrator, spp=1, seed=5)  # (compiles; builds the cache)
    guides = guides_of(scene, spp) if guides is None else guides
    rows = []
    for seed in (0, 1):
        start = time.perf_counter()
        image = np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed))
        seconds = time.perf_counter() - start
        denoised = compare.denoise_guided(np.concatenate([image[..., :3], guides], axis=-1))
        rows.append((metrics.rel_mse(image[..., :3], ref) - noise, metrics.rel_mse(denoised, ref) - noise,
                     metrics.luminance_ratio(image[..., :3], ref), seconds,
                     metrics.finite(image) and metrics.finite(denoised)))
    raw, oidn, lum, seconds, finite = zip(*rows)
    return {"rel_mse": float(np.mean(raw)), "rel_mse_oidn": float(np.mean(oidn)),
            "luminance": float(np.mean(lum)), "seconds": float(np.mean(seconds)), "finite": all(finite)}


def markdown(rows, estimators, spp: int, command: str) -> list[str]:
    lines = ["# pmic's estimators at equal spp", "",
             f"`{command}` ({common.machine_summary()}); {spp} spp, means over render seeds 0 and 1; "
             "relMSE less the reference's own noise; raw renders without AOVs, then OIDN with the albedo/normal guides "
             "of Mitsuba's `aov` integrator (a render that outputs the guides itself is rendered by `adaptive` "
             "as by `final_gather`).", "",
             "| scene | " + " | ".join(f"{e} relMSE / +OIDN / luminance / s" for e in estimators) + " |",
             "|---|" + "---|" * len(estimators)]
    for row in rows:
        cells = [f"{r['rel_mse']:.2e} / {r['rel_mse_oidn']:.2e} / {r['luminance']:.3f} / {r['seconds']:.2f}"
                 for r in (row[e] for e in estimators)]
        lines.append(f"| {row['scene']} | " + " | ".join(cells) + " |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=list(INTERIOR_KINDS) + list(ORDER))
    parser.add_argument("--estimators", nargs="+", default=["final_gather", "adaptive"])
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--reference-seconds", type=float, default=60.0)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    rows = []
    for name in args.scenes:
        scene, ref, noise = load(name, args.reference_seconds)
        row = {"scene": name, "reference_noise": noise}
        guides = guides_of(scene, args.spp)
        for estimator in args.estimators:
            row[estimator] = measure(scene, ref, noise, estimator, args.spp, guides)
            print(f"{name} {estimator}: {row[estimator]}", flush=True)
        rows.append(row)
    lines = markdown(rows, args.estimators, args.spp, common.command(__file__, argv))
    print(f"written {common.write_results(RESULTS, 'estimators', rows, lines)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
