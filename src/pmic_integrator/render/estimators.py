"""The camera path's reads of indirect light: the cache, the photon maps, the
precomputed irradiance of the photons, and ``photon_map``'s gather ray."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from .. import streams
from .._jit import only_where, surface_offset
from ..gather import trace_gather_rays
from ..irradiance import estimate_irradiance
from .config import PathContext


def caustic_irradiance(ctx: PathContext, p, n, depth, active):
    """Irradiance at a camera vertex from light → delta/glossy bounces (caustic map)."""
    view = ctx.view
    if not view.caustic_map.count:
        return dr.zeros(mi.Color3f, dr.width(p))
    return estimate_irradiance(view.caustic_map, view.caustic_grid, p, n, view.caustic_radius,
                               max_depth=ctx.depth_limit(depth), active=active,
                               delta_scale=view.caustic_delta_scale)


def cache_lookup(ctx: PathContext, p, n, shading_n, active, with_direct: bool = False):
    """``(E, covered, R)``: the cache's interpolated irradiance, where records reach
    (p, n), and their weighted mean radius (``shading_n``: see interpolate); with
    ``with_direct``, and the part of E that is the records' direct light."""
    index = ctx.view.index
    lanes = dr.width(p)

    def zeros():
        zero = dr.zeros(mi.Color3f, lanes), dr.zeros(mi.Bool, lanes), dr.zeros(mi.Float, lanes)
        return zero + (dr.zeros(mi.Color3f, lanes),) if with_direct else zero

    def interpolate():
        return index.interpolate(p, n, active, with_radius=True, shading_n=shading_n,
                                 with_direct=with_direct)
    if index is None:
        return zeros()
    if not ctx.config.gather_first:
        return interpolate()  # (the first-hit estimator reads it at nearly every first vertex)
    # (Behind a traced vertex only: at the camera's first vertex no lane reads it.)
    return only_where(active, interpolate, zeros, label="cache_lookup")


def photon_estimate(ctx: PathContext, p, n, depth_limit, active):
    """Global-map estimate of light that bounced at least once (direct light and
    caustic paths are counted elsewhere), excluding L S+ D paths."""
    view = ctx.view
    return estimate_irradiance(view.global_map, view.global_grid, p, n, view.global_radius,
                               min_depth=2, max_depth=depth_limit,
                               skip_specular_paths=view.caustic_map.count > 0, active=active)


def global_irradiance(ctx: PathContext, p, n, depth, active, cached, covered, gathered=True):
    """Irradiance at a camera vertex from light that bounced off a diffuse surface
    first: the cache's ``cached`` value where ``covered``, else the global photon map
    (the method ``photon_map`` reads the map only, and with ``final_gather`` gathers
    it where ``gathered``: see ``records_read_depth``)."""
    config = ctx.config
    depth_limit = ctx.depth_limit(depth)
    if ctx.view.global_map.count == 0:
        return dr.zeros(mi.Color3f, dr.width(p))
    if config.method == "photon_map":
        if config.final_gather:
            return photon_estimate(ctx, p, n, depth_limit, mi.Bool(active) & ~mi.Bool(gathered))
        return photon_estimate(ctx, p, n, depth_limit, active)
    need = mi.Bool(active) & ~covered
    ctx.count_fallback(need & gathered)  # (not the vertices deeper than the records serve)
    fallback = photon_estimate(ctx, p, n, depth_limit, need)
    return dr.select(covered, cached, fallback)


def total_irradiance(ctx: PathContext, si, n, active, cached, covered):
    """Final gather: all the irradiance at a trusted vertex, direct light included:
    the records' where they reach, else the precomputed irradiance of the nearest
    photon that ``si`` sees (a shadow ray: a photon across a thin wall is not read)."""
    need = mi.Bool(active) & ~covered
    ctx.count_fallback(need)
    source = ctx.view.gather_source
    if source is None:
        return dr.select(covered, cached, 0.0)
    # Without delta lights' direct light where the photons keep it apart (the vertex
    # samples it: direct.trusted_direct).
    nodelta = source.photons.irradiance_nodelta is not None
    # (Rare: a vertex no record reaches, past every probe.)
    fallback = only_where(need, lambda: source.irradiance_at(ctx.scene, si.p, n, need, without_delta=nodelta),
                          lambda: dr.zeros(mi.Color3f, dr.width(si.p)), label="photon_fallback")
    return dr.select(covered, cached, fallback)


def final_gather_ray(ctx: PathContext, sampler, si, n, active):
    """``photon_map`` with ``final_gather``: one cosine-distributed gather ray reading
    precomputed irradiance: E ≈ π L."""
    local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
    ray = mi.Ray3f(si.p + n * surface_offset(si.p, ctx.view.ray_offset), mi.Frame3f(n).to_world(local))
    if mi.is_spectral:
        ray.wavelengths = si.wavelengths  # the camera path's: its radiance is a spectrum
    # Glossy bounces along the ray follow the render's seed, as the rest of the path.
    rng = streams.render_rng(sampler, dr.width(si.p))
    radiance, _ = trace_gather_rays(ctx.scene, ctx.view.gather_source, ray, rng, active)
    return radiance * math.pi
