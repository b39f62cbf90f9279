"""Validates the power that pmic's emitted photons carry:
``pmic_integrator.emission.sample_emitter_rays`` against references that sample no
emitted rays, beside Mitsuba's own ``scene.sample_emitter_ray`` (which Mitsuba 3.9 gets
wrong for a rotated envmap, the reason pmic samples emission itself: docs/limits.md).

    python validation/envmap_emission_check.py                 # ~2^18 rays per case
    python validation/envmap_emission_check.py --rays 100000 --render
    python validation/envmap_emission_check.py --matpreview-scene   # (c) on matpreview
    python validation/envmap_emission_check.py --only constant      # the cases named so

It passes when, in table (a), every case's ``pmic`` ratio is 1 within a few of its
standard errors, and in table (d) ``pmic`` has no non-finite weight or ray and no weight
on an inactive lane. ``tests/test_emission.py`` checks a uniform envmap at three
rotations, a NaN texel and textured lights; this adds a non-uniform envmap under
arbitrary rotations (and matpreview's, where ``../shared/scenes`` has it), ``constant``,
``directional``, point and area lights and their mixes, and Mitsuba's error beside pmic's.

Scene: a 2x2 diffuse square in the plane z = 0 (normal +z), lit by an ``envmap`` made
from a small numpy bitmap with a bright off-axis blob (with and without a rotation in
``to_world``), by the matpreview envmap with matpreview's own ``to_world``, by
``constant``, ``directional`` and area lights, and by a mix of all of them.

For each emission routine (``mitsuba`` = ``scene.sample_emitter_ray``, ``pmic`` =
``emission.sample_emitter_rays``):

(a) irradiance on the top of the square from emitted rays: sum of the weights of the
    rays whose first hit is the top of the square / (N * area), against a reference
    computed without ``sample_ray``: next-event estimation from random points on the
    square (``scene.sample_emitter_direction`` with visibility) and, when nothing but
    the square is in the scene, a quadrature of ``emitter.eval`` over the hemisphere;
(b) for envmaps: the emitted flux per world-space direction bin (weights of the rays)
    against pi R^2 * integral of ``emitter.eval`` over the bin, the weight of each ray
    against L pi R^2 / pdf_direction, and where each ray origin lies (it must be on a
    disk of radius R perpendicular to the ray, at distance R behind the centre);
(c) (``--render``) Mitsuba's ``ptracer`` against ``path`` on the same square;
(d) robustness: NaN, infinite and negative texels, inactive lanes, samples at 0 and 1.

Irradiances are the mean of R, G and B (each case's ratio is what matters).
"""
from __future__ import annotations

import argparse
import math
import time as _time
from pathlib import Path

import numpy as np

import pmic_integrator  # noqa: F401  (sets up LLVM; must come before mitsuba)
import drjit as dr
import mitsuba as mi

#: The public matpreview scene (``../shared/scenes`` beside the checkout), if there.
MATPREVIEW = Path(__file__).resolve().parents[2] / "shared" / "scenes" / "scenes" / "matpreview"
HALF = 1.0            # the square is [-HALF, HALF]^2 at z = 0
AREA = (2 * HALF) ** 2


# ---------------------------------------------------------------- scene building
def blob_bitmap(width=64, height=32):
    """Lat-long map: dim sky, a bright coloured blob off the pole, a dark lower half."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    theta = v[:, None] * np.pi                      # envmap local: y is up
    phi = u[None, :] * 2 * np.pi
    d = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta) + 0 * phi,
                  -np.cos(phi) * np.sin(theta)], -1)
    c = np.array([np.sin(1.0) * np.sin(0.7), np.cos(0.7), -np.cos(1.0) * np.sin(0.7)])
    blob = np.exp((d @ c - 1.0) / 0.03)             # ~ 10 degrees wide
    sky = 0.2 + 0.3 * np.clip(d[..., 1], 0, 1)
    img = np.empty((height, width, 3), np.float32)
    img[..., 0] = sky + 20.0 * blob
    img[..., 1] = sky + 12.0 * blob
    img[..., 2] = 1.5 * sky + 5.0 * blob
    return mi.Bitmap(img)


def square(extra=None):
    d = {"type": "scene",
         "square": {"type": "rectangle",
                    "to_world": mi.ScalarTransform4f().scale([HALF, HALF, 1.0]),
                    "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}}}
    d.update(extra or {})
    return d


def rot(axis, angle):
    # Mitsuba's rotate() does not normalise the axis (a non-unit axis gives a matrix
    # that is not a rotation, and then even `path` is wrong): normalise it here.
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return mi.ScalarTransform4f().rotate(axis.tolist(), angle)


def matpreview_to_world():
    m = np.array([[-0.224951, -0.000001, -0.974370, 0.0],
                  [-0.974370, 0.000000, 0.224951, 0.0],
                  [0.000000, 1.000000, -0.000001, 8.87],
                  [0.0, 0.0, 0.0, 1.0]])
    return mi.ScalarTransform4f(m) @ mi.ScalarTransform4f().rotate([0, 1, 0], -180)


def cases():
    bmp = blob_bitmap()
    env = lambda tw=None, **kw: dict({"type": "envmap", "bitmap": bmp,
                                       **({"to_world": tw} if tw is not None else {})}, **kw)
    area = {"type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([0.3, 0.0, 1.0])
            @ mi.ScalarTransform4f().rotate([1, 0, 0], 180) @ mi.ScalarTransform4f().scale(0.4),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [6.0, 5.0, 4.0]}}}
    occluder = {"type": "sphere", "center": [-0.6, 0.4, 0.5], "radius": 0.25,
                "bsdf": {"type": "diffuse"}}
    out = [
        ("envmap, identity", square({"env": env()}), True),
        ("envmap, rotate x 90", square({"env": env(rot([1, 0, 0], 90))}), True),
        ("envmap, rotate (1,1,.3) 50", square({"env": env(rot([1, 1, 0.3], 50))}), True),
        ("envmap, rotate y 120 (about up)", square({"env": env(rot([0, 1, 0], 120))}), True),
        ("envmap, translate only", square({"env": env(mi.ScalarTransform4f().translate([0, 0, 8.87]))}), True),
    ]
    if (MATPREVIEW / "envmap.exr").exists():
        mp = {"type": "envmap", "filename": str(MATPREVIEW / "envmap.exr"), "scale": 3.0}
        out += [("matpreview envmap, identity", square({"env": dict(mp)}), True),
                ("matpreview envmap, its to_world",
                 square({"env": dict(mp, to_world=matpreview_to_world())}), True)]
    out += [
        ("constant", square({"env": {"type": "constant",
                                     "radiance": {"type": "rgb", "value": [1.0, 0.8, 0.6]}}}), True),
        ("directional (direction=)", square({"sun": {"type": "directional", "direction": [0.3, -0.2, -1.0],
                                                     "irradiance": {"type": "rgb", "value": [3.0, 2.0, 1.0]}}}), False),
        ("directional (to_world rot)", square({"sun": {"type": "directional",
                                                       "to_world": rot([1, 0, 0], 150),
                                                       "irradiance": {"type": "rgb", "value": 2.0}}}), False),
        ("area light", square({"lamp": area}), False),
        ("point light", square({"pt": {"type": "point", "position": [0.2, -0.3, 0.8],
                                       "intensity": {"type": "rgb", "value": 2.0}}}), False),
        ("mixed: rot envmap+sun+area+point+occluder", square({
            "env": env(rot([1, 1, 0.3], 50)), "lamp": area, "occ": occluder,
            "sun": {"type": "directional", "direction": [0.3, -0.2, -1.0],
                    "irradiance": {"type": "rgb", "value": [3.0, 2.0, 1.0]}},
            "pt": {"type": "point", "position": [0.2, -0.3, 0.8],
                   "intensity": {"type": "rgb", "value": 2.0}}}), False),
        ("mixed: rot envmap (sampling_weight 3)+area", square({
            "env": env(rot([1, 0, 0], -70), sampling_weight=3.0), "lamp": area}), False),
        ("mixed: constant+sun+area+point", square({
            "c": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}}, "lamp": area,
            "sun": {"type": "directional", "to_world": rot([1, 0, 0], 150),
                    "irradiance": {"type": "rgb", "value": 2.0}},
            "pt": {"type": "point", "position": [0.2, -0.3, 0.8],
                   "intensity": {"type": "rgb", "value": 2.0}}}), False),
    ]
    return out


# ---------------------------------------------------------------- helpers
def rng_samples(n, seed):
    rng = mi.PCG32(size=n, initstate=seed)
    s1 = rng.next_float32()
    s2 = mi.Point2f(rng.next_float32(), rng.next_float32())
    s3 = mi.Point2f(rng.next_float32(), rng.next_float32())
    return s1, s2, s3


def rgb_mean(c):
    """Mean of R, G and B of an (n, 3) or (3,) array (not luminance: a scalar to compare)."""
    return np.asarray(c).mean(axis=-1)


def mean_se(x):
    x = np.asarray(x, np.float64)
    return x.mean(), x.std() / math.sqrt(len(x))


def emit(scene, which, n, seed):
    s1, s2, s3 = rng_samples(n, seed)
    t = dr.zeros(mi.Float, n)
    if which == "mitsuba":
        ray, w, em = scene.sample_emitter_ray(t, s1, s2, s3, mi.Bool(True))
    else:
        from pmic_integrator.emission import sample_emitter_rays
        ray, w, em = sample_emitter_rays(scene, t, s1, s2, s3, mi.Bool(True))
    return ray, w, em, s2


def photon_irradiance(scene, ray, w, n):
    """Irradiance on the top of the square from the rays' first hits."""
    si = scene.ray_intersect(ray)
    top = si.is_valid() & (dr.abs(si.p.z) < 1e-3) & (dr.abs(si.p.x) <= HALF) & \
        (dr.abs(si.p.y) <= HALF) & (ray.d.z < 0)
    c = dr.select(top, mi.Color3f(w), 0.0) / AREA
    dr.eval(c, si.is_valid())
    return mean_se(rgb_mean(c.numpy().T)), float(dr.count(si.is_valid())[0]) / n


def nee_irradiance(scene, m, seed):
    rng = mi.PCG32(size=m, initstate=seed)
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.p = mi.Point3f((2 * rng.next_float32() - 1) * HALF, (2 * rng.next_float32() - 1) * HALF, 0.0)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    si.wi = mi.Vector3f(0, 0, 1)
    ds, w = scene.sample_emitter_direction(si, mi.Point2f(rng.next_float32(), rng.next_float32()),
                                           True, mi.Bool(True))
    c = w * dr.maximum(ds.d.z, 0.0)
    dr.eval(c)
    return mean_se(rgb_mean(c.numpy().T))


def direction_grid(nz, nphi, zmin=-1.0):
    """Midpoint grid in (z, phi) over directions with z > zmin (equal-area cells)."""
    z = zmin + (np.arange(nz) + 0.5) * (1 - zmin) / nz
    phi = (np.arange(nphi) + 0.5) * 2 * np.pi / nphi
    Z, P = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - Z ** 2)
    dirs = np.stack([s * np.cos(P), s * np.sin(P), Z], -1).reshape(-1, 3)
    dw = (1 - zmin) / nz * 2 * np.pi / nphi
    return dirs, dw


def eval_env(emitter, dirs):
    """emitter.eval(L) towards world directions dirs (n, 3), as an (n, 3) array."""
    n = dirs.shape[0]
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = -mi.Vector3f(dirs[:, 0], dirs[:, 1], dirs[:, 2])
    v = mi.Color3f(emitter.eval(si))
    dr.eval(v)
    return v.numpy().T if v.numpy().shape[0] == 3 else v.numpy()


def quadrature_irradiance(emitter, nz=512, nphi=1024):
    dirs, dw = direction_grid(nz, nphi, zmin=0.0)
    L = eval_env(emitter, dirs)
    return float(rgb_mean((L * dirs[:, 2:3]).sum(0) * dw))


def bsphere(scene):
    from pmic_integrator.emission import emission_sphere
    c, r = emission_sphere(scene)
    return np.array([c.x, c.y, c.z]), r


# ---------------------------------------------------------------- (b) envmap diagnostics
def envmap_diagnostics(scene, emitter, to_world, n, seed):
    """Per-ray checks of Mitsuba's envmap sample_ray (scene has this emitter only)."""
    c, R = bsphere(scene)
    ray, w, _, s2 = emit(scene, "mitsuba", n, seed)
    o = ray.o.numpy().T.astype(np.float64)
    d = ray.d.numpy().T.astype(np.float64)
    rel = (o - c) / R
    along = (rel * d).sum(1)                          # must be -1
    lateral = np.linalg.norm(rel - along[:, None] * d, axis=1)   # must be <= 1
    inside = np.linalg.norm(rel, axis=1) < 1 - 1e-4  # origin inside the bounding sphere
    # Hypothesis: the disk is built with Frame3f(d_local) instead of Frame3f(d_world).
    M = np.array(to_world.matrix.numpy())[:3, :3] if to_world is not None else np.eye(3)
    d_local = -(np.linalg.inv(M) @ d.T).T            # sample_ray: d_world = M * (-d_local)
    off = mi.warp.square_to_uniform_disk_concentric(s2)
    hyp = {}
    for name, axis in (("Frame3f(d_local)", d_local), ("Frame3f(-d_world)", -d)):
        fr = mi.Frame3f(mi.Vector3f(axis[:, 0], axis[:, 1], axis[:, 2]))
        perp = fr.to_world(mi.Vector3f(off.x, off.y, 0.0))
        dr.eval(perp)
        o_h = c + (perp.numpy().T - d) * R
        hyp[name] = float(np.abs(o_h - o).max() / R)
    cos_a = np.abs((d_local * d).sum(1))             # tilt of the disk against the ray
    # Weight against L pi R^2 / pdf_direction at the ray's direction.
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(ray.d)
    L = mi.Color3f(emitter.eval(si))
    it = dr.zeros(mi.Interaction3f, n)
    ds = dr.zeros(mi.DirectionSample3f, n)
    ds.d = -ray.d
    pdf = emitter.pdf_direction(it, ds)
    expect = L * (math.pi * R * R) / pdf
    dr.eval(expect, w)
    wn, en = rgb_mean(w.numpy().T), rgb_mean(expect.numpy().T)
    ok = en > 0
    wratio = wn[ok] / en[ok]
    # Direction histogram (world space, equal-area bins in z and phi), flux per bin.
    nzb, npb = 8, 16
    zb = np.clip(((-d[:, 2] + 1) / 2 * nzb).astype(int), 0, nzb - 1)
    pb = np.clip(((np.arctan2(-d[:, 1], -d[:, 0]) % (2 * np.pi)) / (2 * np.pi) * npb).astype(int), 0, npb - 1)
    flux_mc = np.bincount(zb * npb + pb, weights=wn, minlength=nzb * npb) / n
    dirs, dw = direction_grid(nzb * 32, npb * 32)
    Lq = rgb_mean(eval_env(emitter, dirs)) * dw * math.pi * R * R
    flux_ref = Lq.reshape(nzb, 32, npb, 32).sum((1, 3)).reshape(-1)
    big = flux_ref > 0.02 * flux_ref.max()
    bins = flux_mc[big] / flux_ref[big]
    # The same origin checks on the workaround's rays.
    ray_p, _, _, _ = emit(scene, "pmic", n, seed)
    rel_p = (ray_p.o.numpy().T.astype(np.float64) - c) / R
    d_p = ray_p.d.numpy().T.astype(np.float64)
    along_p = (rel_p * d_p).sum(1)
    lat_p = np.linalg.norm(rel_p - along_p[:, None] * d_p, axis=1)
    pmic = (float(np.abs(along_p + 1).max()), float(lat_p.max()),
            float((np.linalg.norm(rel_p, axis=1) < 1 - 1e-4).mean()))
    return dict(pmic=pmic, along=(float(along.min()), float(along.max())), lateral_max=float(lateral.max()),
                inside=float(inside.mean()), hyp=hyp, cos_a=(float(cos_a.min()), float(np.median(cos_a))),
                weight_ratio=(float(np.median(wratio)), float(np.percentile(np.abs(wratio - 1), 99.9))),
                bins=(float(bins.min()), float(bins.max()), int(big.sum())),
                total=float(flux_mc.sum() / flux_ref.sum()))


# ---------------------------------------------------------------- (c) ptracer vs path
def camera():
    return {"type": "perspective", "fov": 40.0,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 2.5], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"}}


def render_means(scene_dict, spp_path=64, spp_pt=256):
    d = dict(scene_dict, cam=camera())
    out = {}
    for name, spp in (("path", spp_path), ("ptracer", spp_pt)):
        scene = mi.load_dict(d)
        # hide_emitters=False: with True, `path` lets camera rays pass through the
        # (black) back of the area light, which ptracer does not.
        integ = mi.load_dict({"type": name, "max_depth": 2, "hide_emitters": False})
        img = mi.render(scene, integrator=integ, spp=spp, seed=7)
        out[name] = float(np.asarray(img).mean())
    return out


def matpreview_scene_check(resx=64, resy=48, spp_path=64, spp_pt=256):
    """ptracer vs path on the real matpreview scene (read in place, not copied)."""
    out = {}
    for name, spp in (("path", spp_path), ("ptracer", spp_pt)):
        scene = mi.load_file(str(MATPREVIEW / "scene.xml"), resx=resx, resy=resy)
        integ = mi.load_dict({"type": name, "max_depth": 3, "hide_emitters": True})
        img = mi.render(scene, integrator=integ, spp=spp, seed=3)
        out[name] = float(np.asarray(img).mean())
    return out


# ---------------------------------------------------------------- (d) robustness
def robustness(n=1 << 16):
    """NaN/inf texels, inactive lanes, samples at 0 and 1: weights finite, rays finite."""
    rows = []
    variants = [("envmap with a NaN texel", np.nan), ("envmap with an inf texel", np.inf),
                ("envmap with a negative texel", -50.0), ("envmap, top 10 rows black", 0.0)]
    for label, value in variants:
        img = np.array(blob_bitmap(), copy=True)
        if label.endswith("black"):
            img[:10] = 0
        else:
            img[5, 7] = value
        scene = mi.load_dict(square({
            "env": {"type": "envmap", "bitmap": mi.Bitmap(img.astype(np.float32)),
                    "to_world": rot([1, 0, 0], 90)},
            "lamp": {"type": "sphere", "radius": 0.1, "center": [0, 0, 1],
                     "emitter": {"type": "area"}}}))
        s1, s2, s3 = rng_samples(n, 1)
        act = dr.arange(mi.UInt32, n) % 2 == 0            # odd lanes inactive
        for which in ("mitsuba", "pmic"):
            if which == "mitsuba":
                ray, w, _ = scene.sample_emitter_ray(dr.zeros(mi.Float, n), s1, s2, s3, act)
            else:
                from pmic_integrator.emission import sample_emitter_rays
                ray, w, _ = sample_emitter_rays(scene, dr.zeros(mi.Float, n), s1, s2, s3, act)
            wn, o, d = w.numpy(), ray.o.numpy(), ray.d.numpy()
            rows.append((label, which, int((~np.isfinite(wn).all(0)).sum()),
                         int((np.abs(wn[:, 1::2]) > 0).any(0).sum()),
                         int((~(np.isfinite(o).all(0) & np.isfinite(d).all(0))).sum()),
                         int((np.abs(wn).max(0) > 0).sum())))
    vals = [0.0, 1e-7, 0.5, 1 - 2 ** -24, 1.0]
    g = np.array(np.meshgrid(*[vals] * 5)).reshape(5, -1).astype(np.float32)
    m = g.shape[1]
    scene = mi.load_dict(square({"env": {"type": "envmap", "bitmap": blob_bitmap(),
                                         "to_world": rot([1, 0, 0], 90)}}))
    for which in ("mitsuba", "pmic"):
        args = (dr.zeros(mi.Float, m), mi.Float(g[0]), mi.Point2f(g[1], g[2]),
                mi.Point2f(g[3], g[4]), mi.Bool(True))
        if which == "mitsuba":
            ray, w, _ = scene.sample_emitter_ray(*args)
        else:
            from pmic_integrator.emission import sample_emitter_rays
            ray, w, _ = sample_emitter_rays(scene, *args)
        wn, o, d = w.numpy(), ray.o.numpy(), ray.d.numpy()
        rows.append((f"samples in {{0,1e-7,.5,1-2^-24,1}}^5", which,
                     int((~np.isfinite(wn).all(0)).sum()), 0,
                     int((~(np.isfinite(o).all(0) & np.isfinite(d).all(0))).sum()),
                     int((np.abs(wn).max(0) > 0).sum())))
    return rows


# ---------------------------------------------------------------- main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rays", type=int, default=1 << 18)
    ap.add_argument("--render", action="store_true", help="(c) ptracer vs path on every case")
    ap.add_argument("--matpreview-scene", action="store_true",
                    help="(c) ptracer vs path on the real matpreview scene (small, slow-ish)")
    ap.add_argument("--only", default=None, help="run the cases whose name contains this")
    args = ap.parse_args(argv)
    mi.set_variant("llvm_ad_rgb")
    n = args.rays
    t0 = _time.time()
    print(f"{n} rays per case and routine; irradiance E on the top of the square "
          f"(mean of RGB); ratio = E / E_nee")
    print(f"{'case':44s} {'E_nee':>9s} {'E_quad':>9s} | {'mitsuba':>14s} {'ratio':>6s} "
          f"| {'pmic':>14s} {'ratio':>6s} | hit%")
    diag_rows, render_rows = [], []
    for name, sd, pure in cases():
        if args.only and args.only not in name:
            continue
        scene = mi.load_dict(sd)
        e_nee, se_nee = nee_irradiance(scene, n, seed=11)
        env = [e for e in scene.emitters() if mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)
               and not mi.has_flag(e.flags(), mi.EmitterFlags.Delta)]
        e_quad = quadrature_irradiance(env[0]) if (pure and env) else float("nan")
        row = f"{name:44s} {e_nee:9.4f} {e_quad:9.4f}"
        for which in ("mitsuba", "pmic"):
            ray, w, _, _ = emit(scene, which, n, seed=5)
            (e, se), hit = photon_irradiance(scene, ray, w, n)
            row += f" | {e:8.4f}±{se:5.3f} {e / e_nee:6.3f}"
        row += f" | {100 * hit:4.1f}"
        print(row, flush=True)
        if pure and env and "envmap" in name:
            tw = sd["env"].get("to_world")
            diag_rows.append((name, envmap_diagnostics(scene, env[0], tw, n, seed=5)))
        if args.render:
            render_rows.append((name, render_means(sd), e_nee if pure else None))
    print("\n(b) Mitsuba envmap sample_ray, per ray: origin o, direction d, R = bounding radius")
    print(f"{'case':44s} {'(o-c).d/R':>15s} {'lat/R':>6s} {'in%':>5s} | max|o - o_hyp|/R: "
          f"{'Frame(d_loc)':>12s} {'Frame(-d)':>9s} | {'|cos a| min,med':>15s} | "
          f"w/(L pi R2/pdf) med,p99.9dev | dir-bin flux/ref min..max (bins) total "
          f"|| pmic: max|(o-c).d/R+1| lat/R in%")
    for name, g in diag_rows:
        print(f"{name:44s} {g['along'][0]:7.3f},{g['along'][1]:7.3f} {g['lateral_max']:6.3f} "
              f"{100 * g['inside']:5.1f} | {g['hyp']['Frame3f(d_local)']:12.2e} "
              f"{g['hyp']['Frame3f(-d_world)']:9.2e} | {g['cos_a'][0]:6.3f},{g['cos_a'][1]:6.3f}  | "
              f"{g['weight_ratio'][0]:.5f}, {g['weight_ratio'][1]:.1e} | "
              f"{g['bins'][0]:.3f}..{g['bins'][1]:.3f} ({g['bins'][2]}) {g['total']:.4f} "
              f"|| {g['pmic'][0]:.1e} {g['pmic'][1]:.3f} {100 * g['pmic'][2]:.1f}")
    if render_rows:
        print("\n(c) mean of a 32x32 image of the square (its central 1.8x1.8), max_depth 2 "
              "(direct light only); for infinite emitters E = path * pi / rho vs E_nee")
        for name, r, e_nee in render_rows:
            ev = f"(E {r['path'] * math.pi / 0.5:.4f} vs {e_nee:.4f})" if e_nee else " " * 23
            print(f"{name:44s} path {r['path']:.4f} {ev}  ptracer {r['ptracer']:.4f}"
                  f"  ptracer/path {r['ptracer'] / r['path']:.3f}")
    if args.matpreview_scene:
        r = matpreview_scene_check()
        print(f"\n(c) matpreview scene (64x48, max_depth 3, hide_emitters): path {r['path']:.4f} "
              f"ptracer {r['ptracer']:.4f} ratio {r['ptracer'] / r['path']:.3f}")
    print("\n(d) robustness (2^16 lanes, half inactive; or 3125 edge samples)")
    print(f"{'case':40s} {'routine':8s} {'w non-finite':>12s} {'inactive w!=0':>13s} "
          f"{'ray non-finite':>14s} {'w != 0':>7s}")
    for r in robustness():
        print(f"{r[0]:40s} {r[1]:8s} {r[2]:12d} {r[3]:13d} {r[4]:14d} {r[5]:7d}")
    print(f"\n{_time.time() - t0:.1f} s")


if __name__ == "__main__":
    main()
