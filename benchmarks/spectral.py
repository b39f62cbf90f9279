"""pmic in ``llvm_ad_spectral`` against ``path`` in ``llvm_ad_spectral``: mean luminance,
each sRGB channel's mean and relMSE, and the time against pmic in ``llvm_ad_rgb`` on
the same scene (its luminance against ``path`` in RGB beside it).

    python benchmarks/spectral.py                       # every case, 128², 16 spp
    python benchmarks/spectral.py --cases cornell_box --spp 64 --reference-spp 4096

Cases: the bundled Cornell box, the window-lit room (an environment map and a sun
through a window, textures) and the textured exterior under an environment map; and
the Cornell box under spectral lamps: a 3000 K blackbody, a 40 nm band around 550 nm
and two narrow lines (450 and 610 nm), where the bounced light's spectrum, rebuilt
from stored sRGB (:mod:`pmic_integrator.spectra`), is farthest from the lamp's.
Results go to ``benchmarks/results/spectral.md``.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import drjit as dr
import mitsuba as mi

import common
from pmic_integrator import kinds, metrics, scenes

#: The lamps of the Cornell-box cases (an area light's ``radiance``), by case name.
LAMPS = {
    "cornell_blackbody": {"type": "blackbody", "temperature": 3000.0},
    "cornell_band_550": {"type": "spectrum",
                         "value": [(530.0, 0.0), (540.0, 40.0), (560.0, 40.0), (570.0, 0.0)]},
    "cornell_lines": {"type": "spectrum",
                      "value": [(440.0, 0.0), (450.0, 30.0), (460.0, 0.0),
                                (600.0, 0.0), (610.0, 30.0), (620.0, 0.0)]},
}
BUNDLED = ["cornell_box", "interior_window", "exterior_envmap"]
CASES = BUNDLED + list(LAMPS)


def load_case(name: str, resolution: int) -> mi.Scene:
    """Case ``name`` in the active variant (the lamps need a spectral one)."""
    if name in BUNDLED:
        return scenes.load_scene(name, resolution=resolution, spp=4)
    d = kinds.cornell(resolution)
    d["light"]["emitter"] = {"type": "area", "radiance": LAMPS[name]}
    return mi.load_dict(d)


def render(scene, integrator: dict, spp: int, seed: int = 0):
    """``(image, seconds)``: the sRGB channels of one render (kernels compiled by an
    untimed 1-spp render first)."""
    mi.render(scene, integrator=mi.load_dict(integrator), spp=1, seed=seed + 1000)
    dr.sync_thread()
    start = time.perf_counter()
    image = np.array(mi.render(scene, integrator=mi.load_dict(integrator), spp=spp, seed=seed))[..., :3]
    dr.sync_thread()
    return image, time.perf_counter() - start


def measure(name: str, resolution: int, spp: int, reference_spp: int) -> dict:
    row = {"case": name}
    for variant in ("llvm_ad_spectral", "llvm_ad_rgb"):
        if variant == "llvm_ad_rgb" and name not in BUNDLED:
            continue  # (spectral lamps exist in spectral variants only)
        mi.set_variant(variant)
        scene = load_case(name, resolution)
        reference, _ = render(scene, {"type": "path", "max_depth": -1}, reference_spp, seed=7)
        image, seconds = render(scene, {"type": "pmic"}, spp)
        assert np.isfinite(image).all(), f"{name} {variant}: NaN/Inf"
        key = "spectral" if variant == "llvm_ad_spectral" else "rgb"
        row[f"{key}_luminance"] = metrics.mean_luminance(image) / metrics.mean_luminance(reference)
        row[f"{key}_seconds"] = seconds
        row[f"{key}_relmse"] = metrics.rel_mse(image, reference)
        if key == "spectral":
            row["channels"] = (image.mean(axis=(0, 1)) / reference.mean(axis=(0, 1))).tolist()
    return row


def table(rows: list[dict], args) -> list[str]:
    lines = ["# pmic in llvm_ad_spectral against path in llvm_ad_spectral", "",
             f"Command: `{common.command(__file__)}`  ",
             f"{args.resolution}², pmic at defaults, {args.spp} spp; references: `path` at "
             f"{args.reference_spp} spp in the same variant; {common.machine_summary()}.", "",
             "| case | luminance / path | R, G, B / path | relMSE | seconds | "
             "RGB variant: luminance / path | seconds |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        channels = ", ".join(f"{c:.3f}" for c in r["channels"])
        rgb = (f"{r['rgb_luminance']:.4f} | {r['rgb_seconds']:.2f}" if "rgb_luminance" in r
               else "(spectral lamp) | -")
        lines.append(f"| {r['case']} | {r['spectral_luminance']:.4f} | {channels} | "
                     f"{r['spectral_relmse']:.2e} | {r['spectral_seconds']:.2f} | {rgb} |")
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=CASES, choices=CASES)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--reference-spp", type=int, default=2048)
    parser.add_argument("--out", type=common.Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    rows = []
    for name in args.cases:
        rows.append(measure(name, args.resolution, args.spp, args.reference_spp))
        print(rows[-1], flush=True)
    lines = table(rows, args)
    md = common.write_results(args.out, "spectral", {"rows": rows, "machine": common.machine(),
                                                     "command": common.command(__file__, argv)}, lines)
    print("\n".join(lines))
    print(f"wrote {md}")


if __name__ == "__main__":
    main()
