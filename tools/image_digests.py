"""Digests of pmic's images over every method, estimator and AOV setting, for checking
that a refactor leaves images bit-identical.

    python tools/image_digests.py --write before.json      # at the old commit
    python tools/image_digests.py --check before.json      # at the new one

Each case renders one scene (the bundled scenes at 128², and small scenes of the kinds
that switch on the camera path's rarer cases: principled and rough plastic, normal
maps, delta lights, a lamp, a window) with one setting, 4 spp, and keeps the SHA-256
of the whole film (image and AOV channels) and its mean. ``--check`` lists every case
whose digest differs, with the relative change of its mean, and exits 1 if any does
(after rendering it again, twice at most).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time

import numpy as np

import pmic_integrator  # noqa: F401  (first: it finds an LLVM that Dr.Jit can use)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from pmic_integrator import kinds, scenes  # noqa: E402

SPP = 4
#: A case whose digest differs is rendered again up to this many times.
RETRIES = 2
BUNDLED_SETTINGS = {
    "final_gather": {},
    "final_gather_aovs": {"aovs": "all"},
    "first_hit_aovs": {"estimator": "first_hit", "aovs": "all"},
    "photon_map": {"method": "photon_map"},
    "photon_map_gather": {"method": "photon_map", "final_gather": True},
    "irradiance_cache": {"method": "irradiance_cache"},
    "bounded": {"max_depth": 4},
    "unguided_hidden": {"guiding": False, "hide_emitters": True},
}
KIND_SETTINGS = {"final_gather_aovs": {"aovs": "all"}, "first_hit": {"estimator": "first_hit"},
                 "bounded": {"max_depth": 5}}
SMALL = {"global_photons": 30_000, "caustic_photons": 10_000, "gather_rays": 64}


def cases():
    """(name, scene factory, pmic parameters) of every case."""
    for name in scenes.SCENES:
        for label, params in BUNDLED_SETTINGS.items():
            yield f"{name}/{label}", (lambda name=name: scenes.load_scene(name)), params
    for name, build in kinds.DIGEST_KINDS.items():
        for label, params in KIND_SETTINGS.items():
            yield f"{name}/{label}", (lambda build=build: mi.load_dict(build())), {**SMALL, **params}
    yield "cornell_caustics/aov_wrapper", (lambda: scenes.load_scene("cornell_caustics")), "aov"


def render(make_scene, params) -> np.ndarray:
    scene = make_scene()
    if params == "aov":
        integrator = mi.load_dict({"type": "aov", "aovs": "nn:sh_normal",
                                   "img": {"type": "pmic"}})
    else:
        integrator = mi.load_dict({"type": "pmic", **params})
    return np.asarray(mi.render(scene, integrator=integrator, spp=SPP, seed=1), dtype=np.float32)


def _digest(image: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", metavar="JSON")
    group.add_argument("--check", metavar="JSON")
    parser.add_argument("--only", default="", help="cases whose name contains this")
    args = parser.parse_args(argv)
    known = {} if args.write else json.load(open(args.check))
    results, differ = {}, []
    for name, make_scene, params in cases():
        if args.only not in name:
            continue
        t0 = time.perf_counter()
        image = render(make_scene, params)
        digest = _digest(image)
        for _ in range(RETRIES if name in known and known[name]["sha256"] != digest else 0):
            # (The classic cache's placement sums records' contributions in thread
            # order: its images differ from run to run now and then, in the last bits.)
            image = render(make_scene, params)
            digest = _digest(image)
            if digest == known[name]["sha256"]:
                break
        results[name] = {"sha256": digest, "mean": float(image.mean()),
                         "finite": bool(np.isfinite(image).all())}
        line = f"{name:45s} {time.perf_counter() - t0:6.1f} s  mean {image.mean():.6g}"
        if name in known and known[name]["sha256"] != digest:
            change = image.mean() / known[name]["mean"] - 1.0 if known[name]["mean"] else 0.0
            differ.append(name)
            line += f"  DIFFERS (mean {change:+.2e})"
        print(line, flush=True)
    if args.write:
        json.dump(results, open(args.write, "w"), indent=1)
        return 0
    missing = sorted(set(known) - set(results)) if not args.only else []
    print(f"{len(results) - len(differ)} of {len(results)} cases bit-identical"
          + (f"; differ: {', '.join(differ)}" if differ else "")
          + (f"; not run: {', '.join(missing)}" if missing else ""))
    return 1 if differ or missing else 0


if __name__ == "__main__":
    sys.exit(main())
