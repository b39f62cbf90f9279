"""Debug views of the method, as the paper's figures show them, from one command:

* Fig. 3: (a) the global photon map, (b) the irradiance precomputed at the photons;
* Fig. 4: (a) cache records placed from the camera (the classic cache,
  ``method=irradiance_cache``) against (b) records placed by walking the photons (pmic).

Points are projected into the scene's first sensor and drawn where the camera sees them
(a shadow ray from the camera), over a dimmed render of the scene. Everything is read
from the project's public cache-file format (``save_cache``: an ``.npz`` of named
arrays), not from private attributes.

    python tools/debug_views.py                    # Cornell box
    python tools/debug_views.py --scene indirect_room --photons 50000

Writes ``benchmarks/results/debug_views_<scene>.png`` (``--out``: elsewhere); the
documentation's copy is ``docs/img/debug_views_cornell_box.png``.
"""
from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import drjit as dr
import mitsuba as mi
import numpy as np

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def cache_arrays(scene, spec: dict, spp: int = 1) -> dict:
    """Render once with ``spec`` and return the saved cache's arrays by name."""
    integrator = mi.load_dict(spec)
    mi.render(scene, integrator=integrator, spp=spp)
    path = Path(tempfile.mkdtemp()) / "cache.npz"
    integrator.save_cache(path)
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files if k != "meta"}


def points(arrays: dict, name: str) -> np.ndarray:
    """(N, 3) array of a saved Point3f/Color3f field (saved as 3 x N)."""
    return np.ascontiguousarray(arrays[name].T)


def project(scene, p: np.ndarray):
    """Pixel coordinates of world points in the first sensor, and whether the camera
    sees them (in front, inside the image, nothing in between)."""
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    params = mi.traverse(sensor)
    fov_x = float(params["x_fov"][0] if dr.is_array_v(params["x_fov"]) else params["x_fov"])
    to_local = sensor.world_transform().inverse()
    local = to_local @ mi.Point3f(*[np.ascontiguousarray(c) for c in p.T])
    x, y, z = (np.array(c) for c in (local.x, local.y, local.z))
    tan_x = math.tan(math.radians(fov_x) / 2)
    tan_y = tan_x * h / w
    with np.errstate(divide="ignore", invalid="ignore"):
        # Mitsuba's perspective camera looks down +z; image x grows towards -x.
        u = (0.5 - 0.5 * x / (z * tan_x)) * w
        v = (0.5 - 0.5 * y / (z * tan_y)) * h
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    origin = sensor.world_transform() @ mi.Point3f(0, 0, 0)
    target = mi.Point3f(*[np.ascontiguousarray(c) for c in p.T])
    d = target - origin
    dist = dr.norm(d)
    ray = mi.Ray3f(mi.Point3f(origin), mi.Vector3f(d / dist))
    ray.maxt = dist * (1 - 1e-3)
    blocked = np.array(scene.ray_test(ray, mi.Bool(inside)))
    return u, v, inside & ~blocked, (w, h)


def splat(base: np.ndarray, u, v, keep, colours, size: int = 1) -> np.ndarray:
    out = base.copy()
    h, w = out.shape[:2]
    for du in range(-size + 1, size):
        for dv in range(-size + 1, size):
            uu = np.clip(u[keep].astype(int) + du, 0, w - 1)
            vv = np.clip(v[keep].astype(int) + dv, 0, h - 1)
            out[vv, uu] = colours[keep]
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="cornell_box")
    parser.add_argument("--resolution", type=int, default=384)
    parser.add_argument("--photons", type=int, default=20_000)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant("llvm_ad_rgb")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pmic_integrator import metrics, scenes

    scene = scenes.load_scene(args.scene, args.resolution, 16)
    base = 0.35 * metrics.tonemap_srgb(np.array(mi.render(scene, spp=16))[..., :3])
    settings = {"type": "pmic", "global_photons": args.photons, "caustic_photons": 0}
    pm = cache_arrays(scene, settings)
    classic = cache_arrays(scene, {**settings, "method": "irradiance_cache"})

    photons = points(pm, "prepared.global_map.position")
    power = points(pm, "prepared.global_map.power")
    u, v, keep, _ = project(scene, photons)
    fig3a = splat(base, u, v, keep, np.clip(power / np.percentile(power.max(1), 95), 0, 1))
    pre = points(pm, "prepared.gather_source.photons.position")
    irr = points(pm, "prepared.gather_source.photons.irradiance")
    u, v, keep, _ = project(scene, pre)
    fig3b = splat(base, u, v, keep, metrics.tonemap_srgb(irr / math.pi * 0.8), size=2)

    panels = [("Fig. 3a: global photon map", fig3a), ("Fig. 3b: irradiance precomputed at photons", fig3b)]
    for title, arrays in (("Fig. 4a: records placed from the camera", classic),
                          ("Fig. 4b: records placed from the photons (pmic)", pm)):
        rec = points(arrays, "prepared.index.records.position")
        u, v, keep, _ = project(scene, rec)
        colours = np.tile([[1.0, 0.9, 0.2]], (len(rec), 1))
        panels.append((f"{title}: {len(rec)} records", splat(base, u, v, keep, colours, size=2)))

    fig, axes = plt.subplots(2, 2, figsize=(9, 9))
    for ax, (title, image) in zip(axes.ravel(), panels):
        ax.imshow(np.clip(image, 0, 1))
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"debug_views_{args.scene}.png"
    fig.savefig(path, dpi=100)
    print("wrote", path)


if __name__ == "__main__":
    main()
