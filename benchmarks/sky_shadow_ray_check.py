#!/usr/bin/env python
"""A minimal reproduction, for Mitsuba's tracker, of sky light leaking through a roof.

Mitsuba 3.9 merges shapes loaded with ``load_dict`` that share one BSDF object into
one mesh, whose ``bbox()`` (and so ``scene.bbox()``) is invalid. Its infinite emitters
(``constant``, ``envmap``, ``directional``) place their direction samples at twice the
radius of the scene's bounding sphere, taken from ``scene.bbox()``; with an invalid
box the samples land 1.6 m from the shading point, and the shadow ray stops there. In
a closed room lit through a window, shadow rays from the floor then stop short of the
2.5 m ceiling and the floor is lit as if there were no roof.

The script renders the same room twice with Mitsuba's ``path`` (direct light only,
``max_depth`` 2): walls sharing one BSDF object (merged, invalid box) and walls with a
BSDF each (not merged). The two must agree; in Mitsuba 3.9 the merged room comes out
about twice as bright. pmic is shown alongside: its shadow rays towards infinite
emitters are unbounded (``pmic_integrator.emission.shadow_ray``), so it agrees with
itself and with the unmerged ``path``.

    python benchmarks/sky_shadow_ray_check.py
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import pmic_integrator  # noqa: F401  (sets up LLVM; must come before mitsuba)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from scene_builders import window_room  # noqa: E402  (needs the variant)


def mean(scene, integrator: dict, spp: int) -> float:
    return float(np.array(mi.render(scene, integrator=mi.load_dict(integrator), spp=spp,
                                    seed=1)).mean())


def main() -> int:
    merged = mi.load_dict(window_room(size=(64, 48), shared_material=True))
    apart = mi.load_dict(window_room(size=(64, 48)))
    print(f"shapes: merged {len(merged.shapes())}, apart {len(apart.shapes())}; "
          f"scene.bbox() valid: merged {merged.bbox().valid()}, apart {apart.bbox().valid()}")
    direct = {"max_depth": 2}
    path_merged = mean(merged, {"type": "path", **direct}, 512)
    path_apart = mean(apart, {"type": "path", **direct}, 512)
    pmic_merged = mean(merged, {"type": "pmic", "global_photons": 20_000, **direct}, 64)
    pmic_apart = mean(apart, {"type": "pmic", "global_photons": 20_000, **direct}, 64)
    print(f"path: merged {path_merged:.5f}, apart {path_apart:.5f} (ratio {path_merged / path_apart:.3f})")
    print(f"pmic: merged {pmic_merged:.5f}, apart {pmic_apart:.5f} (ratio {pmic_merged / pmic_apart:.3f}); "
          f"pmic apart / path apart {pmic_apart / path_apart:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
