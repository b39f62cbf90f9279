"""Many views from one cache: build the view-independent stages once, then render the
sensors of a scene on a Dask cluster (``dask.distributed``), each worker loading the
same cache file.

    from pmic_integrator.views import render_views
    images = render_views("scene.xml", sensors=range(8), spp=64)            # local cluster
    images = render_views("scene.xml", scheduler="tcp://host:8786")         # a real one

A Mitsuba scene cannot be sent between processes, so workers load it from its file (it
must be readable there); the cache travels as bytes with the task. Needs the extra
``views`` (``pip install -e '.[views]'``, i.e. ``dask[distributed]``).
"""
from __future__ import annotations

import atexit
import os
import tempfile
import threading
import time
from pathlib import Path


def _scene(scene_file: str, integrator: dict, load_args: dict):
    import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
    import mitsuba as mi

    if not mi.variant():
        mi.set_variant("llvm_ad_rgb")
    scene = mi.load_file(str(scene_file), **load_args)
    return scene, mi.load_dict(dict(integrator))


def build_cache_file(scene_file, cache_file, integrator: dict | None = None, variant="llvm_ad_rgb",
                     progress: bool = False, **load_args) -> dict:
    """Build the photon maps and cache of ``scene_file`` and save them to
    ``cache_file``; returns the stages' statistics. ``progress``: bars of the photon
    and cache stages on stderr."""
    import pmic_integrator  # noqa: F401
    import mitsuba as mi

    mi.set_variant(variant)
    spec = {"type": "pmic", **(integrator or {})}
    spec.pop("cache_file", None)
    scene, pmic = _scene(scene_file, spec, load_args)
    pmic.progress = progress
    stats = pmic.build_cache(scene)
    pmic.save_cache(cache_file)
    return stats


#: Per worker process: ``key`` (scene file, cache, settings, variant, load arguments) of
#: the last views, their ``scene`` and ``integrator`` (with its loaded cache) and the
#: ``folder`` of the cache file, so that a worker's later views skip loading the scene,
#: reading the cache and compiling the scene's kernels again.
_WORKER_CACHE: dict = {}
#: Worker threads of one process (``processes=False``) share it.
_WORKER_LOCK = threading.Lock()


def _worker_scene(scene_file: str, cache_bytes: bytes, integrator: dict, variant: str,
                  load_args: dict):
    import hashlib

    key = (scene_file, hashlib.blake2b(cache_bytes, digest_size=16).hexdigest(),
           repr(sorted(integrator.items())), variant, repr(sorted(load_args.items())))
    with _WORKER_LOCK:
        if _WORKER_CACHE.get("key") != key:
            _forget_worker_scene()
            folder = tempfile.mkdtemp(prefix="pmic-view-")
            path = os.path.join(folder, "cache.npz")
            Path(path).write_bytes(cache_bytes)
            # Worker threads of one process share the scene and the integrator: its
            # renders take turns, each on the whole Dr.Jit pool. (An integrator per
            # thread, rendering one scene at once, hung once under Dask; the cause
            # was not found.)
            scene, pmic = _scene(scene_file, {**integrator, "type": "pmic", "cache_file": path},
                                 load_args)
            _WORKER_CACHE.update(key=key, scene=scene, integrator=pmic, folder=folder)
        return _WORKER_CACHE["scene"], _WORKER_CACHE["integrator"]


def _forget_worker_scene():
    """Drop the kept scene and integrator, and the folder of their cache file."""
    import shutil

    folder = _WORKER_CACHE.get("folder")
    _WORKER_CACHE.clear()
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


atexit.register(_forget_worker_scene)


def _warm_up(scene_file: str, variant: str, load_args: dict, _index: int) -> bool:
    """Start Mitsuba and Dr.Jit on a worker and read the scene once, while the main
    process builds the cache."""
    import mitsuba as mi

    _set_up_worker(variant)
    mi.load_file(str(scene_file), **load_args)
    return True


def _set_up_worker(variant: str):
    """The variant, pmic registered for it (a worker thread may not have seen the
    variant callback), and this worker's share of Dr.Jit threads."""
    import pmic_integrator
    import mitsuba as mi
    import drjit as dr

    mi.set_variant(variant)
    pmic_integrator.register(variant)
    threads = os.environ.get("PMIC_JIT_THREADS")
    if threads:
        dr.set_thread_count(int(threads))


def render_one(scene_file: str, cache_bytes: bytes, sensor: int, spp: int, seed: int,
               integrator: dict, variant: str, load_args: dict):
    """One view, on a worker: the scene from its file, the cache from ``cache_bytes``
    (both kept for the worker's next views); returns (sensor, image as a float32
    array, seconds)."""
    import mitsuba as mi
    import numpy as np

    _set_up_worker(variant)
    start = time.perf_counter()
    scene, pmic = _worker_scene(scene_file, cache_bytes, integrator, variant, load_args)
    image = np.array(mi.render(scene, integrator=pmic, sensor=int(sensor), spp=int(spp),
                               seed=int(seed)), dtype=np.float32)
    if "cache_loaded_from" not in pmic.stats:  # pragma: no cover - a broken set-up
        raise RuntimeError(f"render_views: worker rebuilt the cache for sensor {sensor}")
    return int(sensor), image, time.perf_counter() - start


def render_views(scene_file, sensors=None, spp: int = 16, seed: int = 0, integrator=None,
                 cache_file=None, scheduler=None, client=None, n_workers: int = 1,
                 threads_per_worker: int = 1, processes: bool = True,
                 variant: str = "llvm_ad_rgb", progress: bool = True, **load_args) -> dict:
    """Render ``sensors`` (indices; default all) of ``scene_file`` from one cache on Dask.

    The cache is built here once (or read from an existing ``cache_file``) and sent to
    the workers as bytes. ``client``: an existing ``dask.distributed.Client``;
    ``scheduler``: a scheduler address to connect to; neither: a ``LocalCluster`` of
    ``n_workers`` processes with ``threads_per_worker`` task threads each (1: a view
    already uses every core through Dr.Jit's own thread pool), or with
    ``processes=False`` of ``n_workers`` threads in this process, which share one
    scene, one loaded cache and the kernels already compiled here (on one machine the
    faster choice: each process must trace and compile its kernels once, and the
    cores are split between them). Returns ``{sensor: image}`` (H x W x C float32
    arrays); the same sensor gives the same image whatever else is rendered, in
    whatever order, and whichever kind of cluster renders it.
    """
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as error:  # pragma: no cover - optional extra
        raise RuntimeError("render_views needs dask.distributed: pip install 'dask[distributed]' "
                           "(or this package's extra: pip install -e '.[views]')") from error
    if isinstance(spp, bool) or int(spp) != spp or spp < 1:
        raise ValueError(f"render_views: 'spp' must be a positive integer, got {spp!r}")
    spec = {k: v for k, v in (integrator or {}).items() if k not in ("type", "cache_file")}
    own_cluster = None
    if client is None:
        if scheduler is not None:
            client = Client(scheduler)
        else:
            # Each worker's Dr.Jit gets its share of this machine's cores: two workers
            # with a full thread pool each would fight over them.
            # (Worker threads share this process's pool: views then run one at a
            # time, each on every core.)
            jit_threads = max(1, (os.cpu_count() or 1) // max(1, n_workers))
            split = {"env": {"PMIC_JIT_THREADS": str(jit_threads)}} if processes else {}
            own_cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker,
                                       processes=bool(processes), dashboard_address=None, **split)
            client = Client(own_cluster)
    try:
        # Workers start Mitsuba and read the scene while the cache is built here.
        # (Worker threads of this process have nothing to start.)
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        warm = [] if own_cluster is not None and not processes else \
            [client.submit(_warm_up, str(scene_file), variant, load_args, i, pure=False)
             for i in range(workers)]
        with tempfile.TemporaryDirectory() as folder:
            path = Path(cache_file) if cache_file else Path(folder) / "cache.npz"
            if not path.exists():
                build_cache_file(scene_file, path, spec, variant, progress, **load_args)
            cache_bytes = path.read_bytes()
        if sensors is None:
            import pmic_integrator  # noqa: F401
            import mitsuba as mi

            mi.set_variant(variant)
            sensors = range(len(mi.load_file(str(scene_file), **load_args).sensors()))
        sensors = [int(s) for s in sensors]
        client.gather(warm)
        shipped = client.scatter(cache_bytes, broadcast=True)
        futures = [client.submit(render_one, str(scene_file), shipped, s, spp, seed, spec, variant,
                                 load_args, pure=False) for s in sensors]
        images = {}
        bar = _bar(len(futures), progress)
        for future in as_completed(futures):
            sensor, image, _ = future.result()
            images[sensor] = image
            bar(sensor)
        return {s: images[s] for s in sensors}
    finally:
        if own_cluster is not None:
            client.close()
            own_cluster.close()


def _bar(total: int, enabled: bool):
    """A one-line progress bar on stderr: views done / total."""
    import sys

    done = [0]

    def step(sensor):
        done[0] += 1
        if enabled:
            filled = int(30 * done[0] / max(total, 1))
            sys.stderr.write(f"\rviews [{'#' * filled}{'.' * (30 - filled)}] {done[0]}/{total} "
                             f"(sensor {sensor})")
            if done[0] == total:
                sys.stderr.write("\n")
            sys.stderr.flush()

    return step
