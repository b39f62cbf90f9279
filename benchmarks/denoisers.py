"""OIDN on the CPU through two bindings: ``pyoidn`` (what pmic_integrator.denoise uses)
and ``mitsuba-oidn`` (nanobind, zero-copy Dr.Jit tensors, OIDN on Dr.Jit's thread pool).

One noisy 512² render of the Cornell box (path, 4 spp) with its albedo and normal
guides (Mitsuba's ``aov`` integrator) is denoised by each, RT filter, HDR, high quality,
``--rounds`` times in alternation after one warm-up each: the fastest and the median
time of each, and how far their outputs are apart (relMSE between them, and each one's
relMSE against the 512² reference).

    pip install mitsuba-oidn    # not a dependency: this benchmark only
    python benchmarks/denoisers.py --rounds 5

Writes benchmarks/results/denoisers.{md,json}.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import mitsuba as mi
import numpy as np

import common


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    import mitsuba_oidn
    import pyoidn
    from pmic_integrator import compare, metrics, scenes
    from pmic_integrator.denoise import OIDN_QUALITY

    scene = scenes.load_scene("cornell_box", resolution=512, spp=4)
    reference = scenes.load_reference("cornell_box", 512)
    image = np.array(mi.render(scene, integrator=mi.load_dict(compare.with_guides(compare.PATH_INTEGRATOR)),
                               spp=4, seed=3), dtype=np.float32)
    color = np.ascontiguousarray(image[..., 0:3])
    albedo = np.ascontiguousarray(np.clip(image[..., 3:6], 0, 1))
    normal = np.ascontiguousarray(np.clip(image[..., 6:9], -1, 1))
    quality = getattr(mitsuba_oidn.Quality, "High")
    runs = {
        "pyoidn": lambda: np.asarray(pyoidn.denoise(color, albedo, normal, hdr=True, quality=OIDN_QUALITY)),
        "mitsuba-oidn (numpy)": lambda: np.asarray(mitsuba_oidn.denoise(color, albedo=albedo, normal=normal,
                                                                        hdr=True, quality=quality)),
        "mitsuba-oidn (TensorXf)": lambda: np.asarray(mitsuba_oidn.denoise(
            mi.TensorXf(color), albedo=mi.TensorXf(albedo), normal=mi.TensorXf(normal), hdr=True,
            quality=quality)),
    }
    outputs = {name: run() for name, run in runs.items()}  # warm-ups
    times = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, run in runs.items():
            outputs[name], seconds = common.timed(run)
            times[name].append(seconds)
    base = outputs["pyoidn"]
    lines = ["# OIDN on the CPU: pyoidn against mitsuba-oidn", "",
             f"`{common.command(__file__, argv)}` ({common.machine_summary()}): one 512² Cornell box (path, 4 spp) with albedo and normal "
             f"guides; RT filter, HDR, high quality; {args.rounds} alternating rounds after a warm-up.", "",
             "| binding | fastest [ms] | median [ms] | relMSE vs pyoidn's output | relMSE vs reference |",
             "|---|---|---|---|---|"]
    for name in runs:
        lines.append(f"| {name} | {1000 * min(times[name]):.0f} | {1000 * float(np.median(times[name])):.0f} | "
                     f"{metrics.rel_mse(outputs[name], base):.2e} | {metrics.rel_mse(outputs[name], reference):.2e} |")
    lines.append(f"| (the noisy input) | | | | {metrics.rel_mse(color, reference):.2e} |")
    data = {"command": common.command(__file__, argv), "machine": common.machine(), "rounds": args.rounds,
            "versions": {"pyoidn": _version("pyoidn"), "mitsuba-oidn": _version("mitsuba-oidn"),
                         "oidn (mitsuba-oidn)": getattr(mitsuba_oidn, "oidn_version", lambda: None)()},
            "bindings": {name: {"seconds": times[name], "fastest_s": min(times[name]),
                                "median_s": float(np.median(times[name])),
                                "rel_mse_vs_pyoidn": metrics.rel_mse(outputs[name], base),
                                "rel_mse_vs_reference": metrics.rel_mse(outputs[name], reference)}
                         for name in runs},
            "noisy_rel_mse_vs_reference": metrics.rel_mse(color, reference)}
    common.write_results(args.out, "denoisers", data, lines)
    print("\n".join(lines))
    return 0


def _version(package: str):
    from importlib import metadata
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


if __name__ == "__main__":
    raise SystemExit(main())
