"""The ``pmic`` Mitsuba 3 integrator: stages 1-4 of Gu & Wang (2010) put together."""
from __future__ import annotations

import logging
import math
import os
import threading
import time
from dataclasses import replace

import drjit as dr
import mitsuba as mi

if mi.variant() is None:
    # This module defines a subclass of the variant's SamplingIntegrator, so it needs a
    # variant; imported before one is chosen (``help(PMICIntegrator)`` in a fresh
    # interpreter), it picks the CPU one, as most users would.
    mi.set_variant("llvm_ad_rgb")

from mitsuba.ad.integrators.common import mis_weight  # noqa: E402

from . import cachefile, camera, pipeline, streams
from ._jit import (ONE_MINUS_EPSILON, jittered, only_where, opaque_u32, shading_normal_on_side,
                   surface_offset)
from .bsdfs import (WHOLE_PEAK_RATIO, diffuse_context, diffuse_response, glossy_beside_diffuse,
                    lobes_separable, near_diffuse, non_diffuse_context, peak_within,
                    response_azimuths, tilted_normal)
from . import emission
from .emission import sample_emitter_direction
from . import skylight
from .gather import trace_gather_rays
from .hashgrid import PointGridPyramid
from .irradiance import NormalBins, estimate_irradiance, may_count_photons
from .pipeline import PreparedScene, SceneInfo, scene_fingerprint  # noqa: F401 (re-exported)
from .settings import METHODS, Settings  # noqa: F401 (METHODS re-exported)

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
#: Guiding (``guiding``): at a traced diffuse vertex that a record reaches, this
#: fraction, times the share of bounced light in the record's irradiance, of the
#: continuation rays is drawn from the record's directional distribution of gathered
#: light, the rest by BSDF sampling, weighted by the mixture's density (one-sample
#: MIS, unbiased whatever the distribution). At most half: the BSDF's density stays at
#: least 1/2 of its own everywhere (never worse than 2× its variance), while a bright
#: source of bounced light (a lit ceiling, a door to a lit room) is met far more often
#: than cosine sampling meets it. Scaled by the bounced share because where direct
#: light is most of the irradiance, BSDF samples also serve it (MIS with the emitters).
GUIDE_FRACTION = 0.5
#: ...and where bright records (:mod:`pmic_integrator.lights`: a lamp's shade lit from
#: inside) face the traced vertex, this fraction of its continuation rays is drawn
#: towards them, the rest as above, all weighted by the three-way mixture's density.
#: A quarter: such a source sends most of the bounced light there, while the BSDF and
#: guide strategies keep 3/4 of their own density (at most 4/3 their variance). Half
#: measured worse in the lamp room (relMSE 0.36-0.76 against 0.30-0.45 over render
#: seeds) for 1.5× the render time (rays into the cone that meet the shade's glossy
#: outside go on bouncing).
LIGHT_FRACTION = 0.25
#: ...and where that record saw the sky through an opening (a window), this fraction
#: of the vertex's emitter samples of the sky follow the sky it saw (chosen from each
#: sample's own square), the rest the whole sky's tables, all weighted by the
#: mixture's density (as are the continuation's emitter hits there). The tables'
#: samples mostly meet the walls of a room lit through a window.
SKY_EMITTER_FRACTION = 0.5
#: Camera samples per pass where caustic-map reads wait for the end of the camera loop
#: (their points, normals and weights: ~130 bytes a sample, 0.5 GB per pass); each
#: further pass costs the loop's tracing again.
DEFERRED_WAVEFRONT = 1 << 22
#: Caustic-map reads a camera path can defer (its slots in the loop): one per traced
#: vertex, and at most MAX_TRACED_BOUNCES vertices are traced (with more, reads stay in
#: the loop: _defers_caustics).
DEFERRED_READS = 3
#: A pixel's samples share the caustic-map estimate made at its first sample's first
#: read where their own reads lie within this many of that estimate's kernel radius
#: (on a surface facing within acos(CAUSTIC_SHARE_COSINE) = 11° of it): there the
#: kernel's own smoothing (one radius) dwarfs the shift, and the estimates of nearby
#: points, made from the same photons, are as good as one. A caustic-lit room's reads
#: (a sky through a thin pane: kernel radius 0.24 m) were 60 % of its render.
CAUSTIC_SHARE_RADII = 0.1
CAUSTIC_SHARE_COSINE = 0.98
#: Behind a traced vertex, a vertex that reads the cache and goes on through a weak
#: glossy lobe alone (a rough plastic's coat: its sample weight is the few per cent
#: the coat reflects) survives with probability weight / this (Russian roulette,
#: unbiased), as gather rays do (:data:`~pmic_integrator.gather.GATHER_ROULETTE_BELOW`).
#: Mitsuba's roulette waits for ``rr_depth``: until then such paths went on as chains
#: of weak coat bounces, each vertex reading the cache, sampling the lights and
#: evaluating the BSDF again.
COAT_ROULETTE_BELOW = 0.5


def _no_light(si):
    """The ``zeros`` of :func:`~pmic_integrator._jit.only_where` for a light estimate at
    ``si``'s lanes (with or without the sampler)."""
    return lambda *sampler: dr.zeros(mi.Spectrum, dr.width(si.p))


def _finite(value, active=True):
    """``value`` where ``active`` and every channel is finite, else 0: a NaN or Inf from
    one emitter, texel or sample must cost that sample only."""
    return dr.select(mi.Bool(active) & dr.all(dr.isfinite(value)), value, 0.0)


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
           keeps converging. ``"first_hit"``: the paper's interpolation at the first
           diffuse vertex (less noise at few samples, but record-sized blotches that
           stay). With either, the cache is view independent: a function of the
           scene, the settings and ``seed`` only.
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
           ``build_cache(scene)``.
       * - ``max_depth``
         - integer
         - -1
         - Longest path, in segments, as in Mitsuba's ``path`` (-1: unbounded, else
           1-1024; 1: only emitters seen directly; 2: direct light only, no photons).
           64 or more (scenes often ask for 65 to mean unbounded) is unbounded where
           paths meet the cache and the photon maps; camera paths still end there.
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
         - Photons stored in the caustic map by its own pass (0-5e7; skipped if the
           scene has no delta or glossy surface; dropped if under a tenth is stored
           after 20 paths per photon, and records then gather caustic light instead).
           The global pass's own caustic photons join the map.
       * - ``lookup_size``
         - integer
         - 64
         - Photons per density estimate (8-10000); sets the base lookup radius from
           where the photons landed (scale does not matter); estimates shrink it
           where photons cluster. Caustic estimates use half as many, up to twice as
           many where caustics carry most of the light surfaces receive first (a
           room lit through glass).
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
           With the final-gather estimator in open scenes (under a quarter of the
           photons' power bounced), records gather a quarter of them first and the
           rest only where bounced light matters (``guiding``'s test), since under an
           open sky records hold little of what the camera sees.
       * - ``final_gather``
         - boolean
         - false
         - ``photon_map`` only: replace the radiance estimate at the first diffuse hit by
           one cosine-distributed gather ray per camera sample that reads the
           precomputed irradiance.
       * - ``guiding``
         - boolean
         - true
         - ``final_gather`` only: a traced diffuse vertex sends up to half its
           continuation rays (half times the share of bounced light there) where a
           record reaching it found bounced light (a directional histogram kept per
           record), the rest by BSDF sampling, weighted by the mixture's
           density (unbiased). Cuts the noise from bright sources of bounced light
           (a lit ceiling, a door to a lit room); costs one record lookup per traced
           vertex, so it is skipped in scenes lit almost only directly (where the
           records that owe a quarter of their light to bounces cover under 12.5 % of
           the records' area). Where a few records
           are far brighter than the rest and hold much of the cache's power (the
           inside of a lampshade), a quarter of the rays is also drawn towards them
           (groups of them as spherical lights, ``pmic_integrator.lights``), which
           removes the fireflies that cosine sampling of such small sources gives.
       * - ``max_photon_paths``
         - integer
         - 0 (auto)
         - Bound on emitted light paths per map (auto: 100 × the photon count, at least
           4 M). A warning is given when fewer than half the photons were stored.
       * - ``direct_samples``
         - integer
         - 4
         - Emitter samples (shadow rays) per camera vertex (1-64) of the lights that are
           not delta lights: shadow rays cost far less than camera samples (which also
           interpolate the cache), and direct light is most of the noise left. They are
           drawn from jittered strata of the sample square (the light chosen, and its
           directions, stratified). Delta lights (``point``, ``spot``,
           ``directional``) take one sample each on top (up to ``direct_samples`` of
           them, in strata of the choice): one is exact up to visibility. An environment
           (``envmap``, ``constant``) is sampled by its radiance times the cosine
           (:mod:`pmic_integrator.skylight`).
       * - ``seed``
         - integer
         - 0
         - Seed of photon tracing and gathering (0 to 2^32-1): the same seed gives the
           same cache.

    **What it does not do**: participating media are ignored (surfaces only, as ``path``
    does; a warning names the shapes and sensors that hold them);
    a bounded ``max_depth`` (under 64) holds where camera paths read the cache and the
    photon maps (the records at the one depth they are made for, the maps by depth), but
    gather rays through delta/glossy chains may add a segment or two to what they read,
    and beyond that one depth camera paths are path-traced (noisier); from 64 on the
    cache may add the light of longer paths (under 0.1 % of an image whose surfaces
    reflect 90 % of the light);
    polarised and spectral variants are not supported (use ``llvm_ad_rgb`` or
    ``cuda_ad_rgb``); it is not differentiable.

    Parameter types are checked as strictly as Mitsuba's plugins do (an integer refuses
    2.9); a bad type or value raises ValueError naming it, before any work.

    After ``mi.render``, ``scene.integrator().stats`` (or this object's ``stats``)
    holds counts and per-stage times in seconds. Progress bars of the photon and cache
    stages (tqdm, in a terminal or Jupyter) appear for stages longer than a second where
    a person watches; ``integrator.progress = False`` (or True) turns them off (or on
    everywhere). Photon counts are logged at Mitsuba's Info level either way.
    ``integrator.prepared`` is the photon maps and cache of the last scene
    (:class:`pmic_integrator.pipeline.PreparedScene`).

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
        #: What sample() reads: the prepared scene of the last render, or its copy
        #: with the view's own records (``irradiance_cache``).
        self._view: PreparedScene | None = None
        #: Progress bars of the photon and cache stages (tqdm): True, False, or None:
        #: on where a person watches (a terminal, Jupyter; pipeline.interactive).
        self.progress = None
        self._cache_builds = 0  #: view-independent caches built from photons so far
        # One render at a time per integrator object: the prepared scene and the
        # per-render state below are shared by render() and the sample() it (or a
        # wrapping integrator such as Mitsuba's ``aov``) calls (a second thread would
        # see them half-updated). Separate integrator objects render concurrently.
        self._render_lock = threading.RLock()
        self._thread = threading.local()  #: ``inside``: this thread is in render()
        #: (prepared scene, its caustic map's normal bins): see _deferred_caustics
        self._caustic_normal_bins = (None, None)
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
            # Re-entered from within this thread's own render (nothing of pmic's does
            # this; a wrapper might): Mitsuba's loop, over the view being rendered.
            return mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
        with self._render_lock:
            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            prepared = self._prepared_for(scene)  # stages 1-3, view independent
            view, view_stats = self._view_of(scene, sensor, prepared)
            image, render_stats = self._render_camera_paths(scene, sensor, view, seed, spp,
                                                            develop, evaluate)  # stage 4
            self.stats = {**prepared.stats, "cache_builds": self._cache_builds, **view_stats,
                          **render_stats, **_memory_stats(view)}
            return image

    @property
    def prepared(self) -> PreparedScene | None:
        """The photon maps and cache of the last scene rendered (None before)."""
        return self._prepared

    def build_cache(self, scene: mi.Scene) -> dict:
        """Run the view-independent stages (photons, precomputed irradiance, cache) for
        ``scene`` now, instead of at the first render; returns their statistics."""
        with self._render_lock:
            return dict(self._prepared_for(scene).stats)

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

    # ----------------------------------------------------------------------------------
    # The stages of render()
    # ----------------------------------------------------------------------------------
    def _prepared_for(self, scene: mi.Scene) -> PreparedScene:
        """Stages 1-3 for ``scene``: the kept ones if scene and settings are unchanged,
        else read from ``cache_file`` or built (:func:`pipeline.prepare`). Published
        only when whole: after a failure (or a Ctrl-C) nothing is kept, and the next
        render starts again from the photons."""
        key = (id(scene), self.settings.key(), scene_fingerprint(scene))  # not its cameras
        if self._prepared is not None and self._prepared.key == key:
            return self._prepared
        self._prepared = self._view = None
        cache_file = self.settings.cache_file
        if cache_file and os.path.exists(cache_file):
            t0 = time.perf_counter()
            prepared = cachefile.load(cache_file, scene, key[2], key[1])
            prepared.key = key
            prepared.stats["cache_loaded_from"] = cache_file
            prepared.stats["time_cache_load"] = time.perf_counter() - t0
        else:
            prepared = pipeline.prepare(scene, self.settings, key, pipeline.Progress(self.progress))
            if prepared.index is not None:
                self._cache_builds += 1
            if cache_file:
                cachefile.save(cache_file, prepared, key[2], key[1])
                prepared.stats["cache_saved_to"] = cache_file
        self._prepared = prepared
        return prepared

    def _view_of(self, scene, sensor, prepared: PreparedScene):
        """What this view reads: the prepared scene itself, except for the classic
        cache (``irradiance_cache``), whose records are placed from this camera (a
        copy with their index; the prepared scene is not changed)."""
        if self.settings.method != "irradiance_cache" or prepared.global_map.count == 0:
            return prepared, {}
        t0 = time.perf_counter()
        index, rounds = pipeline.camera_seeded_index(scene, sensor, self.settings, prepared)
        dr.sync_thread()
        return replace(prepared, index=index), {
            "records": 0, "records_fallback": index.records.count, "placement_rounds": rounds,
            "time_cache_view": time.perf_counter() - t0}

    def _render_camera_paths(self, scene, sensor, view: PreparedScene, seed, spp, develop,
                             evaluate):
        """Stage 4: camera rays over the film (:mod:`.camera`), ``sample()`` for each,
        reading ``view``, splatted into the film."""
        if view.index is not None and view.index.packed_body is None:
            view.index.pack()
        self._view = view
        self._fallback_counter = dr.zeros(mi.UInt32, 1)
        start = time.perf_counter()
        film = sensor.film()
        spp = spp or sensor.sampler().sample_count()
        film.prepare(self.aov_names())
        self._thread.inside = True
        try:
            # Deferred caustic reads keep ~130 bytes per camera sample until the loop
            # ends: passes of at most DEFERRED_WAVEFRONT samples bound that.
            wavefront = DEFERRED_WAVEFRONT if self._defers_caustics(view) else camera.MAX_WAVEFRONT
            for pass_index, pass_spp in enumerate(camera.pass_counts(film, spp, wavefront)):
                sampler = camera.seeded_sampler(
                    sensor, streams.render_pass_seed(seed, pass_index), pass_spp)
                ray, weight, position = camera.camera_rays(sensor, sampler)
                radiance, valid, aovs = self.sample(scene, sampler, ray, None,
                                                    mi.Bool(True))
                block = film.create_block()
                camera.splat(film, block, position, radiance * weight, valid, aovs,
                             ray.wavelengths)
                film.put_block(block)
                del sampler, ray, weight, position, radiance, valid, aovs, block
            image = film.develop() if develop else mi.TensorXf()
            if evaluate:
                dr.eval(image)
            dr.sync_thread()
        finally:
            # ``_view`` stays: an integrator wrapping this one (Mitsuba's ``aov``) calls
            # render() and then sample() for its own image.
            self._thread.inside = False
        return image, {"time_render": time.perf_counter() - start,
                       "shading_points_fallback": int(self._fallback_counter[0])}

    # ----------------------------------------------------------------------------------
    # Stage 4: camera paths
    # ----------------------------------------------------------------------------------
    def _depth_limit(self, depth):
        """Photons completing a path of at most max_depth segments (None: all, also
        where max_depth is deep enough to be unbounded: Settings.bounded)."""
        return None if not self.settings.bounded else mi.UInt32(self.settings.max_depth) - depth - 1

    def _caustic_bins(self):
        """:class:`~pmic_integrator.irradiance.NormalBins` of the caustic map (made
        at the first render of each prepared scene)."""
        prepared = self._view
        known, bins = self._caustic_normal_bins
        if known is not prepared:
            bins = NormalBins.build(prepared.caustic_map, prepared.caustic_grid)
            self._caustic_normal_bins = (prepared, bins)
        return bins

    def _caustic_irradiance(self, p, n, depth, active):
        """Irradiance at a camera vertex from light → delta/glossy bounces (caustic map)."""
        prepared = self._view
        if not prepared.caustic_map.count:
            return dr.zeros(mi.Color3f, dr.width(p))
        return estimate_irradiance(prepared.caustic_map, prepared.caustic_grid, p, n,
                                   prepared.caustic_radius, max_depth=self._depth_limit(depth),
                                   active=active, delta_scale=prepared.caustic_delta_scale)

    def _cache_lookup(self, p, n, shading_n, active, with_direct: bool = False):
        """``(E, covered, R)``: the cache's interpolated irradiance, where records reach
        (p, n), and their weighted mean radius (``shading_n``: see interpolate); with
        ``with_direct``, and the part of E that is the records' direct light."""
        index = self._view.index
        lanes = dr.width(p)

        def zeros():
            zero = dr.zeros(mi.Color3f, lanes), dr.zeros(mi.Bool, lanes), dr.zeros(mi.Float, lanes)
            return zero + (dr.zeros(mi.Color3f, lanes),) if with_direct else zero
        if index is None:
            return zeros()
        if not self.settings.final_gather_camera:
            # (The first-hit estimator reads it at nearly every first vertex.)
            return index.interpolate(p, n, active, with_radius=True, shading_n=shading_n,
                                     with_direct=with_direct)
        # (Behind a traced vertex only: at the camera's first vertex no lane reads it.)
        return only_where(active, lambda: index.interpolate(p, n, active, with_radius=True,
                                                            shading_n=shading_n,
                                                            with_direct=with_direct),
                          zeros, label="cache_lookup")

    def _count_fallback(self, need):
        """Count the camera vertices that no record reached (stats)."""
        dr.scatter_reduce(dr.ReduceOp.Add, self._fallback_counter, mi.UInt32(1), mi.UInt32(0), need)

    def _global_irradiance(self, p, n, depth, active, cached, covered, gathered=True):
        """Irradiance at a camera vertex from light that bounced off a diffuse surface
        first: the cache's ``cached`` value where ``covered``, else the global photon
        map (the method ``photon_map`` reads the map only, and with ``final_gather``
        gathers it where ``gathered``: see ``records_read_depth``)."""
        prepared = self._view
        lanes = dr.width(p)
        depth_limit = self._depth_limit(depth)
        if prepared.global_map.count == 0:
            return dr.zeros(mi.Color3f, lanes)
        if self.settings.method == "photon_map":
            if self.settings.final_gather:
                return self._photon_estimate(p, n, depth_limit, mi.Bool(active) & ~mi.Bool(gathered))
            return self._photon_estimate(p, n, depth_limit, active)
        need = mi.Bool(active) & ~covered
        self._count_fallback(need & gathered)  # (not the vertices deeper than the records serve)
        fallback = self._photon_estimate(p, n, depth_limit, need)
        return dr.select(covered, cached, fallback)

    def _total_irradiance(self, scene, si, n, active, cached, covered):
        """Final gather: all the irradiance at a trusted vertex, direct light included:
        the records' where they reach, else the precomputed irradiance of the nearest
        photon that ``si`` sees (a shadow ray: a photon across a thin wall is not
        read)."""
        need = mi.Bool(active) & ~covered
        self._count_fallback(need)
        source = self._view.gather_source
        if source is None:
            return dr.select(covered, cached, 0.0)
        # Without delta lights' direct light where the photons keep it apart (the
        # vertex samples it: _trusted_direct).
        nodelta = source.photons.irradiance_nodelta is not None
        # (Rare: a vertex no record reaches, past every probe.)
        fallback = only_where(need, lambda: source.irradiance_at(scene, si.p, n, need, without_delta=nodelta),
                              lambda: dr.zeros(mi.Color3f, dr.width(si.p)), label="photon_fallback")
        return dr.select(covered, cached, fallback)

    def _photon_estimate(self, p, n, depth_limit, active):
        """Global-map estimate of light that bounced at least once (direct light and
        caustic paths are counted elsewhere), excluding L S+ D paths."""
        prepared = self._view
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
        prepared = self._view
        hide_emitters = self.settings.hide_emitters
        rr_depth = self.settings.rr_depth
        max_depth = 0xFFFFFFFF if self.settings.max_depth == -1 else self.settings.max_depth
        max_iterations = -1 if self.settings.max_depth == -1 else self.settings.max_depth
        # With max_depth bounding the paths, the records hold the light of paths read from
        # one depth only (Settings.records_read_depth).
        bounded = self.settings.bounded
        read_depth = self.settings.records_read_depth
        use_indirect = prepared.global_map.count > 0 or prepared.caustic_map.count > 0
        has_caustic_map = prepared.caustic_map.count > 0
        photon_map_gather = self.settings.method == "photon_map" and self.settings.final_gather and \
            prepared.global_map.count > 0
        reads_cache = self.settings.method != "photon_map"
        gather_first = self.settings.final_gather_camera
        records_hold_caustics = prepared.index is not None and prepared.index.holds_caustics
        # (opaque: the photons set it, and a constant would make a kernel per seed)
        untrusted_radius = dr.opaque(mi.Float, prepared.global_radius)  # where no record reaches
        # BSDF sampling of the diffuse lobe for direct light, combined with emitter
        # sampling by MIS: emitter sampling alone is noisy for large emitters (skies).
        diffuse_mis = prepared.info.has_infinite_emitter
        delta_lights = prepared.info.has_delta_emitter
        coat_rays = prepared.info.has_delta_coat
        # Rough plastic at and past a vertex that read the caustic map: each sample
        # split between its lobes (see the loop).
        lobes_split = gather_first and has_caustic_map and prepared.info.has_glossy_coat
        # BSDFs whose lobes cannot be taken apart (principled) read the cache with their
        # whole response where a diffuse one would (see the loop).
        whole_reads = gather_first and not bounded and prepared.info.has_glossy_coat
        # ...and so do rough plastics (lobes that can be taken apart), see the loop.
        coat_reads = whole_reads and prepared.index is not None
        inseparable_bsdfs = prepared.info.has_inseparable
        leaning = prepared.info.has_leaning_lobes
        guiding = gather_first and self.settings.guiding and prepared.index is not None and \
            prepared.index.guiding_pays()
        sky_guided = guiding and prepared.sky is not None and prepared.index.sky_guiding_pays()
        lit = gather_first and self.settings.guiding and prepared.index is not None and \
            prepared.index.lights is not None
        n_em = self._emitter_samples
        aovs = self.settings.aov_list
        want_direct, want_indirect = "direct" in aovs, "indirect" in aovs
        want_caustic, want_coverage = "caustic" in aovs, "coverage" in aovs
        # In this integrator's own render, the caustic-map reads are made after the
        # loop, over just the lanes that made one (_deferred_caustics); a caller of
        # sample() alone (Mitsuba's aov integrator) gets them in the loop, and so do
        # the estimators whose paths may read the map at any number of vertices.
        defer_caustics = self._defers_caustics(prepared) and getattr(self._thread, "inside", False)
        del prepared
        ctx_all = mi.BSDFContext()
        ctx_diffuse = diffuse_context()
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
        prev_normal = mi.Vector3f(0.0, 0.0, 1.0)  #: shading normal of prev_si, on its lit side
        #: The record whose sky prev_si's emitter samples followed, and how often (0: never).
        prev_sky_record = mi.UInt32(0)
        prev_sky_fraction = mi.Float(0.0)
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
        #: The last vertex traced its coat's reflection of the lights (_coat_emission)
        #: and the continuation took a delta lobe: emission met now is counted there.
        coat_counted = mi.Bool(False)
        # The paths' caustic-map reads, made after the loop: where, and their weights (β
        # times the diffuse response). At most DEFERRED_READS = 3: they are made at
        # traced diffuse vertices only (defer_caustics), and a vertex is traced only
        # while traced < MAX_TRACED_BOUNCES; past that every lit diffuse vertex reads
        # the cache.
        read1 = mi.Bool(False)
        read1_p = mi.Point3f(0.0)
        read1_n = mi.Vector3f(0.0)
        read1_weight = mi.Spectrum(0.0)
        read2 = mi.Bool(False)
        read2_p = mi.Point3f(0.0)
        read2_n = mi.Vector3f(0.0)
        read2_weight = mi.Spectrum(0.0)
        read3 = mi.Bool(False)
        read3_p = mi.Point3f(0.0)
        read3_n = mi.Vector3f(0.0)
        read3_weight = mi.Spectrum(0.0)

        # ``self`` is read, not state: its cache arrays must not be loop variables.
        while dr.hint(active, label="pmic_camera_path", max_iterations=max_iterations,
                      exclude=[self]):
            si = pi.compute_surface_interaction(ray, ray_flags=mi.RayFlags.All, active=active)
            valid |= (depth == 0) & si.is_valid()
            bsdf = si.bsdf(ray)
            flags = bsdf.flags()

            # ---- Emission reached by BSDF sampling (MIS with emitter sampling) ----
            shown = active & ~crossed & ~coat_counted
            if dr.hint(hide_emitters, mode="scalar"):
                shown &= ~((depth == 0) & ~si.is_valid())
            emitted = self._emission(scene, si, prev_si, prev_normal, prev_bsdf_pdf,
                                     prev_bsdf_delta, prev_sky_record,
                                     prev_sky_fraction if sky_guided else None, β, shown)
            L += emitted

            active_next = active & si.is_valid() & (depth + 1 < max_depth)
            has_diffuse = mi.has_flag(flags, mi.BSDFFlags.Diffuse)
            mixed = has_diffuse & (mi.has_flag(flags, mi.BSDFFlags.Glossy) |
                                   mi.has_flag(flags, mi.BSDFFlags.Delta))
            separable = mi.Bool(True)
            if dr.hint(inseparable_bsdfs, mode="scalar"):
                separable = lobes_separable(bsdf, si, active_next & mixed)
            lit_diffuse = active_next & has_diffuse & separable
            n = mi.Vector3f(si.n)
            n = dr.select(dr.dot(n, ray.d) > 0, -n, n)
            shading_n = shading_normal_on_side(si, n)

            # ---- Where the diffuse lobe reads the cache, and where it is traced ----
            cache_ok = lit_diffuse & mi.Bool(use_indirect) & (depth + 3 <= max_depth)
            # A BSDF whose lobes cannot be taken apart (Mitsuba's principled ignores lobe
            # masks) was traced whole at every vertex, so in a room of principled
            # materials (what Blender exports) no vertex ever read the cache: pmic was a
            # path tracer at twice its cost per sample (0.30x path's speed on a Cornell
            # box of principled walls at roughness 0.5; now 1.3x). Such a vertex now
            # counts as traced, and behind a traced vertex, where it is nearly diffuse
            # for the incident direction (WHOLE_PEAK_RATIO), it reads the cache as the
            # gather rays read it there: its whole response (the cosine-weighted mean of
            # the whole BSDF) times the records' irradiance, and the path ends. Not
            # where it transmits (glass, a leaf): that light comes from behind.
            inseparable = mi.Bool(False)  #: ...and may read the cache here
            traced_whole = mi.Bool(False)  #: ...and is traced whole here
            if dr.hint(whole_reads, mode="scalar"):
                traced_whole = active_next & has_diffuse & ~separable & \
                    ~mi.has_flag(flags, mi.BSDFFlags.Transmission) & mi.Bool(use_indirect)
                inseparable = traced_whole & (traced > 0)
                inseparable &= near_diffuse(bsdf, si, inseparable, WHOLE_PEAK_RATIO)
            # Where the diffuse lobe leans (a normal map's), the cache is read about the
            # normal it leans to (read_n), the records' rotational gradients weighing
            # the incident light as the lobe does. Read about the surface's own normal,
            # a box of walls whose normal map leant 30° came out 1-3 % dark or bright, by
            # the light's direction. (The response is then taken here, for every lane
            # that may read; elsewhere below, for those that do.)
            read_n = mi.Vector3f(shading_n)
            if dr.hint(leaning, mode="scalar"):
                response, tilt = diffuse_response(bsdf, si, lit_diffuse | inseparable, with_tilt=True,
                                                  azimuths=response_azimuths(leaning))
                read_n = tilted_normal(shading_n, tilt)
            if dr.hint(gather_first, mode="scalar"):
                probe = (cache_ok | inseparable) & (traced > 0)
                if dr.hint(bounded, mode="scalar"):
                    probe &= depth == read_depth  # (deeper: traced on, see records_read_depth)
                cached_direct = mi.Color3f(0.0)
                if dr.hint(coat_reads, mode="scalar"):
                    cached, covered, radius, cached_direct = self._cache_lookup(
                        si.p, n, read_n, probe, with_direct=True)
                else:
                    cached, covered, radius = self._cache_lookup(si.p, n, read_n, probe)
                trusted_radius = dr.select(covered, radius, untrusted_radius)
                trust = probe & ((si.t >= TRUST_RECORD_RADII * trusted_radius) |
                                 (traced >= MAX_TRACED_BOUNCES))
                traced_here = lit_diffuse & ~trust
                # Where it is not trusted it is traced whole: a traced diffuse vertex.
                trusted_whole = inseparable & trust
                traced_whole &= ~trusted_whole
            else:
                trust = mi.Bool(cache_ok)
                # (Deeper than the records were made for: the photon map, depth by depth.)
                records_here = trust & ((depth == read_depth) if bounded else True)
                cached, covered, _ = self._cache_lookup(si.p, n, read_n,
                                                        records_here & mi.Bool(reads_cache))
                traced_here = mi.Bool(False)
                traced_whole = mi.Bool(False)
                trusted_whole = mi.Bool(False)
                cached_direct = mi.Color3f(0.0)

            # ---- Light that bounced before reaching the diffuse lobe: where read ----
            read_caustic = (trust | traced_here) & mi.Bool(has_caustic_map) & (depth + 3 <= max_depth)
            if dr.hint(gather_first, mode="scalar"):
                read_caustic &= ~(trust & ~covered)  # the photon's irradiance has them
                if dr.hint(records_hold_caustics, mode="scalar"):
                    read_caustic &= ~trust  # and so do the records
            if dr.hint(leaning, mode="scalar"):
                response = dr.select(trust | read_caustic, response, 0.0)
            else:
                response = diffuse_response(bsdf, si, trust | read_caustic,
                                            azimuths=response_azimuths(leaning))
            # A rough plastic read where records reach: its coat too, where the whole
            # BSDF is nearly diffuse for the incident direction (as the principled reads
            # above, WHOLE_PEAK_RATIO), reflects the records' irradiance, and the path
            # ends. Its coat was followed instead, a path of many weak bounces (~5 % of
            # the light each, until Russian roulette) whose every vertex read the cache,
            # sampled the lights and was tested: in a door-lit room of rough plastic
            # that was half of the render (4.2 s -> 2.2 s at 16 spp, 320x240).
            coat_read = mi.Bool(False)
            coat_response = mi.Color3f(0.0)
            if dr.hint(coat_reads, mode="scalar"):
                coat_read = trust & covered & glossy_beside_diffuse(flags) & separable & \
                    ~mi.has_flag(flags, mi.BSDFFlags.Transmission)
                coat_response = diffuse_response(bsdf, si, coat_read, ctx_rest)
                coat_read &= peak_within(bsdf, si, coat_read, dr.max(response + coat_response),
                                         WHOLE_PEAK_RATIO)
                trusted_whole |= coat_read

            # Guiding: where a record reaches a traced vertex, part of its continuation
            # follows the record's distribution of gathered light (GUIDE_FRACTION).
            traced_on = traced_here & active_next  #: traced, and the path goes on
            guide_record = mi.UInt32(0)
            guide_fraction = mi.Float(0.0)
            if dr.hint(guiding, mode="scalar"):
                guide_record, bounced_share = only_where(
                    traced_on, lambda: self._view.index.guide_record(si.p, n, traced_on),
                    lambda: (dr.zeros(mi.UInt32, dr.width(si.p)), dr.zeros(mi.Float, dr.width(si.p))),
                    label="guide_record")
                guide_fraction = GUIDE_FRACTION * bounced_share
            sky_fraction = mi.Float(0.0)
            if dr.hint(sky_guided, mode="scalar"):
                sees = self._view.index.sees_sky(guide_record, traced_here & (guide_fraction > 0))
                sky_fraction = dr.select(traced_here & active_next & (guide_fraction > 0) & sees,
                                         SKY_EMITTER_FRACTION, 0.0)
            # ...and part towards the bright records that face it.
            light_total = mi.Float(0.0)
            light_fraction = mi.Float(0.0)
            if dr.hint(lit, mode="scalar"):
                light_total = only_where(traced_on, lambda: self._view.index.lights.total_weight(si.p, n, traced_on),
                                         lambda: dr.zeros(mi.Float, dr.width(si.p)), label="record_lights")
                light_fraction = dr.select(light_total > 0, LIGHT_FRACTION, 0.0)

            # Final gather: a trusted vertex reads all of its light from the cache (the
            # records hold direct light too; where none reaches, the precomputed
            # irradiance of the nearest photon it sees is total irradiance): only its
            # other lobes need emitter samples.
            from_records = trust & mi.Bool(gather_first)
            # ---- Direct light by emitter sampling ----
            # (Where the cache gives the diffuse lobe's light, only a glossy lobe is left
            # for them: a delta one, a smooth plastic's coat, cannot be sampled. Its
            # wasted samples were 9 % of the material preview's render, 1.84 -> 1.68 s.)
            active_em = active_next & mi.has_flag(flags, mi.BSDFFlags.Smooth) & \
                ~(from_records & ~mi.has_flag(flags, mi.BSDFFlags.Glossy)) & ~trusted_whole
            direct = β * self._direct_light(scene, sampler, si, shading_n, bsdf, active_em, separable,
                                            traced_here, armed, from_records,
                                            diffuse_mis, ctx_all, ctx_diffuse, ctx_rest,
                                            guide_record, guide_fraction if guiding else None,
                                            sky_fraction if sky_guided else None)

            # ---- Direct light on the diffuse lobe by BSDF sampling (MIS) ----
            if dr.hint(diffuse_mis, mode="scalar"):
                direct += β * self._diffuse_emitter_hit(
                    scene, sampler, si, shading_n, bsdf, lit_diffuse & ~traced_here & ~from_records,
                    ctx_diffuse, n_em)
            # ---- ...and where it reads the cache, from the lights records do not hold ----
            if dr.hint(gather_first & delta_lights, mode="scalar"):
                direct += β * self._trusted_direct(scene, sampler, si, bsdf,
                                                   from_records & (lit_diffuse | trusted_whole),
                                                   ctx_diffuse)
                if dr.hint(coat_reads, mode="scalar"):
                    # (their reflection in the coat too, unless the caustic map holds it)
                    direct += β * self._trusted_direct(scene, sampler, si, bsdf, coat_read & ~armed,
                                                       ctx_rest)
            # ---- A smooth coat's reflection of the lights, traced ----
            coat = mi.Bool(False)
            if dr.hint(coat_rays, mode="scalar"):
                coat = traced_here & active_next & separable & mixed & ~armed & \
                    ~mi.has_flag(flags, mi.BSDFFlags.Glossy)
                direct += β * self._coat_emission(scene, sampler, si, bsdf, coat, ctx_rest)
            L += direct

            # ---- Light that bounced before reaching the diffuse lobe ----
            if dr.hint(defer_caustics, mode="scalar"):
                weight_here = β * response
                now1 = read_caustic & ~read1
                now2 = read_caustic & read1 & ~read2
                now3 = read_caustic & read2 & ~read3
                read1_p[now1] = si.p
                read1_n[now1] = n
                read1_weight[now1] = weight_here
                read2_p[now2] = si.p
                read2_n[now2] = n
                read2_weight[now2] = weight_here
                read3_p[now3] = si.p
                read3_n[now3] = n
                read3_weight[now3] = weight_here
                read1 |= now1
                read2 |= now2
                read3 |= now3
                caustic = mi.Spectrum(0.0)
            else:
                caustic = _finite(β * response * self._caustic_irradiance(si.p, n, depth, read_caustic),
                                  read_caustic)
            if dr.hint(gather_first, mode="scalar"):
                irradiance = self._total_irradiance(scene, si, n, trust, cached, covered)
            else:
                irradiance = self._global_irradiance(si.p, n, depth, trust, cached, covered,
                                                     gathered=records_here)
            if dr.hint(photon_map_gather, mode="scalar"):
                irradiance += self._final_gather_ray(scene, sampler, si, n, records_here)
            indirect = _finite(β * response * irradiance, trust)
            if dr.hint(coat_reads, mode="scalar"):
                # The coat's share: once armed, light that reached this vertex straight
                # from the lights (and its caustics) and leaves by the coat is a caustic
                # of the last traced vertex, which read the map: only the records'
                # bounced light is left for it.
                reflected = dr.maximum(irradiance - dr.select(armed, cached_direct, 0.0), 0.0)
                indirect += _finite(β * coat_response * reflected, coat_read)
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
            pick_light = mi.Bool(False)
            u_light = mi.Float(0.0)
            if dr.hint(lit, mode="scalar"):
                # Lanes drawn towards a bright record: u1 < α_light; u1 / α_light then
                # picks the record, and the rest of u1, stretched back to [0, 1), serves
                # the strategies below.
                pick_light = active_next & whole & (u1 < light_fraction)
                u_light = dr.minimum(u1 / LIGHT_FRACTION, ONE_MINUS_EPSILON)
                u1 = dr.select(light_fraction > 0,
                               dr.clip((u1 - light_fraction) / (1.0 - light_fraction),
                                       0.0, ONE_MINUS_EPSILON), u1)
            pick_guide = mi.Bool(False)
            if dr.hint(guiding, mode="scalar"):
                # Guided lanes: u1 < α picks the record's distribution; the rest of
                # u1, stretched back to [0, 1), draws the BSDF sample (its lobe).
                pick_guide = active_next & whole & (u1 < guide_fraction) & ~pick_light
                u1 = dr.select(guide_fraction > 0,
                               dr.clip((u1 - guide_fraction) / (1.0 - guide_fraction),
                                       0.0, ONE_MINUS_EPSILON), u1)
            bs, bsdf_weight = bsdf.sample(ctx_rest, si, u1, u2, active_next & ~whole)
            bs_all, weight_all = bsdf.sample(ctx_all, si, u1, u2,
                                             active_next & whole & ~pick_guide & ~pick_light)
            bs[whole] = bs_all
            bsdf_weight[whole] = weight_all
            mis_pdf = mi.Float(bs.pdf)
            if dr.hint(guiding | lit, mode="scalar"):
                bs, bsdf_weight, mis_pdf = self._mixed_continuation(
                    si, n, bsdf, bs, bsdf_weight, u2, active_next & whole,
                    pick_guide, guide_record, guide_fraction if guiding else None,
                    pick_light, u_light, light_total, light_fraction if lit else None)
            sampled_diffuse = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
            if dr.hint(lobes_split, mode="scalar"):
                # A rough plastic traced where it reads the caustic map, or once armed:
                # light that leaves by its diffuse lobe after a coat's reflection of the
                # lights is a caustic the map holds (not counted again past it), light
                # that leaves by the coat is the path's, so which lobe the sample counts
                # as decides what the path counts next. A sample of the whole BSDF
                # carries both lobes' values (f_all / p, guided or not), whichever lobe
                # drew it: counted by the lobe drawn, a box of strong rough plastic
                # (index 2.5) came out 2.5 % dark on its floor, and a window-lit room
                # 1 % bright. The sample belongs to the diffuse lobe with probability
                # f_d / (f_d + f_rest) at its direction, to the rest otherwise, with
                # weight f_lobe / (p · that probability): each lobe's light, unbiased,
                # and guiding kept. (Armed vertices sampled the lobes apart before,
                # half and half, unguided: a door-lit room of rough plastic's relMSE
                # 9.5e-4 -> 9.0e-4 at 16 spp, the same time.)
                split = active_next & traced_here & (read_caustic | armed) & separable & \
                    glossy_beside_diffuse(flags) & (bs.pdf > 0)
                f_lobe_d = mi.Color3f(bsdf.eval(ctx_diffuse, si, bs.wo, split))
                f_lobe_rest = mi.Color3f(bsdf.eval(ctx_rest, si, bs.wo, split))
                share_d = dr.max(f_lobe_d) / dr.maximum(dr.max(f_lobe_d) + dr.max(f_lobe_rest), 1e-30)
                as_diffuse = sampler.next_1d() < share_d
                part = dr.select(as_diffuse, f_lobe_d / dr.maximum(share_d, 1e-30),
                                 f_lobe_rest / dr.maximum(1.0 - share_d, 1e-30))
                f_sum = f_lobe_d + f_lobe_rest
                bsdf_weight[split] = dr.select(f_sum > 0, bsdf_weight * part / dr.maximum(f_sum, 1e-30), 0.0)
                sampled_diffuse = dr.select(split, as_diffuse, sampled_diffuse)
            # A traced vertex sampling its diffuse lobe starts a new chain; an
            # inseparable one (no caustic photon is stored behind it) ends the old one;
            # any other continues it through a delta/glossy lobe.
            restart = traced_here & sampled_diffuse
            ended = active_next & has_diffuse & ~separable
            crossed = dr.select(restart | ended, False, crossed | armed)
            armed = dr.select(restart, read_caustic, armed & ~ended)
            traced[traced_here | traced_whole] = traced + 1
            coat_counted = coat & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            if dr.hint(coat_reads, mode="scalar"):
                weak = active_next & ~whole & (traced > 0) & \
                    mi.has_flag(bs.sampled_type, mi.BSDFFlags.Glossy)
                survival = dr.minimum(dr.max(bsdf_weight) * (1.0 / COAT_ROULETTE_BELOW), 1.0)
                weak &= survival < 1.0
                bsdf_weight[weak] = bsdf_weight / dr.maximum(survival, 1e-8)
                # (drawn for those lanes only: the others' random streams are unchanged)
                active_next &= ~weak | (sampler.next_1d(weak) < survival)
            β *= bsdf_weight
            η *= bs.eta
            prev_si = dr.detach(si, True)
            prev_bsdf_pdf = mis_pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            prev_normal = mi.Vector3f(shading_n)
            prev_sky_record = mi.UInt32(guide_record)
            prev_sky_fraction = mi.Float(sky_fraction)
            ray = si.spawn_ray(si.to_world(bs.wo))

            # Russian roulette, as Mitsuba's path tracers (η² keeps it unitless).
            β_max = dr.max(β)
            active_next &= (β_max > 0) & (bs.pdf > 0) & dr.all(dr.isfinite(β)) & ~trusted_whole
            rr_prob = dr.minimum(β_max * dr.square(η), 0.95)
            rr_active = depth + 1 >= rr_depth
            β[rr_active] *= dr.rcp(dr.maximum(rr_prob, 1e-8))
            active_next &= ~rr_active | (sampler.next_1d() < rr_prob)

            pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active_next)
            depth += 1
            active = active_next

        if dr.hint(defer_caustics, mode="scalar"):
            # Every output of the loop in one kernel (each evaluated alone would run the
            # loop again).
            dr.eval(L, valid, L_direct, L_indirect, L_caustic, coverage, read1, read1_p, read1_n,
                    read1_weight, read2, read2_p, read2_n, read2_weight, read3, read3_p, read3_n,
                    read3_weight)
            L, L_caustic = self._deferred_caustics(
                ((read1, read1_p, read1_n, read1_weight), (read2, read2_p, read2_n, read2_weight),
                 (read3, read3_p, read3_n, read3_weight)), L, L_caustic, want_caustic,
                sampler.sample_count())
        values = dict(guides, direct=L_direct, indirect=L_indirect, caustic=L_caustic,
                      coverage=[coverage])
        return L, valid, [c for a in aovs for c in values[a]]

    def _defers_caustics(self, prepared: PreparedScene) -> bool:
        """Whether this integrator's render makes the caustic-map reads after the camera
        loop (:meth:`_deferred_caustics`): the final gather, whose paths read the map at
        traced vertices only (at most three), unbounded (records hold caustics)."""
        return prepared.caustic_map.count > 0 and self.settings.final_gather_camera and \
            prepared.index is not None and prepared.index.holds_caustics and \
            MAX_TRACED_BOUNCES <= DEFERRED_READS

    def _deferred_caustics(self, reads, L, L_caustic, want_caustic, spp: int = 1):
        """The paths' caustic-map reads (``reads``: per read, the mask of the lanes that
        made it, its points, normals and weights), added to ``L``
        (and the caustic AOV), each over just the lanes whose estimate can be other
        than 0 (a compacted wavefront), in a fixed order (the same sums every time).

        In a room whose rough floor spreads caustic photons everywhere, 85 % of these
        reads came to exactly 0 (28 % found no photon near, most of the rest only the
        photons on the far side of the wall they were on), yet in the camera loop a SIMD
        packet paid a whole estimate whenever one of its 16 lanes needed one: the reads
        were 56 % of the render for 4 % of the light (render 1.54 -> 0.9 s). Lanes that
        :func:`~pmic_integrator.irradiance.may_count_photons` rules out are skipped:
        the same image.

        The first reads of a pixel's ``spp`` samples (lane ``i`` is sample ``i % spp`` of
        pixel ``i // spp``) share one estimate where they fall close together on one
        surface (:meth:`_pixel_shared_caustics`)."""
        L = mi.Spectrum(L)
        if want_caustic:
            L_caustic = dr.zeros(mi.Spectrum, dr.width(L)) + L_caustic
        bins = self._caustic_bins()
        for slot, (made, p, n, weight) in enumerate(reads):
            lanes = dr.compress(made)
            if dr.width(lanes):
                lanes = dr.gather(mi.UInt32, lanes, dr.compress(may_count_photons(
                    bins, dr.gather(mi.Point3f, p, lanes), dr.gather(mi.Vector3f, n, lanes))))
            if dr.width(lanes) == 0:
                continue
            # (Unbounded: no depth limit, see defer_caustics.)
            if slot == 0 and spp > 1:
                irradiance = self._pixel_shared_caustics(made, p, n, lanes, spp)
            else:
                irradiance = self._caustic_irradiance(dr.gather(mi.Point3f, p, lanes),
                                                      dr.gather(mi.Vector3f, n, lanes), None, True)
            caustic = _finite(dr.gather(mi.Spectrum, weight, lanes) * irradiance, True)
            dr.scatter_add(L, caustic, lanes)
            if want_caustic:
                dr.scatter_add(L_caustic, caustic, lanes)
            dr.eval(L, L_caustic)
        return L, L_caustic

    def _pixel_shared_caustics(self, made, p, n, lanes, spp: int) -> mi.Color3f:
        """Caustic irradiance for the first reads ``lanes`` (of the wavefront's masks
        ``made``, points ``p``, normals ``n``): estimated at each pixel's first sample,
        and used by the pixel's other samples whose reads lie within
        ``CAUSTIC_SHARE_RADII`` of that estimate's kernel radius and face the same way
        (``CAUSTIC_SHARE_COSINE``); the others estimate their own."""
        prepared = self._view
        first = lanes - lanes % opaque_u32(spp)  # the pixel's first sample
        is_first = first == lanes
        at_first = dr.compress(is_first)
        first_lanes = dr.gather(mi.UInt32, lanes, at_first)
        first_p = dr.gather(mi.Point3f, p, first_lanes)
        first_n = dr.gather(mi.Vector3f, n, first_lanes)
        first_e = self._caustic_irradiance(first_p, first_n, None, True)
        # The narrowest kernel that estimate used (a delta light's photons count with
        # a kernel delta_scale times narrower).
        grid = prepared.caustic_grid
        radius = grid.level_of(first_p)[1] if isinstance(grid, PointGridPyramid) else \
            dr.full(mi.Float, prepared.caustic_radius, dr.width(first_lanes))
        reach = radius * (CAUSTIC_SHARE_RADII * min(prepared.caustic_delta_scale, 1.0))
        # Per lane of the wavefront, the estimate made at it and its reach (0: none).
        width = dr.width(made)
        estimate = dr.zeros(mi.Color3f, width)
        shared_reach = dr.zeros(mi.Float, width)
        dr.scatter(estimate, first_e, first_lanes)
        dr.scatter(shared_reach, reach, first_lanes)
        lane_p = dr.gather(mi.Point3f, p, lanes)
        lane_n = dr.gather(mi.Vector3f, n, lanes)
        first_reach = dr.gather(mi.Float, shared_reach, first)
        share = is_first | ((dr.squared_norm(lane_p - dr.gather(mi.Point3f, p, first)) <
                             dr.square(first_reach)) &
                            (dr.dot(lane_n, dr.gather(mi.Vector3f, n, first)) > CAUSTIC_SHARE_COSINE))
        result = dr.gather(mi.Color3f, estimate, first, share)
        own = dr.compress(~share)
        if dr.width(own):
            own_e = self._caustic_irradiance(dr.gather(mi.Point3f, lane_p, own),
                                             dr.gather(mi.Vector3f, lane_n, own), None, True)
            dr.eval(own_e)
            dr.scatter(result, own_e, own)
        return result

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

    def _emission(self, scene, si, prev_si, prev_normal, prev_bsdf_pdf, prev_bsdf_delta,
                  prev_sky_record, prev_sky_fraction, β, shown):
        """Emission met at ``si`` (the lanes of ``shown``), MIS-weighted against the
        emitter samples of the previous vertex unless a delta lobe led here."""
        shown = shown & (si.emitter(scene) != None)  # noqa: E711

        def compute():
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = self._emitter_pdf(scene, prev_si, ds, prev_normal, shown & ~prev_bsdf_delta,
                                       prev_sky_record, prev_sky_fraction)
            mis = dr.select(prev_bsdf_delta, 1.0, mis_weight(prev_bsdf_pdf, self._emitter_samples * em_pdf))
            return _finite(β * mis * ds.emitter.eval(si, shown), shown)
        return only_where(shown, compute, _no_light(si), label="emission")

    @property
    def _emitter_samples(self) -> float:
        """Emitter samples per vertex (``direct_samples``): the factor of their density
        in every MIS weight against them."""
        return float(self.settings.direct_samples)

    def _emitter_pdf(self, scene, ref, ds, normal, active, sky_record=None, sky_fraction=None):
        """Density of the emitter samples of :meth:`_direct_light` at ``ref`` (shading
        normal ``normal``; ``sky_record``, ``sky_fraction``: the sky guide they followed)
        for the emitter direction ``ds`` (MIS)."""
        guide = None if sky_fraction is None else \
            skylight.SkyGuide(self._view.index, sky_record, sky_fraction)
        return skylight.pdf_emitter_direction(scene, self._view.sky, ref, ds, normal, active, guide,
                                              delta=False)

    def _direct_light(self, scene, sampler, si, normal, bsdf, active, separable, traced, armed,
                      no_diffuse, diffuse_mis, ctx_all, ctx_diffuse, ctx_rest,
                      guide_record=None, guide_fraction=None, sky_fraction=None):
        """Direct light at ``si``: the mean of ``direct_samples`` emitter samples (shadow
        rays) of the lights that are not delta lights, plus one sample of each delta
        light (a sun, a spot: exact up to visibility; up to ``direct_samples`` of them,
        in strata of the choice). Chosen among all lights, half of a sunlit sky's
        samples went to the sun, each the same shadow ray, and the sun's light at a
        point came from 0 to 4 of them: the noise left in a sunlit courtyard.

        Separable BSDFs: the diffuse lobe takes emitter samples alone (or shares them by
        MIS with :meth:`_diffuse_emitter_hit`), the other lobes share them with the
        continuation's BSDF sampling. Inseparable ones share them as a whole, and so do
        traced vertices (whose continuation samples the whole BSDF). Where ``armed``,
        light through the delta/glossy lobes is left out (a caustic the map holds);
        where ``no_diffuse``, the diffuse lobe is (the cache holds its direct light).
        Where ``guide_fraction`` > 0 the MIS weights use the continuation's guided
        mixture density (:meth:`_mixed_continuation`: without its bright-record
        strategy, as the continuation's own emitter hits do). Where ``sky_fraction`` >
        0, every other sample of the sky follows the sky ``guide_record`` saw
        (:data:`SKY_EMITTER_FRACTION`).
        """
        n_em = self._emitter_samples
        index = self._view.index
        sky = self._view.sky
        guided = guide_fraction is not None  # given only where the index guides

        sky_guide = None if sky_fraction is None else \
            skylight.SkyGuide(index, guide_record, sky_fraction)

        soft_samples = self.settings.direct_samples if emission.emitter_subset(scene, False) else 0
        delta_samples = min(self.settings.direct_samples, len(emission.emitter_subset(scene, True)))

        def one_sample(sampler, k=0, delta=False):
            if delta:  # sample k of the delta lights, in its own stratum of the choice
                u = sampler.next_2d()
                u.x = dr.minimum((mi.Float(k) + u.x) / delta_samples, ONE_MINUS_EPSILON)
                ds, em_weight = emission.sample_emitter_direction(scene, si, u, True, active, delta=True)
            else:
                # Sample k of direct_samples, in its own jittered stratum of the square.
                u = jittered(sampler.next_2d(), mi.UInt32(k), self.settings.direct_samples)
                # (The strategy is chosen from u itself, as the rest of the mixture is:
                # choosing it by sample number, every other one, gave each strategy only
                # its samples' strata of the square: 11 % dark in a window-lit room.)
                ds, em_weight = skylight.sample_emitter_direction(scene, sky, si, normal, u, active,
                                                                  sky_guide, delta=False)
            ok = active & (ds.pdf != 0.0)
            wo = si.to_local(ds.d)
            # A traced vertex weighs both parts alike (the continuation samples the
            # whole BSDF): unless armed, one evaluation of the whole serves (its three
            # evaluations were a fifth of the material preview's direct light).
            split = separable & ~(traced & ~armed)
            f_diffuse, pdf_diffuse_lobe = bsdf.eval_pdf(ctx_diffuse, si, wo, ok & split)
            f_rest, pdf_rest_lobe = bsdf.eval_pdf(ctx_rest, si, wo, ok & split)
            f_all, pdf_all = bsdf.eval_pdf(ctx_all, si, wo, ok & (~separable | traced))
            # The pdf with which the continuation would sample this direction.
            if guided:
                pdf_all = (1.0 - guide_fraction) * pdf_all + guide_fraction * index.guide_pdf(
                    guide_record, ds.d, ok & (guide_fraction > 0))
            pdf_rest = dr.select(separable & ~traced, pdf_rest_lobe, pdf_all)
            pdf_diffuse = dr.select(traced, pdf_all, pdf_diffuse_lobe)
            f_rest = dr.select(split, f_rest, f_all)
            f_rest = dr.select(separable & armed, 0.0, f_rest)
            f_diffuse = dr.select(split & ~no_diffuse, f_diffuse, 0.0)
            em_pdf = n_em * ds.pdf
            w_rest = dr.select(ds.delta, 1.0, mis_weight(em_pdf, pdf_rest))
            w_diffuse = dr.select(ds.delta | ~(traced | diffuse_mis), 1.0,
                                  mis_weight(em_pdf, pdf_diffuse))
            return _finite(em_weight * (f_diffuse * w_diffuse + f_rest * w_rest), ok)

        def mean(count, delta):
            if count == 0:
                return mi.Spectrum(0.0)
            if count == 1:
                return only_where(active, lambda sampler: one_sample(sampler, 0, delta), _no_light(si),
                                  sampler, label="pmic_direct_light")

            def body(k, total, sampler):
                return k + 1, total + one_sample(sampler, k, delta), sampler

            _, total, _ = dr.while_loop(
                (dr.zeros(mi.UInt32, dr.width(si.p)), dr.zeros(mi.Spectrum, dr.width(si.p)), sampler),
                lambda k, total, sampler: active & (k < count), body, label="pmic_direct_light")
            return total / count

        return mean(soft_samples, False) + mean(delta_samples, True)

    @staticmethod
    def _coat_emission(scene, sampler, si, bsdf, active, ctx_rest):
        """Emission that a smooth coat (the delta lobes over a diffuse one: a smooth
        plastic) reflects at a traced vertex, along one sample of those lobes (for one
        delta lobe, its only direction): a ray of its own. The continuation samples the
        whole BSDF and takes the coat only now and then (a smooth plastic of IOR 1.9
        one time in six, its reflection of a sky then weighted ×6); the emission it
        meets through a delta lobe is not counted again (``coat_counted``), so this
        replaces that estimate by its mean over the choice of lobe. In the material
        preview the coat's reflection of the sky was half the noise left on the
        object."""
        def compute(sampler):
            bs, weight = bsdf.sample(ctx_rest, si, sampler.next_1d(), sampler.next_2d(), active)
            ok = active & (bs.pdf > 0) & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            hit = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), ok)
            return _finite(weight * hit.emitter(scene, ok).eval(hit, ok), ok)
        return only_where(active, compute, _no_light(si), sampler, label="coat_emission")

    def _mixed_continuation(self, si, n, bsdf, bs, weight, u2, active,
                            pick_guide, guide_record, guide_fraction,
                            pick_light, u_light, light_total, light_fraction):
        """One-sample MIS of up to three strategies for a traced vertex's continuation:
        towards a bright record (:meth:`RecordLights.sample`, where ``pick_light``,
        probability α_l = ``light_fraction``), from the guide record's distribution
        (:meth:`RecordIndex.sample_guide`, where ``pick_guide``, probability
        (1-α_l)·α_g), else the BSDF sample ``bs``. Either way the weight is
        f·cos / p_mix with p_mix = α_l p_light + (1-α_l)((1-α_g) p_bsdf + α_g p_guide)
        (``None`` fractions: that strategy is not used in this scene). A delta lobe's
        sample keeps its weight over (1-α_l)(1-α_g) (no density to mix).

        Also returns the density that emitter hits are MIS-weighted with: the mixture
        without the bright-record strategy. MIS weights need only sum to one over the
        strategies (emitter sampling and this continuation), which they do when both
        use the same density, so the emitter samples need not evaluate the lights'
        density (a loop over the lights per sample): unbiased either way."""
        index = self._view.index
        guided, lit = guide_fraction is not None, light_fraction is not None
        alpha_g = guide_fraction if guided else mi.Float(0.0)
        alpha_l = light_fraction if lit else mi.Float(0.0)
        mixing = active & ((alpha_g > 0) | (alpha_l > 0))
        picked = mi.Bool(False)
        wo_picked = mi.Vector3f(0.0, 0.0, 1.0)
        if guided:
            picked |= pick_guide
            wo_picked = dr.select(pick_guide, index.sample_guide(guide_record, u2, pick_guide), wo_picked)
        if lit:
            picked |= pick_light
            wo_picked = dr.select(pick_light, index.lights.sample(si.p, n, light_total, u_light, u2,
                                                                  pick_light), wo_picked)
        wo_picked_local = si.to_local(wo_picked)
        f_picked, pdf_bsdf_picked = bsdf.eval_pdf(mi.BSDFContext(), si, wo_picked_local, picked)
        delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) & ~picked
        wo_world = dr.select(picked, wo_picked, si.to_world(bs.wo))
        pdf_bsdf = dr.select(picked, pdf_bsdf_picked, bs.pdf)
        mixed = mixing & ~delta
        pdf_mix = pdf_bsdf
        if guided:
            pdf_mix = (1.0 - alpha_g) * pdf_mix + alpha_g * index.guide_pdf(
                guide_record, wo_world, mixed & (alpha_g > 0))
        pdf_mis = dr.select(mixed, pdf_mix, bs.pdf)
        if lit:
            pdf_mix = (1.0 - alpha_l) * pdf_mix + alpha_l * index.lights.pdf(
                si.p, n, light_total, wo_world, mixed & (alpha_l > 0))
        safe = dr.maximum(pdf_mix, 1e-30)
        weight = dr.select(mixed & ~picked, weight * (bs.pdf / safe), weight)
        weight = dr.select(mixing & delta, weight / ((1.0 - alpha_g) * (1.0 - alpha_l)), weight)
        weight = dr.select(picked, mi.Spectrum(f_picked) / safe, weight)
        weight = dr.select(mixed & ~(pdf_mix > 0), 0.0, weight)
        bs.pdf = dr.select(mixed, pdf_mix, bs.pdf)
        bs.wo = dr.select(picked, wo_picked_local, bs.wo)
        bs.eta = dr.select(picked, 1.0, bs.eta)
        bs.sampled_type = dr.select(picked, mi.UInt32(+mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
        bs.sampled_component = dr.select(picked, mi.UInt32(0), bs.sampled_component)
        return bs, weight, pdf_mis

    def _trusted_direct(self, scene, sampler, si, bsdf, active, ctx_diffuse):
        """Direct light on the diffuse lobe of a vertex that reads the cache (final
        gather) from the delta lights (a sun, a spot), which neither the records nor the
        photons it may read instead hold (their sharp shadows would be smeared): one
        sample of them, a shadow ray, exact up to visibility. No MIS: a delta light
        cannot be hit, and the lobe does not continue."""
        def compute(sampler):
            ds, em_weight = sample_emitter_direction(scene, si, sampler.next_2d(), True, active,
                                                     delta=True)
            ok = mi.Bool(active) & (ds.pdf != 0.0)
            f = bsdf.eval(ctx_diffuse, si, si.to_local(ds.d), ok)
            return _finite(em_weight * f, ok)
        return only_where(active, compute, _no_light(si), sampler, label="trusted_direct")

    def _diffuse_emitter_hit(self, scene, sampler, si, normal, bsdf, active, ctx_diffuse, n_em):
        """Direct light on the diffuse lobe from one BSDF-sampled ray that meets an
        emitter (an area light or the environment), MIS-weighted against the
        ``direct_samples`` emitter samples of :meth:`_direct_light`."""
        def compute(sampler):
            bs, weight = bsdf.sample(ctx_diffuse, si, sampler.next_1d(), sampler.next_2d(), active)
            ok = active & (bs.pdf > 0)
            ray = si.spawn_ray(si.to_world(bs.wo))
            hit = scene.ray_intersect(ray, mi.RayFlags.All, coherent=False, active=ok)
            ds = mi.DirectionSample3f(scene, si=hit, ref=si)
            em_pdf = self._emitter_pdf(scene, si, ds, normal, ok)
            emitted = ds.emitter.eval(hit, ok)
            return _finite(weight * emitted * mis_weight(bs.pdf, n_em * em_pdf), ok)
        return only_where(active, compute, _no_light(si), sampler, label="diffuse_emitter_hit")

    def _final_gather_ray(self, scene, sampler, si, n, active):
        """One cosine-distributed gather ray reading precomputed irradiance: E ≈ π L."""
        local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
        ray = mi.Ray3f(si.p + n * surface_offset(si.p, self._view.ray_offset),
                       mi.Frame3f(n).to_world(local))
        # Glossy bounces along the ray follow the render's seed, as the rest of the path.
        rng = streams.render_rng(sampler, dr.width(si.p))
        radiance, _ = trace_gather_rays(scene, self._view.gather_source, ray, rng, active)
        return radiance * math.pi


def _memory_stats(p: PreparedScene) -> dict:
    """Bytes held by the photon maps, their hash grids and the gather lookup copy, and
    by the records."""
    grids = [g for g in (p.global_grid, p.caustic_grid) if g is not None]
    photon_bytes = p.global_map.nbytes() + p.caustic_map.nbytes() + sum(g.nbytes() for g in grids)
    if p.gather_source is not None:
        photon_bytes += p.gather_source.nbytes()
    return {"memory_photons_bytes": photon_bytes,
            "memory_records_bytes": (p.index.records.nbytes() + sum(
                4 * dr.width(a) for a in (p.index.packed_head, p.index.packed_body) if a is not None))
            if p.index else 0}
