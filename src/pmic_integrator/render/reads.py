"""Where a camera vertex reads indirect light, and where it is traced instead.

The estimators differ here only: the first-hit estimator reads the cache (or the
photon map) at every diffuse vertex; the final gather traces the first one and reads
the cache behind it, unless the vertex lies too close to trust the records
(:data:`TRUST_RECORD_RADII`). The BSDF's case (:mod:`pmic_integrator.cases`) decides
what is read: its diffuse lobe, its whole response (inseparable BSDFs), or its coat too
(rough plastic).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .._jit import only_where
from ..bsdfs import (diffuse_response, near_diffuse, non_diffuse_context,
                     peak_within, response_azimuths, tilted_normal)
from ..cases import CAMERA_PEAK_RATIO
from .config import MAX_TRACED_BOUNCES, PathContext, first_reads_allowed
from .estimators import cache_lookup
from .state import PathState
from .vertex import Reads, Vertex

#: Final gather: a diffuse vertex behind a traced one reads the cache only if the
#: segment reaching it is at least this many (weighted mean) record radii long. A
#: record's radius is the harmonic mean distance of the geometry its gather saw: nearer
#: than that, the vertex lies in the corner, contact or gap the record interpolates
#: across, and its error would fill a wide solid angle of the traced vertex (the
#: blotches of first-hit interpolation). Such vertices are traced too, up to
#: :data:`~pmic_integrator.render.config.MAX_TRACED_BOUNCES` per path.
TRUST_RECORD_RADII = 1.0

def _whole_reads(ctx: PathContext, state: PathState, v: Vertex):
    """``(traced_whole, inseparable)``: an inseparable BSDF (Mitsuba's principled ignores
    lobe masks) is traced whole, and behind a traced vertex, where it is nearly diffuse
    for the incident direction (CAMERA_PEAK_RATIO), may read the cache as gather rays
    read it: its whole response (the cosine-weighted mean of the whole BSDF) times the
    records' irradiance, and the path ends. Traced whole everywhere, a room of
    principled materials (what Blender exports) never read the cache: 0.30x path's
    speed on a Cornell box of principled walls at roughness 0.5; now 1.3x. Not where it
    transmits (glass, a leaf): that light comes from behind."""
    traced_whole = v.active_next & v.lobes.diffuse & ~v.separable & ~v.lobes.transmits & \
        mi.Bool(ctx.config.use_indirect)
    inseparable = traced_whole & (state.traced > 0)
    inseparable &= near_diffuse(v.bsdf, v.si, inseparable, CAMERA_PEAK_RATIO)
    return traced_whole, inseparable

def _coat_read(v: Vertex, trust, covered, response):
    """``(coat_read, coat_response)``: a rough plastic read where records reach: its
    coat too, where the whole BSDF is nearly diffuse for the incident direction
    (CAMERA_PEAK_RATIO), reflects the records' irradiance, and the path ends. Its coat
    was followed instead, a path of many weak bounces (~5 % of the light each, until
    Russian roulette) whose every vertex read the cache, sampled the lights and was
    tested: in a door-lit room of rough plastic that was half of the render (4.2 s ->
    2.2 s at 16 spp, 320x240)."""
    coat_read = trust & covered & v.lobes.rough_coat & v.separable & ~v.lobes.transmits
    coat_response = diffuse_response(v.bsdf, v.si, coat_read, non_diffuse_context())
    coat_read &= peak_within(v.bsdf, v.si, coat_read, dr.max(response + coat_response),
                             CAMERA_PEAK_RATIO)
    return coat_read, coat_response

#: The adaptive estimator reads a record at a camera path's first diffuse vertex only
#: where what surrounds it lets its gather be trusted (:func:`survey_first_reads`,
#: measured in docs/tuning.md, "First reads"): at most this share of its rays meet a
#: surface its gather cannot read as diffuse (glass, metal, glossy or principled).
#: Records that see such surfaces gather their light through them approximately
#: (a principled floor read as if lit evenly, glass a few bounces deep): read at the
#: first hit, the glossy Cornell box came out 0.979 of its reference (final gather
#: 0.999), the torus in its glass cube 0.984.
FIRST_READ_MAX_GLOSSY = 0.1
#: ...and at most this share of the light its rays find at their first hits is the
#: emitters' light reflected by such surfaces (one emitter sample and one BSDF sample
#: at each): a glossy floor or a brass box reflects a light onto a wall from a small
#: part of the wall's hemisphere, which a record's gather reads as if it were diffuse.
#: Without this test the glossy Cornell box's default image had record-sized patches
#: 10-20 % dark at the top of its back wall (docs/tuning.md, "First reads").
FIRST_READ_MAX_GLOSSY_LIGHT = 0.02
#: ...and at least this share of its rays' diffuse hits have a precomputed photon
#: within one lookup radius: where photons are too sparse (the lamp room's shades, a
#: sunlit dining room, the torus's base) the gather reads photons found far off. At
#: 0.5 the door-ajar kind lost its gain (its dim room's photons are sparse); at 0.25
#: it keeps most of it.
FIRST_READ_MIN_SUPPORT = 0.25
#: ...and the record gathered its light evenly enough that its own estimate is smooth:
#: the relative variance of one gather ray
#: (:meth:`~pmic_integrator.cache.RecordIndex.bounce_variance`) at most this. Records
#: lit by a small bright source (a lamp's shade seen from the wall) each see it with a
#: few of their rays: read at the first hit they were record-sized blotches (the lamp
#: room: relMSE after OIDN 1.1e-1 without this test, 2.1e-2 with it).
FIRST_READ_MAX_VARIANCE = 8.0
#: A read at the first hit trades the traced bounce's noise, which falls as 1/spp, for
#: the record's error, which does not. Up to this many samples per pixel every record
#: the survey passes is read (at 16 spp reads won in every scene measured; at 64 they
#: still won in Sponza and the door-ajar kind, lost in the material preview);...
FIRST_READ_ANY_SPP = 64
#: ...above it, only records whose traced bounce's relative variance
#: (RecordIndex.bounce_variance) over this many times their squared relative error
#: (RecordIndex.left_out_error) is at least the sample count. Without it, at 256 spp
#: the material preview had 3.5x the final gather's relMSE and the white room 2.4x;
#: with it, 1.3x and 1.4x, and Sponza and the door-ajar kind gained too (docs/tuning.md,
#: "First reads at high sample counts").
FIRST_READ_ERROR_SCALE = 4.0


def survey_first_reads(scene, settings, prepared) -> None:
    """Decide, once per cache, which records the adaptive estimator may read at a
    camera path's first diffuse vertex (``RecordIndex.first_readable``): those whose
    surroundings pass FIRST_READ_MAX_GLOSSY, FIRST_READ_MAX_GLOSSY_LIGHT and
    FIRST_READ_MIN_SUPPORT and whose
    gather was even (FIRST_READ_MAX_VARIANCE) and found bounced light. None in a scene
    with delta lights: there the sunlit classroom kind read 0.93 of its reference at
    the first hit (final gather 0.98), the records' bounced light from a sharp sunlit
    patch too dark. Renders that may make no first reads (config.first_reads_allowed:
    other estimators, a depth bound, an image meant for a denoiser, where the survey
    was 1-2 s of the cache stage in Sponza and the white room) and caches already
    surveyed are left as they are."""
    from ..cache import record_surroundings

    index = prepared.index
    if not first_reads_allowed(settings, prepared) or index.first_readable is not None or \
            prepared.gather_source is None:
        return
    glossy, support, glossy_light = record_surroundings(scene, prepared.gather_source, index.records,
                                                        settings.seed, prepared.ray_offset)
    variance = index.bounce_variance()
    readable = (glossy <= FIRST_READ_MAX_GLOSSY) & (support >= FIRST_READ_MIN_SUPPORT) & \
        (glossy_light <= FIRST_READ_MAX_GLOSSY_LIGHT) & \
        (variance <= FIRST_READ_MAX_VARIANCE) & \
        (mi.luminance(index.records.irradiance) > 0)
    # (A record that no other reaches has no error estimate: read up to FIRST_READ_ANY_SPP.)
    error = index.left_out_error()
    paying = dr.select(dr.isfinite(error), variance / (FIRST_READ_ERROR_SCALE * dr.maximum(error, 1e-30)), 0.0)
    index.first_read_spp = dr.select(readable, dr.maximum(paying, FIRST_READ_ANY_SPP), 0.0)
    dr.eval(readable, index.first_read_spp)
    index.first_readable = readable


def first_read_limit(index) -> float:
    """The largest sample count per pixel at which some record of ``index`` is read at
    a first vertex (:data:`FIRST_READ_ANY_SPP`, :data:`FIRST_READ_ERROR_SCALE`; 0: none
    is)."""
    if index.first_read_spp is None:
        return 0.0
    return index.remembered("first_read_limit", lambda: float(dr.max(index.first_read_spp)[0]))


def any_first_reads(index) -> bool:
    """Whether any record of ``index`` may be read at a first vertex
    (:func:`survey_first_reads`): where none may, the adaptive estimator is the final
    gather and skips the first vertices' lookups (5-15 % of the render)."""
    if index.first_readable is None:
        return False
    return index.remembered("any_first_reads", lambda: bool(dr.any(index.first_readable)[0]))


def first_read_pays(ctx: PathContext, v: Vertex, active):
    """The lanes of ``active`` (first diffuse vertices that records reach) that read
    the records' bounced light rather than trace a bounce: where the record that
    guides there may be read (:func:`survey_first_reads`) and found bounced light.

    Returns ``(lanes, guiding record, its bounced share)``: the continuation's guides
    (``continuation.choose_guides``) take the record from here instead of searching
    for it again."""
    index = ctx.view.index
    active = mi.Bool(active)
    lanes = dr.width(active)
    record, bounced_share = only_where(
        active, lambda: index.guide_record(v.si.p, v.n, active),
        lambda: (dr.zeros(mi.UInt32, lanes), dr.zeros(mi.Float, lanes)), label="first_read_record")
    active &= bounced_share > 0
    # A record that may be read (survey_first_reads), up to the sample count at which
    # its error would show above the traced bounce's noise (FIRST_READ_ERROR_SCALE);
    # first_read_spp is 0 for the others, and the count is at least 1.
    active &= dr.gather(mi.Float, index.first_read_spp, record, active) >= ctx.spp
    # The guiding record is found without a visibility test: read at the first hit,
    # one behind a wall (outside a closed box standing on a floor, under a sky) lit
    # the box's inside (brightest pixel 7.7e-3 where path is black). It must see the
    # vertex as interpolation's records must (RecordIndex.sees). (A shadow ray lifted
    # by the ray offset alone, for every read, grazed the white room's walls: half
    # its reads lost, relMSE 3.7e-2 -> 4.5e-2.)
    active &= index.sees(v.si.p, v.n, record, active)
    return active, record, bounced_share


def where_read(ctx: PathContext, state: PathState, v: Vertex) -> Reads:
    """What vertex ``v`` of ``state``'s paths reads, and where it is traced instead."""
    config = ctx.config
    depth, traced = state.depth, state.traced
    cache_ok = v.lit_diffuse & mi.Bool(config.use_indirect) & (depth + 3 <= config.max_depth)
    inseparable = mi.Bool(False)  #: ...and may read the cache here
    traced_whole = mi.Bool(False)  #: ...and is traced whole here
    if config.whole_reads:
        traced_whole, inseparable = _whole_reads(ctx, state, v)
    # Where the diffuse lobe leans (a normal map's), the cache is read about the normal
    # it leans to (read_n), the records' rotational gradients weighing the incident
    # light as the lobe does. Read about the surface's own normal, a box of walls whose
    # normal map leant 30° came out 1-3 % dark or bright, by the light's direction. (The
    # response is then taken here, for every lane that may read; elsewhere below, for
    # those that do.)
    read_n = mi.Vector3f(v.shading_n)
    if config.leaning:
        response, tilt = diffuse_response(v.bsdf, v.si, v.lit_diffuse | inseparable, with_tilt=True,
                                          azimuths=response_azimuths(config.leaning))
        read_n = tilted_normal(v.shading_n, tilt)
    records_here = mi.Bool(False)
    first_read, first_record, first_share = mi.Bool(False), mi.UInt32(0), mi.Float(0.0)
    if config.gather_first:
        probe = (cache_ok | inseparable) & (traced > 0)
        if config.bounded:
            probe &= depth == config.read_depth  # (deeper: traced on, see records_read_depth)
        first_probe = cache_ok & (traced == 0) if config.first_reads else mi.Bool(False)
        cached_direct = mi.Color3f(0.0)
        if config.coat_reads or config.first_reads:
            cached, covered, radius, cached_direct = cache_lookup(ctx, v.si.p, v.n, read_n, probe | first_probe,
                                                                  with_direct=True)
        else:
            cached, covered, radius = cache_lookup(ctx, v.si.p, v.n, read_n, probe)
        trusted_radius = dr.select(covered, radius, ctx.untrusted_radius)
        trust = probe & ((v.si.t >= TRUST_RECORD_RADII * trusted_radius) |
                         (traced >= MAX_TRACED_BOUNCES))
        if config.first_reads:
            first_read, first_record, first_share = first_read_pays(ctx, v, first_probe & covered)
            # (its light from the lights is sampled here: the records' bounced light only)
            cached = dr.select(first_read, dr.maximum(cached - cached_direct, 0.0), cached)
        traced_here = v.lit_diffuse & ~trust & ~first_read
        # Where it is not trusted it is traced whole: a traced diffuse vertex.
        trusted_whole = inseparable & trust
        traced_whole &= ~trusted_whole
    else:
        trust = mi.Bool(cache_ok)
        # (Deeper than the records were made for: the photon map, depth by depth.)
        records_here = trust & ((depth == config.read_depth) if config.bounded else True)
        cached, covered, _ = cache_lookup(ctx, v.si.p, v.n, read_n,
                                          records_here & mi.Bool(config.reads_cache))
        traced_here = mi.Bool(False)
        traced_whole = mi.Bool(False)
        trusted_whole = mi.Bool(False)
        cached_direct = mi.Color3f(0.0)
    from_records = trust & mi.Bool(config.gather_first)  #: all its light from the records
    trust |= first_read

    # ---- Light that bounced before reaching the diffuse lobe: where read ----
    read_caustic = (trust | traced_here) & mi.Bool(config.has_caustic_map) & \
        (depth + 3 <= config.max_depth)
    if config.gather_first:
        read_caustic &= ~(trust & ~covered)  # the photon's irradiance has them
        if config.records_hold_caustics:
            read_caustic &= ~from_records  # and so do the records
    if config.leaning:
        response = dr.select(trust | read_caustic, response, 0.0)
    else:
        response = diffuse_response(v.bsdf, v.si, trust | read_caustic,
                                    azimuths=response_azimuths(config.leaning))
    coat_read = mi.Bool(False)
    coat_response = mi.Spectrum(0.0)
    if config.coat_reads:
        coat_read, coat_response = _coat_read(v, from_records, covered, response)
        trusted_whole |= coat_read
    return Reads(trust=trust, traced_here=traced_here, traced_whole=traced_whole,
                 trusted_whole=trusted_whole, cached=cached, covered=covered,
                 cached_direct=cached_direct, records_here=records_here,
                 read_caustic=read_caustic, response=response, coat_read=coat_read,
                 coat_response=coat_response, from_records=from_records, first_read=first_read,
                 first_record=first_record, first_share=first_share)
