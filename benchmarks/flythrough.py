"""Fly-throughs from one cache: frame rate, flicker, and the scene fingerprint's cost.

Three measurements, each in one process (timings after a warm-up):

``--fps``      frames of a camera path through the indirectly lit room, rendered from one
               cache (built once) against rebuilding the cache for every frame (a new
               integrator per frame): frames per second of each and their ratio.
``--flicker``  temporal noise at equal time per frame: pmic + OIDN from one cache
               against path + OIDN with the spp that fits the same time (same guides,
               wall time includes the denoiser). Flicker of a sequence is
               mean_t mean(((F_t - R_t) - (F_t-1 - R_t-1))^2 / (R_t^2 + 0.01)): the change
               from frame to frame of each frame's error against its reference R_t, in
               relMSE's units. A static camera (R_t the bundled reference, each frame its
               own render seed) and a moving one (a path reference rendered per frame,
               whose own noise, estimated from its two halves, is subtracted).
``--fingerprint``  scene_fingerprint on a scene of about a million triangles against
               copying every traversed parameter to the host and hashing it there (what
               the fingerprint did before it hashed large buffers on the device).
``--freeze``   whether ``dr.freeze`` can wrap pmic's render (Mitsuba >= 3.7 freezes
               ``mi.render`` for its own integrators).

    python benchmarks/flythrough.py                 # all of them, 128x128, ~10 minutes on 2 cores
    python benchmarks/flythrough.py --flicker --frames 8

Writes benchmarks/results/flythrough.json and .md.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import drjit as dr
import mitsuba as mi
import numpy as np

from pmic_integrator.metrics import rel_mse

import common

SCENE = "indirect_room"
#: pmic's settings for the frames: the defaults but for the spp.
PMIC_SPP = 4
#: pmic's settings for the frames: (parameters, spp). The defaults; and what flickers
#: least at this time per frame (docs/flythrough.md): the first-hit read, whose cache
#: error is the same in every frame, with more spp and one shadow ray per vertex.
PMIC_CONFIGS = {"pmic+OIDN, defaults, 4 spp": ({}, 4),
                "pmic+OIDN, first_hit, direct_samples 1, 8 spp": ({"estimator": "first_hit",
                                                                    "direct_samples": 1}, 8)}
#: path + OIDN's spp ladder (its flicker is read at pmic's time per frame along it).
PATH_SPP = (2, 3, 4, 6, 8, 12)
#: Spp of each moving frame's path reference (noise of the flicker's reference term).
REFERENCE_SPP = 4096


def flicker(frames, references) -> float:
    """mean_t mean(((F_t - R_t) - (F_t-1 - R_t-1))^2 / (R_t^2 + 0.01)) (see the module):
    the relMSE against R_t of R_t plus the change of the frames' error."""
    values = []
    for t in range(1, len(frames)):
        change = (frames[t] - references[t]) - (frames[t - 1] - references[t - 1])
        values.append(rel_mse(references[t] + change, references[t]))
    return float(np.mean(values))


def camera_keys(scene, moving: bool, count: int):
    """Look-ats of ``count`` frames: the scene's own camera, still or moved sideways
    (10 % of the distance to its target over the sequence) and turned with it."""
    matrix = np.array(mi.traverse(scene.sensors()[0])["to_world"].matrix, dtype=np.float64).reshape(4, 4)
    origin, forward = matrix[:3, 3], matrix[:3, 2]
    target = origin + forward
    side = matrix[:3, 0]
    keys = []
    for i in range(count):
        shift = (0.1 * i / max(count - 1, 1)) if moving else 0.0
        keys.append({"origin": list(origin + shift * side), "target": list(target + 0.5 * shift * side),
                     "up": list(matrix[:3, 1])})
    return keys


def render_frames_local(scene, integrator, frames, spp, denoised):
    """Each frame rendered in this process by ``integrator``; returns (images, seconds
    per frame)."""
    from pmic_integrator import compare
    from pmic_integrator.views import place_camera

    images, seconds = [], []
    for frame in frames:
        place_camera(scene, frame)
        image, took = compare.timed_render(scene, integrator, spp, frame.seed, denoised)
        images.append(image)
        seconds.append(took)
    return images, seconds


def path_references(scene, frames, spp):
    """Path references of ``frames`` (two halves of ``spp`` each, averaged) and the
    flicker their own noise adds: 2 x mean((A - B)^2 / 4 / (R^2 + 0.01)) per frame pair
    (each reference's noise variance is a quarter of its halves' squared difference)."""
    from pmic_integrator import compare

    path = mi.load_dict(compare.PATH_INTEGRATOR)
    halves = []
    for offset in (0, 1000):
        shifted = [replace(frame, seed=frame.seed + 10_000 + offset) for frame in frames]
        halves.append(render_frames_local(scene, path, shifted, spp // 2, False)[0])
    references = [(a + b) / 2 for a, b in zip(*halves)]
    # mean((A - B)^2 / 4 / (R^2 + 0.01)): the relMSE against R of R + (A - B) / 2.
    noise = [rel_mse(r + (a - b) / 2, r) for a, b, r in zip(*halves, references)]
    return references, 2 * float(np.mean(noise))


def equal_time_spp(scene, integrator, frames, seconds, denoised, rounds: int = 3) -> int:
    """The spp at which ``integrator`` renders (and denoises) a frame in ``seconds``:
    the denoiser's fixed cost makes time not proportional to spp, so a few rounds."""
    spp = 4
    for _ in range(rounds):
        _, took = render_frames_local(scene, integrator, frames[:3], spp, denoised)
        spp = max(1, int(round(spp * seconds / float(np.median(took)))))
    return spp


def measure_flicker(resolution: int, count: int, log):
    """Flicker of pmic + OIDN in each of :data:`PMIC_CONFIGS`, against path + OIDN at
    the same time per frame (path's flicker interpolated log-log along its spp ladder
    :data:`PATH_SPP`), for a still and a moving camera."""
    from pmic_integrator import compare, scenes
    from pmic_integrator.views import frames_along_path

    scene = scenes.load_scene(SCENE, resolution=resolution, spp=PMIC_SPP)
    still_reference = scenes.load_reference(SCENE, resolution)
    out = {}
    for moving in (False, True):
        frames = frames_along_path("(in memory)", camera_keys(scene, moving, count), count, seed=100)
        if moving:
            references, reference_flicker = path_references(scene, frames, REFERENCE_SPP)
        else:  # one reference: its noise is the same in every frame and cancels
            references, reference_flicker = [still_reference] * count, 0.0
        path = mi.load_dict(compare.with_guides(compare.PATH_INTEGRATOR))
        render_frames_local(scene, path, frames[:1], 1, True)  # warm-up
        ladder = []
        for spp in PATH_SPP:
            images, seconds = render_frames_local(scene, path, frames, spp, True)
            ladder.append(_sequence_row(images, seconds, spp, references, reference_flicker))
        rows = {}
        for label, (params, spp) in PMIC_CONFIGS.items():
            pmic = mi.load_dict(compare.with_guides({"type": "pmic", **params}))
            render_frames_local(scene, pmic, frames[:1], 1, True)  # warm-up: cache and kernels
            images, seconds = render_frames_local(scene, pmic, frames, spp, True)
            row = _sequence_row(images, seconds, spp, references, reference_flicker)
            row["path_flicker_at_equal_time"] = _at_time(ladder, row["s_per_frame"])
            row["flicker_vs_path"] = row["flicker"] / row["path_flicker_at_equal_time"]
            rows[label] = row
        camera = "moving" if moving else "static"
        out[camera] = {"frames": count, "reference_flicker": reference_flicker, "rows": rows,
                       "path_ladder": ladder}
        log(f"flicker, {camera} camera: {out[camera]}")
    return out


def _at_time(ladder, seconds: float) -> float:
    """Path's flicker at ``seconds`` per frame: log-log interpolation along its ladder
    (clamped at its ends)."""
    points = sorted((row["s_per_frame"], row["flicker"]) for row in ladder)
    times, values = np.log([p[0] for p in points]), np.log([max(p[1], 1e-12) for p in points])
    return float(np.exp(np.interp(np.log(seconds), times, values)))


def _sequence_row(images, seconds, spp, references, reference_flicker) -> dict:
    return {"spp": spp, "s_per_frame": float(np.median(seconds)),
            "flicker": flicker(images, references) - reference_flicker,
            "relmse": float(np.mean([rel_mse(a, b) for a, b in zip(images, references)]))}


def measure_fps(resolution: int, count: int, log):
    from pmic_integrator import scenes
    from pmic_integrator.views import frames_along_path

    scene = scenes.load_scene(SCENE, resolution=resolution, spp=PMIC_SPP)
    frames = frames_along_path("(in memory)", camera_keys(scene, True, count), count)
    render_frames_local(scene, mi.load_dict({"type": "pmic"}), frames[:1], 1, False)  # warm-up
    one = mi.load_dict({"type": "pmic"})
    _, one_cache = common.timed(lambda: render_frames_local(scene, one, frames, PMIC_SPP, False))
    _, rebuilt = common.timed(lambda: [render_frames_local(scene, mi.load_dict({"type": "pmic"}), [frame],
                                                           PMIC_SPP, False) for frame in frames])
    row = {"frames": count, "spp": PMIC_SPP, "one_cache_fps": count / one_cache,
           "rebuild_fps": count / rebuilt, "ratio": rebuilt / one_cache,
           "cache_builds_one_cache": one.stats["cache_builds"]}
    log(f"frames per second: {row}")
    return row


def million_triangle_scene():
    """A 1000 x 500 grid of quads (999,002 triangles) under a point light."""
    nx, ny = 1001, 501
    x, y = np.meshgrid(np.linspace(-1, 1, nx, dtype=np.float32), np.linspace(-1, 1, ny, dtype=np.float32))
    z = 0.05 * np.sin(7 * x) * np.cos(5 * y)
    positions = np.stack([x, y, z], -1).reshape(-1, 3)
    i = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel().astype(np.uint32)
    faces = np.concatenate([np.stack([i, i + 1, i + nx], 1), np.stack([i + 1, i + nx + 1, i + nx], 1)])
    mesh = mi.Mesh("terrain", len(positions), len(faces), has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    return mi.load_dict({"type": "scene", "terrain": mesh,
                         "light": {"type": "point", "position": [0, 0, 2], "intensity": 10}}), len(faces)


def host_copy_digest(scene) -> str:
    """The fingerprint before: every traversed parameter copied to the host and hashed."""
    import hashlib

    digest = hashlib.blake2b(digest_size=16)
    params = mi.traverse(scene)
    for key in sorted(params.keys()):
        value = params[key]
        data = np.ascontiguousarray(np.array(value)).tobytes() if dr.is_array_v(value) else repr(value).encode()
        digest.update(key.encode())
        digest.update(data)
    return digest.hexdigest()


def measure_fingerprint(log, rounds: int = 5):
    from pmic_integrator.fingerprint import scene_fingerprint

    scene, triangles = million_triangle_scene()
    timings = {label: common.fastest(lambda: function(scene), rounds)
               for label, function in (("device_hash", scene_fingerprint), ("host_copy", host_copy_digest))}
    row = {"triangles": triangles, "device_hash_s": timings["device_hash"],
           "host_copy_s": timings["host_copy"], "ratio": timings["host_copy"] / timings["device_hash"]}
    log(f"fingerprint: {row}")
    return row


def try_freeze(resolution: int, log):
    """Whether dr.freeze can wrap a pmic render: run it twice, compare with unfrozen."""
    from pmic_integrator import scenes

    scene = scenes.load_scene(SCENE, resolution=resolution, spp=1)
    pmic = mi.load_dict({"type": "pmic"})
    mi.render(scene, integrator=pmic, spp=1)

    @dr.freeze
    def frozen(seed):
        return mi.render(scene, integrator=pmic, spp=1, seed=seed)

    try:
        images = [np.array(frozen(mi.UInt32(s))) for s in (1, 2, 3)]
        plain = np.array(mi.render(scene, integrator=pmic, spp=1, seed=3))
        row = {"works": bool(np.array_equal(images[-1], plain)), "error": ""}
    except Exception as error:  # noqa: BLE001 - reported, not hidden
        chain = []
        while error is not None and len(chain) < 4:
            chain.append(f"{type(error).__name__}: {str(error).splitlines()[0][:300]}")
            error = error.__cause__ or error.__context__
        row = {"works": False, "error": " <- ".join(chain)}
    log(f"dr.freeze: {row}")
    return row


def write_markdown(results, path: Path):
    lines = ["# Fly-throughs from one cache", "",
             f"`python benchmarks/flythrough.py` ({results['machine']}, {results['resolution']}², "
             f"scene {SCENE}).", ""]
    if "fps" in results:
        r = results["fps"]
        lines += ["## Frames per second", "",
                  "| frames | spp | one cache [fps] | cache rebuilt per frame [fps] | ratio |", "|---|---|---|---|---|",
                  f"| {r['frames']} | {r['spp']} | {r['one_cache_fps']:.3f} | {r['rebuild_fps']:.3f} | "
                  f"{r['ratio']:.2f}× |", ""]
    if "flicker" in results:
        lines += ["## Flicker at equal time per frame", "",
                  "| camera | frames | images | spp | s/frame | flicker | path+OIDN's flicker at that time | "
                  "ratio | relMSE |", "|---|---|---|---|---|---|---|---|---|"]
        for camera, cam in results["flicker"].items():
            for label, r in cam["rows"].items():
                lines.append(f"| {camera} | {cam['frames']} | {label} | {r['spp']} | {r['s_per_frame']:.3f} | "
                             f"{r['flicker']:.2e} | {r['path_flicker_at_equal_time']:.2e} | "
                             f"{r['flicker_vs_path']:.3f} | {r['relmse']:.2e} |")
            for r in cam["path_ladder"]:
                lines.append(f"| {camera} | {cam['frames']} | path+OIDN | {r['spp']} | {r['s_per_frame']:.3f} | "
                             f"{r['flicker']:.2e} | | | {r['relmse']:.2e} |")
        lines += ["", "Flicker less the references' own: "
                  + ", ".join(f"{c} {cam['reference_flicker']:.1e}" for c, cam in results["flicker"].items()), ""]
    if "fingerprint" in results:
        r = results["fingerprint"]
        lines += ["## Scene fingerprint", "",
                  f"{r['triangles']:,} triangles: device hash {1000 * r['device_hash_s']:.1f} ms, host copy "
                  f"{1000 * r['host_copy_s']:.1f} ms ({r['ratio']:.1f}× faster; best of 5).", ""]
    if "freeze" in results:
        r = results["freeze"]
        lines += ["## dr.freeze", "", f"works: {r['works']}; {r['error'] or 'images equal to unfrozen renders'}", ""]
    path.write_text("\n".join(lines))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fps", action="store_true")
    parser.add_argument("--flicker", action="store_true")
    parser.add_argument("--fingerprint", action="store_true")
    parser.add_argument("--freeze", action="store_true")
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    every = not (args.fps or args.flicker or args.fingerprint or args.freeze)
    mi.set_variant(common.VARIANT)
    # Measurements not asked for this time keep their last figures.
    kept = args.out / "flythrough.json"
    results = json.loads(kept.read_text()) if kept.is_file() else {}
    results.update({"machine": common.machine_summary(), "resolution": args.resolution})
    log = print
    if every or args.fingerprint:
        results["fingerprint"] = measure_fingerprint(log)
    if every or args.fps:
        results["fps"] = measure_fps(args.resolution, args.frames, log)
    if every or args.flicker:
        results["flicker"] = measure_flicker(args.resolution, args.frames, log)
    if every or args.freeze:
        results["freeze"] = try_freeze(args.resolution, log)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "flythrough.json").write_text(json.dumps(results, indent=2))
    write_markdown(results, args.out / "flythrough.md")
    print(f"written {args.out / 'flythrough.md'}")


if __name__ == "__main__":
    main()
