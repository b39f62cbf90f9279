"""The per-render switches of the camera path, decided once before its loop.

:class:`PathConfig` is frozen and closed over by the loop (as ``gather.py``'s walks
close over their source): what varies per lane is loop state
(:class:`~pmic_integrator.render.state.PathState`), what is the same for every lane
of a render is here. Each switch turns a strategy on for the scenes that need it, so
that the others compile none of its code.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..bsdfs import scene_diffuse_free
from ..pipeline import PreparedScene
from ..settings import Settings

#: Camera samples per pass where caustic-map reads wait for the end of the camera loop
#: (their points, normals and weights: ~130 bytes a sample, 0.5 GB per pass); each
#: further pass costs the loop's tracing again.
DEFERRED_WAVEFRONT = 1 << 22
#: At most this many diffuse bounces per camera path are traced (final gather): then
#: the cache is read however close (bounded cost; the error is by then three diffuse
#: bounces deep). See :data:`~pmic_integrator.render.reads.TRUST_RECORD_RADII`.
MAX_TRACED_BOUNCES = 3
#: Caustic-map reads a camera path can defer (its slots in the loop state): one per
#: traced vertex. Must be at least MAX_TRACED_BOUNCES (checked by :func:`defers_caustics`:
#: with fewer slots, reads stay in the loop).
DEFERRED_READS = 3


def defers_caustics(settings: Settings, prepared: PreparedScene) -> bool:
    """Whether a render's caustic-map reads are made after the camera loop
    (:mod:`~pmic_integrator.render.caustics`): with the final gather, whose paths read
    the map at traced vertices only (at most MAX_TRACED_BOUNCES), and records that hold
    caustics (no depth bound)."""
    return prepared.caustic_map.count > 0 and settings.final_gather_camera and \
        prepared.index is not None and prepared.index.holds_caustics and \
        MAX_TRACED_BOUNCES <= DEFERRED_READS


def first_reads_allowed(settings: Settings, prepared: PreparedScene) -> bool:
    """Whether this render's settings and cache let the adaptive estimator read records
    at first vertices at all: records that guide, no depth bound, and an image not
    meant for a denoiser (Settings.denoiser_guides). A denoiser removes the traced
    first bounce's noise but keeps the records' smooth error: after OIDN, reads at the
    first hit left the white room at 9.9e-3 relMSE against the final gather's 5.4e-3,
    the lamp room at 3.1e-2 against 1.3e-2 (docs/tuning.md, "First reads"). Asked by
    :func:`first_reads` and, before it, by the survey that picks the records
    (reads.survey_first_reads)."""
    index = prepared.index
    return may_read_first_hits(settings, prepared.info) and index is not None and index.guides


def may_read_first_hits(settings: Settings, info) -> bool:
    """:func:`first_reads_allowed` before the cache is built, from the settings and the
    scene's :class:`~pmic_integrator.pipeline.SceneInfo`: the adaptive estimator, no
    depth bound, no denoiser guides, no delta lights (where the sunlit classroom kind
    read 0.93 of its reference at the first hit: reads.survey_first_reads). Stage 3
    gathers records in rounds where it is false (pipeline.GATHER_BUDGET_RAYS)."""
    return settings.final_gather_camera and settings.estimator == "adaptive" and \
        not settings.bounded and not settings.denoiser_guides and not info.has_delta_emitter


def first_reads(settings: Settings, prepared: PreparedScene, spp: int) -> bool:
    """Whether this render, of ``spp`` samples per pixel, reads records at first
    vertices: where they are allowed (:func:`first_reads_allowed`) and some record
    qualifies at that sample count (reads.first_read_limit)."""
    from .reads import first_read_limit  # (reads builds on this module)

    # (A limit of at least spp >= 1 means some record may be read: first_read_spp is 0
    # for the others.)
    return first_reads_allowed(settings, prepared) and first_read_limit(prepared.index) >= spp


@dataclass(frozen=True)
class PathConfig:
    """What a render's camera paths do, the same for every lane."""

    hide_emitters: bool
    rr_depth: int
    max_depth: int  #: longest path in segments (0xFFFFFFFF: unbounded)
    max_iterations: int  #: of the loop (-1: unbounded)
    #: max_depth bounds the paths: records hold the light of paths read from one depth
    #: only (Settings.records_read_depth), read_depth.
    bounded: bool
    read_depth: int
    method: str
    final_gather: bool  #: ``photon_map``'s gather ray at the first diffuse hit
    use_indirect: bool  #: some photon map holds photons
    has_caustic_map: bool
    photon_map_gather: bool
    reads_cache: bool
    #: The final-gather estimator: the first diffuse vertex is traced, the cache read
    #: one bounce later (Settings.final_gather_camera).
    gather_first: bool
    records_hold_caustics: bool
    #: The adaptive estimator: the first diffuse vertex reads the records' bounced light
    #: where they resolved the photons and gathered evenly (reads.first_read_pays),
    #: else is traced; off where no record qualifies (:func:`first_reads`).
    first_reads: bool
    #: BSDF sampling of the diffuse lobe for direct light, combined with emitter
    #: sampling by MIS: emitter sampling alone is noisy for large emitters (skies).
    diffuse_mis: bool
    delta_lights: bool
    coat_rays: bool  #: smooth coats: their reflection of the lights traced (direct.coat_emission)
    #: Rough plastic at and past a vertex that read the caustic map: each sample split
    #: between its lobes (continuation.split_lobes).
    lobes_split: bool
    #: BSDFs whose lobes cannot be taken apart (principled) read the cache with their
    #: whole response where a diffuse one would (reads.where_read)...
    whole_reads: bool
    coat_reads: bool  #: ...and so do rough plastics' coats
    inseparable_bsdfs: bool
    leaning: bool  #: some diffuse lobe leans (normal maps)
    guiding: bool
    sky_guided: bool
    lit: bool  #: bright records (lamp shades) draw continuation rays
    direct_samples: int
    aovs: tuple[str, ...]
    #: Caustic-map reads are made after the loop (:func:`defers_caustics`): only in
    #: pmic's own render; a caller of ``sample()`` alone (Mitsuba's ``aov``) gets them
    #: in the loop, as do the estimators whose paths may read the map at any vertex.
    defer_caustics: bool

    @property
    def emitter_samples(self) -> float:
        """Emitter samples per vertex (``direct_samples``): the factor of their density
        in every MIS weight against them."""
        return float(self.direct_samples)

    def wants(self, aov: str) -> bool:
        return aov in self.aovs

    @staticmethod
    def of(settings: Settings, prepared: PreparedScene, own_render: bool, spp: int = 1) -> "PathConfig":
        """The switches for ``settings`` on ``prepared`` (``own_render``: called from
        pmic's own render(), which makes the deferred caustic reads) in a render of
        ``spp`` samples per pixel."""
        info, index = prepared.info, prepared.index
        gather_first = settings.final_gather_camera
        has_caustic_map = prepared.caustic_map.count > 0
        whole_reads = gather_first and not settings.bounded and info.has_glossy_coat
        guiding = gather_first and settings.guiding and index is not None and index.guiding_pays()
        return PathConfig(
            hide_emitters=settings.hide_emitters, rr_depth=settings.rr_depth,
            max_depth=0xFFFFFFFF if settings.max_depth == -1 else settings.max_depth,
            max_iterations=settings.max_depth, bounded=settings.bounded,
            read_depth=settings.records_read_depth, method=settings.method,
            final_gather=settings.final_gather,
            use_indirect=prepared.global_map.count > 0 or has_caustic_map,
            has_caustic_map=has_caustic_map,
            photon_map_gather=settings.method == "photon_map" and settings.final_gather and
            prepared.global_map.count > 0,
            reads_cache=settings.method != "photon_map", gather_first=gather_first,
            records_hold_caustics=index is not None and index.holds_caustics,
            first_reads=first_reads(settings, prepared, spp),
            diffuse_mis=info.has_infinite_emitter, delta_lights=info.has_delta_emitter,
            coat_rays=info.has_delta_coat,
            lobes_split=gather_first and has_caustic_map and info.has_glossy_coat,
            whole_reads=whole_reads, coat_reads=whole_reads and index is not None,
            inseparable_bsdfs=info.has_inseparable, leaning=info.has_leaning_lobes,
            guiding=guiding,
            sky_guided=guiding and prepared.sky is not None and index.sky_guiding_pays(),
            lit=gather_first and settings.guiding and index is not None and index.lights is not None,
            direct_samples=settings.direct_samples, aovs=settings.aov_list,
            defer_caustics=defers_caustics(settings, prepared) and own_render)


@dataclass(frozen=True)
class PathContext:
    """What the camera path reads beside its state: the scene, the prepared scene of
    the view (photon maps, cache), the switches, and the counter of vertices that no
    record reached (statistics). Closed over by the loop, never its state."""

    scene: mi.Scene
    view: PreparedScene
    config: PathConfig
    fallback_counter: mi.UInt32
    #: The trust radius where no record reaches: the global map's lookup radius (opaque:
    #: the photons set it, and a constant would make a kernel per seed).
    untrusted_radius: mi.Float
    #: The render's samples per pixel (opaque: a constant would make a kernel per
    #: count): records are read at first vertices up to a count of their own
    #: (reads.first_read_pays).
    spp: mi.Float
    #: Mitsuba's ``SamplingIntegrator.skip_area_emitters`` (hidden emitters are looked
    #: through), bound to the integrator.
    skip_area_emitters: object
    #: The scene's BSDFs whose flags list a diffuse lobe they never have (principled
    #: metals and glass: bsdfs.diffuse_free_table), or None.
    diffuse_free: object = None

    @staticmethod
    def of(scene, view: PreparedScene, config: PathConfig, fallback_counter,
           skip_area_emitters, spp: int = 1) -> "PathContext":
        return PathContext(scene, view, config, fallback_counter,
                           dr.opaque(mi.Float, view.global_radius), dr.opaque(mi.Float, spp),
                           skip_area_emitters, scene_diffuse_free(scene))

    def count_fallback(self, need) -> None:
        """Count the camera vertices that no record reached (stats)."""
        dr.scatter_reduce(dr.ReduceOp.Add, self.fallback_counter, mi.UInt32(1), mi.UInt32(0), need)

    def depth_limit(self, depth):
        """Photons completing a path of at most max_depth segments (None: all, also
        where max_depth is deep enough to be unbounded: Settings.bounded)."""
        return None if not self.config.bounded else mi.UInt32(self.config.max_depth) - depth - 1
