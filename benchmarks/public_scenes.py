"""pmic, pmic + OIDN, path and path + OIDN at equal time on the public scenes.

For every scene of ``../shared/scenes`` with a reference (its own ``refs/`` or this
project's ``benchmarks/references/public``, made by ``public_references.py``): pmic with
its default settings at ``--spp``, then ``path`` with the spp that fits the same wall
time; the same again through OIDN (same albedo and normal guides, denoiser time
included). Each image is scored against the reference: mean luminance over the
reference's, relMSE less the reference's own noise, FLIP, NaN/Inf. Equal-error
speed-ups: raw path's relMSE falls as c/t (unbiased Monte Carlo), so path would reach
pmic's error in c/e seconds; path + OIDN's does not, so it runs a ladder of 1, 2 and 4
times the equal-time spp and its time to pmic + OIDN's error is read log-log along it
(extrapolated from its last two runs beyond them, marked "~"). A speed-up over 1: pmic
reaches the error sooner.

    python benchmarks/public_scenes.py                  # every scene with a reference
    python benchmarks/public_scenes.py --scenes torus sponza --spp 32
    python benchmarks/public_scenes.py --scenes --kinds door_ajar sunlit_classroom --stem interior_kinds
    python benchmarks/public_scenes.py --scenes --kinds door_ajar --kind-scale 3 --stem door_ajar_288

``--kinds`` adds scenes built in code of the public interiors' kinds
(:data:`pmic_integrator.kinds.INTERIOR_KINDS`: a room lit through a door ajar, a sky
through windows, sun and sky through windows over a large ground, a small light high
over a tall shaft), their references rendered by ``path`` for ``--reference-seconds``
and kept (:func:`pmic_integrator.reference.cached_reference`).

Writes benchmarks/results/public_scenes.json and .md and a labelled strip per scene
(benchmarks/results/public_<scene>.png).
"""
from __future__ import annotations

import argparse
import json
import math

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import mitsuba as mi
import numpy as np

import common
from common import PUBLIC_REFERENCES, RESULTS, SHARED

ORDER = ("veach_bidir", "matpreview", "dining_room", "white_room", "sponza", "torus", "cornell_glossy")


def reference_of(name: str):
    """(image, its own noise relMSE, where it came from), or None."""
    from pmic_integrator.scenes import read_exr

    shared = SHARED / "refs" / f"{name}.npy"
    if shared.is_file():
        info = json.loads((SHARED / "refs" / f"{name}.json").read_text())
        return np.load(shared)[..., :3].astype(np.float32), info["ref_noise_relmse"], f"shared refs ({info['spp_total']} spp)"
    own = PUBLIC_REFERENCES / f"{name}.exr"
    if own.is_file():
        info = json.loads((PUBLIC_REFERENCES / f"{name}.json").read_text())
        return read_exr(own), info["noise_relmse"], f"project ({info['spp']} spp)"
    return None


def time_to_error(points, target):
    """Seconds at which the log-log curve through ``points`` ((time, relMSE), rising
    time) reaches ``target``; beyond the last point, extrapolated along the last two.
    Returns (seconds, extrapolated)."""
    points = sorted(points)
    logs = [(math.log(t), math.log(max(e, 1e-12))) for t, e in points]
    goal = math.log(max(target, 1e-12))
    if goal >= logs[0][1]:
        return points[0][0] * (points[0][1] / max(target, 1e-12)), True  # as 1/t before the first
    for (t0, e0), (t1, e1) in zip(logs, logs[1:]):
        if e1 <= goal <= e0 and e0 != e1:
            return math.exp(t0 + (goal - e0) * (t1 - t0) / (e1 - e0)), False
    (t0, e0), (t1, e1) = logs[-2], logs[-1]
    slope = (e1 - e0) / (t1 - t0) if t1 != t0 else -1.0
    if slope >= -1e-3:
        return math.inf, True  # the denoised curve stopped falling
    return math.exp(t1 + (goal - e1) / slope), True


def measure_public(name: str, spp: int, log, spec=None, path_seeds: int = 1):
    found = reference_of(name)
    if found is None:
        return None
    return measure(name, common.load_public(name), found, spp, log, spec, path_seeds)


def load_kind(name: str, reference_seconds: float, scale: int = 1):
    """(scene, (reference image, its own noise relMSE, where it came from)) of the kind
    ``name`` (its reference rendered by path for ``reference_seconds`` and kept)."""
    from pmic_integrator import kinds, reference

    scene = mi.load_dict(kinds.INTERIOR_KINDS[name](scale))
    ref = reference.cached_reference(scene, seconds=reference_seconds)
    return scene, (ref.image, ref.noise, f"kept ({ref.spp} spp)")


def scenes_with_references(scenes, kinds, reference_seconds: float, kind_scale: int, log):
    """``(label, scene, (reference, its noise, origin))`` of each public scene of ``scenes``
    that has a reference (the others logged and skipped), then of each kind of
    ``kinds`` at ``kind_scale`` (labelled ``name (×scale)``; its reference rendered
    for ``reference_seconds`` and kept)."""
    for name in scenes:
        found = reference_of(name)
        if found is None:
            log(f"{name}: no reference, skipped")
            continue
        yield name, common.load_public(name), found
    for name in kinds:
        scene, found = load_kind(name, reference_seconds, kind_scale)
        yield f"{name} (×{kind_scale})", scene, found


def add_study_arguments(parser, scenes: list, kinds: list, kind_scale: int) -> None:
    """The options of a study over public scenes and kinds (``caustic_map.py``,
    ``first_reads_spp.py``): ``--scenes``, ``--kinds``, ``--kind-scale``,
    ``--reference-seconds`` and ``--seeds``, with these defaults."""
    parser.add_argument("--scenes", nargs="*", default=scenes, help="public scenes (../shared/scenes)")
    parser.add_argument("--kinds", nargs="*", default=kinds,
                        help="scenes built in code (pmic_integrator.kinds.INTERIOR_KINDS)")
    parser.add_argument("--kind-scale", type=int, default=kind_scale)
    parser.add_argument("--reference-seconds", type=float, default=150.0,
                        help="the kinds' path references' time (kept once rendered)")
    parser.add_argument("--seeds", type=int, default=2, help="render seeds per configuration")


def study_rows(args, measure, spp) -> list:
    """``measure(label, scene, (reference, noise, origin), spp, seeds, log)`` of each
    scene of a study's ``args`` (:func:`add_study_arguments`) that has a reference."""
    return [measure(label, scene, found, spp, args.seeds, print)
            for label, scene, found in scenes_with_references(
                args.scenes, args.kinds, args.reference_seconds, args.kind_scale, print)]


def measure_kind(name: str, spp: int, reference_seconds: float, log, scale: int = 1, spec=None,
                 path_seeds: int = 1):
    scene, found = load_kind(name, reference_seconds, scale)
    return measure(name, scene, found, spp, log, spec, path_seeds)


def more_path_errors(scene, ref, spp: int, count: int) -> list[tuple[float, float]]:
    """(relMSE, seconds) of ``count`` more path renders at ``spp``, render seeds 101,
    102, ...: where path's error is fireflies, one render's relMSE at equal time moved
    2-3x between runs (the dining room: 2.5x vs 1.3x speed-up with identical pmic
    images); their mean is path's expected error."""
    from pmic_integrator import compare, metrics

    integrator = mi.load_dict(compare.PATH_INTEGRATOR)
    out = []
    for k in range(count):
        image, seconds = compare.timed_render(scene, integrator, spp, 101 + k)
        out.append((metrics.rel_mse(image, ref), seconds))
    return out


def measure(name: str, scene, found, spp: int, log, spec=None, path_seeds: int = 1):
    from pmic_integrator import compare, metrics

    ref, noise, origin = found
    results = compare.compare(scene, dict(spec or {}), spp, ref, denoised=True, log=log)
    pmic, path, pmic_dn, path_dn = results
    row = {"scene": name, "reference": origin, "reference_noise": noise}
    for r in results:
        row[r.label] = {"spp": r.spp, "seconds": r.seconds, "rel_mse": r.rel_mse - noise, "flip": r.flip,
                        "luminance": r.luminance_ratio, "finite": metrics.finite(r.image)}
    errors = [(path.rel_mse, path.seconds)] + more_path_errors(scene, ref, path.spp, path_seeds - 1)
    path_error = sum(e for e, _ in errors) / len(errors)
    path_seconds = sum(t for _, t in errors) / len(errors)
    row["path_seeds"] = [{"rel_mse": e - noise, "seconds": t} for e, t in errors]
    row["path"]["rel_mse"] = path_error - noise
    c = max(path_error - noise, 1e-12) * path_seconds
    row["speedup"] = (c / max(pmic.rel_mse - noise, 1e-12)) / pmic.seconds
    integrator = mi.load_dict(compare.with_guides(compare.PATH_INTEGRATOR))
    ladder = [(path_dn.seconds, max(path_dn.rel_mse - noise, 1e-12))]
    for factor in (2, 4):
        image, seconds = compare.timed_render(scene, integrator, path_dn.spp * factor, 7 + factor, True)
        ladder.append((seconds, max(metrics.rel_mse(image, ref) - noise, 1e-12)))
    t_path_dn, extrapolated = time_to_error(ladder, max(pmic_dn.rel_mse - noise, 1e-12))
    # Never reached (the ladder's curve stopped falling above pmic + OIDN's error): at
    # least its longest run's time, marked ">" in the table.
    row["speedup_oidn_not_reached"] = not math.isfinite(t_path_dn)
    row["speedup_oidn"] = (t_path_dn if math.isfinite(t_path_dn) else max(t for t, _ in ladder)) / pmic_dn.seconds
    row["speedup_oidn_extrapolated"] = extrapolated
    row["path_oidn_ladder"] = ladder
    for key, run in (("stats", pmic), ("stats_oidn", pmic_dn)):  # (pmic's stage times, counts)
        row[key] = {k: v for k, v in run.stats.items() if isinstance(v, (int, float, str))}
    compare.write_strip(RESULTS / f"public_{name}.png", results, ref)
    log(f"{name}: {json.dumps({k: row[k] for k in ('speedup', 'speedup_oidn')})}")
    return row


def markdown(rows, spp: int, command: str, title: str = "Public scenes") -> list[str]:
    lines = [f"# {title}: pmic against path at equal time", "",
             f"`{command}` ({common.machine_summary()}); pmic at {spp} spp, its default settings but for the command's. relMSE is "
             "less the reference's own noise; speed-up = how much sooner pmic reaches its error "
             "than path (or path + OIDN) would (~: path + OIDN's curve extrapolated; >: it stopped falling "
             "above pmic + OIDN's error, the bound is its longest run); path relMSE is the "
             "mean over its renders at equal time (`--path-seeds`, default 1).", "",
             "| scene | reference (noise) | pmic luminance | pmic relMSE | path relMSE | speed-up vs path | "
             "pmic+OIDN luminance | pmic+OIDN relMSE | path+OIDN relMSE | speed-up vs path+OIDN | "
             "pmic s | FLIP pmic / path | finite |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p, q, pd, qd = r["pmic"], r["path"], r["pmic+OIDN"], r["path+OIDN"]
        mark = ">" if r.get("speedup_oidn_not_reached") else "~" if r["speedup_oidn_extrapolated"] else ""
        lines.append(f"| {r['scene']} | {r['reference']} ({r['reference_noise']:.1e}) | {p['luminance']:.3f} | "
                     f"{p['rel_mse']:.2e} | {q['rel_mse']:.2e} | {r['speedup']:.2f}× | {pd['luminance']:.3f} | "
                     f"{pd['rel_mse']:.2e} | {qd['rel_mse']:.2e} | {mark}{r['speedup_oidn']:.2f}× | "
                     f"{p['seconds']:.1f} | {p['flip']:.3f} / {q['flip']:.3f} | "
                     f"{all(x['finite'] for x in (p, q, pd, qd))} |")
    lines += ["", "Images: `benchmarks/results/public_<scene>.png` (pmic, path, pmic+OIDN, path+OIDN, "
              "reference; each labelled with its spp, time and relMSE)."]
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=list(ORDER))
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--kinds", nargs="*", default=[],
                        help="scenes built in code (pmic_integrator.kinds.INTERIOR_KINDS)")
    parser.add_argument("--reference-seconds", type=float, default=120.0)
    parser.add_argument("--kind-scale", type=int, default=1,
                        help="the kinds' images this many times wider and taller (their pre-passes "
                             "weigh less against the render)")
    parser.add_argument("--stem", default="public_scenes",
                        help="results file name (benchmarks/results/STEM.md and .json)")
    parser.add_argument("--estimator", default=None, help="pmic's estimator (default: pmic's default)")
    parser.add_argument("--path-seeds", type=int, default=1,
                        help="path renders at equal time (render seeds) whose mean relMSE sets the "
                             "speed-up against path (one render's moves 2-3x where path has fireflies)")
    args = parser.parse_args(argv)
    if args.path_seeds < 1:
        parser.error(f"--path-seeds must be an integer >= 1, got {args.path_seeds}")
    mi.set_variant(common.VARIANT)
    spec = {"estimator": args.estimator} if args.estimator else {}
    rows = [row for name in args.scenes
            if (row := measure_public(name, args.spp, print, spec, args.path_seeds)) is not None]
    rows += [measure_kind(name, args.spp, args.reference_seconds, print, args.kind_scale, spec, args.path_seeds)
             for name in args.kinds]
    lines = markdown(rows, args.spp, common.command(__file__, argv),
                     "Public scenes" if args.scenes else "Scenes of the public interiors' kinds")
    md = common.write_results(RESULTS, args.stem, rows, lines)
    print(f"written {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
