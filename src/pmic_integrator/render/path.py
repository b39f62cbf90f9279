"""The camera path: one loop over :class:`~.state.PathState`, each vertex a sequence of
named strategies. Its switches (:class:`~.config.PathConfig`) and what it reads (the
prepared scene: :class:`~.config.PathContext`) are closed over, not loop state.

At each vertex::

    meet the surface          Vertex.meet
    emission met              direct.emission_met
    where to read or trace    reads.where_read
    guides for a traced one   continuation.choose_guides
    direct light             direct.direct_at_vertex
    indirect light            indirect_at_vertex (cache / photons, caustic map or deferred)
    AOVs                      _add_aovs
    go on                     continuation.continue_path
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .._jit import finite
from .config import DEFERRED_READS, PathContext
from .continuation import choose_guides, continue_path
from .direct import direct_at_vertex, emission_met
from .estimators import caustic_irradiance, final_gather_ray, global_irradiance, total_irradiance
from .reads import where_read
from .. import spectra
from ..spectra import from_rgb
from .state import PathState
from .vertex import Reads, Vertex


def _defer_caustic_read(state: PathState, v: Vertex, reads: Reads) -> None:
    """Keep this vertex's caustic-map read in the path's first free slot (made after
    the loop, :mod:`.caustics`). A path reads the map at traced vertices only, at most
    MAX_TRACED_BOUNCES of them: it never runs out of slots (DEFERRED_READS)."""
    weight_here = state.β * reads.response
    taken, before = [], mi.Bool(True)  # (before: every slot before this one is taken)
    for slot in state.reads:
        taken.append(reads.read_caustic & before & ~slot.made)
        before = slot.made
    for slot, now in zip(state.reads, taken):
        slot.p[now] = v.si.p
        slot.n[now] = v.n
        slot.weight[now] = weight_here
        slot.made |= now


def indirect_at_vertex(ctx: PathContext, sampler, state: PathState, v: Vertex, reads: Reads):
    """``(caustic, indirect)``: the light that bounced before reaching the vertex's
    diffuse lobe (times the path's throughput): the caustic map's (0 where deferred)
    and the cache's or global map's (with a rough plastic's coat's share)."""
    config, β, wavelengths = ctx.config, state.β, v.si.wavelengths
    if config.defer_caustics:
        _defer_caustic_read(state, v, reads)
        caustic = mi.Spectrum(0.0)
    else:
        caustic_rgb = caustic_irradiance(ctx, v.si.p, v.n, state.depth, reads.read_caustic)
        caustic = finite(β * reads.response * from_rgb(caustic_rgb, wavelengths), reads.read_caustic)
    # (The maps and records hold linear sRGB: spectra.from_rgb at the path's wavelengths.)
    if config.gather_first:
        irradiance = total_irradiance(ctx, v.si, v.n, reads.trust, reads.cached, reads.covered)
    else:
        irradiance = global_irradiance(ctx, v.si.p, v.n, state.depth, reads.trust, reads.cached,
                                       reads.covered, gathered=reads.records_here)
    irradiance = from_rgb(irradiance, wavelengths)
    if config.photon_map_gather:
        irradiance += final_gather_ray(ctx, sampler, v.si, v.n, reads.records_here)
    indirect = finite(β * reads.response * irradiance, reads.trust)
    if config.coat_reads:
        # The coat's share: once armed, light that reached this vertex straight from the
        # lights (and its caustics) and leaves by the coat is a caustic of the last
        # traced vertex, which read the map: only the records' bounced light is left.
        armed_direct = from_rgb(dr.select(state.armed, reads.cached_direct, 0.0), wavelengths)
        reflected = dr.maximum(irradiance - armed_direct, 0.0)
        indirect += finite(β * reads.coat_response * reflected, reads.coat_read)
    return caustic, indirect


def _add_aovs(ctx: PathContext, state: PathState, reads: Reads, emitted, direct, indirect, caustic):
    config = ctx.config
    if config.wants("direct"):
        state.L_direct += emitted + direct
    if config.wants("indirect"):
        state.L_indirect += indirect
    if config.wants("caustic"):
        state.L_caustic += caustic
    if config.wants("coverage"):
        first_read = reads.trust & state.unread
        state.coverage[first_read] = dr.select(reads.covered, 1.0, 0.0)
        state.unread &= ~first_read


def camera_vertex(ctx: PathContext, sampler, state: PathState) -> PathState:
    """One vertex of every active path of ``state`` (the loop's body)."""
    config = ctx.config
    v = Vertex.meet(state, config, ctx.diffuse_free)
    state.valid |= (state.depth == 0) & v.si.is_valid()
    shown = state.active & ~state.crossed & ~state.coat_counted
    if config.hide_emitters:
        shown &= ~((state.depth == 0) & ~v.si.is_valid())
    emitted = emission_met(ctx, state, v.si, shown)
    state.L += emitted
    reads = where_read(ctx, state, v)
    guides = choose_guides(ctx, v, reads)
    direct, coat = direct_at_vertex(ctx, sampler, state, v, reads, guides)
    state.L += direct
    caustic, indirect = indirect_at_vertex(ctx, sampler, state, v, reads)
    state.L += caustic + indirect
    _add_aovs(ctx, state, reads, emitted, direct, indirect, caustic)
    continue_path(ctx, sampler, state, v, reads, guides, coat)
    return state


def first_intersection(ctx: PathContext, ray, active):
    """Where camera rays meet the scene (a hidden area emitter looked through, as in
    Mitsuba's path tracers)."""
    scene = ctx.scene
    pi = scene.ray_intersect_preliminary(ray, coherent=True, active=active)
    if ctx.config.hide_emitters:
        skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
        si_skip = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip)
        pi[skip] = ctx.skip_area_emitters(scene, si_skip.spawn_ray(ray.d), True, skip)
    return pi


def denoiser_guides(pi, ray, active, aovs) -> dict:
    """The denoiser's guides at the first surface, as Mitsuba's ``aov`` integrator
    computes them: diffuse reflectance and world-space shading normal (0 where the
    camera ray meets nothing)."""
    guides = {}
    if "albedo" not in aovs and "normal" not in aovs:
        return guides
    si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
    hit = active & si.is_valid()
    albedo = spectra.reflectance_to_rgb(si.bsdf(ray).eval_diffuse_reflectance(si, hit), si.wavelengths)
    guides["albedo"] = dr.select(hit, albedo, 0.0)
    guides["normal"] = dr.select(hit, si.sh_frame.n, 0.0)
    return guides


def trace_camera_paths(ctx: PathContext, sampler, ray, active):
    """The camera paths of ``ray``: returns the loop's final :class:`PathState` (its
    ``L``, ``valid``, AOV sums and deferred caustic reads) and the denoiser's guides
    (:func:`denoiser_guides`)."""
    ray = mi.Ray3f(dr.detach(ray))
    active = mi.Bool(active)
    pi = first_intersection(ctx, ray, active)
    guides = denoiser_guides(pi, ray, active, ctx.config.aovs)
    slots = DEFERRED_READS if ctx.config.defer_caustics else 0
    state = PathState.start(ray, pi, active, slots)

    def body(state, sampler):
        return camera_vertex(ctx, sampler, state), sampler

    state, _ = dr.while_loop((state, sampler), lambda state, sampler: state.active, body,
                             label="pmic_camera_path", max_iterations=ctx.config.max_iterations)
    return state, guides
