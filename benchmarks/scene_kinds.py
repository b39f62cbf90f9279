#!/usr/bin/env python
"""pmic against ``path`` at equal time on scenes of the kinds the public checks use,
built in code: a room lit through a door ajar from the next room (diffuse floor, and a
rough-aluminium floor whose glossy lobe fills the caustic map, every surface of
Mitsuba's principled BSDF as Blender exports them, and every surface rough plastic), a courtyard under a
constant sky, with and without a sun, a room lit by a sky through a thin glass pane
in its window (all of its light caustic), the lit room of the door-ajar pair lit by a
bulb (a point light) and a spot instead (delta lights, which the records leave out),
and that room with a glass sphere on a table (a caustic under an area light).

    python benchmarks/scene_kinds.py                     # 320×240, pmic 16 spp, ~8 minutes
    python benchmarks/scene_kinds.py --scenes courtyard_sun --resolution 160
    python benchmarks/scene_kinds.py --rounds 5 --path-spp 64   # alternating rounds

As ``../shared/scenes/compare_with_path.py`` does it: pmic at its defaults and ``--spp``
samples per pixel, timed after a warm-up with another seed (every stage included);
``path`` then given pmic's wall time (its spp from its measured rate); each timed as the
fastest of two runs; both scored by
relMSE against a ``path`` reference of ``--ref-spp`` samples (computed once, kept in
``~/.cache/pmic-benchmarks``; its own noise is in both errors). Speed-up = how much
sooner pmic reaches its error than ``path`` would, with path's relMSE falling as 1/t.
Writes ``benchmarks/results/scene_kinds_<res>.{json,md}`` (with ``--rounds``:
``scene_kinds_<res>_rounds``, see :func:`measure_rounds`). The luminance ratio is
:func:`pmic_integrator.metrics.luminance_ratio` (Rec. 709 weights); the tables written
up to commit 3439931 hold the ratio of the plain means of R, G and B.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import mitsuba as mi

from pmic_integrator import kinds
from pmic_integrator.compare import timed_render
from pmic_integrator.metrics import luminance_ratio, rel_mse

import common

CACHE = Path.home() / ".cache" / "pmic-benchmarks"
ROUGH_ALUMINIUM = {"type": "roughconductor", "material": "Al", "alpha": 0.25}


def scene_dict(name: str, size):
    """Scenes of :mod:`pmic_integrator.kinds`, with Mitsuba's default pixel filter (a
    Gaussian), as real scenes have, instead of the tests' box."""
    if name == "door_diffuse":
        d = kinds.two_rooms(door_width=0.25, size=size)
    elif name == "door_rough_floor":
        d = kinds.two_rooms(door_width=0.25, size=size, floor_bsdf=ROUGH_ALUMINIUM)
    elif name == "door_principled":
        # Every surface Mitsuba's principled BSDF at Blender's default roughness (what
        # Blender exports): its lobes cannot be taken apart.
        def principled(rgb):
            return {"type": "principled", "base_color": {"type": "rgb", "value": list(rgb)},
                    "roughness": 0.5}
        d = kinds.two_rooms(door_width=0.25, size=size, wall_bsdf=principled((0.7, 0.7, 0.7)))
        for key, rgb in (("back", (0.6, 0.6, 0.4)), ("left", (0.7, 0.2, 0.2)), ("right", (0.2, 0.6, 0.2))):
            d[key]["bsdf"] = principled(rgb)
    elif name == "door_rough_plastic":
        # Every surface rough plastic, as exported scenes often have it (walls alpha 0.3,
        # a glossier floor, 0.15): each coat a weak glossy lobe beside the diffuse one.
        def rough_plastic(rgb, alpha=0.3):
            return {"type": "roughplastic", "diffuse_reflectance": {"type": "rgb", "value": list(rgb)},
                    "alpha": alpha}
        d = kinds.two_rooms(door_width=0.25, size=size, wall_bsdf=rough_plastic((0.7, 0.7, 0.7)),
                         floor_bsdf=rough_plastic((0.6, 0.5, 0.4), alpha=0.15))
        for key, rgb in (("back", (0.6, 0.6, 0.4)), ("left", (0.7, 0.2, 0.2)), ("right", (0.2, 0.6, 0.2))):
            d[key]["bsdf"] = rough_plastic(rgb)
    elif name == "courtyard_sun":
        d = kinds.courtyard(size=size)
    elif name == "courtyard_overcast":
        d = kinds.courtyard(size=size, sun=False)
    elif name == "room_lamps":
        d = kinds.two_rooms(door_width=0.25, size=size, camera_in_lit_room=True)
        d.pop("light")
        d["bulb"] = {"type": "point", "position": [-1.5, 0.6, 0.3],
                     "intensity": {"type": "rgb", "value": [3.0, 3.0, 2.5]}}
        d["spot"] = {"type": "spot", "intensity": 15.0, "cutoff_angle": 25.0,
                     "to_world": mi.ScalarTransform4f().look_at(origin=[-0.5, 0.95, -0.5],
                                                                target=[-1.0, -1.0, 0.0], up=[0, 0, 1])}
    elif name == "glass_on_table":
        d = kinds.two_rooms(door_width=0.25, size=size, camera_in_lit_room=True)
        d["table"] = kinds._box_part((-1.0, -0.6, 0.0), (0.4, 0.02, 0.4), kinds._diffuse((0.6, 0.5, 0.4)))
        d["glass"] = {"type": "sphere", "center": [-1.0, -0.45, 0.0], "radius": 0.13,
                      "bsdf": {"type": "dielectric"}}
    elif name == "window_pane":
        d = kinds.window_room(size=size)
        d["pane"] = {"type": "rectangle", "bsdf": {"type": "thindielectric"},
                     "to_world": mi.ScalarTransform4f().translate([0, 1.4, 1.99]).scale([0.6, 0.4, 1])}
    else:
        raise ValueError(f"scene must be one of {SCENES}; got {name!r}")
    d["sensor"]["film"].pop("rfilter", None)
    return d


SCENES = ("door_diffuse", "door_rough_floor", "door_principled", "door_rough_plastic", "courtyard_sun",
          "courtyard_overcast", "window_pane", "room_lamps", "glass_on_table")
REPEATS = 2


def reference(name, size, ref_spp, scene):
    """The scene's ``path`` reference of ``ref_spp`` samples, computed once and kept."""
    CACHE.mkdir(parents=True, exist_ok=True)
    ref_file = CACHE / f"{name}_{size[0]}x{size[1]}_{ref_spp}_gaussian.npy"
    if not ref_file.exists():
        np.save(ref_file, np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}),
                                             spp=ref_spp, seed=1_000_000), dtype=np.float32))
    return np.load(ref_file)[..., :3].astype(np.float64)


def measure_rounds(name, size, spp, ref_spp, rounds, path_spp):
    """pmic (``spp``) and ``path`` (``path_spp``) rendered alternately, ``rounds`` times
    each, every round with other seeds (pmic's scene seed and render seed; path's render
    seed): the median time and the mean relMSE of each. Steadier than one equal-time
    run where the two are close: the machine's speed drifts between two runs by more
    than they differ, and one run's relMSE is one draw. Speed-up as :func:`measure`'s
    (path's relMSE falling as 1/t)."""
    scene = mi.load_dict(scene_dict(name, size))
    ref = reference(name, size, ref_spp, scene)
    timed_render(scene, mi.load_dict({"type": "pmic", "seed": 1000}), spp, 1000)  # warm-ups
    path = mi.load_dict({"type": "path"})
    timed_render(scene, path, 8, 1000)
    pmic_runs, path_runs = [], []
    for r in range(rounds):
        pmic = mi.load_dict({"type": "pmic", "seed": r})
        img, t = timed_render(scene, pmic, spp, r)
        pmic_runs.append((t, rel_mse(img, ref), luminance_ratio(img, ref), pmic.stats))
        pimg, t = timed_render(scene, path, path_spp, 100 + r)
        path_runs.append((t, rel_mse(pimg, ref)))
    t_pmic = float(np.median([x[0] for x in pmic_runs]))
    t_path = float(np.median([x[0] for x in path_runs]))
    e_pmic = float(np.mean([x[1] for x in pmic_runs]))
    e_path = float(np.mean([x[1] for x in path_runs]))
    stats = min(pmic_runs, key=lambda x: x[0])[3]
    return {"scene": name, "resolution": list(size), "pmic_spp": spp, "pmic_s": t_pmic,
            "pmic_relmse": e_pmic, "pmic_relmse_sd": float(np.std([x[1] for x in pmic_runs])),
            "pmic_luminance_ratio": float(np.mean([x[2] for x in pmic_runs])),
            "pmic_stages": {k: stats[k] for k in ("time_photons", "time_precompute", "time_cache",
                                                   "time_render")},
            "photons_caustic": stats["photons_caustic"], "records": stats["records"],
            "path_spp": path_spp, "path_s": t_path, "path_relmse": e_path,
            "path_relmse_sd": float(np.std([x[1] for x in path_runs])), "rounds": rounds,
            "speedup": (e_path * t_path) / (e_pmic * t_pmic),
            "finite": all(bool(np.isfinite(x[1])) for x in pmic_runs), "reference_spp": ref_spp}


def measure(name, size, spp, ref_spp):
    scene = mi.load_dict(scene_dict(name, size))
    ref = reference(name, size, ref_spp, scene)
    timed_render(scene, mi.load_dict({"type": "pmic", "seed": 1}), spp, 1)  # warm-up (compiles)
    # The fastest of REPEATS runs of each (a fresh pmic each time: every stage again;
    # the same seeds, so the same images): one run's time moved by ±30 %.
    runs = []
    for _ in range(REPEATS):
        pmic = mi.load_dict({"type": "pmic"})
        img, t = timed_render(scene, pmic, spp, 0)
        runs.append((t, img, pmic.stats))
    t_pmic, img, stats = min(runs, key=lambda r: r[0])
    path = mi.load_dict({"type": "path"})
    _, t_rate = timed_render(scene, path, 8, 1)  # warm-up, then the rate
    _, t_rate = timed_render(scene, path, 32, 2)
    path_spp = max(1, round(32 * t_pmic / t_rate))
    pimg, t_path = min((timed_render(scene, path, path_spp, 3) for _ in range(REPEATS)), key=lambda r: r[1])
    e_pmic, e_path = rel_mse(img, ref), rel_mse(pimg, ref)
    return {"scene": name, "resolution": list(size), "pmic_spp": spp, "pmic_s": t_pmic,
            "pmic_relmse": e_pmic, "pmic_luminance_ratio": luminance_ratio(img, ref),
            "pmic_stages": {k: stats[k] for k in ("time_photons", "time_precompute", "time_cache",
                                                   "time_render")},
            "photons_caustic": stats["photons_caustic"], "records": stats["records"],
            "path_spp": path_spp, "path_s": t_path, "path_relmse": e_path,
            "speedup": (e_path * t_path) / (e_pmic * t_pmic),
            "finite": bool(np.isfinite(img).all()), "reference_spp": ref_spp}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--resolution", type=int, default=320, help="width; height is 3/4 of it")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--ref-spp", type=int, default=2048)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    parser.add_argument("--rounds", type=int, default=0,
                        help="instead of one equal-time run: this many alternating rounds of "
                             "pmic and path (path at --path-spp), other seeds each round")
    parser.add_argument("--path-spp", type=int, default=64, help="path's spp with --rounds")
    args = parser.parse_args(argv)
    if args.rounds < 0 or args.path_spp < 1 or args.spp < 1:
        parser.error("--rounds must be >= 0, --spp and --path-spp >= 1")
    mi.set_variant(common.VARIANT)
    size = (args.resolution, args.resolution * 3 // 4)
    rows = []
    for name in args.scenes:
        row = measure_rounds(name, size, args.spp, args.ref_spp, args.rounds, args.path_spp) \
            if args.rounds else measure(name, size, args.spp, args.ref_spp)
        rows.append(row)
        print(f"{name:20s} pmic {row['pmic_s']:.2f} s relMSE {row['pmic_relmse']:.2e} "
              f"lum {row['pmic_luminance_ratio']:.4f} | path {row['path_spp']} spp {row['path_s']:.2f} s "
              f"relMSE {row['path_relmse']:.2e} | speed-up {row['speedup']:.2f}", flush=True)
    stem = f"scene_kinds_{size[0]}" + ("_rounds" if args.rounds else "")
    command = common.command(__file__, argv)
    earlier = args.out / f"{stem}.json"
    if set(args.scenes) != set(SCENES) and earlier.exists():
        # A run over some of the scenes replaces their rows and keeps the others'
        # (each row says which command measured it).
        kept = json.loads(earlier.read_text())
        for row in kept["rows"]:
            row.setdefault("command", kept.get("command", ""))
        for row in rows:
            row["command"] = command
        done = {r["scene"] for r in rows}
        rows = [r for r in kept["rows"] if r["scene"] not in done] + rows
        rows.sort(key=lambda r: SCENES.index(r["scene"]) if r["scene"] in SCENES else len(SCENES))
    how = (f"{args.rounds} alternating rounds, pmic {args.spp} spp and path {args.path_spp} spp; median "
           f"time, mean relMSE" if args.rounds else f"pmic {args.spp} spp, path at equal time")
    lines = [f"# pmic against path, scenes of the public checks' kinds, {size[0]}×{size[1]}",
             "", f"`{command}` ({how}; reference: path {args.ref_spp} spp)", "",
             "| scene | pmic s | photons / precompute / cache / render s | pmic relMSE | luminance | "
             "path spp | path relMSE | speed-up |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        st = r["pmic_stages"]
        lines.append(f"| {r['scene']} | {r['pmic_s']:.2f} | {st['time_photons']:.2f} / "
                     f"{st['time_precompute']:.2f} / {st['time_cache']:.2f} / {st['time_render']:.2f} | "
                     f"{r['pmic_relmse']:.2e} | {r['pmic_luminance_ratio']:.4f} | {r['path_spp']} | "
                     f"{r['path_relmse']:.2e} | {r['speedup']:.2f} |")
    others = [r for r in rows if r.get("command", command) != command]
    if others:
        lines += ["", "Rows measured by an earlier run (kept by a run over other scenes):", ""]
        lines += [f"* {r['scene']}: `{r['command']}`" for r in others]
    md = common.write_results(args.out, stem, {"command": command, "rows": rows}, lines)
    print(f"wrote {md.with_suffix('')}.json/.md")


if __name__ == "__main__":
    main()
