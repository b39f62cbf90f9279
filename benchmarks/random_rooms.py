#!/usr/bin/env python
"""Random rooms against ``path``: scenes no one designed, to find what the bundled ones miss.

Each seed builds a room (two-sided or one-sided walls of a random material; closed, a
window, a door or an open roof), one to four objects (cube, sphere, cylinder, a thin
one-sided panel) of random materials (diffuse, textured, plastic, rough plastic, rough
and smooth conductors, principled, blend, bump map, glass, thin glass, rough glass),
one or two lights (area, small sphere, point, spot, sun, constant sky, an environment
map with a bright patch) and a camera inside. At 64×48, ``path`` (two halves of
``--path-spp``, their difference the reference's own noise) against pmic at its
defaults and with ``first_hit`` (64 spp): mean luminance over the reference's, relMSE,
NaN/Inf. A row is flagged where pmic's luminance is off by more than 2 % (3 % for
first_hit) or three times the halves' difference.

    python benchmarks/random_rooms.py --first 0 --count 40        # ~10 minutes on 2 cores

Flags are leads, not verdicts: ``path`` cannot carry light from a point, spot or sun
light through delta surfaces (a mirror, glass, a smooth plastic's coat) at all, which
pmic's photons do, so such rooms come out brighter than ``path``'s image (the rows say
which lights and materials). Writes ``benchmarks/results/random_rooms.{json,md}``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import mitsuba as mi

from pmic_integrator.compare import timed_render
from pmic_integrator.metrics import finite, mean_luminance, rel_mse

import common

mi.set_variant(common.VARIANT)
T = mi.ScalarTransform4f
W, H = 64, 48


def rgb(v):
    return {'type': 'rgb', 'value': [float(x) for x in v]}


def checker(rng):
    return {'type': 'checkerboard', 'color0': rgb(rng.uniform(0.05, 0.4, 3)), 'color1': rgb(rng.uniform(0.4, 0.9, 3)),
            'to_uv': T().scale([float(rng.integers(2, 12))] * 2 + [1])}


def material(rng, allow_glass=True):
    kinds = ['diffuse', 'diffuse', 'diffuse_tex', 'plastic', 'roughplastic', 'roughconductor', 'conductor',
             'principled', 'twosided', 'blend', 'bump', 'coated']
    if allow_glass:
        kinds += ['dielectric', 'thindielectric', 'roughdielectric']
    k = kinds[rng.integers(len(kinds))]
    alb = rng.uniform(0.1, 0.9, 3)
    if k == 'diffuse':
        return k, {'type': 'diffuse', 'reflectance': rgb(alb)}
    if k == 'diffuse_tex':
        return k, {'type': 'diffuse', 'reflectance': checker(rng)}
    if k == 'plastic':
        return k, {'type': 'plastic', 'diffuse_reflectance': rgb(alb)}
    if k == 'roughplastic':
        return k, {'type': 'roughplastic', 'diffuse_reflectance': rgb(alb), 'alpha': float(rng.uniform(0.05, 0.6))}
    if k == 'roughconductor':
        return k, {'type': 'roughconductor', 'alpha': float(rng.uniform(0.05, 0.6)),
                   'material': ['Au', 'Cu', 'Al', 'Ag'][rng.integers(4)]}
    if k == 'conductor':
        return k, {'type': 'conductor'}
    if k == 'principled':
        return k, {'type': 'principled', 'base_color': rgb(alb), 'metallic': float(rng.uniform(0, 1)),
                   'roughness': float(rng.uniform(0.1, 0.9)), 'specular': float(rng.uniform(0.2, 0.8))}
    if k == 'twosided':
        return k, {'type': 'twosided', 'bsdf': {'type': 'diffuse', 'reflectance': rgb(alb)}}
    if k == 'blend':
        return k, {'type': 'blendbsdf', 'weight': float(rng.uniform(0.2, 0.8)),
                   'bsdf_0': {'type': 'diffuse', 'reflectance': rgb(alb)},
                   'bsdf_1': {'type': 'roughconductor', 'alpha': 0.3}}
    if k == 'bump':
        bump = np.kron(rng.uniform(0, 1, (8, 8)).astype(np.float32), np.ones((4, 4), np.float32))[..., None]
        return k, {'type': 'bumpmap', 'arg': {'type': 'bitmap', 'bitmap': mi.Bitmap(bump), 'raw': True}, 'scale': float(rng.uniform(0.1, 1.0)),
                   'bsdf': {'type': 'diffuse', 'reflectance': rgb(alb)}}
    if k == 'coated':
        return k, {'type': 'roughplastic', 'diffuse_reflectance': checker(rng), 'alpha': 0.1, 'nonlinear': True}
    if k == 'dielectric':
        return k, {'type': 'dielectric'}
    if k == 'thindielectric':
        return k, {'type': 'thindielectric'}
    return k, {'type': 'roughdielectric', 'alpha': float(rng.uniform(0.05, 0.4))}


def distinct(bsdf, index: int):
    """``bsdf`` with its colours scaled by 1 - 1e-4·(index + 1): Mitsuba 3.9 merges shapes
    of equal BSDFs into one mesh whose bounding box is empty, and the scene's bounding
    sphere then leaves those walls out: ``path``'s shadow rays to an environment or a sun,
    sized by that sphere, stopped short of them and lit closed rooms through their walls
    (two rooms of the first run, 0.80 of ``path``'s too-bright image)."""
    if isinstance(bsdf, dict):
        out = {k: distinct(v, index) for k, v in bsdf.items()}
        if out.get("type") == "rgb":
            out["value"] = [v * (1.0 - 1e-4 * (index + 1)) for v in out["value"]]
        elif out.get("type") in ("conductor", "roughconductor") and "specular_reflectance" not in out:
            out["specular_reflectance"] = rgb([1.0 - 1e-4 * (index + 1)] * 3)
        return out
    return bsdf


def make_scene(seed):
    rng = np.random.default_rng(seed)
    sx, sy, sz = (float(v) for v in rng.uniform(1.5, 5, 3))
    sy = min(sy, 3.5)
    desc = []
    d = {'type': 'scene'}
    wall_kind, wall_bsdf = material(rng, allow_glass=False)
    one_sided = rng.random() < 0.5
    if not one_sided:
        wall_bsdf = {'type': 'twosided', 'bsdf': wall_bsdf} if wall_kind != 'twosided' else wall_bsdf
    desc.append(f"walls {wall_kind}{'' if one_sided else ' 2s'} {sx:.1f}x{sy:.1f}x{sz:.1f}")
    open_side = rng.integers(0, 4)  # 0: closed, 1: window in +x wall, 2: door (+z wall missing half), 3: open roof
    desc.append(['closed', 'window', 'door', 'open roof'][open_side])
    # walls facing inwards: rectangles are in xy plane, normal +z
    walls = {
        'floor': T().translate([0, 0, 0]).rotate([1, 0, 0], -90).scale([sx, sz, 1]),
        'ceiling': T().translate([0, 2 * sy, 0]).rotate([1, 0, 0], 90).scale([sx, sz, 1]),
        'back': T().translate([0, sy, -sz]).scale([sx, sy, 1]),
        'left': T().translate([-sx, sy, 0]).rotate([0, 1, 0], 90).scale([sz, sy, 1]),
    }
    if open_side == 3:
        del walls['ceiling']
    for name, tf in walls.items():
        d[name] = {'type': 'rectangle', 'to_world': tf, 'bsdf': wall_bsdf}
    floor_kind, floor_bsdf = material(rng, allow_glass=False)
    d['floor']['bsdf'] = floor_bsdf
    desc.append(f"floor {floor_kind}")
    # +x wall: with a window (four pieces round a hole) or whole
    rightT = lambda cy, cz, hy, hz: T().translate([sx, cy, cz]).rotate([0, 1, 0], -90).scale([hz, hy, 1])
    if open_side == 1:
        wy0, wy1 = sy * 0.6, sy * 1.4
        wz0, wz1 = -sz * 0.4, sz * 0.4
        d['r_below'] = {'type': 'rectangle', 'to_world': rightT(wy0 / 2, 0, wy0 / 2, sz), 'bsdf': wall_bsdf}
        d['r_above'] = {'type': 'rectangle', 'to_world': rightT((2 * sy + wy1) / 2, 0, (2 * sy - wy1) / 2, sz), 'bsdf': wall_bsdf}
        d['r_back'] = {'type': 'rectangle', 'to_world': rightT(sy, (-sz + wz0) / 2, (wy1 - wy0) / 2, (wz0 + sz) / 2), 'bsdf': wall_bsdf}
        d['r_front'] = {'type': 'rectangle', 'to_world': rightT(sy, (sz + wz1) / 2, (wy1 - wy0) / 2, (sz - wz1) / 2), 'bsdf': wall_bsdf}
        if rng.random() < 0.4:
            d['pane'] = {'type': 'rectangle', 'to_world': rightT(sy, 0, (wy1 - wy0) / 2, wz1), 'bsdf': {'type': 'thindielectric'}}
            desc.append('pane')
    else:
        d['right'] = {'type': 'rectangle', 'to_world': rightT(sy, 0, sy, sz), 'bsdf': wall_bsdf}
    # front wall (+z): with a door opening, or none (the camera looks in from there)
    if open_side == 2:
        d['front_l'] = {'type': 'rectangle', 'to_world': T().translate([-sx / 2 - 0.2, sy, sz]).rotate([0, 1, 0], 180).scale([sx / 2 - 0.2, sy, 1]), 'bsdf': wall_bsdf}
    # objects
    n_obj = rng.integers(1, 5)
    for i in range(n_obj):
        kind, bsdf = material(rng)
        shape = ['cube', 'sphere', 'cylinder', 'panel'][rng.integers(4)]
        s = float(rng.uniform(0.15, 0.6)) * min(sx, sy, sz)
        cx, cz = float(rng.uniform(-sx + s, sx - s)), float(rng.uniform(-sz + s, sz * 0.3))
        if shape == 'cube':
            o = {'type': 'cube', 'to_world': T().translate([cx, s, cz]).rotate([0, 1, 0], float(rng.uniform(0, 90))).scale([s, s, s])}
        elif shape == 'sphere':
            o = {'type': 'sphere', 'center': [cx, s + float(rng.uniform(0, sy)), cz], 'radius': s}
        elif shape == 'cylinder':
            o = {'type': 'cylinder', 'p0': [cx, 0, cz], 'p1': [cx, 2 * s, cz], 'radius': s * 0.5}
        else:  # thin one-sided panel standing on the floor
            o = {'type': 'rectangle', 'to_world': T().translate([cx, s, cz]).rotate([0, 1, 0], float(rng.uniform(0, 180))).scale([s, s, 1])}
        o['bsdf'] = bsdf
        d[f'obj{i}'] = o
        desc.append(f"{shape}:{kind}")
    # lights
    lights = []
    n_l = rng.integers(1, 3)
    for i in range(n_l):
        lk = ['area', 'area', 'sphere', 'point', 'spot', 'sun', 'env', 'envmap'][rng.integers(8)]
        if lk in ('sun', 'env', 'envmap') and open_side == 0:
            lk = 'area'
        if lk == 'area':
            a = float(rng.uniform(0.1, 0.5))
            y = 2 * sy - 0.01 if open_side != 3 else sy * 1.8
            d[f'light{i}'] = {'type': 'rectangle', 'to_world': T().translate([float(rng.uniform(-sx / 2, sx / 2)), y, float(rng.uniform(-sz / 2, sz / 2))]).rotate([1, 0, 0], 90).scale([a, a, 1.0]),
                              'emitter': {'type': 'area', 'radiance': rgb(rng.uniform(5, 20, 3) / (a * a * 4))}}
        elif lk == 'sphere':
            r = float(rng.uniform(0.03, 0.2))
            d[f'light{i}'] = {'type': 'sphere', 'center': [float(rng.uniform(-sx / 2, sx / 2)), float(rng.uniform(sy, 1.8 * sy)), float(rng.uniform(-sz / 2, sz / 2))], 'radius': r,
                              'emitter': {'type': 'area', 'radiance': rgb(rng.uniform(1, 4, 3) / (r * r))}}
        elif lk == 'point':
            d[f'light{i}'] = {'type': 'point', 'position': [float(rng.uniform(-sx / 2, sx / 2)), float(rng.uniform(sy, 1.8 * sy)), float(rng.uniform(-sz / 2, sz / 2))],
                              'intensity': rgb(rng.uniform(2, 10, 3))}
        elif lk == 'spot':
            o = [float(rng.uniform(-sx / 2, sx / 2)), float(1.8 * sy), float(rng.uniform(-sz / 2, sz / 2))]
            d[f'light{i}'] = {'type': 'spot', 'to_world': T().look_at(origin=o, target=[o[0] + 0.5, 0, o[2]], up=[0, 0, 1]),
                              'intensity': rgb(rng.uniform(5, 30, 3)), 'cutoff_angle': float(rng.uniform(15, 50))}
        elif lk == 'sun':
            dirn = [-1.0, -float(rng.uniform(0.3, 1.0)), float(rng.uniform(-0.3, 0.3))] if open_side == 1 else [float(rng.uniform(-0.5, 0.5)), -1.0, float(rng.uniform(-0.5, 0.5))]
            d[f'light{i}'] = {'type': 'directional', 'direction': dirn, 'irradiance': rgb(rng.uniform(2, 6, 3))}
        elif lk == 'env':
            d[f'light{i}'] = {'type': 'constant', 'radiance': rgb(rng.uniform(0.3, 2, 3))}
        else:
            env = np.ones((32, 64, 3), np.float32) * rng.uniform(0.2, 1, 3).astype(np.float32)
            env[4:10, 20:28] = 50.0  # a bright patch (a sun-ish blob)
            d[f'light{i}'] = {'type': 'envmap', 'bitmap': mi.Bitmap(env)}
        if lk in ('env', 'envmap'):
            # only one environment emitter is allowed
            for k in [k for k in d if k.startswith('light') and k != f'light{i}' and d[k]['type'] in ('constant', 'envmap')]:
                del d[k]
        lights.append(lk)
    desc.append("lights " + "+".join(lights))
    for index, key in enumerate(sorted(k for k, v in d.items() if isinstance(v, dict) and 'bsdf' in v)):
        d[key]['bsdf'] = distinct(d[key]['bsdf'], index)
    eye = [float(rng.uniform(-sx * 0.5, sx * 0.5)), float(rng.uniform(0.5, 1.5) * sy), float(sz * rng.uniform(0.6, 0.95))]
    target = [float(rng.uniform(-sx * 0.5, sx * 0.5)), float(rng.uniform(0.2, 1.0) * sy), float(-sz)]
    d['sensor'] = {'type': 'perspective', 'fov': float(rng.uniform(40, 75)),
                   'to_world': T().look_at(origin=eye, target=target, up=[0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': W, 'height': H, 'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}}
    return d, ", ".join(desc)


def render(scene, integ, spp, seed=0):
    return timed_render(scene, mi.load_dict(integ), spp, seed)[0]


def measure(seed: int, path_spp: int) -> dict:
    d, desc = make_scene(seed)
    row = {"seed": seed, "scene": desc}
    scene = mi.load_dict(d)
    ra = render(scene, {'type': 'path', 'max_depth': -1}, path_spp // 2, 11)
    rb = render(scene, {'type': 'path', 'max_depth': -1}, path_spp // 2, 12)
    ref = 0.5 * (ra + rb)
    lum_ref = mean_luminance(ref)
    img, row["pmic_s"] = timed_render(scene, mi.load_dict({'type': 'pmic'}), 64, 1)
    first_hit = render(scene, {'type': 'pmic', 'estimator': 'first_hit'}, 64, 2)
    row["finite"] = finite(img) and finite(first_hit)
    if lum_ref <= 0:
        row.update(path_black=True, pmic_mean=mean_luminance(img), first_hit_mean=mean_luminance(first_hit),
                   flag=mean_luminance(img) > 0 or mean_luminance(first_hit) > 0 or not row["finite"])
        return row
    row["halves"] = abs(mean_luminance(ra) - mean_luminance(rb)) / lum_ref
    row["pmic_lum"], row["first_hit_lum"] = mean_luminance(img) / lum_ref, mean_luminance(first_hit) / lum_ref
    row["pmic_relmse"], row["first_hit_relmse"] = rel_mse(img, ref), rel_mse(first_hit, ref)
    row["flag"] = (not row["finite"] or abs(row["pmic_lum"] - 1) > max(0.02, 3 * row["halves"])
                   or abs(row["first_hit_lum"] - 1) > max(0.03, 3 * row["halves"]))
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--count", type=int, default=40)
    parser.add_argument("--path-spp", type=int, default=2048)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    if args.count < 1 or args.path_spp < 2:
        parser.error("--count must be >= 1 and --path-spp >= 2")
    rows = []
    for seed in range(args.first, args.first + args.count):
        try:
            row = measure(seed, args.path_spp)
        except Exception as error:  # a room Mitsuba cannot load or render is a row too
            row = {"seed": seed, "scene": make_scene(seed)[1], "error": f"{type(error).__name__}: {error}", "flag": True}
        rows.append(row)
        print(json.dumps(row), flush=True)
    command = common.command(__file__, argv)
    lines = [f"# Random rooms against path (64×48; pmic 64 spp, path {args.path_spp} spp)", "",
             f"`{command}`", "", "| seed | pmic lum | first_hit lum | path halves | pmic relMSE | flag | room |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['seed']} | error | | | | yes | {r['scene']}: {r['error'][:80]} |")
        elif r.get("path_black"):
            lines.append(f"| {r['seed']} | path black; pmic {r['pmic_mean']:.3g} | {r['first_hit_mean']:.3g} | | | "
                         f"{'yes' if r['flag'] else ''} | {r['scene']} |")
        else:
            lines.append(f"| {r['seed']} | {r['pmic_lum']:.4f} | {r['first_hit_lum']:.4f} | {r['halves']:.4f} | "
                         f"{r['pmic_relmse']:.2e} | {'yes' if r['flag'] else ''} | {r['scene']} |")
    common.write_results(args.out, "random_rooms", {"command": command, "rows": rows}, lines)


if __name__ == "__main__":
    main()
