#!/usr/bin/env python
"""Render the path-traced references of the bundled scenes.

Every error the project reports (relMSE, luminance ratio, CIEDE2000) is measured against
these images, so they are rendered with Mitsuba's own unbounded path tracer (``path``,
``max_depth = -1``, variant ``llvm_ad_rgb``) and many samples per pixel. The samples are
rendered in passes with different seeds and averaged: memory stays that of one pass, the
progress can be printed, and the spread between passes gives an estimate of the noise
left in the reference itself (the floor below which a measured relMSE means nothing).

Output: ``scenes/references/{scene}_{resolution}.exr`` (RGB float32; the EXR header
records how it was made) and ``scenes/references/README.md``, a table rebuilt from the
headers of all the reference EXRs present.

Usage (from the repository root, with the package installed)::

    python tools/make_references.py                       # all scenes, 128^2, 8192 spp
    python tools/make_references.py --scenes indirect_room --spp 1024
"""
from __future__ import annotations

import argparse
import datetime
import shlex
import sys
import time
from pathlib import Path

import pmic_integrator  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
from pmic_integrator import scenes as sc
from pmic_integrator.metrics import finite, mean_luminance

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

VARIANT = "llvm_ad_rgb"
#: Seed of the first pass. Far from 0, the default of ``mi.render``: a test render made
#: with the same seed and spp as a pass would reuse that pass's random numbers exactly,
#: and its error against the reference would come out too small.
DEFAULT_SEED = 1_000_000
#: eps of the project's relMSE, used for the reference's own noise estimate.
REL_MSE_EPS = 1e-2


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Render path-traced reference images of the bundled scenes."
    )
    parser.add_argument("--scenes", nargs="+", choices=sc.SCENES, default=list(sc.SCENES),
                        help="scenes to render (default: all)")
    parser.add_argument("--resolution", type=int, default=sc.DEFAULT_RESOLUTION,
                        help="image width and height in pixels (default: %(default)s)")
    parser.add_argument("--spp", type=int, default=8192,
                        help="total samples per pixel (default: %(default)s)")
    parser.add_argument("--pass-spp", type=int, default=512,
                        help="samples per pixel of one pass; must divide --spp "
                             "(default: %(default)s)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED,
                        help="seed of the first pass; pass i uses seed + i (default: %(default)s)")
    parser.add_argument("--out-dir", type=Path, default=None,
                        help="output folder (default: the scenes folder's references/)")
    args = parser.parse_args(argv)
    if args.resolution < 1 or args.spp < 1 or args.pass_spp < 1:
        parser.error("--resolution, --spp and --pass-spp must be positive")
    if args.spp % args.pass_spp:
        parser.error(f"--pass-spp ({args.pass_spp}) must divide --spp ({args.spp}) so "
                     f"that every pass has the same weight")
    return args


def command_line(args: argparse.Namespace, name: str) -> str:
    """The command that re-renders exactly this reference (recorded in the EXR header)."""
    parts = ["python", "tools/make_references.py", "--scenes", name,
             "--resolution", str(args.resolution), "--spp", str(args.spp),
             "--pass-spp", str(args.pass_spp), "--seed", str(args.seed)]
    return shlex.join(parts)


def render_reference(name: str, args: argparse.Namespace) -> tuple[np.ndarray, dict]:
    """Average ``spp / pass_spp`` independent passes; return the image and its metadata."""
    passes = args.spp // args.pass_spp
    scene = sc.load_scene(name, resolution=args.resolution, spp=args.pass_spp)
    total = np.zeros((args.resolution, args.resolution, 3))
    total_sq = np.zeros_like(total)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i in range(passes):
        # np.asarray evaluates the lazily-built tensor, so the timing covers the render.
        img = np.asarray(mi.render(scene, seed=args.seed + i), dtype=np.float64)
        if not finite(img):
            raise RuntimeError(f"{name}: pass {i} (seed {args.seed + i}) has NaN/Inf pixels")
        total += img
        total_sq += img * img
        elapsed = time.perf_counter() - wall0
        left = elapsed / (i + 1) * (passes - i - 1)
        print(f"[{name}] pass {i + 1}/{passes} ({(i + 1) * args.pass_spp} spp): "
              f"{elapsed:.1f} s elapsed, ~{left:.0f} s left", flush=True)
    wall = time.perf_counter() - wall0
    cpu = time.process_time() - cpu0

    mean = total / passes
    # Noise left in the reference: the variance of a mean of `passes` independent pass
    # images is the between-pass variance / passes. Expressed as the relMSE that a
    # perfect (noise-free) image would show against this reference.
    if passes > 1:
        var_pass = np.maximum(total_sq / passes - mean * mean, 0.0) * passes / (passes - 1)
        noise_rel_mse = float(np.mean(var_pass / passes / (mean * mean + REL_MSE_EPS)))
    else:
        noise_rel_mse = float("nan")

    meta = {
        "pmic_scene": name,
        "pmic_resolution": args.resolution,
        "pmic_spp": args.spp,
        "pmic_passes": f"{passes} x {args.pass_spp} spp, seeds {args.seed}..{args.seed + passes - 1}",
        "pmic_integrator": "path (max_depth=-1)",
        "pmic_variant": VARIANT,
        "pmic_mitsuba": mi.__version__,
        "pmic_drjit": dr.__version__,
        "pmic_wall_time_s": f"{wall:.1f}",
        "pmic_cpu_time_s": f"{cpu:.1f}",
        "pmic_mean_luminance": f"{mean_luminance(mean):.6f}",
        "pmic_noise_rel_mse": f"{noise_rel_mse:.3g}",
        "pmic_date": datetime.date.today().isoformat(),
        "pmic_command": command_line(args, name),
    }
    return mean.astype(np.float32), meta


def write_readme(out_dir: Path) -> Path:
    """Rebuild README.md from the headers of every reference EXR in ``out_dir``.

    Rebuilding from the files (rather than from this run) keeps the table right when
    only some scenes are re-rendered.
    """
    rows = []
    for path in sorted(out_dir.glob("*.exr")):
        meta = sc.read_exr_metadata(path)
        if "pmic_scene" not in meta:
            continue
        order = sc.SCENES.index(meta["pmic_scene"]) if meta["pmic_scene"] in sc.SCENES else 99
        rows.append((order, int(meta.get("pmic_resolution", 0)), path.name, meta))
    rows.sort(key=lambda r: r[:3])

    lines = [
        "# Path-traced references",
        "",
        "Rendered by `tools/make_references.py` (earlier `benchmarks/make_references.py`, as",
        "the commands these files record say) with Mitsuba 3's `path` integrator",
        "(`max_depth = -1`: no depth limit, Russian roulette from depth 5), variant",
        "`llvm_ad_rgb`, box pixel filter, as the average of independent passes with",
        "different seeds. The seeds start at 1000000, away from `mi.render`'s default 0,",
        "so that a test render never reuses the random numbers of a reference pass.",
        "Linear RGB, float32. Each EXR's header repeats these facts",
        "(`pmic_*` attributes; `pmic_integrator.scenes.read_exr_metadata`).",
        "",
        "*Noise relMSE* estimates the noise left in the reference from the spread between",
        "passes: the relMSE (eps = 1e-2) that a noise-free image would have against it.",
        "Measured errors close to it are limited by the reference, not by the renderer;",
        "scenes where path tracing converges slowly get more samples to keep it low.",
        "Times are wall-clock / CPU seconds on a shared 2-core machine: orders of magnitude.",
        "",
        "| scene | file | resolution | spp | wall time (s) | CPU time (s) | mean luminance | noise relMSE | command |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for _, res, fname, meta in rows:
        lines.append(
            f"| {meta['pmic_scene']} | `{fname}` | {res}x{res} | {meta.get('pmic_spp', '?')} "
            f"| {meta.get('pmic_wall_time_s', '?')} | {meta.get('pmic_cpu_time_s', '?')} "
            f"| {meta.get('pmic_mean_luminance', '?')} | {meta.get('pmic_noise_rel_mse', '?')} "
            f"| `{meta.get('pmic_command', '?')}` |"
        )
    if rows:
        first = rows[0][3]
        lines += ["", f"Mitsuba {first.get('pmic_mitsuba', '?')}, Dr.Jit "
                      f"{first.get('pmic_drjit', '?')}."]
    readme = out_dir / "README.md"
    readme.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return readme


def main(argv=None) -> int:
    args = parse_args(argv)
    mi.set_variant(VARIANT)
    out_dir = args.out_dir if args.out_dir is not None else sc.scenes_dir() / "references"
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in args.scenes:
        image, meta = render_reference(name, args)
        path = out_dir / f"{name}_{args.resolution}.exr"
        sc.write_exr(path, image, metadata=meta)
        print(f"[{name}] wrote {path}: {meta['pmic_wall_time_s']} s wall, mean luminance "
              f"{meta['pmic_mean_luminance']}, noise relMSE {meta['pmic_noise_rel_mse']}",
              flush=True)
    print(f"wrote {write_readme(out_dir)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
