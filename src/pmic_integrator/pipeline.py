"""Stages 1-3 of the method, view independent: photons → irradiance precomputed at the
photons → the irradiance cache, seeded from the photons.

:func:`prepare` runs them for a scene and a :class:`~pmic_integrator.settings.Settings`
and returns a :class:`PreparedScene`, built in locals and returned whole: a stage that
fails leaves nothing behind. It needs no camera: the cache is a pure function of the
scene, the settings and the scene seed. Where photons are too sparse to tell (surfaces
no photon reached, the shadowed gap between a light and the ceiling), *surface probes*
(points sampled on every diffuse surface by area) stand in for what a camera would
have told the classic cache.

:func:`camera_seeded_index` is the classic, view-dependent cache of the
``irradiance_cache`` method (records placed from one camera); it returns a new index
and changes nothing that is shared.
"""
from __future__ import annotations

import logging
import math
import sys
import time
import warnings
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from . import cache as cache_mod, spectra, streams
from .emission import focus_box, is_delta, scene_bbox  # noqa: F401  (scene_bbox re-exported)
from .fingerprint import SceneFingerprint, scene_fingerprint  # noqa: F401 (re-exported)
from ._jit import concat, every_nth, opaque_float, rng as make_rng
from .bsdfs import (glossy_beside_diffuse, ignores_lobe_masks, lobes_lean, non_diffuse_context, scene_bsdfs,
                    scene_diffuse_free, scene_flags)
from .cache import CacheRecords, RecordIndex
from .gather import NEAR_HIT_LOOKUPS, VISIBILITY_LIFT, GatherSource, trace_gather_rays
from .hashgrid import BallGrid, PointGridPyramid
from .lights import RecordLights
from .irradiance import (adapted_lookup_radius, caustic_sample, caustic_standout, estimate_irradiance,
                         lookup_radius, precompute_irradiance, sort_into_grid)
from .photons import CAUSTIC, GLOBAL, PhotonMap, merge_caustic_photons, trace_photons
from .settings import Settings, check_against_scene, rays_strata
from .skylight import SkySampler

log = logging.getLogger("pmic")

# --- Tuning constants of stages 1-3 ------------------------------------------------------
#: Final gather: records first gather this share of ``gather_rays`` (at least
#: FIRST_GATHER_MIN_RAYS), and the rest only where bounced light matters
#: (RecordIndex.guiding_pays): under an open sky the records hold little of what the
#: camera sees, read one diffuse bounce away, and their noise does not show (the material
#: preview at 64 rays: relMSE 4.20e-3 against 4.17e-3, its cache 0.63 -> 0.36 s), while in
#: rooms it does (64 rays everywhere: a door-ajar room's equal-time speed-up 3.5 -> 2.4,
#: the window-lit room's relMSE 3.1e-3 -> 5.7e-3). Where the rest is gathered, the two
#: independent gathers are blended (CacheRecords.blend): the same rays in all.
FIRST_GATHER_SHARE = 0.25
FIRST_GATHER_MIN_RAYS = 16
#: ...in scenes where the global photons' power that bounced before landing is under
#: this share of their power (open scenes 0.01-0.09: the material preview, the bundled
#: exterior, courtyards; rooms 0.45-0.60). Rooms gather all of their rays at once: the
#: second round would cost them 0.03 s and its answer is known.
FIRST_GATHER_MAX_BOUNCED = 0.25
#: ...and in rooms whose records would gather more than this many rays in all (their
#: count times ``gather_rays``) where no render of the settings reads a record at a
#: camera path's first hit (render.config.may_read_first_hits): there records keep
#: their first round, read one traced bounce away, where their noise is averaged over
#: the bounce's directions (a cache file of them read by a render that makes first
#: reads gathers the rest: ready_for_first_reads). Sponza and the white room (~7 000
#: records, 1.7-1.9M rays: 6-10 s of the cache stage on two cores) spent most of a
#: 16-spp render for a denoiser on the gathers; the rooms under it (the lamp and dining
#: rooms, the glossy Cornell box: 0.3-0.7M rays, under 3 s) keep every ray, which their
#: denoised images need (the glossy Cornell box at 64 rays: relMSE after OIDN +47 %).
#: docs/tuning.md, "Gather rounds", has the measurement.
GATHER_BUDGET_RAYS = 1 << 20
#: Precomputed irradiance is estimated from every path but the precomputed ones
#: (irradiance.precompute_irradiance) in scenes where at least this share of the global
#: photons' power bounced before landing (rooms: 0.45-0.60), from the odd half only
#: elsewhere (open scenes: 0.01-0.09). In a room lit through a door the dim room's
#: estimates are the image's noise from one photon seed to the next (sd 0.94 % -> 0.50 %
#: of its mean); under an open sky that noise is little of the image, and the bigger
#: grid cost the sunny courtyard 0.02-0.03 s of its 0.1 s precomputation, for nothing
#: (relMSE 8.72e-4 against 8.66e-4).
OTHER_PATHS_MIN_BOUNCED = 0.25
#: Smallest record *reach* (a·R), in units of the global photon lookup radius:
#: irradiance is only resolved to about one lookup radius, so smaller records add cost,
#: not detail; and a reach of ~4 photon spacings leaves no gaps between the photons.
MIN_REACH_LOOKUPS = 1.0
#: Largest record radius as a fraction of the scene's length scale: a view-independent
#: cache has no pixel footprint to bound it, the scene size does.
R_MAX_DIAGONAL = 0.08
#: Neighbour clamping looks this many photon lookup radii around each candidate, and
#: repeats until the bound has spread over the largest radius (at most this many passes).
CLAMP_STEP_LOOKUPS = 2.0
CLAMP_ITERATIONS = 6
#: Surface probes (first-hit estimator): this many points sampled by area over every
#: diffuse surface, per global photon, within the bounds below. Uncovered probes get
#: records of their own (coverage where photons missed); every PROBE_CLAMP_STRIDE-th
#: probe also bounds its neighbours' radii (the light gap; the classic cache's camera
#: points did this per view, 1 in 16 of 512² pixels). At most 65536: at 1M photons,
#: 262144 probes added 900 records (cache stage 5.2 s, against 3.4 s).
PROBES_PER_PHOTON = 0.25
MIN_PROBES = 16384
MAX_PROBES = 65536
PROBE_CLAMP_STRIDE = 4
#: A probe whose pilot rays' harmonic mean distance is below this many ray offsets is
#: enclosed (a face resting on another): no camera sees it, so it bounds no record.
ENCLOSED_OFFSETS = 100.0
#: A probe bounds its neighbours by its own pilot radius, floored at this fraction of
#: the smallest record radius (not at it, as records are): in a gap narrower than a
#: record (1 cm between a light and the ceiling), records from outside must not
#: reach in, so the probes there get records of their own. 1.0 left the gap lit
#: (relMSE 1.0e-2 in the Cornell box's light-gap crop at a = 0.5; 1.4e-3 at 0.1).
PROBE_FLOOR = 0.1
#: Shrinking records may uncover photons, which get records of their own that must obey
#: the probes' bounds too: repeat at most this many times (a record covers its photon).
#: The photons the last pass uncovers get their records with the uncovered probes', in
#: one gather: passes beyond the second uncovered 1-20 photons (Cornell box, 100k
#: photons), each costing a placement and a gather of its own (~15 ms).
PROBE_CLAMP_PASSES = 3
#: Candidates walked first, evenly spread, before the ones they leave uncovered.
PLACEMENT_SUBSET = 16384
#: Records are placed so as to cover at most this many photons, evenly spread (every
#: k-th of the map): beyond, the photons are denser than any record (the smallest
#: reaches one lookup radius, which holds lookup_size photons), and testing each one's
#: coverage only cost time (0.25 s of 1.9 at 1M photons). As many as the classic
#: cache's camera points at 512².
MAX_PLACEMENT_PHOTONS = 1 << 18
#: Ray origins are pushed off the surface by this fraction of the scene's length scale
#: (see ``PreparedScene.length_scale``), plus RAY_OFFSET_RELATIVE of the point's largest
#: coordinate (float precision far from the origin).
RAY_OFFSET_DIAGONAL = 1e-5
#: The length scale is the diagonal, but at most this many global lookup radii: a
#: 2·10⁶-unit ground plane under a 1-unit box must not push rays 28 units off the box,
#: nor let records grow to 10⁵ units. Photons tell where the light, and so the
#: detail, is.
LENGTH_SCALE_LOOKUPS = 100.0
#: The precomputed estimates (what gather rays read) are corrected for discs that run
#: past their surface by probes traced over the disc (boundary.surface_mass), not by
#: the photons' centroid (docs/tuning.md, ``MIN_SURFACE_MASS``).
SURFACE_PROBED_ESTIMATES = True
#: Photons per caustic estimate relative to ``lookup_size``: caustics are sharper.
CAUSTIC_LOOKUP_FRACTION = 0.5
#: ...times up to CAUSTIC_LOOKUP_GROWTH where caustics are much of the light that
#: reaches surfaces first (:func:`caustic_lookup_size`): the share of caustic photons'
#: power in caustic + direct photons' over CAUSTIC_SHARE_FOR_GROWTH. Read at the first
#: diffuse vertex, a caustic estimate's noise is a blotch the size of its disc, ~1/√k
#: of it for k photons; where the caustic is a glass sphere's focus (3-6 % of that
#: light in the scenes measured) it is a small part of any pixel, but where a room is
#: lit through a glass pane (98 %) the estimate is the image. There, 4 × 32 photons:
#: relMSE 2.8e-4 -> 1.7e-4, low-frequency error (σ 4 px) 5.5e-5 -> 2.8e-5, luminance
#: 0.993 -> 0.996 of path's (2 seeds, 320×240, 16 spp). The door-ajar proxy's rough
#: floor (22 %) stays at 32: 128 photons cost it 23 % more time for 3 % less relMSE.
CAUSTIC_SHARE_FOR_GROWTH = 0.25
CAUSTIC_LOOKUP_GROWTH = 4
#: ...and there, the caustic map's base radius is set over the surfaces' area, not
#: over its photons (``adapted_lookup_radius(by_area=True)``), with this many pyramid
#: levels (r / 2⁵ at the finest: its sharp parts as sharp as before). With a sun and a
#: sky through a glass pane, most caustic photons crowd into the sun's patch; over the
#: photons, the radius fitted the patch (4.5 cm), and the walls that the sky lights
#: through the pane read a few photons each: against the light traced through the pane
#: at 1500 wall points, relative RMS 98 %, 18 % of them 0. Over the area: 20 cm, 26 %,
#: none 0, the same mean (0.998 and 1.007 over 8 photon seeds, ±0.005). Elsewhere
#: (caustics under 25 % of the light) it cost 9-15 % of the render for no gain.
CAUSTIC_ROOM_PYRAMID_LEVELS = 6
#: The caustic pass emits at most this many paths per requested photon...
CAUSTIC_PATHS_PER_PHOTON = 20
#: ...and is dropped (records gather caustic light instead) below this yield (a map of
#: a few dozen photons, under an open sky, is no estimate)... At 0.25 a room lit by a
#: sky through a glass pane dropped its 18k photons (18 %), though all its light is
#: caustic there: gathered instead, its relMSE at 16 spp was 7.0e-3 (thin pane) and
#: 3.2e-2 (dielectric), 0.66× and 0.47× `path` at equal time; kept, 4.0e-4 and 1.2e-3
#: (10-12×), with luminance 0.980 and 0.977 of `path` against 0.991 and 0.996 (the
#: density estimates' bias at that sparseness: 0.988 with 93k photons).
CAUSTIC_MIN_YIELD = 0.1
#: A render for a denoiser (``aovs`` with the denoiser's guides, the final gather's or
#: adaptive camera path, no delta light) skips the caustic pass where the global map's
#: caustics stand out from the light around them by less than this
#: (irradiance.caustic_standout) and tracing finds them readily
#: (:data:`CAUSTIC_MAX_TRACED_MOMENT`): light that a lamp's glass spreads through a
#: room, which the camera paths and the records' gathers then trace. There the map's
#: pass and its lookups at every camera vertex cost more than it saves: the white room
#: (standout 0.11, traced moment 16-20) went 1.12-1.28x further per second after OIDN
#: without it (three runs), at the same brightness. `python benchmarks/caustic_map.py`;
#: docs/tuning.md, "The caustic map". Raw images keep the map: without it the lamp
#: room's raw relMSE was 13x, the torus's 500x (fireflies).
CAUSTIC_MIN_STANDOUT = 0.3
#: ...where the relative second moment of traced caustic samples (:func:`traced_caustics_moment`)
#: is at most this: above it, tracing finds them by rare bright samples, which a
#: denoiser partly removes, light and all. The lamp room (884-1 100) and the stairwell
#: kind (a lamp 4 cm wide over a glass drop: 2e4 to infinite, one ray in 10^5 met the
#: lamp) went 2.4-2.6x further per second after OIDN without their maps, but 1.1 % and
#: 1.5 % darker; the glossy Cornell box (standout 0.40) 180.
CAUSTIC_MAX_TRACED_MOMENT = 100.0
#: Cosine rays per caustic photon that measure it (:func:`traced_caustics_moment`).
CAUSTIC_PILOT_STRATA = (8, 8)
#: The pass stops as soon as it is clear that it will end under that yield
#: (photons.GIVE_UP_SIGMAS): the rest of the paths are not traced (1.9 M paths for
#: nothing in the material preview, 0.2 s). It stopped at half of it before, and a
#: Cornell box with a rough plastic floor traced all of its 2 M paths (0.25 s of a
#: 1.2 s render) for a map of under 10 % that it then dropped.
#: Default emitted-path bound per map, as a multiple of the requested photon count.
MAX_PATHS_PER_PHOTON = 100
#: ...and never less than this many paths (small requests in dim scenes).
MIN_MAX_PATHS = 1 << 22


@dataclass
class SceneInfo:
    """What the pipeline needs to know about a scene before tracing anything."""

    diagonal: float  #: length of the bounding-box diagonal (sets world-space scales)
    surface_area: float  #: sum of the shapes' surface areas (sets photon radii)
    emitters: int  #: number of emitters
    has_diffuse: bool  #: some BSDF has a diffuse lobe (else no cache, no global map)
    has_specular: bool  #: some BSDF has a delta or glossy lobe (else no caustic map)
    has_infinite_emitter: bool = False  #: an environment (envmap, constant) lights the scene
    has_delta_emitter: bool = False  #: a point, spot or directional light (no ray hits it)
    #: Some BSDF has a diffuse lobe under delta ones and no glossy lobe (a smooth
    #: plastic's coat): camera paths trace its reflection of the lights (coat rays).
    has_delta_coat: bool = False
    #: Some BSDF has a diffuse lobe beside a glossy one (a rough plastic): past a vertex
    #: that read the caustic map, camera paths sample its lobes apart.
    has_glossy_coat: bool = False
    #: Some BSDF has a diffuse lobe and transmits (principled glass, a principledthin
    #: leaf): gather rays that meet it go on through it (GatherSource.crossing).
    has_diffuse_transmission: bool = False
    #: Some BSDF ignores lobe masks (principled: bsdfs.ignores_lobe_masks): photons,
    #: gathers and camera paths test each vertex for it (bsdfs.lobes_separable).
    has_inseparable: bool = False
    #: Some BSDF's diffuse response leans off the shading normal (a normal map:
    #: bsdfs.lobes_lean): responses are evaluated at three azimuths per level, and
    #: camera paths read the cache about the normal the lobe leans to.
    has_leaning_lobes: bool = False

    @staticmethod
    def of(scene: mi.Scene) -> "SceneInfo":
        bbox = scene_bbox(scene)
        diagonal = float(dr.norm(bbox.extents())) if bbox.valid() else 0.0
        has_diffuse, has_specular, has_coat, has_glossy_coat = False, False, False, False
        has_diffuse_transmission = False
        bsdfs = scene_bsdfs(scene)
        for flags in [scene_flags(bsdf) for bsdf in bsdfs]:
            has_diffuse |= bool(flags & int(mi.BSDFFlags.Diffuse))
            has_specular |= bool(flags & (int(mi.BSDFFlags.Delta) | int(mi.BSDFFlags.Glossy)))
            has_coat |= bool(flags & int(mi.BSDFFlags.Diffuse)) and \
                bool(flags & int(mi.BSDFFlags.Delta)) and not flags & int(mi.BSDFFlags.Glossy)
            has_glossy_coat |= bool(glossy_beside_diffuse(flags))
            has_diffuse_transmission |= bool(flags & int(mi.BSDFFlags.Diffuse)) and \
                bool(flags & int(mi.BSDFFlags.Transmission))
        area = sum(_shape_area(shape) for shape in scene.shapes())
        if not math.isfinite(diagonal) or diagonal <= 0:
            diagonal = 1.0
        if not math.isfinite(area) or area <= 0:
            area = diagonal * diagonal
        infinite = any(mi.has_flag(e.flags(), mi.EmitterFlags.Infinite) for e in scene.emitters())
        delta = any(is_delta(e) for e in scene.emitters())
        return SceneInfo(diagonal, area, len(scene.emitters()), has_diffuse, has_specular, infinite,
                         delta, has_coat, has_glossy_coat, has_diffuse_transmission,
                         any(ignores_lobe_masks(bsdf) for bsdf in bsdfs),
                         any(lobes_lean(bsdf) for bsdf in bsdfs))


@dataclass
class PreparedScene:
    """Everything the render stage reads, built once per scene (view independent)."""

    #: (id of the scene object, Settings.key(), SceneFingerprint): what it was built for
    key: tuple
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
    #: Sky radiance × cosine tables for direct light (None: no environment emitter).
    sky: SkySampler | None = None
    #: Delta lights' caustic photons count with a kernel this many times narrower than
    #: the caustic radius (``estimate_irradiance``'s ``delta_scale``; see
    #: CAUSTIC_LOOKUP_GROWTH).
    caustic_delta_scale: float = 1.0

    @property
    def length_scale(self) -> float:
        return length_scale(self.info.diagonal, self.global_radius)

    @property
    def ray_offset(self) -> float:
        return ray_offset(self.info.diagonal, self.global_radius)


def length_scale(diagonal: float, global_radius: float) -> float:
    """World-space scale for ray offsets and the largest record: the diagonal, but no
    more than LENGTH_SCALE_LOOKUPS global lookup radii."""
    if global_radius > 0:
        return min(diagonal, LENGTH_SCALE_LOOKUPS * global_radius)
    return diagonal


def ray_offset(diagonal: float, global_radius: float) -> float:
    """How far rays start off the surfaces they leave: RAY_OFFSET_DIAGONAL of the
    :func:`length_scale`."""
    return RAY_OFFSET_DIAGONAL * length_scale(diagonal, global_radius)


# ----------------------------------------------------------------------------------------
# Progress
# ----------------------------------------------------------------------------------------
#: Seconds a stage runs before its progress bar appears: shorter stages show none.
PROGRESS_DELAY = 1.0


def interactive() -> bool:
    """Whether a person is watching: standard error is a terminal, or this runs in
    IPython or Jupyter (progress bars are then on by default)."""
    if "ipykernel" in sys.modules or hasattr(sys, "ps1"):
        return True
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


class Progress:
    """Progress bars of the stages (tqdm: a terminal or a Jupyter notebook), one per
    stage, shown once a stage has run for :data:`PROGRESS_DELAY` seconds. ``enabled``:
    True, False, or None for :func:`interactive`. Photon counts go to Mitsuba's log at
    Info level always."""

    def __init__(self, enabled: bool | None = None, stream=None, delay: float | None = None):
        self.enabled = interactive() if enabled is None else bool(enabled)
        self.stream = stream if stream is not None else sys.stderr
        self.delay = PROGRESS_DELAY if delay is None else delay
        self._bars: dict = {}

    def _bar(self, stage: str):
        from tqdm.auto import tqdm

        if stage not in self._bars:
            self._bars[stage] = tqdm(total=100, desc=stage, unit="%", file=self.stream, leave=True,
                                     delay=self.delay, mininterval=0.1, bar_format="{desc:22s} {percentage:3.0f}%|{bar}| "
                                     "{elapsed} {postfix}")
        return self._bars[stage]

    def update(self, stage: str, fraction: float, detail: str = ""):
        if not self.enabled:
            return
        bar = self._bar(stage)
        bar.set_postfix_str(detail, refresh=False)
        # (update() draws only once the bar's delay has passed, and at most every 0.1 s)
        bar.update(int(100 * min(max(float(fraction), 0.0), 1.0)) - bar.n)
        if fraction >= 1.0:
            bar.close()
            del self._bars[stage]

    def photons(self, kind, stored, target, emitted):
        """The photon tracer's callback."""
        mi.Log(mi.LogLevel.Info, f"pmic: {kind} photons {stored}/{target} ({emitted} paths emitted)")
        # Below 1: the stage's bar is finished by done(), once, with the stored count.
        self.update(f"photons ({kind})", min(stored / max(target, 1), 0.999), f"{emitted} paths")

    def done(self, stage: str, detail: str = ""):
        self.update(stage, 1.0, detail)


def check_environment_maps(scene: mi.Scene) -> None:
    """Refuse an environment map with NaN or Inf texels (before any photon is traced):
    Mitsuba builds its sampling distribution from the texels, and with a NaN or an Inf
    in it the directions it samples and the densities it reports are NaN or degenerate
    (``path`` renders NaN pixels; pmic's photons were all dropped, and with NaN its sky
    samples too: a silently dark image)."""
    for emitter in scene.emitters():
        if not mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite):
            continue
        params = mi.traverse(emitter)
        if "data" not in params.keys():
            continue
        data = np.asarray(params["data"])
        bad = ~np.isfinite(data.reshape(-1, data.shape[-1]) if data.ndim > 1 else data.reshape(-1, 1))
        bad_texels = int(bad.any(1).sum())
        if bad_texels:
            name = emitter.id() or emitter.class_name()
            raise ValueError(f"emitter {name!r} ({emitter.class_name()}): its image has {bad_texels} NaN/Inf "
                             f"texel{'s' if bad_texels > 1 else ''}; an environment map must hold finite radiance "
                             f"(replace them, e.g. with numpy.nan_to_num, before loading)")


def warn_of_media(scene: mi.Scene) -> None:
    """Warn once per scene that participating media are ignored: pmic renders surfaces
    only, as Mitsuba's ``path`` does (a shape's ``interior``/``exterior`` medium, a
    sensor's ``medium``); the image is that of the scene without them."""
    holders = [f"shape {shape.id() or shape.class_name()!r}" for shape in scene.shapes()
               if shape.interior_medium() is not None or shape.exterior_medium() is not None]
    holders += [f"sensor {sensor.id() or sensor.class_name()!r}" for sensor in scene.sensors()
                if any(key.startswith("medium.") for key in mi.traverse(sensor).keys())]
    if holders:
        more = f" and {len(holders) - 3} more" if len(holders) > 3 else ""
        warnings.warn(f"pmic renders surfaces only: the participating media of {', '.join(holders[:3])}{more} "
                      f"are ignored, as Mitsuba's path ignores them (render media with 'volpath')",
                      RuntimeWarning, stacklevel=4)


def warn_if_unlit(scene: mi.Scene) -> None:
    """Warn where a scene has no emitter: its image is black (as with ``path``), which a
    user would otherwise take for a failure of the integrator."""
    if not scene.emitters():
        warnings.warn("the scene has no emitter, so its image is black (with path too): add a light, "
                      "e.g. an 'area' emitter on a shape, an 'envmap' or a 'constant' environment",
                      RuntimeWarning, stacklevel=4)


# ----------------------------------------------------------------------------------------
# The pipeline
# ----------------------------------------------------------------------------------------
def prepare(scene: mi.Scene, settings: Settings, key: tuple | None = None,
            progress: Progress | None = None) -> PreparedScene:
    """Stages 1-3 for ``scene``: returns the whole :class:`PreparedScene` (nothing is
    published before the last stage has finished)."""
    progress = progress or Progress()
    if key is None:
        key = (id(scene), settings.key(), scene_fingerprint(scene))
    info = SceneInfo.of(scene)
    check_against_scene(settings, info.surface_area, info.diagonal)
    check_environment_maps(scene)
    warn_of_media(scene)
    warn_if_unlit(scene)
    stats = {}
    need_global, need_caustic, skipped = plan_passes(info, settings)

    t0 = time.perf_counter()
    global_map, caustic_map = trace_maps(scene, settings, info, need_global, need_caustic, skipped,
                                         progress, stats)
    dr.sync_thread()
    stats["time_photons"] = time.perf_counter() - t0
    stats["photons_global"] = global_map.count
    stats["photons_caustic"] = caustic_map.count
    # (of which the global pass's: merge_caustic_photons numbers their paths after the
    # caustic pass's)
    stats["photons_caustic_from_global"] = int(dr.count(caustic_map.path >= caustic_map.paths_emitted)[0]) \
        if caustic_map.count else 0
    stats["paths_emitted"] = global_map.paths_emitted + caustic_map.paths_emitted
    stats["paths_emitted_caustic"] = caustic_map.paths_emitted

    t0 = time.perf_counter()
    lookups = precompute(scene, settings, info, global_map, caustic_map, skipped)
    dr.sync_thread()
    source = lookups["gather_source"]
    progress.done("precomputed irradiance",
                  f"at {source.photons.count if source is not None else 0} of "
                  f"{lookups['global_map'].count} photons")
    stats["time_precompute"] = time.perf_counter() - t0
    stats["lookup_radius"] = lookups["global_radius"]
    stats["caustic_radius"] = lookups["caustic_radius"]

    t0 = time.perf_counter()
    prepared = PreparedScene(key=key, info=info, index=None,
                             skipped=skipped, stats=stats, sky=SkySampler.build(scene), **lookups)
    index, cache_stats = build_cache(scene, settings, prepared, progress)
    dr.sync_thread()
    stats.update(cache_stats)
    stats["time_cache"] = time.perf_counter() - t0
    stats["skipped"] = list(skipped)
    for reason in skipped:
        log.info("pmic: skipped %s", reason)
    prepared.index = index
    return prepared


def pack_for_queries(prepared: "PreparedScene") -> "PreparedScene":
    """Lay out the photon maps, their grids and the gather source's grids entry by
    entry for the queries (:meth:`PhotonMap.pack`, :meth:`PointGridPyramid.pack`,
    :meth:`GatherSource.pack`), as a build does; for a prepared scene read from a cache
    file, which does not hold these derived arrays. The records are packed at each
    render (:meth:`RecordIndex.pack`). Returns ``prepared``."""
    for photons, grid in ((prepared.global_map, prepared.global_grid),
                          (prepared.caustic_map, prepared.caustic_grid)):
        if photons.count and grid is not None:
            photons.pack()
            grid.pack()
    if prepared.gather_source is not None:
        prepared.gather_source.pack()
    return prepared


def plan_passes(info: SceneInfo, settings: Settings):
    """Which photon maps this scene needs: ``(need_global, need_caustic, skipped)``,
    each skip with its reason."""
    skipped = []
    need_global = need_caustic = True
    if settings.max_depth != -1 and settings.max_depth <= 2:
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
    if need_caustic and settings.max_depth != -1 and settings.max_depth < 3:
        # light -> specular -> diffuse -> camera is 3 segments.
        skipped.append("caustic map: max_depth < 3 leaves no room for a caustic path")
        need_caustic = False
    if settings.global_photons == 0 and need_global:
        skipped.append("global map: global_photons = 0")
        need_global = False
    if settings.caustic_photons == 0 and need_caustic:
        skipped.append("caustic map: caustic_photons = 0")
        need_caustic = False
    return need_global, need_caustic, skipped


def max_paths(settings: Settings, photons: int) -> int:
    """Emitted-path bound of a map of ``photons`` photons."""
    if settings.max_photon_paths:
        return settings.max_photon_paths
    return max(MAX_PATHS_PER_PHOTON * photons, MIN_MAX_PATHS)


def leaves_caustics_to_denoiser(settings: Settings, info: SceneInfo) -> bool:
    """Whether this render may skip its caustic pass for a denoiser where caustics do not
    stand out (:data:`CAUSTIC_MIN_STANDOUT`): an image meant for one (the denoiser's
    guides), a camera path that traces its first bounce (the final gather's, the
    adaptive estimator's), no delta light."""
    return settings.denoiser_guides and settings.final_gather_camera and not info.has_delta_emitter


def caustics_traced_for_denoiser(scene, settings: Settings, info: SceneInfo, global_map: PhotonMap,
                                 stats: dict) -> str:
    """Why a render for a denoiser traces the caustics of this global map instead of
    mapping them ('' where it maps them): they stand out little from the light around
    them (:data:`CAUSTIC_MIN_STANDOUT`) and tracing finds them readily
    (:data:`CAUSTIC_MAX_TRACED_MOMENT`). Records the figures in ``stats``."""
    radius = lookup_radius(info.surface_area, global_map.count, settings.lookup_size)
    standout = stats["caustic_standout"] = caustic_standout(global_map, radius, settings.lookup_size)
    if standout >= CAUSTIC_MIN_STANDOUT:
        return ""
    moment = stats["caustic_traced_moment"] = traced_caustics_moment(
        scene, settings, info, global_map, ray_offset(info.diagonal, radius))
    if not moment <= CAUSTIC_MAX_TRACED_MOMENT:
        return ""
    stats["caustics_left_to_denoiser"] = True
    return (f"caustic map: for a denoiser, caustics that stand out {standout:.2f} from the light "
            f"around them (under {CAUSTIC_MIN_STANDOUT}) and that tracing finds readily (relative "
            f"second moment {moment:.0f}, at most {CAUSTIC_MAX_TRACED_MOMENT:.0f}) are traced instead")


def with_scene_bsdfs(source: GatherSource, info: SceneInfo, scene: mi.Scene) -> GatherSource:
    """``source`` told what the scene's BSDFs need of gather rays (those that transmit,
    ignore lobe masks, lean, or list a diffuse lobe they do not have); returns it."""
    source.crossing = info.has_diffuse_transmission
    source.inseparable = info.has_inseparable
    source.leaning = info.has_leaning_lobes
    source.diffuse_free = scene_diffuse_free(scene)
    return source


def traced_caustics_moment(scene, settings: Settings, info: SceneInfo, global_map: PhotonMap,
                           offset: float) -> float:
    """The relative second moment, E[v²] / E[v]², of the caustic light v that one gather
    ray finds by tracing (emission met after delta and glossy bounces, as the records'
    gathers and the camera paths count it without a caustic map), over
    :data:`CAUSTIC_PILOT_STRATA` cosine rays from each photon of the global map's
    :func:`~pmic_integrator.irradiance.caustic_sample`: 1 where every ray finds the
    same light, large where a few find it all (a small lamp seen through glass); +inf
    where none does."""
    chosen = caustic_sample(global_map)
    if dr.width(chosen) == 0:
        return math.inf
    source = with_scene_bsdfs(GatherSource.build(PhotonMap.empty(), 1.0), info, scene)  # (only traced light)
    source.caustics_by_gathering = True
    ray, _, _, _, _, rng = cache_mod._stratified_rays(
        dr.gather(mi.Point3f, global_map.position, chosen), dr.gather(mi.Vector3f, global_map.normal, chosen),
        CAUSTIC_PILOT_STRATA, settings.seed, streams.CAUSTIC_PILOT, offset)
    if mi.is_spectral:
        ray.wavelengths, weight = spectra.sample_wavelengths(rng.next_float32())
        spectra.prepare_basis()  # (the walk's loop reads it; the first call may come here)
    radiance, _ = trace_gather_rays(scene, source, ray, rng, mi.Bool(True))
    if mi.is_spectral:
        radiance = spectra.to_rgb(radiance * weight, ray.wavelengths)
    value = mi.luminance(mi.Color3f(radiance))
    dr.eval(value)  # (then sums of it: a mean's width would be written into the walk's kernel)
    total, squares = dr.sum(value)[0], dr.sum(dr.square(value))[0]
    if not (total > 0 and math.isfinite(squares)):
        return math.inf
    return float(squares * dr.width(value) / (total * total))


def trace_maps(scene, settings: Settings, info: SceneInfo, need_global: bool, need_caustic: bool,
               skipped: list, progress: Progress, stats: dict | None = None):
    """Stage 1: the global and caustic photon maps (empty where not needed). ``stats``
    (if given) records the caustic standout where it was measured
    (:func:`leaves_caustics_to_denoiser`)."""
    global_map = caustic_map = PhotonMap.empty()
    if need_global:
        global_map = trace_photons(scene, GLOBAL, settings.global_photons, settings.max_depth,
                                   settings.seed, max_paths(settings, settings.global_photons),
                                   progress.photons, inseparable=info.has_inseparable,
                                   # Not with a caustic pass to come: the global pass's
                                   # caustic photons join its map (merge_caustic_photons),
                                   # and weighted ones made a room lit through a glass
                                   # pane noisier (relMSE +10 %, luminance 0.984-0.998
                                   # over four seeds against 0.995-0.999).
                                   guide_emission=not need_caustic)
        progress.done(f"photons ({GLOBAL})", f"{global_map.count} stored")
    if need_caustic and need_global and global_map.count == 0:
        # Every caustic photon would also have been stored in the global map.
        skipped.append("caustic map: no global photon reached a diffuse surface")
        need_caustic = False
    if need_caustic and need_global and leaves_caustics_to_denoiser(settings, info):
        reason = caustics_traced_for_denoiser(scene, settings, info, global_map,
                                              {} if stats is None else stats)
        if reason:
            skipped.append(reason)
            need_caustic = False
    if need_caustic:
        paths = min(max_paths(settings, settings.caustic_photons),
                    CAUSTIC_PATHS_PER_PHOTON * settings.caustic_photons)
        # Rare caustic paths (an environment light and a small glossy object): a map of
        # a few thousand photons costs seconds and gives blotches; records gather those
        # paths instead (see GatherSource). Not with a point, spot or directional
        # light: no gather ray can hit those, and their caustics would be lost (a sun
        # through a window onto glass).
        droppable = not info.has_delta_emitter
        minimum = int(CAUSTIC_MIN_YIELD * settings.caustic_photons)
        caustic_map = trace_photons(scene, CAUSTIC, settings.caustic_photons, settings.max_depth,
                                    settings.seed, paths, progress.photons, warn=False,
                                    give_up_below=minimum if droppable else 0,
                                    inseparable=info.has_inseparable)
        progress.done(f"photons ({CAUSTIC})", f"{caustic_map.count} stored")
        if caustic_map.count < minimum and droppable:
            skipped.append(f"caustic map: {caustic_map.count} of {settings.caustic_photons} "
                           f"photons after {caustic_map.paths_emitted} of {paths} paths (under "
                           f"{minimum} expected); gather rays count caustic light instead")
            paths_traced = caustic_map.paths_emitted
            caustic_map = PhotonMap.empty()
            caustic_map.paths_emitted = paths_traced  # (stats: the work done)
        else:
            caustic_map = merge_caustic_photons(caustic_map, global_map)
    global_map.shared_path = caustic_map.shared_path = None  # (only the merge reads them)
    return global_map, caustic_map


def caustic_share(global_map: PhotonMap, caustic_map: PhotonMap) -> float:
    """Caustics' share of the light that reaches surfaces first: the caustic photons'
    power over theirs plus the global map's direct photons' (depth 1; both maps' powers
    are per emitted path of their own pass). 0 without a caustic map."""
    if not (caustic_map.count and global_map.count):
        return 0.0
    caustic = float(dr.sum(mi.luminance(caustic_map.power))[0])
    direct = float(dr.sum(dr.select(global_map.depth == 1, mi.luminance(global_map.power), 0.0))[0])
    share = caustic / (caustic + direct) if caustic + direct > 0 else 0.0
    return share if math.isfinite(share) else 0.0


def caustic_lookup_size(lookup_size: int, share: float) -> int:
    """Photons per caustic estimate where caustics have ``share`` of the first-bounce
    light (:func:`caustic_share`; :data:`CAUSTIC_LOOKUP_GROWTH`)."""
    growth = min(max(share / CAUSTIC_SHARE_FOR_GROWTH, 1.0), CAUSTIC_LOOKUP_GROWTH)
    return max(1, int(lookup_size * CAUSTIC_LOOKUP_FRACTION * growth))


def _in_focus(scene: mi.Scene, info: SceneInfo, positions: mi.Point3f) -> mi.Point3f:
    """Those of ``positions`` inside the focus of the scene's skies and suns
    (emission.focus_box), or all of them where there is none (or none inside): the
    sparser photons of the focus's rings (emission.focus_rings), the sparsest 30 %
    otherwise, must not set the lookup radius (irradiance.DENSITY_QUANTILE): records are
    at least a lookup radius wide, and the building's would grow to a room's size."""
    focus = focus_box(scene) if info.has_infinite_emitter and dr.width(positions.x) else None
    if focus is None:
        return positions
    low, high = focus.min, focus.max
    inside = dr.compress((positions.x >= low.x) & (positions.x <= high.x) & (positions.y >= low.y) &
                         (positions.y <= high.y) & (positions.z >= low.z) & (positions.z <= high.z))
    return dr.gather(mi.Point3f, positions, inside) if dr.width(inside) else positions


def precompute(scene: mi.Scene, settings: Settings, info: SceneInfo, global_map: PhotonMap,
               caustic_map: PhotonMap, skipped: list) -> dict:
    """Stage 2: lookup radii, hash grids, and irradiance precomputed at the global
    photons (what gather rays read). Returns the PreparedScene fields it fills."""
    global_radius = settings.lookup_radius or adapted_lookup_radius(
        _in_focus(scene, info, global_map.position),
        lookup_radius(info.surface_area, global_map.count, settings.lookup_size), settings.lookup_size)
    share = caustic_share(global_map, caustic_map)
    caustic_size = caustic_lookup_size(settings.lookup_size, share)
    # Where caustics light the room (CAUSTIC_ROOM_PYRAMID_LEVELS).
    lit_by_caustics = share >= CAUSTIC_SHARE_FOR_GROWTH
    # A delta light's caustic (a sun's patch through a window) keeps the base count of
    # photons per estimate, and so its sharp edge: its photons' kernel is narrower by
    # the square root of the growth.
    from_delta = caustic_map.count and caustic_map.delta_light is not None and \
        bool(dr.any(caustic_map.delta_light)[0])
    delta_scale = min(1.0, math.sqrt(settings.lookup_size * CAUSTIC_LOOKUP_FRACTION / caustic_size)) \
        if from_delta else 1.0
    caustic_radius = adapted_lookup_radius(
        caustic_map.position, lookup_radius(info.surface_area, caustic_map.count, caustic_size),
        caustic_size, by_area=lit_by_caustics)
    global_map, global_grid = sort_into_grid(global_map, global_radius, settings.lookup_size)
    caustic_map, caustic_grid = sort_into_grid(caustic_map, caustic_radius, caustic_size,
                                               CAUSTIC_ROOM_PYRAMID_LEVELS if lit_by_caustics else None)
    gather_source = None
    if global_map.count and settings.method == "photon_map" and not settings.final_gather:
        skipped.append("precomputed irradiance: photon_map without final gathering never reads it")
    elif global_map.count:
        # A photon of k interactions read by a gather ray completes a camera path of
        # records_read_depth + 2 + k segments: at most max_depth.
        depth_limit = None if not settings.bounded else \
            settings.max_depth - 2 - settings.records_read_depth
        # Gather rays read this copy (a fraction of the photons, see precompute_irradiance).
        # Gather rays that bounce on at a near hit read its caustics from here
        # (unbounded max_depth only: see GatherSource.near_hit_distance).
        caustics = (caustic_map, caustic_grid, caustic_radius, delta_scale) \
            if depth_limit is None and caustic_map.count else None
        gather_source = GatherSource.build(
            precompute_irradiance(global_map, global_radius, settings.lookup_size, depth_limit,
                                  caustics,
                                  other_paths=global_map.bounced_share() >= OTHER_PATHS_MIN_BOUNCED,
                                  surface=(scene, settings.seed, ray_offset(info.diagonal, global_radius))
                                  if SURFACE_PROBED_ESTIMATES else None),
            global_radius)
        gather_source = with_scene_bsdfs(gather_source, info, scene)
        gather_source.caustics_by_gathering = caustic_map.count == 0
        if depth_limit is None:
            gather_source.near_hit_distance = NEAR_HIT_LOOKUPS * global_radius
        if gather_source.photons.count == 0:
            # A map of a handful of photons (a tiny max_photon_paths) can leave a half
            # empty: nothing to gather from, so no cache.
            skipped.append("cache: too few global photons to precompute irradiance")
            global_map, global_grid, gather_source = PhotonMap.empty(), None, None
    return dict(global_map=global_map, global_grid=global_grid, caustic_map=caustic_map,
                caustic_grid=caustic_grid, global_radius=global_radius,
                caustic_radius=caustic_radius, caustic_delta_scale=delta_scale,
                gather_source=gather_source)


def build_cache(scene, settings: Settings, prepared: PreparedScene, progress: Progress):
    """Stage 3: records placed by walking the global photons (Fig. 2), then, for the
    first-hit estimator, bounded and completed by surface probes; for the final
    gather, each record's direct irradiance. Returns ``(index, stats)``."""
    stats = {"records": 0, "records_fallback": 0, "records_probes": 0, "placement_rounds": 0}
    if settings.method != "pmic":
        return None, stats
    photons = prepared.global_map
    if not photons.count:
        prepared.skipped.append("cache: no global photons")
        return None, stats
    builder = CacheBuilder(scene, settings, prepared)
    progress.update("cache", 0.05, "placing records at the photons")
    position, normal = builder.placement_photons()
    probes = not settings.final_gather_camera
    # The records are placed first, then gathered (with probes to come, after the
    # probes: complete_with_probes), and their visibility settled.
    index, rounds = builder.build_records(position, normal, None, settle=False, gather=False)
    stats["placement_rounds"] = rounds
    rounds_of_rays = "one"
    if not probes:
        rounds_of_rays = builder.choose_gather_rounds(index.records.count)
        progress.update("cache", 0.3, f"{index.records.count} records: gathering")
        index, more = builder.settle(builder.gather_placed(index), position, normal)
        stats["placement_rounds"] += more
    if probes:
        progress.update("cache", 0.5, f"{index.records.count} records: surface probes")
        before = index.records.count
        index = builder.complete_with_probes(index)
        stats["records_probes"] = index.records.count - before
    index = index.for_lookup()
    if settings.final_gather_camera:
        # What a gather hit reflects is all of its light: records keep their direct
        # irradiance too (but for delta lights', below), so the camera path needs no
        # other shadow rays there. Gather hits closer than a record radius are traced
        # instead: no probes are needed.
        progress.update("cache", 0.7, f"{index.records.count} records: direct light")
        # Delta lights (a sun, a spot) are kept apart: interpolated across their sharp
        # shadows they lit the floor round a sunlit patch 11-15 % too bright (over the
        # floor, by where photons put records: ±1.5 % on a whole room from one photon
        # seed to the next); the camera path samples them where it reads the cache.
        (soft, soft_rotation), (delta, delta_rotation) = cache_mod.direct_irradiance_parts(
            scene, index.records.position, index.records.normal, cache_mod.RECORD_DIRECT_SAMPLES,
            settings.seed, prepared.ray_offset, shading_normal=index.records.shading_normal,
            sky=prepared.sky, guides=index)
        if prepared.info.has_delta_emitter:
            index.direct, index.direct_all = soft, soft + delta
            index.direct_rotation = soft_rotation
            dr.eval(index.direct_all)
        else:
            index.direct = soft + delta
            index.direct_rotation = soft_rotation + delta_rotation
        if not settings.bounded and prepared.caustic_map.count:
            # And their caustics, so that camera paths read the caustic map at their
            # traced vertex only, not again where they read the cache: every diffuse
            # vertex read it before, and where coats of rough plastic spread caustic
            # photons over a whole room those reads were 14 of 22 s of the render.
            # Behind one diffuse bounce the records' smoothing of a caustic is not
            # seen. (With a bounded max_depth the reads stay per vertex, by depth.)
            index.direct = index.direct + estimate_irradiance(
                prepared.caustic_map, prepared.caustic_grid, index.records.position,
                index.records.normal, prepared.caustic_radius, delta_scale=prepared.caustic_delta_scale)
            index.holds_caustics = True
        dr.eval(index.direct, index.direct_rotation)
        if rounds_of_rays == "open" and index.guiding_pays():
            progress.update("cache", 0.8, f"{index.records.count} records: the rest of their gathers")
            index = builder.complete_gathers(index)
    stats["records"] = index.records.count
    built = replace(prepared, index=index)
    # The render's per-cache decisions (guiding pays, a sky is seen, first reads may
    # pay: reads back from the device) made here, once: renders then start without
    # a host read (RecordIndex.remembered; benchmarks/kernel_report.py).
    from .render.config import PathConfig

    ready_for_first_reads(scene, settings, built, progress)
    if settings.final_gather_camera:
        # Records far brighter than the rest (a lamp's shade lit from inside) become
        # spherical lights that continuation rays are drawn towards.
        index.lights = RecordLights.select(index.records.position,
                                           index.records.radius * index.max_error,
                                           index.records.irradiance + index.light_direct)
    stats["records_partial"] = 0 if index.records.partial is None else \
        int(dr.count(index.records.partial)[0])
    PathConfig.of(settings, built, own_render=True)
    progress.done("cache", f"{index.records.count} records")
    return index, stats


def first_round_rays(gather_rays: int) -> int:
    """The rays of a record's first gather round (:data:`FIRST_GATHER_SHARE`)."""
    return max(FIRST_GATHER_MIN_RAYS, int(FIRST_GATHER_SHARE * gather_rays))


def ready_for_first_reads(scene, settings: Settings, prepared: PreparedScene, progress=None) -> None:
    """Survey which records the adaptive estimator may read at first vertices
    (:func:`~pmic_integrator.render.reads.survey_first_reads`); where it may read
    some, records that gathered only their first round (:data:`GATHER_BUDGET_RAYS`)
    gather the rest: read at the first hit, a record's own noise is seen. Every such
    record, not only those the survey passed: a first read interpolates all the
    records that reach it (completing only those, Sponza's relMSE rose 1.1e-2 ->
    1.4e-2). After a cache is built or read from a file."""
    from .render.reads import any_first_reads, survey_first_reads

    index = prepared.index
    survey_first_reads(scene, settings, prepared)
    if index is None or index.records.partial is None or not any_first_reads(index):
        return
    owed = index.records.partial
    if not dr.any(owed)[0]:
        return
    if progress is not None:
        progress.update("cache", 0.9, f"{index.records.count} records read at first hits: "
                        "the rest of their gathers")
    CacheBuilder(scene, settings, prepared).complete_gathers(index, owed)


class CacheBuilder:
    """Record placement and computation for one scene (stage 3), shared by the photon
    walk, the surface probes and the camera-seeded classic cache."""

    def __init__(self, scene: mi.Scene, settings: Settings, prepared: PreparedScene,
                 strata: tuple[int, int] | None = None):
        self.scene = scene
        self.settings = settings
        self.prepared = prepared
        self.offset = prepared.ray_offset
        #: M×N strata of the records' gathers (default: the settings' gather_rays).
        self.strata = strata or settings.gather_strata
        #: The records gathered are marked as owing the rest of their rays
        #: (CacheRecords.partial; :meth:`choose_gather_rounds`).
        self.partial = False

    def index(self, records: CacheRecords) -> RecordIndex:
        """The coverage index of ``records`` used while building (its
        :meth:`~RecordIndex.for_lookup` is what renders read), with visibility tests
        for records that reach past a surface."""
        return RecordIndex.build(records, self.settings.max_error, self.scene,
                                 VISIBILITY_LIFT * self.prepared.global_radius, lookup=False)

    def radius_bounds(self):
        prepared = self.prepared
        r_max = R_MAX_DIAGONAL * prepared.length_scale
        r_min = min(MIN_REACH_LOOKUPS * prepared.global_radius / self.settings.max_error, r_max) \
            if prepared.global_radius > 0 else 1e-3 * r_max
        return r_min, r_max

    def placement_photons(self):
        """Positions and normals of the global photons that records must cover: all
        of them, or every k-th, at most ``MAX_PLACEMENT_PHOTONS``."""
        photons = self.prepared.global_map
        if photons.count <= MAX_PLACEMENT_PHOTONS:
            return photons.position, photons.normal
        chosen = every_nth(photons.count, -(-photons.count // MAX_PLACEMENT_PHOTONS))
        return (dr.gather(mi.Point3f, photons.position, chosen),
                dr.gather(mi.Vector3f, photons.normal, chosen))

    def pilot_distance(self, p, n, seed_offset: int):
        """The harmonic mean distance of a cheap pilot gather at each (p, n)."""
        pilot, _ = cache_mod.harmonic_mean_distance(self.scene, p, n, cache_mod.PILOT_STRATA,
                                                    self.settings.seed + seed_offset, self.offset)
        return pilot

    def pilot_radius(self, p, n, seed_offset: int):
        """R from a cheap pilot gather, clamped to the world-space bounds."""
        r_min, r_max = self.radius_bounds()
        return dr.clip(self.pilot_distance(p, n, seed_offset), opaque_float(r_min),
                       opaque_float(r_max))

    def _place(self, cand_p, cand_n, existing: RecordIndex | None):
        """Pilot radii, then placement (Fig. 2); returns the chosen (p, n, R), rounds."""
        r_max = self.radius_bounds()[1]
        pilot = self.pilot_radius(cand_p, cand_n, streams.PLACEMENT_PILOT)
        step = max(CLAMP_STEP_LOOKUPS * self.prepared.global_radius, r_max / CLAMP_ITERATIONS)
        pilot = cache_mod.clamp_to_neighbours(cand_p, cand_n, pilot, step,
                                              int(math.ceil(r_max / step)))
        dr.eval(pilot)
        selected, rounds = cache_mod.place_records(cand_p, cand_n, pilot, self.settings.max_error,
                                                   existing)
        return (dr.gather(mi.Point3f, cand_p, selected), dr.gather(mi.Vector3f, cand_n, selected),
                dr.gather(mi.Float, pilot, selected)), rounds

    def build_records(self, cand_p, cand_n, existing: RecordIndex | None, settle: bool = True,
                      gather: bool = True):
        """Place records among candidates (Fig. 2), compute them, return the index and
        the number of placement rounds. Without ``gather`` the new records are placed
        only (:meth:`CacheRecords.geometry_only`; :meth:`gather_placed` computes them
        later, all in one gather).

        With many candidates the walk visits an evenly spread subset first
        (``PLACEMENT_SUBSET`` of them) and then only the candidates that the subset's
        records leave uncovered: the same guarantee (every candidate covered), but
        pilot rays only where they can matter, so the cost no longer grows with the
        photon count.
        """
        count = dr.width(cand_p.x)
        rounds = 0
        remaining_p, remaining_n = cand_p, cand_n
        prior = existing  # the records placed so far, as an index (None: none)
        new_p, new_n, new_r = [], [], []
        if count > PLACEMENT_SUBSET:
            subset = every_nth(count, -(-count // PLACEMENT_SUBSET))
            (p, n, r), k = self._place(dr.gather(mi.Point3f, cand_p, subset),
                                       dr.gather(mi.Vector3f, cand_n, subset), existing)
            rounds += k
            new_p.append(p), new_n.append(n), new_r.append(r)
            placed = CacheRecords.geometry_only(p, n, r)
            prior = self.index(placed if existing is None else existing.records.extend(placed))
            uncovered = dr.compress(~prior.covered(cand_p, cand_n))
            remaining_p = dr.gather(mi.Point3f, cand_p, uncovered)
            remaining_n = dr.gather(mi.Vector3f, cand_n, uncovered)
        if dr.width(remaining_p.x):
            (p, n, r), k = self._place(remaining_p, remaining_n, prior)
            rounds += k
            new_p.append(p), new_n.append(n), new_r.append(r)
        p = concat(new_p, mi.Point3f)
        n = concat(new_n, mi.Vector3f)
        r = concat(new_r, mi.Float)
        before = existing.records.count if existing is not None else 0
        records = self._gather(p, n, r, before) if gather else CacheRecords.geometry_only(p, n, r)
        all_records = existing.records.extend(records) if existing is not None else records
        index = self.index(all_records)
        if settle:
            index, more = self.settle(index, cand_p, cand_n)
            rounds += more
        return index, rounds

    def _gather(self, p, n, r, first: int) -> CacheRecords:
        """The records at (p, n) of radius r, gathered; ``first``: the index of the
        first of them in the cache (their random streams follow it)."""
        records = cache_mod.compute_records(self.scene, self.prepared.gather_source, p, n, r,
                                            self.strata, self.settings.seed + streams.RECORDS + first,
                                            self.offset, self.sky_openness)
        if self.partial:
            records.partial = dr.full(mi.Bool, True, records.count)
        return records

    def gather_placed(self, index: RecordIndex) -> RecordIndex:
        """``index`` with every record gathered (placed with ``gather=False``): one
        gather for all, at their final radii."""
        records = index.records
        return self.index(self._gather(records.position, records.normal, records.radius, 0))

    @property
    def sky_openness(self) -> float:
        """What the records' gathers count as seeing the sky (:func:`cache.escaped_sky`)."""
        sky = self.prepared.sky
        return cache_mod.EVEN_SKY_OPENNESS if sky is not None and sky.even \
            else cache_mod.SKY_GUIDE_OPENNESS

    def choose_gather_rounds(self, records: int) -> str:
        """Whether ``records`` records gather all of their rays at once (``"one"``), or
        a first round (:data:`FIRST_GATHER_SHARE`) and the rest where it is needed:
        all of them where bounced light matters (``"open"``:
        :data:`FIRST_GATHER_MAX_BOUNCED`), none in a large room that no render of these
        settings reads at first hits (``"budget"``: :data:`GATHER_BUDGET_RAYS`; a file
        of such a cache read by one that does: :func:`ready_for_first_reads`). Sets
        the builder's strata."""
        from .render.config import may_read_first_hits  # (the render builds on this module)

        rays = self.settings.gather_rays
        first_rays = first_round_rays(rays)
        rounds = "one"
        if first_rays < rays:
            if self.prepared.global_map.bounced_share() < FIRST_GATHER_MAX_BOUNCED:
                rounds = "open"
            elif records * rays > GATHER_BUDGET_RAYS and \
                    not may_read_first_hits(self.settings, self.prepared.info):
                rounds = "budget"
        if rounds != "one":
            self.strata = rays_strata(first_rays)
            self.partial = rounds == "budget"
        return rounds

    def complete_gathers(self, index: RecordIndex, which: mi.Bool = None) -> RecordIndex:
        """Gather the rest of the settings' ``gather_rays`` at every record of
        ``index`` (built with fewer: the first round's, :meth:`choose_gather_rounds`),
        or at those of ``which``, and blend them in (:meth:`CacheRecords.blend`).
        The same records; returns ``index``."""
        records = index.records
        first = math.prod(rays_strata(first_round_rays(self.settings.gather_rays)))
        rest = rays_strata(self.settings.gather_rays - first)
        lanes = None if which is None else dr.compress(which)
        some = records if lanes is None else records.take(lanes)
        more = cache_mod.compute_records(self.scene, self.prepared.gather_source, some.position,
                                         some.normal, some.radius, rest,
                                         self.settings.seed + streams.RECORDS, self.offset,
                                         self.sky_openness, stream=streams.RECORD_GATHER_REST)
        some = some.blend(more, rest[0] * rest[1] / (first + rest[0] * rest[1]))
        if some.partial is not None:
            some.partial = dr.zeros(mi.Bool, some.count)
        index.records = some if lanes is None else records.put(lanes, some)
        dr.eval(index.records)
        return index

    def settle(self, index: RecordIndex, cand_p, cand_n):
        """Records for the candidates that ``index`` leaves uncovered once visibility
        is known; returns the index and the placement rounds.

        Placement tests coverage without visibility (the records' gathers, which tell
        which records reach past a surface, come after it): candidates covered only by
        records they cannot see get records of their own. A record covers its own
        candidate, so one pass settles it. Callers that build in several steps settle
        once, at the end, over all their candidates: each step's few lost candidates
        would otherwise cost a placement and a gather of their own."""
        lost = dr.compress(~index.covered(cand_p, cand_n))
        if not dr.width(lost):
            return index, 0
        return self.build_records(dr.gather(mi.Point3f, cand_p, lost),
                                  dr.gather(mi.Vector3f, cand_n, lost), index, settle=False)

    def complete_with_probes(self, index: RecordIndex) -> RecordIndex:
        """Surface probes (first-hit estimator): records may not reach a probe further
        than its own pilot radius plus their distance (neighbour clamping against the
        surfaces photons barely reach: the gap between a light and the ceiling), and
        probes that no record is near get records (surfaces no photon reached). Every
        photon stays covered. View independent: the same for every camera.

        ``index`` may be unsettled and ungathered (:meth:`settle`, :meth:`gather_placed`);
        what this returns is both."""
        photons = self.prepared.global_map
        photon_p, photon_n = self.placement_photons()
        probe_p, probe_n = surface_probes(self.scene, _probe_count(photons.count),
                                          self.settings.seed)
        # Only probes among the photons: a vast ground plane far from the light would
        # otherwise fill with records of nearly nothing (the photon map covers it).
        if dr.width(probe_p.x):
            lo, hi = _bounds(photons.position, 2.0 * self.prepared.global_radius)
            inside = dr.compress(dr.all((probe_p >= lo) & (probe_p <= hi)))
            probe_p = dr.gather(mi.Point3f, probe_p, inside)
            probe_n = dr.gather(mi.Vector3f, probe_n, inside)
        if not dr.width(probe_p.x):
            return self.settle(self.gather_placed(index), photon_p, photon_n)[0]
        clamp = every_nth(dr.width(probe_p.x), PROBE_CLAMP_STRIDE)
        clamp_p = dr.gather(mi.Point3f, probe_p, clamp)
        clamp_n = dr.gather(mi.Vector3f, probe_n, clamp)
        raw = self.pilot_distance(clamp_p, clamp_n, streams.PROBE_PILOT)
        # Probes that no camera can see (a floor under a block resting on it: every
        # pilot ray hits within a hair) must not shrink the records beside them.
        seen = dr.compress(raw > opaque_float(ENCLOSED_OFFSETS * self.offset))
        r_min, r_max = self.radius_bounds()
        clamp_p, clamp_n = dr.gather(mi.Point3f, clamp_p, seen), dr.gather(mi.Vector3f, clamp_n, seen)
        clamp_r = dr.clip(dr.gather(mi.Float, raw, seen), opaque_float(PROBE_FLOOR * r_min), opaque_float(r_max))
        pending_p, pending_n = [], []  # photons the last pass uncovered
        for clamp_pass in range(PROBE_CLAMP_PASSES):
            shrunk = cache_mod.clamp_records_to_points(
                index, clamp_p, clamp_n, clamp_r, self.scene,
                VISIBILITY_LIFT * self.prepared.global_radius)
            if shrunk is None:
                break
            records = index.records
            # Only photons within the old reach of a shrunk record can have lost cover.
            was = dr.compress(shrunk < records.radius)
            old_reach = BallGrid.build(dr.gather(mi.Point3f, records.position, was),
                                       dr.gather(mi.Float, records.radius, was) * self.settings.max_error)
            near = dr.compress(_inside_any(old_reach, photon_p))
            records.radius = shrunk
            index = self.index(records)
            # (Tested on those photons only, gathered: masked, the test cost as much
            # for every photon as for the few near ones.)
            lost = dr.gather(mi.UInt32, near, dr.compress(~index.covered(
                dr.gather(mi.Point3f, photon_p, near), dr.gather(mi.Vector3f, photon_n, near))))
            if not dr.width(lost):
                break
            lost_p, lost_n = dr.gather(mi.Point3f, photon_p, lost), dr.gather(mi.Vector3f, photon_n, lost)
            if clamp_pass == PROBE_CLAMP_PASSES - 1:
                pending_p, pending_n = [lost_p], [lost_n]
            else:
                index, _ = self.build_records(lost_p, lost_n, index, settle=False, gather=False)
        uncovered = dr.compress(~index.covered(probe_p, probe_n))
        probe_p = dr.gather(mi.Point3f, probe_p, uncovered)
        probe_n = dr.gather(mi.Vector3f, probe_n, uncovered)
        cand_p = concat(pending_p + [probe_p], mi.Point3f)
        if dr.width(cand_p.x):
            index, _ = self.build_records(cand_p, concat(pending_n + [probe_n], mi.Vector3f),
                                          index, settle=False, gather=False)
        return self.settle(self.gather_placed(index), concat([photon_p, probe_p], mi.Point3f),
                           concat([photon_n, probe_n], mi.Vector3f))[0]


def _probe_count(photons: int) -> int:
    return int(min(max(PROBES_PER_PHOTON * photons, MIN_PROBES), MAX_PROBES))


def _bounds(points: mi.Point3f, margin: float):
    """Bounding box of ``points``, grown by ``margin``, as two Python-side points."""
    lo = [float(dr.min(c)[0]) - margin for c in (points.x, points.y, points.z)]
    hi = [float(dr.max(c)[0]) + margin for c in (points.x, points.y, points.z)]
    return mi.Point3f(*lo), mi.Point3f(*hi)


def _shape_area(shape) -> float:
    try:
        a = float(dr.sum(shape.surface_area())[0])
    except Exception:  # instances and shape groups have no area of their own
        return 0.0
    return a if math.isfinite(a) and a > 0 else 0.0


def _bsdf_flags(shape) -> int:
    bsdf = shape.bsdf()
    return scene_flags(bsdf) if bsdf is not None else 0


def _shape_order(shape_and_area):
    """A key that orders shapes by what they are, not by when they were loaded."""
    shape, area = shape_and_area
    box = shape.bbox()
    return (shape.id(), type(shape).__name__, area, tuple(box.min), tuple(box.max),
            _bsdf_flags(shape), shape.primitive_count())


def surface_probes(scene: mi.Scene, count: int, seed: int):
    """About ``count`` points sampled uniformly by area over every surface with a
    diffuse lobe, each with the normal of the side that reflects (both sides of a
    ``twosided`` BSDF). Returns ``(p, n)``; deterministic in ``seed``."""
    shapes = [(s, _shape_area(s)) for s in scene.shapes()
              if _bsdf_flags(s) & int(mi.BSDFFlags.Diffuse)]
    # Mitsuba loads a scene's children in parallel: ``scene.shapes()`` comes in a
    # different order from one load to the next, and so would the probes.
    shapes = sorted(((s, a) for s, a in shapes if a > 0), key=_shape_order)
    total = sum(a for _, a in shapes)
    ps, ns = [], []
    first = 0
    for shape, area in shapes:
        k = int(round(count * area / total)) if total > 0 else 0
        if k == 0:
            continue
        rng = make_rng(k, seed, stream=streams.SURFACE_PROBES + first)
        first += k
        try:
            sample = shape.sample_position(0.0, mi.Point2f(rng.next_float32(), rng.next_float32()))
        except Exception:  # pragma: no cover - a shape without position sampling
            continue
        normal = mi.Vector3f(sample.n)
        ok = dr.compress(dr.all(dr.isfinite(sample.p)) & (dr.squared_norm(normal) > 0))
        p = dr.gather(mi.Point3f, sample.p, ok)
        n = dr.normalize(dr.gather(mi.Vector3f, normal, ok))
        ps.append(p), ns.append(n)
        if _bsdf_flags(shape) & int(mi.BSDFFlags.BackSide):
            ps.append(p), ns.append(-n)
    if not ps:
        return mi.Point3f(), mi.Vector3f()
    p, n = concat(ps, mi.Point3f), concat(ns, mi.Vector3f)
    dr.eval(p, n)
    return p, n


# ----------------------------------------------------------------------------------------
# The classic cache (method irradiance_cache): records placed from one camera
# ----------------------------------------------------------------------------------------
def camera_points(scene: mi.Scene, sensor: mi.Sensor, seed: int):
    """First surface with a diffuse lobe seen through each pixel centre."""
    film = sensor.film()
    size = film.crop_size()
    w, h = int(size[0]), int(size[1])
    idx = dr.arange(mi.UInt32, w * h)
    pos = mi.Vector2f(mi.Float(idx % w) + 0.5, mi.Float(idx // w) + 0.5) / mi.Vector2f(w, h)
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), pos, mi.Point2f(0.5, 0.5))
    rng = make_rng(w * h, seed, stream=streams.CAMERA_POINTS)
    p, n, found = _first_diffuse_hit(scene, mi.Ray3f(ray), rng)
    keep = dr.compress(found)
    return dr.gather(mi.Point3f, p, keep), dr.gather(mi.Vector3f, n, keep)


def camera_seeded_index(scene: mi.Scene, sensor: mi.Sensor, settings: Settings,
                        prepared: PreparedScene):
    """The classic Ward cache of one view: records placed at what ``sensor`` sees.
    Returns ``(index, rounds)``; ``prepared`` is not changed."""
    cam_p, cam_n = camera_points(scene, sensor, settings.seed)
    index, rounds = CacheBuilder(scene, settings, prepared).build_records(cam_p, cam_n, None)
    return index.for_lookup(), rounds


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
