"""Stage timings of the photon maps: tracing throughput, hash-grid build, precomputed
irradiance (paper: 15.6 s for 100,000 photons on a 2-core E8400; our bar: < 0.1 s), and
memory per photon, including a 10-million-photon render (``--memory``).

    python benchmarks/precompute.py              # 100k and 1M photons, Cornell box
    python benchmarks/precompute.py --memory     # also render with 10M global photons

Each figure is the median of ``--repeats`` runs after a warm-up in the same process.
Writes benchmarks/results/precompute.json and .md.
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
from pathlib import Path

import pmic_integrator  # noqa: F401
import drjit as dr
import mitsuba as mi

import common
from common import timed


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--photons", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--memory", action="store_true", help="also render with 10M global photons")
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    from pmic_integrator import scenes
    from pmic_integrator.pipeline import SceneInfo
    from pmic_integrator.irradiance import lookup_radius, precompute_irradiance, sort_into_grid
    from pmic_integrator.photons import GLOBAL, trace_photons

    scene = scenes.load_scene("cornell_box", resolution=128, spp=4)
    info = SceneInfo.of(scene)
    rows = []
    for count in args.photons:
        timed(lambda: trace_photons(scene, GLOBAL, count, -1, 0, 1 << 40))  # warm-up (compiles)
        traces, builds, pres = [], [], []
        for rep in range(args.repeats):
            photons, t_trace = timed(lambda: trace_photons(scene, GLOBAL, count, -1, rep + 1, 1 << 40))
            radius = lookup_radius(info.surface_area, photons.count, 64)
            (photons, grid), t_build = timed(lambda: sort_into_grid(photons, radius, 64))
            timed(lambda: precompute_irradiance(photons, radius, 64, None))  # warm-up, finished
            _, t_pre = timed(lambda: precompute_irradiance(photons, radius, 64, None))
            traces.append(t_trace), builds.append(t_build), pres.append(t_pre)
        row = {"photons": count, "paths_emitted": photons.paths_emitted,
               "trace_s": statistics.median(traces),
               "stored_per_s": count / statistics.median(traces),
               "grid_build_s": statistics.median(builds),
               "precompute_s": statistics.median(pres),
               "precompute_min_s": min(pres), "precompute_max_s": max(pres)}
        rows.append(row)
        print(json.dumps(row), flush=True)

    memory = None
    if args.memory:
        count = 10_000_000
        integrator = mi.load_dict({"type": "pmic", "global_photons": count})
        image, seconds = timed(lambda: mi.render(scene, integrator=integrator, spp=4))
        s = integrator.stats
        memory = {"global_photons": s["photons_global"], "seconds": seconds,
                  "photon_bytes": s["memory_photons_bytes"],
                  "bytes_per_photon": s["memory_photons_bytes"] / max(1, s["photons_global"]),
                  "records": s["records"], "record_bytes": s["memory_records_bytes"],
                  "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                  "finite": bool(dr.all(dr.isfinite(image.array), axis=None))}
        print(json.dumps(memory), flush=True)

    command = common.command(__file__, argv)
    md = ["# Photon stage timings (Cornell box, 2 cores)", "", f"`{command}`", "",
          "| global photons | tracing [s] | stored photons/s | grid build [s] | precomputed irradiance [s] |",
          "|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['photons']:,} | {r['trace_s']:.3f} | {r['stored_per_s'] / 1e6:.2f} M | "
                  f"{r['grid_build_s']:.3f} | {r['precompute_s']:.3f} (min {r['precompute_min_s']:.3f}) |")
    md.append("\nThe paper: 15.6 s to precompute irradiance for 100,000 photons (2008, 2 cores).")
    if memory:
        md += ["", f"10M global photons: rendered in {memory['seconds']:.1f} s, "
                   f"{memory['bytes_per_photon']:.0f} bytes per photon ({memory['photon_bytes'] / 2**30:.2f} GiB), "
                   f"peak RSS {memory['peak_rss_gib']:.1f} GiB, finite image: {memory['finite']}."]
    common.write_results(args.out, "precompute", {"command": command, "rows": rows, "memory": memory}, md)
    print("\n".join(md))


if __name__ == "__main__":
    main()
