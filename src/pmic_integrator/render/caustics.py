"""The camera paths' deferred caustic-map reads, made after the camera loop over just
the lanes that made one (a compacted wavefront), in a fixed order (the same sums every
time).

In a room whose rough floor spreads caustic photons everywhere, 85 % of these reads
came to exactly 0 (28 % found no photon near, most of the rest only the photons on the
far side of the wall they were on), yet in the camera loop a SIMD packet paid a whole
estimate whenever one of its 16 lanes needed one: the reads were 56 % of the render for
4 % of the light (render 1.54 -> 0.9 s). Lanes that
:func:`~pmic_integrator.irradiance.may_count_photons` rules out are skipped: the same
image.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .._jit import finite, opaque_u32
from ..hashgrid import PointGridPyramid
from ..irradiance import NormalBins, may_count_photons
from .config import PathContext
from .estimators import caustic_irradiance
from .state import CausticRead
from ..spectra import from_rgb

#: A pixel's samples share the caustic-map estimate made at its first sample's first
#: read where their own reads lie within this many of that estimate's kernel radius
#: (on a surface facing within acos(CAUSTIC_SHARE_COSINE) = 11° of it): there the
#: kernel's own smoothing (one radius) dwarfs the shift, and the estimates of nearby
#: points, made from the same photons, are as good as one. A caustic-lit room's reads
#: (a sky through a thin pane: kernel radius 0.24 m) were 60 % of its render.
CAUSTIC_SHARE_RADII = 0.1
CAUSTIC_SHARE_COSINE = 0.98


def add_deferred_caustics(ctx: PathContext, bins: NormalBins, reads: list[CausticRead], L,
                          L_caustic, want_caustic: bool, spp: int = 1, wavelengths=None):
    """The paths' caustic-map ``reads`` added to ``L`` (and to the caustic AOV), at the
    paths' ``wavelengths`` (spectral variants; the map holds linear sRGB). The
    first reads of a pixel's ``spp`` samples (lane ``i`` is sample ``i % spp`` of pixel
    ``i // spp``) share one estimate where they fall close together on one surface
    (:func:`_pixel_shared_caustics`). ``bins``: the caustic map's normal bins."""
    L = mi.Spectrum(L)
    if want_caustic:
        L_caustic = dr.zeros(mi.Spectrum, dr.width(L)) + L_caustic
    for slot, read in enumerate(reads):
        lanes = dr.compress(read.made)
        if dr.width(lanes):
            lanes = dr.gather(mi.UInt32, lanes, dr.compress(may_count_photons(
                bins, dr.gather(mi.Point3f, read.p, lanes), dr.gather(mi.Vector3f, read.n, lanes))))
        if dr.width(lanes) == 0:
            continue
        # (Unbounded: no depth limit, see config.defers_caustics.)
        if slot == 0 and spp > 1:
            irradiance = _pixel_shared_caustics(ctx, read, lanes, spp)
        else:
            irradiance = caustic_irradiance(ctx, dr.gather(mi.Point3f, read.p, lanes),
                                            dr.gather(mi.Vector3f, read.n, lanes), None, True)
        if mi.is_spectral:
            irradiance = from_rgb(irradiance, dr.gather(mi.Spectrum, wavelengths, lanes))
        caustic = finite(dr.gather(mi.Spectrum, read.weight, lanes) * irradiance, True)
        dr.scatter_add(L, caustic, lanes)
        if want_caustic:
            dr.scatter_add(L_caustic, caustic, lanes)
        dr.eval(L, L_caustic)
    return L, L_caustic


def _pixel_shared_caustics(ctx: PathContext, read: CausticRead, lanes, spp: int) -> mi.Color3f:
    """Caustic irradiance for the first reads ``lanes`` of ``read``: estimated at each
    pixel's first sample, and used by the pixel's other samples whose reads lie within
    ``CAUSTIC_SHARE_RADII`` of that estimate's kernel radius and face the same way
    (``CAUSTIC_SHARE_COSINE``); the others estimate their own."""
    view, p, n = ctx.view, read.p, read.n
    first = lanes - lanes % opaque_u32(spp)  # the pixel's first sample
    is_first = first == lanes
    at_first = dr.compress(is_first)
    first_lanes = dr.gather(mi.UInt32, lanes, at_first)
    first_p = dr.gather(mi.Point3f, p, first_lanes)
    first_n = dr.gather(mi.Vector3f, n, first_lanes)
    first_e = caustic_irradiance(ctx, first_p, first_n, None, True)
    # The narrowest kernel that estimate used (a delta light's photons count with a
    # kernel delta_scale times narrower).
    grid = view.caustic_grid
    radius = grid.level_of(first_p)[1] if isinstance(grid, PointGridPyramid) else \
        dr.full(mi.Float, view.caustic_radius, dr.width(first_lanes))
    reach = radius * (CAUSTIC_SHARE_RADII * min(view.caustic_delta_scale, 1.0))
    # Per lane of the wavefront, the estimate made at it and its reach (0: none).
    width = dr.width(read.made)
    estimate = dr.zeros(mi.Color3f, width)
    shared_reach = dr.zeros(mi.Float, width)
    dr.scatter(estimate, first_e, first_lanes)
    dr.scatter(shared_reach, reach, first_lanes)
    lane_p = dr.gather(mi.Point3f, p, lanes)
    lane_n = dr.gather(mi.Vector3f, n, lanes)
    first_reach = dr.gather(mi.Float, shared_reach, first)
    share = is_first | ((dr.squared_norm(lane_p - dr.gather(mi.Point3f, p, first)) < dr.square(first_reach)) &
                        (dr.dot(lane_n, dr.gather(mi.Vector3f, n, first)) > CAUSTIC_SHARE_COSINE))
    result = dr.gather(mi.Color3f, estimate, first, share)
    own = dr.compress(~share)
    if dr.width(own):
        own_e = caustic_irradiance(ctx, dr.gather(mi.Point3f, lane_p, own),
                                   dr.gather(mi.Vector3f, lane_n, own), None, True)
        dr.eval(own_e)
        dr.scatter(result, own_e, own)
    return result
