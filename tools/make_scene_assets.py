#!/usr/bin/env python
"""Write the meshes and textures of the bundled real-scene-like scenes, from code.

    python tools/make_scene_assets.py      # writes scenes/assets/*

The scenes (``scenes/exterior_envmap.xml``, ``scenes/interior_window.xml``) reference:

* ``sky.exr``: a 128×64 lat-long sky, a blue gradient with a small bright sun; the
  scenes rotate it, as real scenes' envmaps are;
* ``checker.png``: an 8×8 checkerboard (sRGB), the exterior's textured ground;
* ``planks.png``: a plank pattern, the interior's glossy floor;
* ``torus.obj``: a 48×24-segment torus, a triangle mesh with normals and UVs.

Everything is deterministic: running it again writes the same files.
"""
from __future__ import annotations

import math
from pathlib import Path

import pmic_integrator  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
import mitsuba as mi
import numpy as np

ASSETS = Path(__file__).resolve().parents[1] / "scenes" / "assets"


def sky(width=128, height=64):
    theta = (np.arange(height) + 0.5) / height * math.pi  # 0 at the zenith
    horizon = np.clip(np.sin(theta), 0, 1)[:, None]
    zenith = np.array([0.25, 0.45, 0.95], np.float32)
    haze = np.array([0.85, 0.85, 0.8], np.float32)
    img = (zenith * (1 - horizon[..., None] ** 4) + haze * horizon[..., None] ** 4) * 0.8
    img = np.repeat(img, width, axis=1).astype(np.float32)
    img[theta > math.pi / 2] *= 0.3  # darker below the horizon (ground bounce)
    sun_row, sun_col = int(height * 0.22), int(width * 0.62)
    img[sun_row - 1:sun_row + 2, sun_col - 1:sun_col + 2] = [400.0, 380.0, 330.0]
    return img


def checker(size=256, squares=8):
    u = (np.arange(size) * squares // size) % 2
    board = (u[:, None] ^ u[None, :]).astype(np.float32)
    value = 0.15 + 0.65 * board
    return np.repeat(value[..., None], 3, axis=2)


def planks(size=256, rows=8):
    y = np.arange(size)[:, None] / size * rows
    x = np.arange(size)[None, :] / size
    row = np.floor(y)
    shade = 0.75 + 0.25 * np.sin(row * 12.9898) ** 2
    grain = 0.9 + 0.1 * np.sin(40 * x + 7 * row)
    seam = (np.abs(y - np.round(y)) < 0.03)
    base = np.array([0.55, 0.36, 0.2])
    img = base * (shade * grain)[..., None]
    img[np.broadcast_to(seam, img.shape[:2])] *= 0.4
    return img.astype(np.float32)


def torus_obj(major=0.5, minor=0.18, n_major=48, n_minor=24) -> str:
    lines = ["# torus written by tools/make_scene_assets.py"]
    for i in range(n_major + 1):
        u = 2 * math.pi * i / n_major
        for j in range(n_minor + 1):
            v = 2 * math.pi * j / n_minor
            cx, cz = math.cos(u), math.sin(u)
            x = (major + minor * math.cos(v)) * cx
            z = (major + minor * math.cos(v)) * cz
            y = minor * math.sin(v)
            lines.append(f"v {x:.6f} {y:.6f} {z:.6f}")
            lines.append(f"vn {math.cos(v) * cx:.6f} {math.sin(v):.6f} {math.cos(v) * cz:.6f}")
            lines.append(f"vt {i / n_major:.6f} {j / n_minor:.6f}")
    stride = n_minor + 1
    for i in range(n_major):
        for j in range(n_minor):
            a = i * stride + j + 1
            b = (i + 1) * stride + j + 1
            c, d = b + 1, a + 1
            lines.append(f"f {a}/{a}/{a} {d}/{d}/{d} {c}/{c}/{c} {b}/{b}/{b}")
    return "\n".join(lines) + "\n"


def main():
    mi.set_variant("scalar_rgb")
    ASSETS.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(sky()).write(str(ASSETS / "sky.exr"))
    for name, img in (("checker.png", checker()), ("planks.png", planks())):
        srgb = np.clip(img, 0, 1) ** (1 / 2.2)
        mi.Bitmap((srgb * 255 + 0.5).astype(np.uint8), pixel_format=mi.Bitmap.PixelFormat.RGB,
                  ).write(str(ASSETS / name))
    (ASSETS / "torus.obj").write_text(torus_obj())
    print(f"wrote {', '.join(sorted(p.name for p in ASSETS.iterdir()))} to {ASSETS}")


if __name__ == "__main__":
    main()
