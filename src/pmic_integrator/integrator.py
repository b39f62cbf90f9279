"""The ``pmic`` Mitsuba 3 integrator: stages 1-4 of Gu & Wang (2010) put together."""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import replace

import drjit as dr
import mitsuba as mi

if mi.variant() is None:
    # ``PMICIntegrator`` is a subclass of the variant's SamplingIntegrator, so this module
    # needs a variant; imported before one is chosen (``help(PMICIntegrator)`` in a fresh
    # interpreter), it picks the CPU one, as most users would.
    mi.set_variant("llvm_ad_rgb")

from . import cachefile, camera, pipeline, spectra, streams  # noqa: E402
from .irradiance import NormalBins  # noqa: E402
from .pipeline import PreparedScene, SceneInfo, scene_fingerprint  # noqa: E402,F401 (re-exported)
from .render.caustics import add_deferred_caustics  # noqa: E402
from .render import config as path_config  # noqa: E402
from .render.config import PathConfig, PathContext  # noqa: E402
from .render.path import trace_camera_paths  # noqa: E402
from .settings import METHODS, Settings  # noqa: E402,F401 (METHODS re-exported)

log = logging.getLogger("pmic")


class _PMICMethods:
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
         - ``"adaptive"``
         - ``pmic`` only. ``"adaptive"``: the first diffuse vertex of a camera path
           reads the records' bounced light (its direct light still sampled) where
           it can trust them (a record whose gather met no glass, metal or glossy
           surface, found photons near where its rays landed and gathered evenly),
           and is path-traced elsewhere; not in scenes with delta lights, nor in a
           render that outputs the denoiser's guides (``aovs`` with ``albedo`` and
           ``normal``), which is rendered as by ``"final_gather"``.
           ``"final_gather"``: the first diffuse vertex is always path-traced (one
           BSDF sample, MIS with the emitters) and the cache, which then also holds
           direct light, is read where that ray lands, unless it lands closer than
           a record radius (corners, contacts, gaps: traced once more, up to 3
           times). Its error is noise, which a denoiser removes, and it keeps
           converging. ``"first_hit"``: the paper's interpolation at the first
           diffuse vertex (less noise at few samples, but record-sized blotches
           that stay). With any of them, the cache is view independent: a function
           of the scene, the settings and ``seed`` only.
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
           after 20 paths per photon, and records then gather caustic light instead;
           skipped in a render for a denoiser, ``aovs`` with albedo and normal, where
           the caustics stand out little from the light around them and tracing
           finds them readily: docs/tuning.md, "The caustic map"). The global pass's
           own caustic photons join the map.
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
    polarised and monochrome variants are not supported (the JIT RGB and spectral ones
    are: ``llvm_ad_rgb``, ``llvm_ad_spectral``, ``cuda_ad_*``; in spectral ones the maps
    and the cache store linear sRGB, :mod:`pmic_integrator.spectra`); it is not
    differentiable.

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
        # (The variant's SamplingIntegrator: integrator_class makes one class per variant,
        # and a user's subclass of it may stand between.)
        next(c for c in type(self).__mro__ if c.__module__.startswith("mitsuba")).__init__(self, props)
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
        #: (prepared scene, its caustic map's normal bins): see _caustic_bins
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
            if prepared.stats.get("caustics_left_to_denoiser") and not self.settings.denoiser_guides:
                log.warning("pmic: cache_file '%s' was built for a denoiser (aovs with albedo and "
                            "normal) and has no caustic map: this render traces its caustic light, "
                            "which may leave bright single pixels. Build the file with a render "
                            "without those aovs for images that are not denoised.", cache_file)
            pipeline.ready_for_first_reads(scene, self.settings, prepared)  # (the survey: not kept in the file)
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
        """Stage 4: camera rays over the film (:mod:`.camera`), a camera path for each
        (:meth:`_sample`), reading ``view``, splatted into the film."""
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
            wavefront = path_config.DEFERRED_WAVEFRONT if path_config.defers_caustics(self.settings, view) \
                else camera.MAX_WAVEFRONT
            for pass_index, pass_spp in enumerate(camera.pass_counts(film, spp, wavefront)):
                sampler = camera.seeded_sampler(
                    sensor, streams.render_pass_seed(seed, pass_index), pass_spp)
                ray, weight, position = camera.camera_rays(sensor, sampler)
                radiance, valid, aovs = self._sample(scene, sampler, ray, mi.Bool(True),
                                                     own_render=True, spp=spp)
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
    # Stage 4: camera paths (pmic_integrator.render)
    # ----------------------------------------------------------------------------------
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        """One camera path per lane (:func:`~pmic_integrator.render.path.trace_camera_paths`):
        emission, direct light, indirect light at diffuse lobes from the cache (or
        photon map) and the caustic map, continued through the other lobes. Called by
        an integrator wrapping this one (Mitsuba's ``aov``) after render(): it reads
        the view of the last render, its caustic-map reads made in the loop."""
        return self._sample(scene, sampler, ray, active, own_render=False,
                            spp=sampler.sample_count())

    def _sample(self, scene, sampler, ray, active, own_render: bool, spp: int):
        """Camera paths for ``ray``, in a render of ``spp`` samples per pixel in all."""
        view = self._view
        config = PathConfig.of(self.settings, view, own_render, spp)
        ctx = PathContext.of(scene, view, config, self._fallback_counter, self.skip_area_emitters, spp)
        state, guides = trace_camera_paths(ctx, sampler, ray, active)
        L, L_caustic = state.L, state.L_caustic
        if config.defer_caustics:
            # Every output of the loop in one kernel (each evaluated alone would run the
            # loop again).
            dr.eval(state.L, state.valid, state.L_direct, state.L_indirect, state.L_caustic,
                    state.coverage, state.reads)
            L, L_caustic = add_deferred_caustics(ctx, self._caustic_bins(), state.reads, L, L_caustic,
                                                 config.wants("caustic"), sampler.sample_count(),
                                                 ray.wavelengths)
        values = dict(guides, direct=state.L_direct,
                      indirect=state.L_indirect, caustic=L_caustic, coverage=[state.coverage])
        if mi.is_spectral:  # the film takes AOVs as they are: linear sRGB
            for name in ("direct", "indirect", "caustic"):
                values[name] = spectra.camera_to_rgb(values[name], ray.wavelengths)
        return L, state.valid, [c for a in config.aovs for c in values[a]]

    def _caustic_bins(self) -> NormalBins:
        """:class:`~pmic_integrator.irradiance.NormalBins` of the caustic map (made at
        the first render of each prepared scene)."""
        prepared = self._view
        known, bins = self._caustic_normal_bins
        if known is not prepared:
            bins = NormalBins.build(prepared.caustic_map, prepared.caustic_grid)
            self._caustic_normal_bins = (prepared, bins)
        return bins


_classes: dict = {}


def integrator_class(variant: str | None = None) -> type:
    """The ``pmic`` integrator class of ``variant`` (default: the active one): Mitsuba's
    base classes are per variant, so a process that renders in ``llvm_ad_rgb`` and then
    in ``llvm_ad_spectral`` (a notebook, a test run over every variant) needs a class
    for each. The methods are the same (:class:`_PMICMethods`)."""
    variant = variant or mi.variant()
    cls = _classes.get(variant)
    if cls is None:
        base = getattr(__import__(f"mitsuba.{variant}", fromlist=["SamplingIntegrator"]),
                       "SamplingIntegrator") if variant != mi.variant() else mi.SamplingIntegrator
        # (One base only: nanobind refuses a mixin; the methods are copied instead.)
        methods = {k: v for k, v in vars(_PMICMethods).items() if k not in ("__dict__", "__weakref__")}
        cls = type("PMICIntegrator", (base,), dict(methods, __qualname__="PMICIntegrator"))
        _classes[variant] = cls
    return cls


#: The integrator class of the variant active when this module was imported
#: (:func:`integrator_class` gives any variant's).
PMICIntegrator = integrator_class()


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
