"""``pmic-compare``: render a bundled scene with pmic and with Mitsuba's path tracer at
equal time, print both errors against the path-traced reference, and write the images.

Examples::

    pmic-compare                                   # Cornell box, 512x512, 32 spp
    pmic-compare indirect_room --spp 64 --set max_error=0.3 --set gather_rays=1024
    pmic-compare cornell_caustics --output out/ --variant cuda_ad_rgb
"""
from __future__ import annotations

import argparse
import time
import json
import sys
from pathlib import Path

import pmic_integrator  # noqa: F401  (sets up LLVM before Mitsuba loads)


def _parse_value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    return text


def _parse_settings(items):
    settings = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"pmic-compare: --set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        settings[name.strip()] = _parse_value(value.strip())
    return settings


def _parse_defines(items) -> dict:
    """``-D key=value`` pairs (Mitsuba's command line), for a scene file's ``$key``."""
    defines = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"-D expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        defines[key.strip()] = value.strip()
    return defines


def build_parser() -> argparse.ArgumentParser:
    from pmic_integrator.scenes import SCENES

    parser = argparse.ArgumentParser(
        prog="pmic-compare",
        description="Render a bundled scene with pmic and with Mitsuba's path tracer at equal "
                    "time; print both errors against the path-traced reference.")
    parser.add_argument("scene", nargs="?", default="cornell_box", choices=SCENES,
                        help="bundled scene (default: cornell_box)")
    parser.add_argument("--resolution", type=int, default=512,
                        help="image width and height in pixels; a reference must exist at this size: "
                             "512 for cornell_box and indirect_room, 128 for every scene (default: 512)")
    parser.add_argument("--spp", type=int, default=32, help="pmic samples per pixel (default: 32)")
    parser.add_argument("--set", action="append", metavar="NAME=VALUE",
                        help="a pmic parameter, e.g. --set global_photons=400000 (repeatable)")
    parser.add_argument("--denoise", action="store_true",
                        help="also render pmic + OIDN and path + OIDN at equal time (same albedo "
                             "and normal guides, wall time includes the denoiser)")
    parser.add_argument("--output", type=Path, default=Path("pmic-output"),
                        help="folder for the EXR/PNG images and results.json (default: pmic-output)")
    parser.add_argument("--variant", default="llvm_ad_rgb",
                        help="Mitsuba variant: llvm_ad_rgb (CPU) or cuda_ad_rgb (default: llvm_ad_rgb)")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.spp < 1:
        raise SystemExit(f"pmic-compare: --spp must be >= 1, got {args.spp}")
    import mitsuba as mi
    import numpy as np

    mi.set_variant(args.variant)
    from pmic_integrator import compare, scenes
    from pmic_integrator.metrics import tonemap_srgb

    spec = {"type": "pmic", **_parse_settings(args.set)}
    mi.load_dict(dict(spec))  # checks the parameters before any heavy work
    try:
        reference = scenes.load_reference(args.scene, args.resolution)
    except FileNotFoundError as error:
        print(f"pmic-compare: {error}", file=sys.stderr)
        return 2
    scene = scenes.load_scene(args.scene, resolution=args.resolution, spp=args.spp)
    print(f"scene {args.scene} at {args.resolution}x{args.resolution}, variant {args.variant}")
    print("rendering with pmic (a warm-up render compiles the kernels first) ...", flush=True)
    pmic = compare.render_measured(scene, spec, args.spp, reference, label="pmic", progress=True)
    print(f"rendering with path for the same time ({pmic.seconds:.2f} s) ...", flush=True)
    path = compare.path_at_equal_time(scene, pmic.seconds, reference)
    results = [pmic, path]
    if args.denoise:
        print("rendering pmic + OIDN, then path + OIDN for the same time ...", flush=True)
        pmic_dn = compare.render_measured(scene, spec, args.spp, reference, label="pmic+OIDN",
                                          denoised=True)
        path_dn = compare.path_at_equal_time(scene, pmic_dn.seconds, reference, denoised=True)
        path_dn.label = "path+OIDN"
        results += [pmic_dn, path_dn]

    print()
    print(f"{'integrator':12s} {'spp':>6s} {'time [s]':>9s} {'relMSE':>10s} {'FLIP':>7s} "
          f"{'low-freq':>10s} {'RMSE':>9s} {'luminance':>10s} {'CIEDE2000':>10s}")
    for r in results:
        print(f"{r.label:12s} {r.spp:6d} {r.seconds:9.2f} {r.rel_mse:10.2e} {r.flip:7.3f} "
              f"{r.low_frequency:10.2e} {r.rmse:9.4f} {r.luminance_ratio:10.4f} {r.ciede2000:10.3f}")
    print("(low-freq = relMSE of both images blurred by a 4-pixel Gaussian: structured error)")
    if args.denoise:
        dn_ratio = path_dn.rel_mse / pmic_dn.rel_mse if pmic_dn.rel_mse > 0 else float("inf")
        if dn_ratio >= 1:
            print(f"Denoised, at equal time: pmic+OIDN's relMSE is {dn_ratio:.2f}x lower than "
                  f"path+OIDN's.")
        else:
            print(f"Denoised, at equal time: path+OIDN's relMSE is {1 / dn_ratio:.2f}x lower than "
                  f"pmic+OIDN's.")
    ratio = path.rel_mse / pmic.rel_mse if pmic.rel_mse > 0 else float("inf")
    print("(relMSE = mean((img-ref)^2/(ref^2+0.01)); luminance = mean luminance / the reference's)")
    if ratio >= 1:
        print(f"\nAt equal time, pmic's relMSE is {ratio:.1f}x lower than path's.")
    else:
        hints = []
        if pmic.stats.get("time_render", pmic.seconds) < 0.5 * pmic.seconds:
            hints.append("pmic's fixed cost, photons and cache, is most of this run: try more "
                         "--spp or a larger --resolution")
        if spec.get("estimator", "final_gather") == "final_gather":
            hints.append("its default estimator (final gather) leaves noise for a denoiser to "
                         "remove: compare denoised with --denoise, or try --set estimator=first_hit")
        hint = "; ".join(hints) or "see the README's results"
        print(f"\nAt equal time, path's relMSE is {1 / ratio:.1f}x lower than pmic's ({hint}).")
    stats = pmic.stats
    stage_names = ("time_photons", "time_precompute", "time_cache", "time_cache_view", "time_render")
    stages = ", ".join(f"{k[5:]} {stats[k]:.2f} s" for k in stage_names if k in stats)
    probes = stats.get("records_probes", 0)  # first_hit only
    print(f"pmic stages: {stages}; {stats.get('photons_global', 0)} global + "
          f"{stats.get('photons_caustic', 0)} caustic photons, {stats.get('records', 0)} records"
          f"{f' ({probes} of them at surface probes)' if probes else ''}; first-run compile "
          f"overhead {pmic.compile_s:.2f} s")

    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    for r in results:
        scenes.write_exr(out / f"{args.scene}_{r.label}.exr", r.image)
    scenes.write_exr(out / f"{args.scene}_reference.exr", reference)
    strip = np.concatenate([tonemap_srgb(pmic.image), tonemap_srgb(path.image), tonemap_srgb(reference)], 1)
    mi.Bitmap(np.ascontiguousarray((strip * 255 + 0.5).clip(0, 255).astype(np.uint8))).write(
        str(out / f"{args.scene}_pmic_path_reference.png"))
    (out / "results.json").write_text(json.dumps(
        {"scene": args.scene, "resolution": args.resolution, "variant": args.variant,
         "results": [r.row() for r in results]}, indent=2, default=str))
    print(f"images and results.json written to {out.resolve()}")
    return 0


def render_views_main(argv=None) -> int:
    """``pmic-render-views``: frames from one cache: every sensor of a scene (or
    ``--sensors``), several scene files that share their geometry, or a camera path
    (``--camera-path keys.json --frames N``); on a local Dask cluster or
    ``--scheduler``; EXR images and PNG previews into ``--output``."""
    parser = argparse.ArgumentParser(
        prog="pmic-render-views",
        description="Build pmic's cache of a scene once and render many frames from it on Dask "
                    "(a local cluster, or --scheduler ADDRESS): the sensors of one scene, scene "
                    "files that share their shapes, materials and lights (one frame each), or a "
                    "camera path through key look-ats. Writes EXR images and PNG previews.")
    parser.add_argument("scenes", type=Path, nargs="+", metavar="scene.xml",
                        help="Mitsuba XML scene file; several: one frame per file (sensor 0), "
                             "all rendered from the first file's cache")
    parser.add_argument("--sensors", type=int, nargs="+", default=None,
                        help="one scene: sensor indices (default: all)")
    parser.add_argument("--camera-path", type=Path, default=None, metavar="KEYS.json",
                        help="one scene: a JSON list of key cameras, each {\"origin\": [x, y, z], "
                             "\"target\": [x, y, z], \"up\": [x, y, z] (optional), \"fov\": degrees "
                             "(optional)}; sensor 0 moves through them, interpolated linearly")
    parser.add_argument("--frames", type=int, default=None,
                        help="with --camera-path: how many frames (default: one per key)")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0,
                        help="render seed; frames of a camera path or of several files use "
                             "seed, seed+1, ... (default: 0)")
    parser.add_argument("--set", action="append", metavar="NAME=VALUE", help="a pmic parameter (repeatable)")
    parser.add_argument("-D", dest="defines", action="append", metavar="KEY=VALUE", default=[],
                        help="a value for a $KEY parameter of the scene files (repeatable)")
    parser.add_argument("--cache-file", type=Path, default=None, help="reuse or keep the cache here")
    parser.add_argument("--scheduler", default=None, help="address of a Dask scheduler")
    parser.add_argument("--workers", type=int, default=1, help="local cluster: worker processes")
    parser.add_argument("--threads", action="store_true",
                        help="local cluster: workers are threads of this process, sharing one "
                             "scene, one cache and the compiled kernels (faster on one machine)")
    parser.add_argument("--no-png", action="store_true", help="write the EXR images only")
    parser.add_argument("--output", type=Path, default=Path("pmic-views"))
    parser.add_argument("--variant", default="llvm_ad_rgb")
    args = parser.parse_args(argv)
    from pmic_integrator import views

    scene = args.scenes[0]
    load_args = _parse_defines(args.defines)
    if len(args.scenes) > 1:
        if args.sensors or args.camera_path:
            parser.error("several scene files take neither --sensors nor --camera-path")
        frames = views.frames_of_files(args.scenes, args.seed)
    elif args.camera_path is not None:
        if args.sensors:
            parser.error("--camera-path moves sensor 0: give no --sensors")
        keys = json.loads(args.camera_path.read_text())
        frames = views.frames_along_path(scene, keys, args.frames or len(keys), seed=args.seed)
    else:
        if args.frames is not None:
            parser.error("--frames goes with --camera-path")
        import mitsuba as mi

        mi.set_variant(args.variant)
        frames = views.frames_of_sensors(scene, args.sensors, args.seed, load_args)
    start = time.perf_counter()
    images = views.render_frames(frames, args.spp, _parse_settings(args.set), args.cache_file,
                                 args.scheduler, n_workers=args.workers, processes=not args.threads,
                                 variant=args.variant, **load_args)
    views.write_frames(frames, images, args.output, png=not args.no_png)
    seconds = time.perf_counter() - start
    print(f"{len(images)} frames in {seconds:.1f} s ({len(images) / seconds:.2f} frames/s), "
          f"written to {args.output.resolve()} (EXR{'' if args.no_png else ' and PNG'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
