"""Path-traced references of the public scenes in ../shared/scenes that have none.

Each reference is Mitsuba's ``path`` (unbounded), rendered for a time budget in 8 passes
with different seeds (:func:`pmic_integrator.reference.render_reference`): the passes'
spread estimates the reference's own noise (its expected relMSE against the noise-free
image), which every error measured against it contains. Written to
``benchmarks/references/public/<scene>.exr`` (half-float RGB) with ``<scene>.json``
(spp, seconds, noise, resolution); with ``--npy DIR`` also as ``DIR/<scene>.npy`` and
``.json`` in the layout of ``../shared/scenes/refs`` (what ``compare_with_path.py --refs
DIR`` reads).

    python benchmarks/public_references.py --seconds 300            # the five without a reference
    python benchmarks/public_references.py --scenes torus --seconds 1200
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import mitsuba as mi
import numpy as np

import common

#: The public scenes that came without a reference.
WITHOUT_REFERENCE = ("dining_room", "white_room", "sponza", "torus", "cornell_glossy")


def main(argv=None) -> int:
    from pmic_integrator import reference, scenes
    from pmic_integrator.metrics import finite, mean_luminance

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(WITHOUT_REFERENCE))
    parser.add_argument("--seconds", type=float, default=300.0, help="time budget per scene")
    parser.add_argument("--out", type=Path, default=common.PUBLIC_REFERENCES)
    parser.add_argument("--npy", type=Path, default=None, help="also write compare_with_path.py's layout here")
    args = parser.parse_args(argv)
    if not common.SHARED.is_dir():
        parser.error(f"no public scenes at {common.SHARED}")
    mi.set_variant(common.VARIANT)
    for name in args.scenes:
        scene = common.load_public(name)
        ref = reference.render_reference(scene, seconds=args.seconds, progress=True)
        info = {"scene": name, "integrator": "path", "max_depth": -1, "spp": ref.spp,
                "seconds": round(ref.seconds, 1), "noise_relmse": ref.noise,
                "shape": list(ref.image.shape), "mean_luminance": mean_luminance(ref.image),
                "finite": finite(ref.image), "machine": common.machine_summary(),
                "command": common.command(__file__, ["--scenes", name, "--seconds", f"{args.seconds:g}"])}
        scenes.write_exr(args.out / f"{name}.exr", ref.image, {k: info[k] for k in ("spp", "noise_relmse")},
                         half=True)
        (args.out / f"{name}.json").write_text(json.dumps(info, indent=1))
        if args.npy is not None:
            args.npy.mkdir(parents=True, exist_ok=True)
            np.save(args.npy / f"{name}.npy", ref.image.astype(np.float32))
            (args.npy / f"{name}.json").write_text(json.dumps({**info, "ref_noise_relmse": ref.noise}, indent=1))
        print(f"{name}: {ref.describe()}, mean luminance {info['mean_luminance']:.4g}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
