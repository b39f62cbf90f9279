"""Many views and fly-throughs from one cache: build the view-independent stages once,
then render frames on a Dask cluster (``dask.distributed``), each worker loading the
same cache file.

    from pmic_integrator.views import render_views, render_frames, frames_along_path
    images = render_views("scene.xml", sensors=range(8), spp=64)            # local cluster
    images = render_views("scene.xml", scheduler="tcp://host:8786")         # a real one
    keys = [{"origin": [0, 1, 4], "target": [0, 1, 0]}, {"origin": [3, 1, 3], "target": [0, 1, 0]}]
    images = render_frames(frames_along_path("scene.xml", keys, 48), spp=16)

A frame is a scene file, one of its sensors and, optionally, a camera placement that
replaces that sensor's (:class:`Frame`): the sensors of one scene, scene files that
share their geometry (each frame a file, as exporters write animations) and a camera
path of key look-ats all render from the one cache, which depends on the scene's shapes,
materials and lights only (:mod:`pmic_integrator.fingerprint`).

A Mitsuba scene cannot be sent between processes, so workers load it from its file (it
must be readable there); the cache travels as bytes with the task. Needs the extra
``views`` (``pip install -e '.[views]'``, i.e. ``dask[distributed]``).
"""
from __future__ import annotations

import atexit
import json
import math
import os
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Frame:
    """One image of a fly-through: ``sensor`` of ``scene_file``, placed at ``to_world``
    (a 4×4 camera-to-world matrix as nested tuples, rows first) with horizontal field
    of view ``fov`` (degrees) where given, else where the file puts it."""

    scene_file: str
    sensor: int = 0
    to_world: tuple | None = None
    fov: float | None = None
    seed: int = 0  #: the render's seed (camera-path noise), not the cache's
    name: str = ""  #: file name stem of the written images


def frames_of_sensors(scene_file, sensors=None, seed: int = 0, load_args: dict | None = None):
    """A frame per sensor of ``scene_file`` (default: all of them), all with ``seed``."""
    if sensors is None:
        import pmic_integrator  # noqa: F401
        import mitsuba as mi

        if not mi.variant():
            mi.set_variant("llvm_ad_rgb")
        sensors = range(len(mi.load_file(str(scene_file), **(load_args or {})).sensors()))
    stem = Path(scene_file).stem
    return [Frame(str(scene_file), int(s), seed=seed, name=f"{stem}_sensor{int(s)}") for s in sensors]


def frames_of_files(scene_files, seed: int = 0, sensor: int = 0):
    """A frame per scene file (``sensor`` of each): files that share their shapes,
    materials and lights, as an exporter writes an animated camera, render from one
    cache. Frame ``i`` renders with seed ``seed + i``."""
    return [Frame(str(f), sensor, seed=seed + i, name=Path(f).stem) for i, f in enumerate(scene_files)]


def _look_at_matrix(origin, target, up) -> tuple:
    import mitsuba as mi
    import numpy as np

    matrix = np.array(mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target),
                                                     up=list(up)).matrix, dtype=np.float64)
    return tuple(tuple(float(v) for v in row) for row in matrix.reshape(4, 4))


def _check_key(i: int, key) -> dict:
    if not isinstance(key, dict) or "origin" not in key or "target" not in key:
        raise ValueError(f"camera path: key {i} must be a dict with 'origin' and 'target' (and "
                         f"optionally 'up' and 'fov'), got {key!r}")
    out = {"origin": key["origin"], "target": key["target"], "up": key.get("up", (0, 1, 0)),
           "fov": key.get("fov")}
    for name in ("origin", "target", "up"):
        value = out[name]
        if len(value) != 3 or not all(math.isfinite(float(v)) for v in value):
            raise ValueError(f"camera path: key {i}'s {name!r} must be 3 finite numbers, got {value!r}")
    if out["fov"] is not None and not 0 < float(out["fov"]) < 180:
        raise ValueError(f"camera path: key {i}'s 'fov' must be in (0, 180) degrees, got {out['fov']!r}")
    return out


def frames_along_path(scene_file, keys, count: int, sensor: int = 0, seed: int = 0):
    """``count`` frames along a camera path through ``keys`` (dicts of ``origin``,
    ``target``, optional ``up`` and ``fov``; or a JSON file holding that list), moving
    ``sensor`` of ``scene_file``: positions, targets, up vectors and fields of view
    interpolated linearly between consecutive keys, evenly in key index; the first
    frame at the first key, the last at the last. Frame ``i`` renders with seed
    ``seed + i``."""
    if isinstance(keys, (str, os.PathLike)):
        keys = json.loads(Path(keys).read_text())
    from .scenes import check_positive_int

    check_positive_int(count, "camera path: 'count' (frames)")
    keys = [_check_key(i, k) for i, k in enumerate(keys)]
    if not keys:
        raise ValueError("camera path: needs at least one key")
    if any((k["fov"] is None) != (keys[0]["fov"] is None) for k in keys):
        raise ValueError("camera path: give 'fov' in every key or in none")
    frames = []
    for i in range(int(count)):
        t = i * (len(keys) - 1) / max(int(count) - 1, 1)
        a = min(int(t), len(keys) - 1)
        b, w = min(a + 1, len(keys) - 1), t - a

        def lerp(name):
            return [(1 - w) * float(x) + w * float(y) for x, y in zip(keys[a][name], keys[b][name])]

        fov = None if keys[0]["fov"] is None else (1 - w) * float(keys[a]["fov"]) + w * float(keys[b]["fov"])
        frames.append(Frame(str(scene_file), sensor, _look_at_matrix(lerp("origin"), lerp("target"), lerp("up")),
                            fov, seed + i, f"frame_{i:04d}"))
    return frames


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
            try:
                scene, pmic = _scene(scene_file, {**integrator, "type": "pmic", "cache_file": path},
                                     load_args)
                pmic.build_cache(scene)  # loads the file now (refused if another scene's)
            except BaseException:
                import shutil

                shutil.rmtree(folder, ignore_errors=True)
                raise
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
    """Start Mitsuba and Dr.Jit on a worker and read the (first) scene once, while the
    main process builds the cache."""
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


#: Worker threads of one process share a scene: placing its camera and rendering take turns.
_RENDER_LOCK = threading.Lock()


def place_camera(scene, frame: Frame) -> None:
    """Move ``frame.sensor`` of ``scene`` to ``frame.to_world`` and ``frame.fov`` (where
    given) through ``mi.traverse``, as Mitsuba animates a camera."""
    import mitsuba as mi

    if frame.to_world is None and frame.fov is None:
        return
    params = mi.traverse(scene.sensors()[frame.sensor])
    if frame.to_world is not None:
        params["to_world"] = mi.ScalarTransform4f([list(row) for row in frame.to_world])
    if frame.fov is not None:
        if "x_fov" not in params.keys():
            raise ValueError(f"frame {frame.name!r}: sensor {frame.sensor} has no field of view "
                             f"to set (not a perspective camera)")
        params["x_fov"] = float(frame.fov)
    params.update()


def render_frame(frame: Frame, cache_bytes: bytes, spp: int, integrator: dict, variant: str,
                 load_args: dict):
    """One frame, on a worker: the scene from its file, the cache from ``cache_bytes``
    (both kept for the worker's next frames), the camera placed; returns (frame, image
    as a float32 array, seconds)."""
    import mitsuba as mi
    import numpy as np

    from .cachefile import CacheFileError

    _set_up_worker(variant)
    start = time.perf_counter()
    try:
        scene, pmic = _worker_scene(frame.scene_file, cache_bytes, integrator, variant, load_args)
    except CacheFileError as error:
        raise CacheFileError(f"frame {frame.name!r} ({frame.scene_file}) cannot use the fly-through's "
                             f"cache: {error}") from None
    if not 0 <= frame.sensor < len(scene.sensors()):
        raise ValueError(f"frame {frame.name!r}: sensor {frame.sensor} is not in {frame.scene_file} "
                         f"({len(scene.sensors())} sensors)")
    with _RENDER_LOCK:
        place_camera(scene, frame)
        image = np.array(mi.render(scene, integrator=pmic, sensor=frame.sensor, spp=int(spp),
                                   seed=int(frame.seed)), dtype=np.float32)
    if "cache_loaded_from" not in pmic.stats:  # pragma: no cover - a broken set-up
        raise RuntimeError(f"render_frames: worker rebuilt the cache for frame {frame.name!r}")
    return frame, image, time.perf_counter() - start


def render_views(scene_file, sensors=None, spp: int = 16, seed: int = 0, integrator=None,
                 cache_file=None, scheduler=None, client=None, n_workers: int = 1,
                 threads_per_worker: int = 1, processes: bool = True,
                 variant: str = "llvm_ad_rgb", progress: bool = True, **load_args) -> dict:
    """Render ``sensors`` (indices; default all) of ``scene_file`` from one cache on Dask,
    each with ``seed``; returns ``{sensor: image}`` (H x W x C float32 arrays). The
    other arguments are :func:`render_frames`'."""
    _check_spp(spp)
    if sensors is None:
        import pmic_integrator  # noqa: F401
        import mitsuba as mi

        mi.set_variant(variant)
    frames = frames_of_sensors(scene_file, sensors, seed, load_args)
    images = render_frames(frames, spp, integrator, cache_file, scheduler, client, n_workers,
                           threads_per_worker, processes, variant, progress, **load_args)
    return {frame.sensor: image for frame, image in zip(frames, images)}


def _check_spp(spp) -> None:
    from .scenes import check_positive_int

    check_positive_int(spp, "render_frames: 'spp'")


def _client(scheduler, n_workers: int, threads_per_worker: int, processes: bool):
    """(client, the cluster made for it or None): a client of ``scheduler``, else of a
    LocalCluster of ``n_workers`` processes (or threads of this one)."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as error:  # pragma: no cover - optional extra
        raise RuntimeError("render_frames needs dask.distributed: pip install 'dask[distributed]' "
                           "(or this package's extra: pip install -e '.[views]')") from error
    if scheduler is not None:
        return Client(scheduler), None
    # Each worker's Dr.Jit gets its share of this machine's cores: two workers with a
    # full thread pool each would fight over them. (Worker threads share this
    # process's pool: frames then run one at a time, each on every core.)
    jit_threads = max(1, (os.cpu_count() or 1) // max(1, n_workers))
    split = {"env": {"PMIC_JIT_THREADS": str(jit_threads)}} if processes else {}
    cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker,
                           processes=bool(processes), dashboard_address=None, **split)
    return Client(cluster), cluster


def render_frames(frames, spp: int = 16, integrator=None, cache_file=None, scheduler=None,
                  client=None, n_workers: int = 1, threads_per_worker: int = 1,
                  processes: bool = True, variant: str = "llvm_ad_rgb", progress: bool = True,
                  **load_args) -> list:
    """Render ``frames`` (:class:`Frame`; see :func:`frames_of_sensors`,
    :func:`frames_of_files`, :func:`frames_along_path`) from one cache on Dask; returns
    their images (H x W x C float32 arrays) in order.

    The cache is built here once, from the first frame's scene file (or read from an
    existing ``cache_file``), and sent to the workers as bytes; every frame's scene
    must have the same shapes, materials and lights (else the cache is refused,
    naming what differs). ``integrator``: pmic's parameters. ``client``: an existing
    ``dask.distributed.Client``; ``scheduler``: a scheduler address to connect to;
    neither: a ``LocalCluster`` of ``n_workers`` processes with ``threads_per_worker``
    task threads each (1: a frame already uses every core through Dr.Jit's own thread
    pool), or with ``processes=False`` of ``n_workers`` threads in this process, which
    share one scene, one loaded cache and the kernels already compiled here (on one
    machine the faster choice: each process must trace and compile its kernels once,
    and the cores are split between them). A frame gives the same image whatever else
    is rendered, in whatever order, and whichever kind of cluster renders it.
    ``progress``: a bar of the cache stages, then one of the frames (tqdm).
    """
    from dask.distributed import as_completed

    _check_spp(spp)
    frames = list(frames)
    if not frames:
        return []
    spec = {k: v for k, v in (integrator or {}).items() if k not in ("type", "cache_file")}
    own_cluster = None
    if client is None:
        client, own_cluster = _client(scheduler, n_workers, threads_per_worker, processes)
    try:
        # Workers start Mitsuba and read the scene while the cache is built here.
        # (Worker threads of this process have nothing to start.)
        first = frames[0].scene_file
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        warm = [] if own_cluster is not None and not processes else \
            [client.submit(_warm_up, first, variant, load_args, i, pure=False) for i in range(workers)]
        with tempfile.TemporaryDirectory() as folder:
            path = Path(cache_file) if cache_file else Path(folder) / "cache.npz"
            if not path.exists():
                build_cache_file(first, path, spec, variant, progress, **load_args)
            cache_bytes = path.read_bytes()
        client.gather(warm)
        shipped = client.scatter(cache_bytes, broadcast=True)
        futures = {client.submit(render_frame, frame, shipped, spp, spec, variant, load_args,
                                 pure=False): i for i, frame in enumerate(frames)}
        images = [None] * len(frames)
        with _progress_bar(len(frames), progress, "frames") as bar:
            for future in as_completed(futures):
                frame, image, _ = future.result()
                images[futures[future]] = image
                bar.set_postfix_str(frame.name, refresh=False)
                bar.update()
        return images
    finally:
        if own_cluster is not None:
            client.close()
            own_cluster.close()


def _progress_bar(total: int, enabled: bool, unit: str):
    """A tqdm bar (terminal or Jupyter), off where ``enabled`` is false."""
    from tqdm.auto import tqdm

    return tqdm(total=total, disable=not enabled, unit=unit.rstrip("s"), desc=unit, leave=True)


def write_frames(frames, images, folder, exr: bool = True, png: bool = True) -> list:
    """Write each image as ``folder/<frame name>.exr`` (linear, float32) and a ``.png``
    preview (sRGB, clipped at 1); returns the paths written."""
    from .scenes import write_exr, write_png

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for i, (frame, image) in enumerate(zip(frames, images)):
        stem = frame.name or f"frame_{i:04d}"
        if exr:
            write_exr(folder / f"{stem}.exr", image[..., :3])
            written.append(folder / f"{stem}.exr")
        if png:
            write_png(folder / f"{stem}.png", image[..., :3])
            written.append(folder / f"{stem}.png")
    return written
