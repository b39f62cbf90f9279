"""The ``pmic`` Mitsuba 3 integrator: stages 1-4 of Gu & Wang (2010) put together."""
from __future__ import annotations

import hashlib
import logging
import math
import os
import re
import threading
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import cache as cache_mod, cachefile
from ._jit import concat, every_nth, opaque_float, rng as make_rng, surface_offset
from .cache import CacheRecords, RecordIndex
from mitsuba.ad.integrators.common import mis_weight

from .bsdfs import diffuse_response, lobes_separable, non_diffuse_context
from .gather import VISIBILITY_LIFT, GatherSource, trace_gather_rays
from .hashgrid import BallGrid, PointGrid, PointGridPyramid
from .irradiance import (adapted_lookup_radius, estimate_irradiance, lookup_radius,
                         precompute_irradiance, sort_into_grid)
from .photons import CAUSTIC, GLOBAL, PhotonMap, trace_photons
from .settings import METHODS, Settings, check_against_scene  # noqa: F401 (METHODS re-exported)

log = logging.getLogger("pmic")


# --- Internal tuning constants -------------------------------------------------------
#: Final gather (estimator "final_gather"): a diffuse vertex behind a traced one reads
#: the cache only if the segment reaching it is at least this many (weighted mean)
#: record radii long. A record's radius is the harmonic mean distance of the geometry
#: its gather saw: nearer than that, the vertex lies in the corner, contact or gap the
#: record interpolates across, and its error would fill a wide solid angle of the
#: traced vertex (the blotches of first-hit interpolation). Such vertices are traced
#: too...
TRUST_RECORD_RADII = 1.0
#: ...but at most this many diffuse bounces per camera path: then the cache is read
#: however close (bounded cost; the error is by then three diffuse bounces deep).
MAX_TRACED_BOUNCES = 3
#: Smallest record *reach* (a·R), in units of the global photon lookup radius:
#: irradiance is only resolved to about one lookup radius, so smaller records add cost,
#: not detail; and a reach of ~4 photon spacings leaves no gaps between the photons.
MIN_REACH_LOOKUPS = 1.0
#: Largest record radius as a fraction of the scene's bounding-box diagonal: a
#: view-independent cache has no pixel footprint to bound it, the scene size does.
R_MAX_DIAGONAL = 0.08
#: Neighbour clamping looks this many photon lookup radii around each candidate, and
#: repeats until the bound has spread over the largest radius (at most this many passes).
CLAMP_STEP_LOOKUPS = 2.0
CLAMP_ITERATIONS = 6
#: Every this-many-th camera point probes the cache for neighbour clamping.
VIEW_PROBE_STRIDE = 16
VIEW_CLAMP_PASSES = 4
#: Candidates walked first, evenly spread, before the ones they leave uncovered.
PLACEMENT_SUBSET = 16384
#: Ray origins are pushed off the surface by this fraction of the scene's length scale
#: (see ``_length_scale``), plus RAY_OFFSET_RELATIVE of the point's largest coordinate
#: (float precision far from the origin).
RAY_OFFSET_DIAGONAL = 1e-5
#: The length scale is the diagonal, but at most this many global lookup radii: a
#: 2·10⁶-unit ground plane under a 1-unit box must not push rays 28 units off the box,
#: nor let records grow to 10⁵ units. Photons tell where the light, and so the
#: detail, is.
LENGTH_SCALE_LOOKUPS = 100.0
#: Photons per caustic estimate relative to ``lookup_size``: caustics are sharper.
CAUSTIC_LOOKUP_FRACTION = 0.5
#: The caustic pass emits at most this many paths per requested photon...
CAUSTIC_PATHS_PER_PHOTON = 20
#: ...and is dropped (records gather caustic light instead) below this yield.
CAUSTIC_MIN_YIELD = 0.25
#: Default emitted-path bound per map, as a multiple of the requested photon count.
MAX_PATHS_PER_PHOTON = 100
#: ...and never less than this many paths (small requests in dim scenes).
MIN_MAX_PATHS = 1 << 22


def _finite(value, active=True):
    """``value`` where ``active`` and every channel is finite, else 0: a NaN or Inf from
    one emitter, texel or sample must cost that sample only."""
    return dr.select(mi.Bool(active) & dr.all(dr.isfinite(value)), value, 0.0)


@dataclass
class SceneInfo:
    """What the integrator needs to know about a scene before tracing anything."""

    diagonal: float  #: length of the bounding-box diagonal (sets world-space scales)
    surface_area: float  #: sum of the shapes' surface areas (sets photon radii)
    emitters: int  #: number of emitters
    has_diffuse: bool  #: some BSDF has a diffuse lobe (else no cache, no global map)
    has_specular: bool  #: some BSDF has a delta or glossy lobe (else no caustic map)
    has_infinite_emitter: bool = False  #: an environment (envmap, constant) lights the scene
    has_delta_emitter: bool = False  #: a point, spot or directional light (no ray hits it)

    @staticmethod
    def of(scene: mi.Scene) -> "SceneInfo":
        bbox = scene.bbox()
        diagonal = float(dr.norm(bbox.extents())) if bbox.valid() else 0.0
        area, has_diffuse, has_specular = 0.0, False, False
        for shape in scene.shapes():
            a = float(dr.sum(shape.surface_area())[0]) if hasattr(shape, "surface_area") else 0.0
            area += a if math.isfinite(a) and a > 0 else 0.0
            bsdf = shape.bsdf()
            flags = int(bsdf.flags()) if bsdf is not None else 0
            has_diffuse |= bool(flags & int(mi.BSDFFlags.Diffuse))
            has_specular |= bool(flags & (int(mi.BSDFFlags.Delta) | int(mi.BSDFFlags.Glossy)))
        if not math.isfinite(diagonal) or diagonal <= 0:
            diagonal = 1.0
        if not math.isfinite(area) or area <= 0:
            area = diagonal * diagonal
        infinite = any(mi.has_flag(e.flags(), mi.EmitterFlags.Infinite) for e in scene.emitters())
        delta = any(mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition) or
                    mi.has_flag(e.flags(), mi.EmitterFlags.DeltaDirection) for e in scene.emitters())
        return SceneInfo(diagonal, area, len(scene.emitters()), has_diffuse, has_specular, infinite,
                         delta)


@dataclass
class PreparedScene:
    """Everything the render stage reads, built once per scene (view independent)."""

    key: tuple  #: fingerprint of the scene and the parameters it was built with
    info: SceneInfo
    global_map: PhotonMap
    caustic_map: PhotonMap
    global_grid: PointGridPyramid | None
    caustic_grid: PointGridPyramid | None
    global_radius: float  #: world-space radius of global-map estimates
    caustic_radius: float  #: world-space radius of caustic-map estimates
    index: RecordIndex | None  #: the irradiance cache (None: not used)
    skipped: list = field(default_factory=list)  #: passes skipped, with reasons
    stats: dict = field(default_factory=dict)  #: figures of the stages above
    gather_source: GatherSource | None = None  #: what gather rays read (stage 2)


class PMICIntegrator(mi.SamplingIntegrator):
    r"""Photon mapping with a view-independent irradiance cache (``pmic``).

    Implements Gu Xiao-Ling and Wang Yi-Gang, *Irradiance Caching Algorithm Based on
    Photon Mapping* (2010): photons are traced from the lights (Jensen 1996), irradiance
    is precomputed at the photons (Christensen 2000), irradiance-cache records (Ward et
    al. 1988) are placed by walking the photons instead of the camera, and the image is
    rendered with direct light + caustics + cache interpolation.

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Default
         - Meaning
       * - ``method``
         - string
         - ``"pmic"``
         - ``"pmic"`` (the paper's method), ``"photon_map"`` (radiance estimate at the
           first diffuse hit, the paper's Fig. 5a baseline) or ``"irradiance_cache"``
           (classic view-dependent Ward cache, records placed from the camera).
       * - ``estimator``
         - string
         - ``"final_gather"``
         - ``pmic`` only. ``"final_gather"``: the first diffuse vertex of a camera path
           is path-traced (one BSDF sample, MIS with the emitters) and the cache, which
           then also holds direct light, is read where that ray lands, unless it
           lands closer than a record radius (corners, contacts, gaps: traced once
           more, up to 3 times). Its error is noise, which a denoiser removes, and it
           keeps converging; the cache is view independent. ``"first_hit"``: the
           paper's interpolation at the first diffuse vertex (less noise at few
           samples, but record-sized blotches that stay).
       * - ``aovs``
         - string
         - ``""``
         - Extra output channels, comma-separated (or ``"all"``): ``albedo`` and
           ``normal`` (the denoiser's guides at the first surface, as Mitsuba's
           ``aov`` integrator computes them), ``direct``, ``indirect`` (cache and
           photon map) and ``caustic`` radiance (they add up to the image), and
           ``coverage`` (1 where the first cache read found a record, 0 where it fell
           back to the photon map or no cache was read).
       * - ``cache_file``
         - string
         - ``""``
         - A ``.npz`` file holding the photon maps and cache: loaded if it exists
           (after checking it was built for this scene and these settings: an error
           otherwise), else built and written there. Also ``save_cache(path)`` and
           ``build_cache(scene)``. With ``first_hit``, the records a rendered view
           added are saved too.
       * - ``max_depth``
         - integer
         - -1
         - Longest path, in segments, as in Mitsuba's ``path`` (-1: unbounded, else
           1-1024; 1: only emitters seen directly; 2: direct light only, no photons).
       * - ``rr_depth``
         - integer
         - 5
         - Camera-path depth from which Russian roulette may end paths (1-1024).
       * - ``hide_emitters``
         - boolean
         - false
         - Hide directly visible emitters; as in ``path``, a hidden area light is
           looked through.
       * - ``global_photons``
         - integer
         - 200000
         - Photons *stored* in the global map (1000-5e7; emission runs until reached).
       * - ``caustic_photons``
         - integer
         - 100000
         - Photons stored in the caustic map (0-5e7; skipped if the scene has no delta
           or glossy surface; dropped if under a quarter is stored after 20 paths per
           photon, and records then gather caustic light instead).
       * - ``lookup_size``
         - integer
         - 64
         - Photons per density estimate (8-10000); sets the base lookup radius from
           where the photons landed (scale does not matter); estimates shrink it
           where photons cluster.
       * - ``lookup_radius``
         - float
         - 0 (auto)
         - World-space base radius of global-map estimates; overrides ``lookup_size``.
           Must hold a photon per disc on average and stay under 0.1 of the scene's
           diagonal (checked before any work).
       * - ``max_error``
         - float
         - 0.5
         - Ward's maximum error *a* (0.01-1): a record is used within ``a·R`` of its
           position. Smaller: more records, more accurate, slower.
       * - ``gather_rays``
         - integer
         - 256
         - Final-gather rays per cache record (16-16384, stratified M×N hemisphere).
       * - ``final_gather``
         - boolean
         - false
         - ``photon_map`` only: replace the radiance estimate at the first diffuse hit by
           one cosine-distributed gather ray per camera sample that reads the
           precomputed irradiance.
       * - ``max_photon_paths``
         - integer
         - 0 (auto)
         - Bound on emitted light paths per map (auto: 100 × the photon count, at least
           4 M). A warning is given when fewer than half the photons were stored.
       * - ``direct_samples``
         - integer
         - 4
         - Emitter samples (shadow rays) per camera vertex (1-64): shadow rays cost far less
           than camera samples (which also interpolate the cache), and direct light is
           most of the noise left.
       * - ``seed``
         - integer
         - 0
         - Seed of photon tracing and gathering (0 to 2^32-1): the same seed gives the
           same cache.

    **What it does not do**: participating media are ignored (surfaces only);
    ``max_depth`` is exact for light reaching the first diffuse surface a camera path
    meets and approximate for deeper vertices reached through specular chains;
    polarised and spectral variants are not supported (use ``llvm_ad_rgb`` or
    ``cuda_ad_rgb``); it is not differentiable.

    Parameter types are checked as strictly as Mitsuba's plugins do (an integer refuses
    2.9); a bad type or value raises ValueError naming it, before any work.

    After ``mi.render``, ``scene.integrator().stats`` (or this object's ``stats``)
    holds counts and per-stage times in seconds.

    .. code-block:: python

        import pmic_integrator, mitsuba as mi
        mi.set_variant("llvm_ad_rgb")
        scene = mi.load_file("scenes/cornell_box.xml", integrator="pmic")
        image = mi.render(scene, spp=16)
        # or: mi.load_dict({"type": "pmic", "global_photons": 100000, "max_error": 0.3})
    """

    def __init__(self, props: mi.Properties):
        # Parsed before Mitsuba's base class reads its own parameters (hide_emitters),
        # so that every bad parameter gets pmic's message.
        settings = Settings.parse(props)
        super().__init__(props)
        #: Every parameter, parsed and checked once (ValueError naming a bad one).
        self.settings = settings
        self.stats: dict = {}
        self._prepared: PreparedScene | None = None
        self._cache_builds = 0  #: view-independent caches built from photons so far
        # One render at a time per integrator object: the prepared scene and the
        # per-render state below are shared by the Python render() and the sample()
        # that Mitsuba's C++ render() calls back into (a second thread would see them
        # half-updated). Separate integrator objects render concurrently.
        self._render_lock = threading.RLock()
        self._thread = threading.local()  #: ``inside``: this thread is in render()
        self._fallback_counter = None

    # ----------------------------------------------------------------------------------
    # Mitsuba interface
    # ----------------------------------------------------------------------------------
    def to_string(self) -> str:
        return (f"PMICIntegrator[method={self.settings.method}, max_depth={self.settings.max_depth}, "
                f"global_photons={self.settings.global_photons}, caustic_photons={self.settings.caustic_photons}, "
                f"max_error={self.settings.max_error}, gather_rays={self.settings.gather_rays}]")

    def aov_names(self):
        return self.settings.aov_channels

    def render(self, scene: mi.Scene, sensor=0, seed=0, spp: int = 0, develop: bool = True,
               evaluate: bool = True):
        if getattr(self._thread, "inside", False):
            # Mitsuba's C++ render() calls back into this override: hand it to C++.
            return mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
        with self._render_lock:
            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            try:
                self._prepare_scene(scene)
                # Scene-level figures (kept while the cache is reused) plus this render's.
                self.stats = self._prepared.stats
                self.stats["cache_builds"] = self._cache_builds
                self._prepare_view(scene, sensor)
            except BaseException:
                # Nothing half-built survives a failure (or a Ctrl-C): the next render
                # starts again from the photons.
                self._prepared = None
                raise
            self._fallback_counter = dr.zeros(mi.UInt32, 1)
            start = time.perf_counter()
            self._thread.inside = True
            try:
                image = mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
            finally:
                self._thread.inside = False
            dr.eval(image)
            dr.sync_thread()
            self.stats["time_render"] = time.perf_counter() - start
            self.stats["shading_points_fallback"] = int(self._fallback_counter[0])
            self._publish_stats()
            return image

    # ----------------------------------------------------------------------------------
    # Stages 1-3: view independent, built once per scene and parameter set
    # ----------------------------------------------------------------------------------
    @staticmethod
    def _scene_fingerprint(scene: mi.Scene) -> str:
        """Digest of the scene's parameters, so that an edited scene is rebuilt and a
        cache file is only read for its own scene. Stable across processes: unnamed
        objects' keys (``object_<address>``) are normalised and entries sorted."""
        params = mi.traverse(scene)
        entries = []
        for key in params.keys():
            try:
                value = params[key]
            except Exception:  # pragma: no cover - unreadable parameters are skipped
                continue
            if dr.is_array_v(value):
                data = np.ascontiguousarray(np.array(value)).tobytes()
            else:
                data = repr(value).encode()
            entries.append((re.sub(r"object_\d+", "object", key).encode(), data))
        digest = hashlib.blake2b(digest_size=16)
        for name, data in sorted(entries):
            digest.update(name)
            digest.update(len(data).to_bytes(8, "little"))
            digest.update(data)
        return digest.hexdigest()

    def build_cache(self, scene: mi.Scene) -> dict:
        """Run the view-independent stages (photons, precomputed irradiance, cache) for
        ``scene`` now, instead of at the first render; returns their statistics."""
        with self._render_lock:
            try:
                self._prepare_scene(scene)
            except BaseException:
                self._prepared = None
                raise
            return dict(self._prepared.stats)

    def save_cache(self, path) -> str:
        """Write the photon maps and the cache built for the last scene to ``path``
        (``.npz``; see :mod:`pmic_integrator.cachefile`). Load it with the
        ``cache_file`` parameter, in this or another process."""
        with self._render_lock:
            prepared = self._prepared
            if prepared is None:
                raise ValueError("save_cache: nothing to save yet: render the scene or call "
                                 "build_cache(scene) first")
            return str(cachefile.save(path, prepared, prepared.key[2], prepared.key[1]))

    def _prepare_scene(self, scene: mi.Scene):
        key = (id(scene), self.settings.key(), self._scene_fingerprint(scene))
        if self._prepared is not None and self._prepared.key == key:
            return
        self._scene_ref = scene
        cache_file = self.settings.cache_file
        if cache_file and os.path.exists(cache_file):
            t0 = time.perf_counter()
            prepared = cachefile.load(cache_file, scene, key[2], key[1])
            prepared.key = key
            prepared.stats["cache_loaded_from"] = cache_file
            prepared.stats["time_cache_load"] = time.perf_counter() - t0
            self._prepared = prepared
            return
        self._build_prepared(scene, key)
        if cache_file:
            cachefile.save(cache_file, self._prepared, key[2], key[1])
            self._prepared.stats["cache_saved_to"] = cache_file

    def _build_prepared(self, scene: mi.Scene, key: tuple):
        info = SceneInfo.of(scene)
        check_against_scene(self.settings, info.surface_area, info.diagonal)
        skipped = []
        stats = {}

        # What this scene needs (each skip is logged and reported in stats).
        direct_only = self.settings.max_depth != -1 and self.settings.max_depth <= 2
        need_global = True
        need_caustic = True
        if direct_only:
            skipped.append("photons: max_depth <= 2 allows direct light only")
            need_global = need_caustic = False
        if info.emitters == 0:
            skipped.append("photons: the scene has no emitter")
            need_global = need_caustic = False
        if not info.has_diffuse:
            skipped.append("global map and cache: no surface has a diffuse lobe")
            need_global = need_caustic = False
        if need_caustic and not info.has_specular:
            skipped.append("caustic map: no delta or glossy surface can focus light")
            need_caustic = False
        if need_caustic and self.settings.max_depth != -1 and self.settings.max_depth < 3:
            # light -> specular -> diffuse -> camera is 3 segments.
            skipped.append("caustic map: max_depth < 3 leaves no room for a caustic path")
            need_caustic = False
        if self.settings.global_photons == 0 and need_global:
            skipped.append("global map: global_photons = 0")
            need_global = False
        if self.settings.caustic_photons == 0 and need_caustic:
            skipped.append("caustic map: caustic_photons = 0")
            need_caustic = False
        # Stage 1: photon maps.
        t0 = time.perf_counter()
        global_map = PhotonMap.empty()
        caustic_map = PhotonMap.empty()
        if need_global:
            global_map = trace_photons(scene, GLOBAL, self.settings.global_photons, self.settings.max_depth, self.settings.seed,
                                       self._max_paths(self.settings.global_photons), _progress)
        if need_caustic and need_global and global_map.count == 0:
            # Every caustic photon would also have been stored in the global map.
            skipped.append("caustic map: no global photon reached a diffuse surface")
            need_caustic = False
        if need_caustic:
            paths = min(self._max_paths(self.settings.caustic_photons),
                        CAUSTIC_PATHS_PER_PHOTON * self.settings.caustic_photons)
            caustic_map = trace_photons(scene, CAUSTIC, self.settings.caustic_photons,
                                        self.settings.max_depth, self.settings.seed, paths, _progress,
                                        warn=False)
            if caustic_map.count < CAUSTIC_MIN_YIELD * self.settings.caustic_photons and \
                    not info.has_delta_emitter:
                # Rare caustic paths (an environment light and a small glossy object):
                # a map of a few thousand photons costs seconds and gives blotches;
                # records gather those paths instead (see GatherSource). Not with a
                # point, spot or directional light: no gather ray can hit those, and
                # their caustics would be lost (a sun through a window onto glass).
                skipped.append(f"caustic map: only {caustic_map.count} of "
                               f"{self.settings.caustic_photons} photons after {caustic_map.paths_emitted} "
                               f"paths; gather rays count caustic light instead")
                caustic_map = PhotonMap.empty()
        dr.sync_thread()
        stats["time_photons"] = time.perf_counter() - t0
        stats["photons_global"] = global_map.count
        stats["photons_caustic"] = caustic_map.count
        stats["paths_emitted"] = global_map.paths_emitted + caustic_map.paths_emitted

        # Stage 2: hash grids and irradiance precomputed at the global photons.
        t0 = time.perf_counter()
        gather_source = None
        global_radius = self.settings.lookup_radius or adapted_lookup_radius(
            global_map.position, lookup_radius(info.surface_area, global_map.count,
                                               self.settings.lookup_size), self.settings.lookup_size)
        caustic_size = max(1, int(self.settings.lookup_size * CAUSTIC_LOOKUP_FRACTION))
        caustic_radius = adapted_lookup_radius(
            caustic_map.position, lookup_radius(info.surface_area, caustic_map.count, caustic_size),
            caustic_size)
        global_map, global_grid = sort_into_grid(global_map, global_radius, self.settings.lookup_size)
        caustic_map, caustic_grid = sort_into_grid(caustic_map, caustic_radius, caustic_size)
        if global_map.count and self.settings.method == "photon_map" and not self.settings.final_gather:
            skipped.append("precomputed irradiance: photon_map without final gathering never reads it")
        elif global_map.count:
            depth_limit = None if self.settings.max_depth == -1 else self.settings.max_depth - 2
            # Gather rays read this copy (half the photons, see precompute_irradiance).
            gather_source = GatherSource.build(
                precompute_irradiance(global_map, global_radius, self.settings.lookup_size,
                                      depth_limit), global_radius)
            gather_source.caustics_by_gathering = caustic_map.count == 0
            if gather_source.photons.count == 0:
                # A map of a handful of photons (a tiny max_photon_paths) can leave a
                # half empty: nothing to gather from, so no cache.
                skipped.append("cache: too few global photons to precompute irradiance")
                global_map, global_grid, gather_source = PhotonMap.empty(), None, None
        dr.sync_thread()
        stats["time_precompute"] = time.perf_counter() - t0
        stats["lookup_radius"] = global_radius
        stats["caustic_radius"] = caustic_radius

        # Stage 3: the view-independent cache, seeded from the global photons.
        t0 = time.perf_counter()
        index = None
        stats["records"] = 0
        stats["records_fallback"] = 0
        stats["placement_rounds"] = 0
        self._prepared = PreparedScene(key, info, global_map, caustic_map, global_grid, caustic_grid,
                                       global_radius, caustic_radius, None, skipped, stats,
                                       gather_source)
        offset = RAY_OFFSET_DIAGONAL * self._length_scale()
        if self.settings.method == "pmic" and global_map.count:
            candidates_p, candidates_n = global_map.position, global_map.normal
            index, rounds = self._build_records(scene, candidates_p, candidates_n, None, offset)
            stats["records"] = index.records.count
            stats["placement_rounds"] = rounds
            self._cache_builds += 1
        elif self.settings.method == "pmic":
            skipped.append("cache: no global photons")
        if index is not None and self.settings.final_gather_camera:
            # What a gather hit reflects is all of its light: records keep their direct
            # irradiance too, so the camera path needs no shadow rays there.
            index.direct = cache_mod.direct_irradiance(
                scene, index.records.position, index.records.normal,
                cache_mod.RECORD_DIRECT_SAMPLES, self.settings.seed, offset)
            dr.eval(index.direct)
        dr.sync_thread()
        self._prepared.index = index
        stats["time_cache"] = time.perf_counter() - t0
        stats["skipped"] = list(skipped)
        for reason in skipped:
            log.info("pmic: skipped %s", reason)

    def _index(self, records: CacheRecords) -> RecordIndex:
        """The lookup structure of ``records``, with visibility tests for records that
        reach past a surface."""
        return RecordIndex.build(records, self.settings.max_error, self._scene_ref,
                                 VISIBILITY_LIFT * self._prepared.global_radius)

    def _length_scale(self) -> float:
        """World-space scale for offsets and the largest record: the diagonal, but no
        more than LENGTH_SCALE_LOOKUPS global lookup radii."""
        prepared = self._prepared
        if prepared.global_radius > 0:
            return min(prepared.info.diagonal, LENGTH_SCALE_LOOKUPS * prepared.global_radius)
        return prepared.info.diagonal

    def _max_paths(self, photons: int) -> int:
        if self.settings.max_photon_paths:
            return self.settings.max_photon_paths
        return max(MAX_PATHS_PER_PHOTON * photons, MIN_MAX_PATHS)

    def _radius_bounds(self):
        prepared = self._prepared
        r_max = R_MAX_DIAGONAL * self._length_scale()
        r_min = min(MIN_REACH_LOOKUPS * prepared.global_radius / self.settings.max_error, r_max) \
            if prepared.global_radius > 0 else 1e-3 * r_max
        return r_min, r_max

    def _source(self) -> GatherSource:
        return self._prepared.gather_source

    def _pilot_radius(self, scene, p, n, seed_offset: int, offset):
        """R from a cheap pilot gather, clamped to the world-space bounds."""
        r_min, r_max = self._radius_bounds()
        pilot, _ = cache_mod.harmonic_mean_distance(scene, p, n, cache_mod.PILOT_STRATA,
                                                    self.settings.seed + seed_offset, offset)
        return dr.clip(pilot, opaque_float(r_min), opaque_float(r_max))

    def _place(self, scene, cand_p, cand_n, existing: RecordIndex | None, offset):
        """Pilot radii, then placement (Fig. 2); returns the chosen (p, n, R), rounds."""
        r_max = self._radius_bounds()[1]
        pilot = self._pilot_radius(scene, cand_p, cand_n, 17, offset)
        step = max(CLAMP_STEP_LOOKUPS * self._prepared.global_radius, r_max / CLAMP_ITERATIONS)
        pilot = cache_mod.clamp_to_neighbours(cand_p, cand_n, pilot, step,
                                              int(math.ceil(r_max / step)))
        dr.eval(pilot)
        selected, rounds = cache_mod.place_records(cand_p, cand_n, pilot, self.settings.max_error, existing)
        return (dr.gather(mi.Point3f, cand_p, selected), dr.gather(mi.Vector3f, cand_n, selected),
                dr.gather(mi.Float, pilot, selected)), rounds

    def _build_records(self, scene, cand_p, cand_n, existing: RecordIndex | None, offset,
                       _recursing: bool = False):
        """Place records among candidates (Fig. 2), compute them, return the index.

        With many candidates the walk visits an evenly spread subset first
        (``PLACEMENT_SUBSET`` of them) and then only the candidates that the subset's
        records leave uncovered: the same guarantee (every candidate covered), but
        pilot rays only where they can matter, so the cost no longer grows with the
        photon count.
        """
        count = dr.width(cand_p.x)
        placed = CacheRecords.empty() if existing is None else existing.records
        rounds = 0
        remaining_p, remaining_n = cand_p, cand_n
        new_p, new_n, new_r = [], [], []
        if count > PLACEMENT_SUBSET:
            stride = -(-count // PLACEMENT_SUBSET)
            subset = every_nth(count, stride)
            (p, n, r), k = self._place(scene, dr.gather(mi.Point3f, cand_p, subset),
                                       dr.gather(mi.Vector3f, cand_n, subset), existing, offset)
            rounds += k
            new_p.append(p), new_n.append(n), new_r.append(r)
            placed = placed.extend(CacheRecords.geometry_only(p, n, r))
            uncovered = dr.compress(~self._index(placed).covered(cand_p, cand_n))
            remaining_p = dr.gather(mi.Point3f, cand_p, uncovered)
            remaining_n = dr.gather(mi.Vector3f, cand_n, uncovered)
        if dr.width(remaining_p.x):
            prior = self._index(placed) if placed.count else None
            (p, n, r), k = self._place(scene, remaining_p, remaining_n, prior, offset)
            rounds += k
            new_p.append(p), new_n.append(n), new_r.append(r)
        p = concat(new_p, mi.Point3f)
        n = concat(new_n, mi.Vector3f)
        r = concat(new_r, mi.Float)
        records = cache_mod.compute_records(scene, self._source(), p, n, r, self.settings.gather_strata,
                                            self.settings.seed + 31 + (existing.records.count if existing else 0),
                                            offset)
        all_records = existing.records.extend(records) if existing is not None else records
        index = self._index(all_records)
        # Placement tests coverage without visibility (the records' gathers, which tell
        # which records reach past a surface, come after it): candidates covered only
        # by records they cannot see get records of their own. A record covers its own
        # candidate, so one pass settles it.
        lost = dr.compress(~index.covered(cand_p, cand_n))
        if dr.width(lost) and not _recursing:
            index, more = self._build_records(scene, dr.gather(mi.Point3f, cand_p, lost),
                                              dr.gather(mi.Vector3f, cand_n, lost), index, offset,
                                              _recursing=True)
            rounds += more
        return index, rounds

    # ----------------------------------------------------------------------------------
    # Per-view preparation: records where the camera sees what no photon reached
    # ----------------------------------------------------------------------------------
    def _camera_points(self, scene: mi.Scene, sensor: mi.Sensor):
        """First surface with a diffuse lobe seen through each pixel centre."""
        film = sensor.film()
        size = film.crop_size()
        w, h = int(size[0]), int(size[1])
        idx = dr.arange(mi.UInt32, w * h)
        pos = mi.Vector2f(mi.Float(idx % w) + 0.5, mi.Float(idx // w) + 0.5) / mi.Vector2f(w, h)
        ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), pos, mi.Point2f(0.5, 0.5))
        rng = make_rng(w * h, self.settings.seed, stream=101)
        p, n, found = _first_diffuse_hit(scene, mi.Ray3f(ray), rng)
        keep = dr.compress(found)
        return dr.gather(mi.Point3f, p, keep), dr.gather(mi.Vector3f, n, keep)

    def _prepare_view(self, scene: mi.Scene, sensor: mi.Sensor):
        prepared = self._prepared
        if self.settings.method == "photon_map" or prepared.global_map.count == 0:
            return
        if self.settings.final_gather_camera:
            # Gather rays see the whole scene, not what this camera sees: the cache
            # stays view independent (where no record reaches, the photon map is read).
            return
        t0 = time.perf_counter()
        offset = RAY_OFFSET_DIAGONAL * self._length_scale()
        cam_p, cam_n = self._camera_points(scene, sensor)
        if self.settings.method == "irradiance_cache":
            # Classic cache: records placed from this camera only, rebuilt per view.
            index, rounds = self._build_records(scene, cam_p, cam_n, None, offset)
            prepared.index = index
            self.stats["records"] = 0
            self.stats["records_fallback"] = index.records.count
            self.stats["placement_rounds"] = rounds
        else:
            before = prepared.index.records.count if prepared.index else 0
            if prepared.index is not None:
                self._clamp_to_view(scene, cam_p, cam_n, offset)
            uncovered = ~prepared.index.covered(cam_p, cam_n) if prepared.index else mi.Bool(True)
            keep = dr.compress(uncovered)
            if dr.width(keep):
                index, _ = self._build_records(scene, dr.gather(mi.Point3f, cam_p, keep),
                                               dr.gather(mi.Vector3f, cam_n, keep), prepared.index, offset)
                prepared.index = index
            added = prepared.index.records.count - before
            self.stats["records_fallback"] = self.stats.get("records_fallback", 0) + added
            self.stats["camera_points_uncovered"] = int(dr.width(keep))
        dr.sync_thread()
        self.stats["time_cache_view"] = time.perf_counter() - t0

    def _clamp_to_view(self, scene, cam_p, cam_n, offset):
        """Neighbour clamping against what the camera sees: a record may not reach a
        visible point x further than R(x) + |x − xᵢ|, where R(x) is x's own pilot
        radius. Photons are sparse exactly where this matters (the shadowed gap
        between a light and its ceiling), so the photon-seeded records cannot know.
        Shrunk records may uncover photons; those get records of their own, so every
        photon stays covered."""
        prepared = self._prepared
        index = prepared.index
        probes = every_nth(dr.width(cam_p.x), VIEW_PROBE_STRIDE)
        probe_p = dr.gather(mi.Point3f, cam_p, probes)
        probe_n = dr.gather(mi.Vector3f, cam_n, probes)
        probe_r = self._pilot_radius(scene, probe_p, probe_n, 23, offset)
        photons = prepared.global_map
        # Records made for photons that shrinking uncovered must obey the bound too;
        # a record always covers its own photon, so this settles in a few passes.
        for _ in range(VIEW_CLAMP_PASSES):
            shrunk = cache_mod.clamp_records_to_points(
                index, probe_p, probe_n, probe_r, scene, VISIBILITY_LIFT * prepared.global_radius)
            if shrunk is None:
                break
            records = index.records
            # Only photons within the old reach of a shrunk record can have lost cover.
            was = dr.compress(shrunk < records.radius)
            old_reach = BallGrid.build(dr.gather(mi.Point3f, records.position, was),
                                       dr.gather(mi.Float, records.radius, was) * self.settings.max_error)
            near = _inside_any(old_reach, photons.position)
            records.radius = shrunk
            index = self._index(records)
            lost = dr.compress(near & ~index.covered(photons.position, photons.normal, near))
            if dr.width(lost):
                index, _ = self._build_records(scene, dr.gather(mi.Point3f, photons.position, lost),
                                               dr.gather(mi.Vector3f, photons.normal, lost), index,
                                               offset)
        prepared.index = index

    def _publish_stats(self):
        p = self._prepared
        grids = [g for g in (p.global_grid, p.caustic_grid) if g is not None]
        photon_bytes = p.global_map.nbytes() + p.caustic_map.nbytes() + sum(g.nbytes() for g in grids)
        if p.gather_source is not None and p.gather_source.fine_grid is not None:
            photon_bytes += p.gather_source.fine_photons.nbytes() + p.gather_source.fine_grid.nbytes()
        # Photon maps, their hash grids and the gather lookup copy, all included.
        self.stats["memory_photons_bytes"] = photon_bytes
        self.stats["memory_records_bytes"] = p.index.records.nbytes() if p.index else 0
        if self.settings.method != "pmic":
            self.stats.setdefault("records", 0)

    # ----------------------------------------------------------------------------------
    # Stage 4: camera paths
    # ----------------------------------------------------------------------------------
    def _depth_limit(self, depth):
        """Photons completing a path of at most max_depth segments (None: all)."""
        return None if self.settings.max_depth == -1 else mi.UInt32(self.settings.max_depth) - depth - 1

    def _caustic_irradiance(self, p, n, depth, active):
        """Irradiance at a camera vertex from light → delta/glossy bounces (caustic map)."""
        prepared = self._prepared
        if not prepared.caustic_map.count:
            return dr.zeros(mi.Color3f, dr.width(p))
        return estimate_irradiance(prepared.caustic_map, prepared.caustic_grid, p, n,
                                   prepared.caustic_radius, max_depth=self._depth_limit(depth),
                                   active=active)

    def _cache_lookup(self, p, n, active):
        """``(E, covered, R)``: the cache's interpolated irradiance, where records reach
        (p, n), and their weighted mean radius."""
        index = self._prepared.index
        lanes = dr.width(p)
        if index is None:
            return dr.zeros(mi.Color3f, lanes), dr.zeros(mi.Bool, lanes), dr.zeros(mi.Float, lanes)
        return index.interpolate(p, n, active, with_radius=True)

    def _count_fallback(self, need):
        """Count the camera vertices that no record reached (stats)."""
        dr.scatter_reduce(dr.ReduceOp.Add, self._fallback_counter, mi.UInt32(1), mi.UInt32(0), need)

    def _global_irradiance(self, p, n, depth, active, cached, covered):
        """Irradiance at a camera vertex from light that bounced off a diffuse surface
        first: the cache's ``cached`` value where ``covered``, else the global photon
        map (the method ``photon_map`` reads the map only)."""
        prepared = self._prepared
        lanes = dr.width(p)
        depth_limit = self._depth_limit(depth)
        if prepared.global_map.count == 0:
            return dr.zeros(mi.Color3f, lanes)
        if self.settings.method == "photon_map":
            if self.settings.final_gather:
                return dr.zeros(mi.Color3f, lanes)
            return self._photon_estimate(p, n, depth_limit, active)
        need = mi.Bool(active) & ~covered
        self._count_fallback(need)
        fallback = self._photon_estimate(p, n, depth_limit, need)
        return dr.select(covered, cached, fallback)

    def _total_irradiance(self, scene, si, n, active, cached, covered):
        """Final gather: all the irradiance at a trusted vertex, direct light included:
        the records' where they reach, else the precomputed irradiance of the nearest
        photon that ``si`` sees (a shadow ray: a photon across a thin wall is not
        read)."""
        need = mi.Bool(active) & ~covered
        self._count_fallback(need)
        source = self._prepared.gather_source
        if source is None:
            return dr.select(covered, cached, 0.0)
        return dr.select(covered, cached, source.irradiance_at(scene, si, n, need))

    def _photon_estimate(self, p, n, depth_limit, active):
        """Global-map estimate of light that bounced at least once (direct light and
        caustic paths are counted elsewhere), excluding L S+ D paths."""
        prepared = self._prepared
        return estimate_irradiance(prepared.global_map, prepared.global_grid, p, n,
                                   prepared.global_radius, min_depth=2, max_depth=depth_limit,
                                   skip_specular_paths=prepared.caustic_map.count > 0,
                                   active=active)

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        """One camera path: emission, direct light, indirect light at diffuse lobes from
        the cache (or photon map) and the caustic map, continued through the other lobes.

        With the final-gather estimator the first diffuse vertex is path-traced (its
        whole BSDF is sampled, its direct light shares samples with that by MIS) and the
        cache is read at the next diffuse vertex, unless that one is closer than
        ``TRUST_RECORD_RADII`` record radii (corners, contacts, thin gaps): then it is
        path-traced too, up to ``MAX_TRACED_BOUNCES``.

        Light that a traced diffuse vertex's caustic-map read already holds (light →
        delta/glossy bounces → that vertex) is not counted again along the path.

        Every contribution is checked on its own (:func:`_finite`): a NaN or Inf from one
        emitter or texel drops that sample only, not the whole camera sample.
        """
        # Plain values only below: @dr.syntax makes every variable the loop touches
        # part of its state, and dataclasses would be traversed (and written back).
        prepared = self._prepared
        hide_emitters = self.settings.hide_emitters
        rr_depth = self.settings.rr_depth
        max_depth = 0xFFFFFFFF if self.settings.max_depth == -1 else self.settings.max_depth
        max_iterations = -1 if self.settings.max_depth == -1 else self.settings.max_depth
        use_indirect = prepared.global_map.count > 0 or prepared.caustic_map.count > 0
        has_caustic_map = prepared.caustic_map.count > 0
        photon_map_gather = self.settings.method == "photon_map" and self.settings.final_gather and \
            prepared.global_map.count > 0
        reads_cache = self.settings.method != "photon_map"
        gather_first = self.settings.final_gather_camera
        untrusted_radius = prepared.global_radius  # trust test where no record reaches
        # BSDF sampling of the diffuse lobe for direct light, combined with emitter
        # sampling by MIS: emitter sampling alone is noisy for large emitters (skies).
        diffuse_mis = prepared.info.has_infinite_emitter
        n_em = float(self.settings.direct_samples)
        aovs = self.settings.aov_list
        want_direct, want_indirect = "direct" in aovs, "indirect" in aovs
        want_caustic, want_coverage = "caustic" in aovs, "coverage" in aovs
        del prepared
        ctx_all = mi.BSDFContext()
        ctx_diffuse = mi.BSDFContext(mi.TransportMode.Radiance, int(mi.BSDFFlags.Diffuse), None)
        ctx_rest = non_diffuse_context()

        ray = mi.Ray3f(dr.detach(ray))
        depth = mi.UInt32(0)
        L = mi.Spectrum(0.0)
        β = mi.Spectrum(1.0)
        η = mi.Float(1.0)
        active = mi.Bool(active)
        pi = scene.ray_intersect_preliminary(ray, coherent=True, active=active)
        if dr.hint(hide_emitters, mode="scalar"):
            # As Mitsuba's path tracers: a hidden area emitter is looked through.
            skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
            si_skip = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip)
            pi[skip] = self.skip_area_emitters(scene, si_skip.spawn_ray(ray.d), True, skip)
        guides = self._guide_aovs(pi, ray, active, aovs)
        prev_si = dr.zeros(mi.SurfaceInteraction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)
        valid = mi.Bool(False)
        traced = mi.UInt32(0)  #: diffuse vertices path-traced so far (final gather)
        # ``armed``: the last traced diffuse vertex read the caustic map and every vertex
        # since continued through a delta/glossy lobe; ``crossed``: armed, and at least
        # one such lobe lies behind. Light reaching the path through a delta/glossy
        # lobe once armed (emitter samples through this vertex's lobes), or by emission
        # once crossed, is a caustic that map already holds.
        armed = mi.Bool(False)
        crossed = mi.Bool(False)
        # AOVs (left as width-1 constants when not asked for).
        L_direct = mi.Spectrum(0.0)
        L_indirect = mi.Spectrum(0.0)
        L_caustic = mi.Spectrum(0.0)
        coverage = mi.Float(0.0)
        unread = mi.Bool(True)  #: no vertex has read the cache yet (coverage AOV)

        # ``self`` is read, not state: its cache arrays must not be loop variables.
        while dr.hint(active, label="pmic_camera_path", max_iterations=max_iterations,
                      exclude=[self]):
            si = pi.compute_surface_interaction(ray, ray_flags=mi.RayFlags.All, active=active)
            valid |= (depth == 0) & si.is_valid()
            bsdf = si.bsdf(ray)
            flags = bsdf.flags()

            # ---- Emission reached by BSDF sampling (MIS with emitter sampling) ----
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
            mis = dr.select(prev_bsdf_delta, 1.0, mis_weight(prev_bsdf_pdf, n_em * em_pdf))
            shown = active & ~crossed
            if dr.hint(hide_emitters, mode="scalar"):
                shown &= ~((depth == 0) & ~si.is_valid())
            emitted = _finite(β * mis * ds.emitter.eval(si, shown), shown)
            L += emitted

            active_next = active & si.is_valid() & (depth + 1 < max_depth)
            has_diffuse = mi.has_flag(flags, mi.BSDFFlags.Diffuse)
            mixed = has_diffuse & (mi.has_flag(flags, mi.BSDFFlags.Glossy) |
                                   mi.has_flag(flags, mi.BSDFFlags.Delta))
            separable = lobes_separable(bsdf, si, active_next & mixed)
            lit_diffuse = active_next & has_diffuse & separable
            n = mi.Vector3f(si.n)
            n = dr.select(dr.dot(n, ray.d) > 0, -n, n)

            # ---- Where the diffuse lobe reads the cache, and where it is traced ----
            cache_ok = lit_diffuse & mi.Bool(use_indirect) & (depth + 3 <= max_depth)
            if dr.hint(gather_first, mode="scalar"):
                probe = cache_ok & (traced > 0)
                cached, covered, radius = self._cache_lookup(si.p, n, probe)
                trusted_radius = dr.select(covered, radius, untrusted_radius)
                trust = probe & ((si.t >= TRUST_RECORD_RADII * trusted_radius) |
                                 (traced >= MAX_TRACED_BOUNCES))
                traced_here = lit_diffuse & ~trust
            else:
                trust = mi.Bool(cache_ok)
                cached, covered, _ = self._cache_lookup(si.p, n, trust & mi.Bool(reads_cache))
                traced_here = mi.Bool(False)

            # Final gather: a trusted vertex reads all of its light from the cache (the
            # records hold direct light too; where none reaches, the precomputed
            # irradiance of the nearest photon it sees is total irradiance): only its
            # other lobes need emitter samples.
            from_records = trust & mi.Bool(gather_first)
            # ---- Direct light by emitter sampling ----
            active_em = active_next & mi.has_flag(flags, mi.BSDFFlags.Smooth) & \
                ~(from_records & ~mixed)
            direct = β * self._direct_light(scene, sampler, si, bsdf, active_em, separable,
                                            traced_here, armed, from_records,
                                            diffuse_mis, ctx_all, ctx_diffuse, ctx_rest)

            # ---- Direct light on the diffuse lobe by BSDF sampling (MIS) ----
            if dr.hint(diffuse_mis, mode="scalar"):
                direct += β * self._diffuse_emitter_hit(
                    scene, sampler, si, bsdf, lit_diffuse & ~traced_here & ~from_records,
                    ctx_diffuse, n_em)
            L += direct

            # ---- Light that bounced before reaching the diffuse lobe ----
            read_caustic = (trust | traced_here) & mi.Bool(has_caustic_map) & (depth + 3 <= max_depth)
            if dr.hint(gather_first, mode="scalar"):
                read_caustic &= ~(trust & ~covered)  # the photon's irradiance has them
            response = diffuse_response(bsdf, si, trust | read_caustic)
            caustic = _finite(β * response * self._caustic_irradiance(si.p, n, depth, read_caustic),
                              read_caustic)
            if dr.hint(gather_first, mode="scalar"):
                irradiance = self._total_irradiance(scene, si, n, trust, cached, covered)
            else:
                irradiance = self._global_irradiance(si.p, n, depth, trust, cached, covered)
            if dr.hint(photon_map_gather, mode="scalar"):
                irradiance += self._final_gather_ray(scene, sampler, si, n, trust)
            indirect = _finite(β * response * irradiance, trust)
            L += caustic + indirect

            if dr.hint(want_direct, mode="scalar"):
                L_direct += emitted + direct
            if dr.hint(want_indirect, mode="scalar"):
                L_indirect += indirect
            if dr.hint(want_caustic, mode="scalar"):
                L_caustic += caustic
            if dr.hint(want_coverage, mode="scalar"):
                first_read = trust & unread
                coverage[first_read] = dr.select(covered, 1.0, 0.0)
                unread &= ~first_read

            # ---- Continue through the other lobes (all lobes if inseparable or traced) ----
            whole = ~separable | traced_here
            u1, u2 = sampler.next_1d(), sampler.next_2d()
            bs, bsdf_weight = bsdf.sample(ctx_rest, si, u1, u2, active_next & ~whole)
            bs_all, weight_all = bsdf.sample(ctx_all, si, u1, u2, active_next & whole)
            bs[whole] = bs_all
            bsdf_weight[whole] = weight_all
            sampled_diffuse = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
            # A traced vertex sampling its diffuse lobe starts a new chain; an
            # inseparable one (no caustic photon is stored behind it) ends the old one;
            # any other continues it through a delta/glossy lobe.
            restart = traced_here & sampled_diffuse
            ended = active_next & has_diffuse & ~separable
            crossed = dr.select(restart | ended, False, crossed | armed)
            armed = dr.select(restart, read_caustic, armed & ~ended)
            traced[traced_here] = traced + 1
            β *= bsdf_weight
            η *= bs.eta
            prev_si = dr.detach(si, True)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            ray = si.spawn_ray(si.to_world(bs.wo))

            # Russian roulette, as Mitsuba's path tracers (η² keeps it unitless).
            β_max = dr.max(β)
            active_next &= (β_max > 0) & (bs.pdf > 0) & dr.all(dr.isfinite(β))
            rr_prob = dr.minimum(β_max * dr.square(η), 0.95)
            rr_active = depth + 1 >= rr_depth
            β[rr_active] *= dr.rcp(dr.maximum(rr_prob, 1e-8))
            active_next &= ~rr_active | (sampler.next_1d() < rr_prob)

            pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active_next)
            depth += 1
            active = active_next

        values = dict(guides, direct=L_direct, indirect=L_indirect, caustic=L_caustic,
                      coverage=[coverage])
        return L, valid, [c for a in aovs for c in values[a]]

    @staticmethod
    def _guide_aovs(pi, ray, active, aovs) -> dict:
        """The denoiser's guides at the first surface, as Mitsuba's ``aov`` integrator
        computes them: diffuse reflectance and world-space shading normal (0 where the
        camera ray meets nothing)."""
        guides = {}
        if "albedo" not in aovs and "normal" not in aovs:
            return guides
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
        hit = active & si.is_valid()
        guides["albedo"] = dr.select(hit, si.bsdf(ray).eval_diffuse_reflectance(si, hit), 0.0)
        guides["normal"] = dr.select(hit, si.sh_frame.n, 0.0)
        return guides

    def _direct_light(self, scene, sampler, si, bsdf, active, separable, traced, armed,
                      no_diffuse, diffuse_mis, ctx_all, ctx_diffuse, ctx_rest):
        """Mean of ``direct_samples`` emitter samples (shadow rays) at ``si``.

        Separable BSDFs: the diffuse lobe takes emitter samples alone (or shares them by
        MIS with :meth:`_diffuse_emitter_hit`), the other lobes share them with the
        continuation's BSDF sampling. Inseparable ones share them as a whole, and so do
        traced vertices (whose continuation samples the whole BSDF). Where ``armed``,
        light through the delta/glossy lobes is left out (a caustic the map holds);
        where ``no_diffuse``, the diffuse lobe is (the cache holds its direct light).
        """
        n_em = float(self.settings.direct_samples)

        def one_sample(sampler):
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active)
            ok = active & (ds.pdf != 0.0)
            wo = si.to_local(ds.d)
            f_diffuse, pdf_diffuse = bsdf.eval_pdf(ctx_diffuse, si, wo, ok & separable)
            f_rest, pdf_rest = bsdf.eval_pdf(ctx_rest, si, wo, ok & separable)
            f_all, pdf_all = bsdf.eval_pdf(ctx_all, si, wo, ok & (~separable | traced))
            # The pdf with which the continuation would sample this direction.
            pdf_rest = dr.select(separable & ~traced, pdf_rest, pdf_all)
            pdf_diffuse = dr.select(traced, pdf_all, pdf_diffuse)
            f_rest = dr.select(separable, f_rest, f_all)
            f_rest = dr.select(separable & armed, 0.0, f_rest)
            f_diffuse = dr.select(separable & ~no_diffuse, f_diffuse, 0.0)
            em_pdf = n_em * ds.pdf
            w_rest = dr.select(ds.delta, 1.0, mis_weight(em_pdf, pdf_rest))
            w_diffuse = dr.select(ds.delta | ~(traced | diffuse_mis), 1.0,
                                  mis_weight(em_pdf, pdf_diffuse))
            return _finite(em_weight * (f_diffuse * w_diffuse + f_rest * w_rest), ok)

        if self.settings.direct_samples == 1:
            return one_sample(sampler)

        def body(k, total, sampler):
            return k + 1, total + one_sample(sampler), sampler

        _, total, sampler = dr.while_loop(
            (dr.zeros(mi.UInt32, dr.width(si.p)), dr.zeros(mi.Spectrum, dr.width(si.p)), sampler),
            lambda k, total, sampler: active & (k < self.settings.direct_samples), body,
            label="pmic_direct_light")
        return total / n_em

    def _diffuse_emitter_hit(self, scene, sampler, si, bsdf, active, ctx_diffuse, n_em):
        """Direct light on the diffuse lobe from one BSDF-sampled ray that meets an
        emitter (an area light or the environment), MIS-weighted against the
        ``direct_samples`` emitter samples of :meth:`_direct_light`."""
        bs, weight = bsdf.sample(ctx_diffuse, si, sampler.next_1d(), sampler.next_2d(), active)
        ok = active & (bs.pdf > 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        hit = scene.ray_intersect(ray, mi.RayFlags.All, coherent=False, active=ok)
        ds = mi.DirectionSample3f(scene, si=hit, ref=si)
        em_pdf = scene.pdf_emitter_direction(si, ds, ok)
        emitted = ds.emitter.eval(hit, ok)
        return _finite(weight * emitted * mis_weight(bs.pdf, n_em * em_pdf), ok)

    def _final_gather_ray(self, scene, sampler, si, n, active):
        """One cosine-distributed gather ray reading precomputed irradiance: E ≈ π L."""
        local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
        ray = mi.Ray3f(si.p + n * surface_offset(si.p, RAY_OFFSET_DIAGONAL * self._length_scale()),
                       mi.Frame3f(n).to_world(local))
        rng = make_rng(dr.width(si.p), self.settings.seed, stream=7)
        radiance, _ = trace_gather_rays(scene, self._source(), ray, rng, active)
        return radiance * math.pi


@dr.syntax
def _first_diffuse_hit(scene: mi.Scene, ray: mi.Ray3f, rng: mi.PCG32):
    """Follow delta/glossy bounces from ``ray`` to the first surface with a diffuse lobe."""
    lanes = dr.width(ray.o)
    active = dr.full(mi.Bool, True, lanes)
    found = dr.zeros(mi.Bool, lanes)
    p = dr.zeros(mi.Point3f, lanes)
    n = dr.zeros(mi.Vector3f, lanes)
    bounce = dr.zeros(mi.UInt32, lanes)
    ctx_rest = non_diffuse_context()
    while dr.hint(active, label="camera_first_diffuse", max_iterations=8):
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        flags = bsdf.flags()
        hit = active & mi.has_flag(flags, mi.BSDFFlags.Diffuse)
        normal = mi.Vector3f(si.n)
        normal = dr.select(dr.dot(normal, ray.d) > 0, -normal, normal)
        p = dr.select(hit, si.p, p)
        n = dr.select(hit, normal, n)
        found |= hit
        bs, _ = bsdf.sample(ctx_rest, si, rng.next_float32(),
                            mi.Point2f(rng.next_float32(), rng.next_float32()), active & ~hit)
        ray = si.spawn_ray(si.to_world(bs.wo))
        bounce += 1
        active &= ~hit & (bs.pdf > 0) & (bounce < 8)
    return p, n, found


def _inside_any(grid: BallGrid, points: mi.Point3f) -> mi.Bool:
    """Mask of points inside the bounding cells of some ball of ``grid``: a cheap,
    conservative pre-filter (a point in no ball's cells is in no ball)."""
    return grid.for_each_ball(points, dr.zeros(mi.Bool, dr.width(points.x)),
                              lambda hit, index, valid: hit | valid, finished=lambda hit: hit,
                              label="inside_any_ball")


def _progress(kind, stored, target, emitted):
    mi.Log(mi.LogLevel.Info, f"pmic: {kind} photons {stored}/{target} ({emitted} paths emitted)")
