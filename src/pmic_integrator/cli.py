"""``pmic-compare``: render a scene (bundled, or any Mitsuba XML file) with pmic and with
Mitsuba's path tracer at equal time, print both errors against a path-traced reference,
and write the images. ``pmic-reference``: a reference of any scene file.
``pmic-render-views``: many frames from one cache.

Examples::

    pmic-compare                                   # Cornell box, 512x512, 32 spp
    pmic-compare indirect_room --spp 64 --set max_error=0.3 --set gather_rays=1024
    pmic-compare my_room.xml -D spp=16 --denoise   # your scene; its reference made and kept
    pmic-reference my_room.xml --time 600 -o my_room_ref.exr
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


def _key_values(items, option: str) -> dict:
    """``KEY=VALUE`` items of a repeatable ``option`` as a dict of stripped strings."""
    pairs = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"{option} expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        pairs[key.strip()] = value.strip()
    return pairs


def _parse_settings(items):
    """``--set NAME=VALUE``: pmic parameters, numbers and booleans parsed."""
    return {name: _parse_value(value) for name, value in _key_values(items, "--set").items()}


def _parse_defines(items) -> dict:
    """``-D key=value`` pairs (Mitsuba's command line), for a scene file's ``$key``."""
    return _key_values(items, "-D")


def build_parser() -> argparse.ArgumentParser:
    from pmic_integrator.scenes import SCENES

    parser = argparse.ArgumentParser(
        prog="pmic-compare",
        description="Render a scene with pmic and with Mitsuba's path tracer at equal time; print "
                    "both errors against a path-traced reference. The scene is a bundled one "
                    f"({', '.join(SCENES)}) or any Mitsuba XML file; for a file, a reference is "
                    "rendered with path on demand and kept (see --reference-spp).")
    parser.add_argument("scene", nargs="?", default="cornell_box",
                        help="a bundled scene's name or a Mitsuba XML scene file (default: cornell_box)")
    parser.add_argument("-D", dest="defines", action="append", metavar="KEY=VALUE", default=[],
                        help="a value for the scene file's $KEY parameter, as Mitsuba's command line "
                             "takes it (repeatable)")
    parser.add_argument("--resolution", type=int, default=None,
                        help="bundled scenes: image width and height; a reference must exist at this "
                             "size: 512 for cornell_box and indirect_room, 128 for every scene "
                             "(default: 512). A scene file renders at its film's size.")
    parser.add_argument("--spp", type=int, default=32, help="pmic samples per pixel (default: 32)")
    parser.add_argument("--set", action="append", metavar="NAME=VALUE",
                        help="a pmic parameter, e.g. --set global_photons=400000 (repeatable)")
    parser.add_argument("--denoise", action="store_true",
                        help="also render pmic + OIDN and path + OIDN at equal time (same albedo "
                             "and normal guides, wall time includes the denoiser)")
    parser.add_argument("--reference", type=Path, default=None, metavar="REF.exr",
                        help="a scene file's reference image (linear RGB EXR of the film's size) "
                             "instead of one rendered by path")
    parser.add_argument("--reference-spp", type=int, default=1024,
                        help="a scene file's path reference: samples per pixel, rendered once and "
                             "kept in ~/.cache/pmic/references ($PMIC_CACHE_DIR) (default: 1024)")
    parser.add_argument("--reference-time", type=float, default=None, metavar="SECONDS",
                        help="render the reference for about this long instead of --reference-spp")
    parser.add_argument("--output", type=Path, default=Path("pmic-output"),
                        help="folder for the EXR/PNG images and results.json (default: pmic-output)")
    parser.add_argument("--variant", default="llvm_ad_rgb",
                        help="Mitsuba variant: llvm_ad_rgb (CPU), llvm_ad_spectral, cuda_ad_rgb "
                             "(default: llvm_ad_rgb; the bundled scenes' references are RGB "
                             "renders: in a spectral variant compare on a scene file, whose "
                             "reference is rendered in that variant)")
    return parser


def _scene_and_reference(args, parser):
    """(scene, its name, reference image, a line saying what the reference is)."""
    from pmic_integrator import reference as refs, scenes

    if args.scene in scenes.SCENES and not Path(args.scene).is_file():
        if args.reference is not None or args.defines:
            parser.error("a bundled scene takes neither --reference nor -D")
        resolution = args.resolution or 512
        try:
            reference = scenes.load_reference(args.scene, resolution)
        except FileNotFoundError as error:
            parser.exit(2, f"pmic-compare: {error}\n")
        scene = scenes.load_scene(args.scene, resolution=resolution, spp=args.spp)
        return scene, args.scene, reference, f"bundled path reference ({resolution}x{resolution})"
    path = Path(args.scene)
    if not path.is_file():
        parser.error(f"{args.scene!r} is neither a bundled scene ({', '.join(scenes.SCENES)}) nor a file")
    if args.resolution is not None:
        parser.error("--resolution is for bundled scenes: a scene file renders at its film's size "
                     "(set it with -D if the file has a $ parameter for it)")
    scene = scenes.load_file(path, {"type": "path"}, **_parse_defines(args.defines))
    if args.reference is not None:
        reference = scenes.read_exr(args.reference)
        size = tuple(scene.sensors()[0].film().crop_size())[::-1]
        if reference.shape[:2] != size:
            parser.error(f"--reference {args.reference} is {reference.shape[1]}x{reference.shape[0]}; "
                         f"the scene's film is {size[1]}x{size[0]}")
        return scene, path.stem, reference, f"reference {args.reference}"
    max_depth = _parse_settings(args.set).get("max_depth", -1)
    print(f"path reference: {args.reference_time or args.reference_spp} "
          f"{'s' if args.reference_time else 'spp'} (kept for the next runs) ...", flush=True)
    ref = refs.cached_reference(scene, None if args.reference_time else args.reference_spp,
                                args.reference_time, integrator={"max_depth": max_depth})
    return scene, path.stem, ref.image, ref.describe()


def _print_results(results, spec, pmic, path, denoised):
    print()
    print(f"{'integrator':12s} {'spp':>6s} {'time [s]':>9s} {'relMSE':>10s} {'FLIP':>7s} "
          f"{'low-freq':>10s} {'RMSE':>9s} {'luminance':>10s} {'CIEDE2000':>10s}")
    for r in results:
        print(f"{r.label:12s} {r.spp:6d} {r.seconds:9.2f} {r.rel_mse:10.2e} {r.flip:7.3f} "
              f"{r.low_frequency:10.2e} {r.rmse:9.4f} {r.luminance_ratio:10.4f} {r.ciede2000:10.3f}")
    print("(low-freq = relMSE of both images blurred by a 4-pixel Gaussian: structured error)")
    if denoised:
        pmic_dn, path_dn = results[2], results[3]
        dn_ratio = path_dn.rel_mse / pmic_dn.rel_mse if pmic_dn.rel_mse > 0 else float("inf")
        better, factor = ("pmic+OIDN's", dn_ratio) if dn_ratio >= 1 else ("path+OIDN's", 1 / dn_ratio)
        other = "path+OIDN's" if dn_ratio >= 1 else "pmic+OIDN's"
        print(f"Denoised, at equal time: {better} relMSE is {factor:.2f}x lower than {other}.")
    ratio = path.rel_mse / pmic.rel_mse if pmic.rel_mse > 0 else float("inf")
    print("(relMSE = mean((img-ref)^2/(ref^2+0.01)); luminance = mean luminance / the reference's)")
    if ratio >= 1:
        print(f"\nAt equal time, pmic's relMSE is {ratio:.1f}x lower than path's.")
    else:
        hints = []
        if pmic.stats.get("time_render", pmic.seconds) < 0.5 * pmic.seconds:
            hints.append("pmic's fixed cost, photons and cache, is most of this run: try more "
                         "--spp or a larger image")
        estimator = spec.get("estimator", "adaptive")
        if estimator in ("adaptive", "final_gather"):
            traced = "where the cache cannot be trusted" if estimator == "adaptive" else "always"
            hints.append(f"its estimator ({estimator}) traces the first diffuse bounce {traced} and "
                         "leaves that noise for a denoiser: compare denoised with --denoise, or "
                         "try --set estimator=first_hit")
        hint = "; ".join(hints) or "see docs/tuning.md"
        print(f"\nAt equal time, path's relMSE is {1 / ratio:.1f}x lower than pmic's ({hint}).")
    stats = pmic.stats
    stage_names = ("time_photons", "time_precompute", "time_cache", "time_cache_view", "time_render")
    stages = ", ".join(f"{k[5:]} {stats[k]:.2f} s" for k in stage_names if k in stats)
    probes = stats.get("records_probes", 0)  # first_hit only
    print(f"pmic stages: {stages}; {stats.get('photons_global', 0)} global + "
          f"{stats.get('photons_caustic', 0)} caustic photons, {stats.get('records', 0)} records"
          f"{f' ({probes} of them at surface probes)' if probes else ''}; first-run compile "
          f"overhead {pmic.compile_s:.2f} s")


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.spp < 1:
        parser.error(f"--spp must be >= 1, got {args.spp}")
    import mitsuba as mi

    mi.set_variant(args.variant)
    from pmic_integrator import compare, scenes

    spec = {"type": "pmic", **_parse_settings(args.set)}
    mi.load_dict(dict(spec))  # checks the parameters before any heavy work
    scene, name, reference, what = _scene_and_reference(args, parser)
    film = scene.sensors()[0].film().crop_size()
    print(f"scene {name} at {film[0]}x{film[1]}, variant {args.variant}; {what}")
    results = compare.compare(scene, spec, args.spp, reference, args.denoise, progress=None,
                              log=lambda line: print(line, flush=True))
    pmic, path = results[0], results[1]
    _print_results(results, spec, pmic, path, args.denoise)

    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    for r in results:
        scenes.write_exr(out / f"{name}_{r.label}.exr", r.image)
    scenes.write_exr(out / f"{name}_reference.exr", reference)
    compare.write_strip(out / f"{name}_comparison.png", results, reference)
    (out / "results.json").write_text(json.dumps(
        {"scene": str(args.scene), "film": list(film), "variant": args.variant, "reference": what,
         "results": [r.row() for r in results]}, indent=2, default=str))
    print(f"images, {name}_comparison.png and results.json written to {out.resolve()}")
    return 0


def reference_main(argv=None) -> int:
    """``pmic-reference scene.xml``: a path-traced reference of any scene file, to an
    spp or a time budget, written as an EXR (its spp and noise in the header)."""
    parser = argparse.ArgumentParser(
        prog="pmic-reference",
        description="Render a path-traced reference of a Mitsuba scene file (Mitsuba's path, "
                    "unbounded, in 8 passes whose spread estimates the reference's own noise).")
    parser.add_argument("scene", type=Path, help="Mitsuba XML scene file")
    budget = parser.add_mutually_exclusive_group(required=True)
    budget.add_argument("--spp", type=int, help="samples per pixel in all")
    budget.add_argument("--time", type=float, metavar="SECONDS", help="render for about this long")
    parser.add_argument("-D", dest="defines", action="append", metavar="KEY=VALUE", default=[],
                        help="a value for the scene file's $KEY parameter (repeatable)")
    parser.add_argument("--max-depth", type=int, default=-1, help="path's max_depth (default: -1)")
    parser.add_argument("--sensor", type=int, default=0)
    parser.add_argument("--output", "-o", type=Path, default=None,
                        help="EXR file to write (default: SCENE_reference.exr beside this folder)")
    parser.add_argument("--variant", default="llvm_ad_rgb")
    args = parser.parse_args(argv)
    import mitsuba as mi

    mi.set_variant(args.variant)
    from pmic_integrator import reference as refs, scenes

    if not args.scene.is_file():
        parser.error(f"no scene file {str(args.scene)!r}")
    scene = scenes.load_file(args.scene, {"type": "path"}, **_parse_defines(args.defines))
    ref = refs.render_reference(scene, args.spp, args.time, args.sensor, {"max_depth": args.max_depth},
                                progress=None)
    out = args.output or Path(f"{args.scene.stem}_reference.exr")
    scenes.write_exr(out, ref.image, {"pmic_spp": ref.spp, "pmic_seconds": ref.seconds,
                                      "pmic_noise": ref.noise, "pmic_integrator": "path"})
    print(f"{ref.describe()}; written to {out.resolve()}")
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
