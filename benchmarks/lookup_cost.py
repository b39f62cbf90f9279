"""Cost of the cache lookups alone: ``RecordIndex.interpolate`` at ~1M points where
gather rays from the camera's first hits meet the scene (what the final gather reads
at every camera sample), timed apart from the render. Also the walk of the records'
grid cells alone, and the first pass (which records reach each point), to show where
a lookup's time goes.

    python benchmarks/lookup_cost.py                         # Cornell box
    python benchmarks/lookup_cost.py --scene indirect_room --points 2097152

For an A/B of two versions on a noisy machine, run this script alternately with each
version on ``PYTHONPATH`` (and ``PMIC_SCENES_DIR`` pointing at this checkout's
``scenes``), several times, and compare the fastest runs: the lookups themselves are
the same sums up to rounding whatever the version (``--save`` writes them for a check).
"""
from __future__ import annotations

import argparse

import numpy as np

import pmic_integrator  # noqa: F401  (before mitsuba: the LLVM it needs)
import drjit as dr
import mitsuba as mi

import common
from common import fastest

#: The cache of the error-versus-time benchmark's cheapest pmic runs.
SETTINGS = {"global_photons": 50_000, "max_error": 1.0, "gather_rays": 64, "direct_samples": 1}


def gather_hits(scene, count: int, seed: int):
    """Points (and normals facing the ray) where one cosine-distributed ray from each
    of ``count`` camera first hits meets the scene; lanes that miss are inactive."""
    sensor = scene.sensors()[0]
    rng = mi.PCG32(count, seed)
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(rng.next_float32(), rng.next_float32()), mi.Point2f(0.5))
    first = scene.ray_intersect(ray)
    local = mi.warp.square_to_cosine_hemisphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    bounce = first.spawn_ray(first.to_world(local))
    hit = scene.ray_intersect(bounce, first.is_valid())
    normal = mi.Vector3f(hit.n)
    normal = dr.select(dr.dot(normal, bounce.d) > 0, -normal, normal)
    active = hit.is_valid()
    dr.eval(hit.p, normal, active)
    return hit.p, normal, active


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="cornell_box")
    parser.add_argument("--points", type=int, default=1 << 20)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--save", default=None, help="write the interpolated irradiance (.npy)")
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    from pmic_integrator import cache, scenes

    scene = scenes.load_scene(args.scene, resolution=128, spp=1)
    integrator = mi.load_dict({"type": "pmic", **SETTINGS})
    mi.render(scene, integrator=integrator, spp=1)
    index = integrator.prepared.index.for_lookup().pack()
    x, n, active = gather_hits(scene, args.points, 7)

    def lookups():
        out = index.interpolate(x, n, active, with_radius=True, shading_n=n)
        dr.eval(out)
        dr.sync_thread()
        return out

    def walk():
        out = index.grid.for_each_ball(x, dr.zeros(mi.UInt32, args.points), lambda s, i, v: s + i,
                                       active=active)
        dr.eval(out)
        dr.sync_thread()

    def first_pass():
        def visit(found, record, valid):
            p, normal, radius = index._record_geometry(record, valid)
            return dr.select(valid & cache.covers(x, n, p, normal, radius, index.max_error), found + 1, found)
        out = index.grid.for_each_ball(x, dr.zeros(mi.UInt32, args.points), visit, active=active)
        dr.eval(out)
        dr.sync_thread()

    active_share = dr.mean(dr.select(active, 1.0, 0.0))[0]
    print(f"{args.scene}: {index.records.count} records, {args.points} points ({active_share:.2f} hit)")
    for label, run in (("walk of the grid cells", walk), ("first pass (which records reach)", first_pass),
                       ("interpolate (whole lookup)", lookups)):
        print(f"  {label:34s} {1e3 * fastest(run, args.repeats):7.1f} ms (fastest of {args.repeats})")
    if args.save:
        np.save(args.save, np.array(lookups()[0]))


if __name__ == "__main__":
    main()
