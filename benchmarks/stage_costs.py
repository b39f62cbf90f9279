#!/usr/bin/env python
"""Where pmic's time goes on an interior of ~100k triangles and 20 textures, per stage,
against ``path``'s cost per sample, in one run.

    python benchmarks/stage_costs.py                  # 320×240, 16 spp
    python benchmarks/stage_costs.py --spp 32 --repeat 2

The scene is built in code (nothing is read from disk): a 6 × 3 × 4 m room of
rectangles (a textured plank floor in rough plastic, a checkered back wall), lit by a
ceiling panel, holding 18 smooth-shaded tori of 5 376 triangles each (96 × 28
segments: 96 768 triangles in all), each with a texture of its own (12 diffuse, 6
rough plastic), and a glass sphere. Per method: the stages' seconds (photons,
precomputed irradiance, cache, render), the render's seconds per sample per pixel,
and that over ``path``'s whole cost per sample per pixel. Every figure is the fastest
of ``--repeat`` runs, after a warm-up render that compiles the kernels.
Writes ``benchmarks/results/stage_costs.{json,md}``.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import pmic_integrator  # noqa: F401  (registers pmic, points Dr.Jit at libLLVM)
import mitsuba as mi
import numpy as np

from pmic_integrator import metrics
from pmic_integrator.compare import timed_render

import common

TORI = 18
N_MAJOR, N_MINOR = 96, 28  #: 96 × 28 × 2 = 5 376 triangles per torus


def _texture(seed: int, res: int = 128) -> dict:
    """A deterministic coloured pattern: stripes and checks of two random albedos."""
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0.1, 0.8, 3), rng.uniform(0.1, 0.8, 3)
    period = int(rng.integers(4, 16))
    u = (np.arange(res) * period // res) % 2
    mask = (u[:, None] ^ u[None, :]) if seed % 2 else np.broadcast_to(u[None, :], (res, res))
    img = np.where(mask[..., None] > 0, a, b).astype(np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(img), "raw": True}


def torus_mesh(name: str, bsdf: dict, to_world, major=0.3, minor=0.1) -> mi.Mesh:
    """A triangle-mesh torus with smooth vertex normals and UVs."""
    i, j = np.meshgrid(np.arange(N_MAJOR + 1), np.arange(N_MINOR + 1), indexing="ij")
    u, v = 2 * math.pi * i / N_MAJOR, 2 * math.pi * j / N_MINOR
    ring = major + minor * np.cos(v)
    local = np.stack([ring * np.cos(u), minor * np.sin(v), ring * np.sin(u)], -1).reshape(-1, 3)
    normal = np.stack([np.cos(v) * np.cos(u), np.sin(v), np.cos(v) * np.sin(u)], -1).reshape(-1, 3)
    uv = np.stack([i / N_MAJOR, j / N_MINOR], -1).reshape(-1, 2)
    m = np.array(to_world.matrix, dtype=np.float64)
    world = local @ m[:3, :3].T + m[:3, 3]
    world_n = normal @ np.linalg.inv(m[:3, :3])
    world_n /= np.linalg.norm(world_n, axis=1, keepdims=True)
    stride = N_MINOR + 1
    a = (np.arange(N_MAJOR)[:, None] * stride + np.arange(N_MINOR)[None, :]).ravel()
    b, c, d = a + stride, a + stride + 1, a + 1
    faces = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)]).astype(np.uint32)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(name, len(world), len(faces), props, has_vertex_normals=True,
                   has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = world.astype(np.float32).ravel()
    params["vertex_normals"] = world_n.astype(np.float32).ravel()
    params["vertex_texcoords"] = uv.astype(np.float32).ravel()
    params["faces"] = faces.ravel()
    params.update()
    return mesh


def interior(width=320, height=240) -> dict:
    """The benchmark room (see the module docstring)."""
    T = mi.ScalarTransform4f
    half_w, h, half_d = 3.0, 3.0, 2.0
    wall = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.55]}}
    planks = _texture(101)
    scene = {"type": "scene",
             "sensor": {"type": "perspective", "fov": 65,
                        "to_world": T().look_at(origin=[2.6, 1.6, 1.8], target=[-1.0, 0.6, -1.2],
                                                up=[0, 1, 0]),
                        "film": {"type": "hdrfilm", "width": width, "height": height,
                                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                        "sampler": {"type": "independent"}},
             "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale([half_w, half_d, 1]),
                       "bsdf": {"type": "roughplastic", "alpha": 0.15, "diffuse_reflectance": planks}},
             "ceiling": {"type": "rectangle", "bsdf": wall,
                         "to_world": T().translate([0, h, 0]).rotate([1, 0, 0], 90).scale([half_w, half_d, 1])},
             "back": {"type": "rectangle", "to_world": T().translate([0, h / 2, -half_d]).scale([half_w, h / 2, 1]),
                      "bsdf": {"type": "diffuse", "reflectance": _texture(102)}},
             "front": {"type": "rectangle", "bsdf": wall,
                       "to_world": T().translate([0, h / 2, half_d]).rotate([0, 1, 0], 180).scale([half_w, h / 2, 1])},
             "left": {"type": "rectangle", "bsdf": wall,
                      "to_world": T().translate([-half_w, h / 2, 0]).rotate([0, 1, 0], 90).scale([half_d, h / 2, 1])},
             "right": {"type": "rectangle", "bsdf": wall,
                       "to_world": T().translate([half_w, h / 2, 0]).rotate([0, 1, 0], -90).scale([half_d, h / 2, 1])},
             "panel": {"type": "rectangle",
                       "to_world": T().translate([0, h - 0.01, 0]).rotate([1, 0, 0], 90).scale([0.6, 0.4, 1]),
                       "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [18.0, 17.0, 15.0]}}},
             "glass": {"type": "sphere", "center": [0.4, 0.35, 0.6], "radius": 0.35, "bsdf": {"type": "dielectric"}}}
    for k in range(TORI):
        row, col = divmod(k, 6)
        x, z = -2.4 + col * 0.95, -1.4 + row * 0.9
        texture = _texture(k)
        bsdf = {"type": "diffuse", "reflectance": texture} if k % 3 else \
            {"type": "roughplastic", "alpha": 0.1, "diffuse_reflectance": texture}
        to_world = T().translate([x, 0.12 + 0.25 * (k % 2), z]).rotate([1, 0, 0], 35 * (k % 3)) \
            .rotate([0, 1, 0], 20 * k)
        scene[f"torus_{k}"] = torus_mesh(f"torus_{k}", bsdf, to_world)
    return scene


def _render(scene, spec, spp):
    integrator = mi.load_dict(spec)
    image, seconds = timed_render(scene, integrator, spp, seed=1)
    return seconds, getattr(integrator, "stats", {}) or {}, image


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    scene = mi.load_dict(interior(args.width, args.height))
    triangles = sum(s.primitive_count() for s in scene.shapes() if s.is_mesh())
    pixels = args.width * args.height
    methods = [("path", {"type": "path"}),
               ("pmic (defaults: final gather)", {"type": "pmic"}),
               ("pmic first_hit", {"type": "pmic", "estimator": "first_hit"}),
               # Rough-plastic coats are glossy, so light off them counts as caustic:
               # without a caustic map such light is gathered instead.
               ("pmic, caustic_photons 0", {"type": "pmic", "caustic_photons": 0})]
    rows = []
    for label, spec in methods:
        _render(scene, spec, 1)  # warm-up: compiles the kernels
        best = None
        for _ in range(args.repeat):
            seconds, stats, image = _render(scene, spec, args.spp)
            if best is None or seconds < best[0]:
                best = (seconds, stats, image)
        seconds, stats, image = best
        render_s = stats.get("time_render", seconds)
        row = {"method": label, "total_s": seconds, "luminance": metrics.mean_luminance(image),
               "finite": metrics.finite(image),
               **{k: stats[k] for k in ("time_photons", "time_precompute", "time_cache", "time_render",
                                        "records", "photons_global", "photons_caustic") if k in stats},
               "render_us_per_sample": 1e6 * render_s / (pixels * args.spp)}
        rows.append(row)
        print(label, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    path_cost = rows[0]["render_us_per_sample"]
    for row in rows:
        row["render_cost_over_path"] = row["render_us_per_sample"] / path_cost
    command = common.command(__file__, argv)
    result = {"command": command, "width": args.width, "height": args.height, "spp": args.spp,
              "triangles": triangles, "textures": TORI + 2, "shapes": len(scene.shapes()), "rows": rows}
    lines = [f"# Stage costs: {triangles} triangles, {TORI + 2} textures, {args.width}×{args.height}, "
             f"{args.spp} spp", "", f"`{command}`", "",
             "Seconds (fastest of the runs, after a warm-up); render cost per sample per pixel, "
             "and over path's whole cost per sample.", "",
             "| method | photons | precompute | cache | render | total | µs/sample | × path | records | luminance |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        f = lambda k: f"{row[k]:.2f}" if k in row else "—"  # noqa: E731
        lines.append(f"| {row['method']} | {f('time_photons')} | {f('time_precompute')} | {f('time_cache')} | "
                     f"{f('time_render')} | {row['total_s']:.2f} | {row['render_us_per_sample']:.2f} | "
                     f"{row['render_cost_over_path']:.2f} | {row.get('records', 0)} | {row['luminance']:.4f} |")
    common.write_results(args.out, "stage_costs", result, lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
