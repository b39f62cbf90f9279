"""Views per second from one view-independent cache, against rebuilding per view and
against the classic camera-seeded cache (``method=irradiance_cache``, records placed
from each camera).

A Cornell box with ``--views`` sensors on a circle, 256² at 16 spp each:
  * ``pmic, one cache``: one integrator; the cache is built at the first view and reused;
  * ``pmic, rebuilt per view``: a new integrator per view (what a farm without cache files does);
  * ``irradiance_cache``: the view-dependent cache, rebuilt for every view by design;
  * ``pmic, one process per view``: what a farm without cache files runs (each process
    loads the scene and builds its own cache);
  * ``pmic on Dask``: ``views.render_views`` on a LocalCluster (``--workers``), the cache
    built once and shipped as bytes (its time includes starting the cluster): worker
    processes (as on a real cluster), and worker threads of one process
    (``processes=False``: one scene, one loaded cache and one set of compiled kernels).
Every configuration renders once untimed first (kernel compilation). Writes
``benchmarks/results/views.json`` and ``.md``.

    python benchmarks/views.py --views 16 --workers 2
"""
from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import mitsuba as mi
import numpy as np

import common
from common import timed

SENSOR = """<sensor type="perspective"><float name="fov" value="39.3"/>
    <transform name="to_world"><lookat origin="{x:.4f}, 0.0, {z:.4f}" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/>
        <rfilter type="box"/></film></sensor>"""


def scene_file(folder: Path, views: int, res: int) -> Path:
    """The bundled Cornell box with ``views`` sensors looking in from the open side."""
    from pmic_integrator import scenes

    text = scenes.scene_path("cornell_box").read_text()
    sensors = "".join(SENSOR.format(x=3.9 * math.sin(a), z=3.9 * math.cos(a), res=res)
                      for a in np.linspace(-0.35, 0.35, views))
    start, end = text.index("<sensor"), text.index("</sensor>") + len("</sensor>")
    path = folder / "cornell_views.xml"
    text = text[:start] + sensors + text[end:]
    path.write_text(text)
    # Relative references (meshes, textures) keep working next to the original file.
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=6)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", type=Path, default=common.RESULTS)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    from pmic_integrator.views import render_views

    folder = Path(tempfile.mkdtemp())
    path = scene_file(folder, args.views, args.resolution)
    scene = mi.load_file(str(path))
    views = range(args.views)
    rows = {}

    def render_all(make, reuse):
        integrator = make()
        for v in views:
            if not reuse:
                integrator = make()
            image = mi.render(scene, integrator=integrator, sensor=v, spp=args.spp, seed=v)
            np.array(image)

    configs = {
        "pmic, one cache": (lambda: mi.load_dict({"type": "pmic"}), True),
        "pmic, rebuilt per view": (lambda: mi.load_dict({"type": "pmic"}), False),
        "irradiance_cache (camera-seeded)": (lambda: mi.load_dict({"type": "pmic", "method": "irradiance_cache"}), True),
    }
    for name, (make, reuse) in configs.items():
        mi.render(scene, integrator=make(), sensor=0, spp=1)  # compile
        _, seconds = timed(lambda: render_all(make, reuse))
        rows[name] = {"seconds": seconds, "views_per_second": args.views / seconds}
        print(f"{name:34s} {seconds:7.2f} s  {args.views / seconds:.2f} views/s", flush=True)
    _, dask_seconds = timed(lambda: render_views(path, list(views), args.spp, n_workers=args.workers,
                                                 progress=False))
    _, dask_thread_seconds = timed(lambda: render_views(path, list(views), args.spp,
                                                        n_workers=args.workers, processes=False,
                                                        progress=False))
    # A farm without cache files: one process per view, each loading the scene and
    # building its own cache (kernels come from Dr.Jit's on-disk cache, as on a farm).
    one_view = (f"import pmic_integrator, mitsuba as mi, numpy as np, sys; mi.set_variant({common.VARIANT!r}); "
                "s = mi.load_file(sys.argv[1]); np.array(mi.render(s, integrator=mi.load_dict("
                "{'type': 'pmic'}), sensor=int(sys.argv[2]), spp=int(sys.argv[3]), seed=int(sys.argv[2])))")
    _, seconds = timed(lambda: [subprocess.run([sys.executable, "-c", one_view, str(path), str(v), str(args.spp)],
                                               check=True) for v in views])
    rows["pmic, one process per view (cache rebuilt)"] = {"seconds": seconds,
                                                          "views_per_second": args.views / seconds}
    print(f"pmic, one process per view: {seconds:7.2f} s", flush=True)
    plural = "s" if args.workers > 1 else ""
    dask_name = f"pmic on Dask ({args.workers} worker process{'es' if plural else ''})"
    thread_name = f"pmic on Dask ({args.workers} worker thread{plural}, one process)"
    rows[dask_name] = {"seconds": dask_seconds, "views_per_second": args.views / dask_seconds}
    rows[thread_name] = {"seconds": dask_thread_seconds,
                         "views_per_second": args.views / dask_thread_seconds}
    for name in (dask_name, thread_name):
        print(f"{name}: {rows[name]['seconds']:7.2f} s  {rows[name]['views_per_second']:.2f} views/s "
              f"(includes cluster start-up)")
    rebuilt = rows["pmic, rebuilt per view"]["seconds"]
    processes = rows["pmic, one process per view (cache rebuilt)"]["seconds"]
    speedup, speedup_processes = rebuilt / dask_seconds, processes / dask_seconds
    thread_speedup, thread_speedup_processes = rebuilt / dask_thread_seconds, processes / dask_thread_seconds
    print(f"Dask from one cache against independent renders: processes {speedup:.2f}x (against "
          f"rebuilds in one process), {speedup_processes:.2f}x (one process each); threads "
          f"{thread_speedup:.2f}x, {thread_speedup_processes:.2f}x")

    command = common.command(__file__, argv)
    md = [f"# {args.views} views of the Cornell box, {args.resolution}², {args.spp} spp", "",
          f"`{command}`", "", "| configuration | time [s] | views/s |", "|---|---|---|"]
    md += [f"| {k} | {v['seconds']:.2f} | {v['views_per_second']:.2f} |" for k, v in rows.items()]
    md += ["", f"One cache on Dask against {args.views} independent renders (each building "
               f"its own cache): {dask_name}: {speedup:.2f}x sooner than the rebuilds in one warm "
               f"process, {speedup_processes:.2f}x sooner than one process per view; "
               f"{thread_name}: {thread_speedup:.2f}x and {thread_speedup_processes:.2f}x."]
    print("wrote", common.write_results(
        args.out, "views", {"command": command, "views": args.views, "resolution": args.resolution,
                            "spp": args.spp, "rows": rows, "dask_speedup_over_rebuilt": speedup,
                            "dask_speedup_over_processes": speedup_processes,
                            "dask_threads_speedup_over_rebuilt": thread_speedup,
                            "dask_threads_speedup_over_processes": thread_speedup_processes}, md))


if __name__ == "__main__":
    main()
