"""Stage 2: irradiance from photons (density estimation), and its precomputation at the
photons themselves (Christensen 2000, "Faster photon map global illumination").

Every estimate filters photons by geometry, not only by distance: a photon counts only
if its normal agrees with the query normal and it lies close to the query's tangent
plane. A plain sphere of radius r would leak light across thin gaps (the 1 cm between a
Cornell-box light and its ceiling), around corners and through thin walls, which is
where classic photon-map renderers lose most of their accuracy.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from . import boundary
from ._jit import every_nth, finite, opaque_float, opaque_u32, scatter_count
from .hashgrid import PointGrid, PointGridPyramid, _neighbour_offset, _next_pow2, cell_of, hash_cell
from .photons import PhotonMap

# --- Internal tuning constants -------------------------------------------------------
#: Minimum cosine between photon and query normals (about 37 degrees): keeps curved
#: surfaces (spheres) usable while rejecting the other face of a corner.
NORMAL_COSINE = 0.8
#: A photon farther than this fraction of the radius from the query's tangent plane is
#: on another surface (the thin-gap leak), or on a surface curving away.
PLANE_TOLERANCE = 0.25


def lookup_radius(surface_area: float, photons: int, per_estimate: int) -> float:
    """Radius whose disc holds ``per_estimate`` photons on average.

    ``surface_area`` is the scene's total surface area, so the radius scales with the
    scene (a scene modelled in millimetres gets the same estimate as in metres).
    """
    if photons <= 0 or surface_area <= 0:
        return 0.0
    return math.sqrt(per_estimate * surface_area / (math.pi * photons))


#: Mean area of a surface inside a grid cell, in cell faces: 1 for a wall aligned with
#: the grid, 3/2 averaged over orientations (Cauchy's mean cross-section of a cube).
CELL_SURFACE_FACES = 1.25
#: The radius is set so that this quantile of the photons (by their neighbourhoods'
#: density, sparsest first) has ``per_estimate`` photons per disc: below the median,
#: so that dimly lit surfaces are not starved where most photons cluster (a lamp shade).
DENSITY_QUANTILE = 0.3
#: Photons sampled to find that quantile.
DENSITY_SAMPLE = 1 << 16
#: Irradiance is precomputed at one in PRECOMPUTE_STRIDE of the even paths' photons (as
#: Christensen precomputes it at a fraction of the map), while at least
#: MIN_PRECOMPUTED remain: an estimate spans ~per_estimate photons, so neighbouring
#: photons' estimates share most of them, and a gather ray reading the nearest of a
#: sparser set reads nearly the same value. Bundled scenes' relMSE and luminance were
#: unchanged at strides 4 and 8 (1/8 and 1/16 of the map); the stage took half the
#: time (lamp room 0.28 -> 0.13 s), and the gather source's grids shrank with it. Since
#: the estimates count every other path's photons (precompute_irradiance), 8 rather
#: than 4: as many photons scanned as the odd half's at 4 (the door-ajar proxy's
#: precomputation 0.09 s either way; 0.14 s at 4), and the dim room's estimates less
#: noisy still (see precompute_irradiance).
PRECOMPUTE_STRIDE = 8
MIN_PRECOMPUTED = 1 << 14


def adapted_lookup_radius(positions: mi.Point3f, radius: float, per_estimate: int,
                          iterations: int = 8, by_area: bool = False) -> float:
    """Shrink an area-based ``radius`` to where photons actually are.

    The area-based radius assumes photons spread over every surface. They do not: most
    of a huge ground plane, the outside of a room and the back of every wall get none,
    and with the whole area counted, each estimate scanned nearly every photon (a
    2·10⁶-unit ground under a 1-unit box hung). Photons are counted per grid cell of
    the current radius; a photon's cell count c gives ~π c / CELL_SURFACE_FACES photons
    per disc, and the radius is scaled until the :data:`DENSITY_QUANTILE` photon has
    ``per_estimate``. Never grows the radius. With ``by_area`` the quantile is taken over
    the occupied cells instead of the photons: where most photons crowd into a small
    bright patch (a sun's, through a window), the photons' quantile lies in the patch,
    and the rest of the surfaces get a radius that holds a few photons.
    """
    count = dr.width(positions.x)
    if count == 0 or radius <= 0:
        return radius
    origin = mi.Point3f(dr.min(positions.x), dr.min(positions.y), dr.min(positions.z))
    table = _next_pow2(2 * count)
    sample = every_nth(count, max(1, count // DENSITY_SAMPLE))
    for _ in range(iterations):
        inv = dr.opaque(mi.Float, 1.0 / radius)
        bucket = hash_cell(cell_of(positions, origin, inv), opaque_u32(table - 1))
        counts = dr.zeros(mi.UInt32, table)
        scatter_count(counts, bucket)
        if by_area:
            occupied = dr.compress(counts > 0)
            cells = dr.gather(mi.UInt32, occupied,
                              every_nth(dr.width(occupied), max(1, dr.width(occupied) // DENSITY_SAMPLE)))
            occupancy = np.array(dr.gather(mi.UInt32, counts, cells))
        else:
            occupancy = np.array(dr.gather(mi.UInt32, counts, dr.gather(mi.UInt32, bucket, sample)))
        per_disc = math.pi * float(np.quantile(occupancy, DENSITY_QUANTILE)) / CELL_SURFACE_FACES
        if per_disc <= 1.25 * per_estimate:
            break
        radius *= max(math.sqrt(per_estimate / per_disc), 1e-3)
    return radius


def _edge_tables(samples: int = 257, grid: int = 801):
    """For a disc of radius 1 cut by a straight edge at distance h from its centre (the
    surface on the centre's side): the fraction of the Simpson kernel's mass left on
    the surface, and the kernel-weighted centroid's distance from the centre, for h
    from 1 (no cut) down to 0 (half a disc). Numerical integration, once."""
    x = (np.arange(grid) + 0.5) / grid * 2 - 1
    xx, yy = np.meshgrid(x, x)
    d2 = xx * xx + yy * yy
    k = np.where(d2 < 1, (1 - d2) ** 2, 0.0)
    total = k.sum()
    hs = np.linspace(1.0, 0.0, samples)
    mass, centroid = [], []
    for h in hs:
        inside = xx <= h
        kk = k * inside
        mass.append(kk.sum() / total)
        centroid.append(-(kk * xx).sum() / kk.sum())
    return np.array(centroid), np.array(mass)


#: Squared centroid offsets under this many times their variance are taken as noise.
EDGE_SIGNIFICANCE = 9.0
#: Kernel mass on the surface against the centroid's offset (both for a unit disc).
_EDGE_CENTROID, _EDGE_MASS = _edge_tables()


def _edge_correction(centroid2: mi.Float) -> mi.Float:
    """1 / (kernel mass on the surface), from the squared centroid offset (in radii)."""
    c = dr.sqrt(dr.maximum(centroid2, 0.0))
    table_c = mi.Float(_EDGE_CENTROID.astype(np.float32))
    table_m = mi.Float(_EDGE_MASS.astype(np.float32))
    n = len(_EDGE_CENTROID)
    # The centroid grows monotonically as h falls: find its interval.
    i = dr.binary_search(0, n - 1, lambda k: dr.gather(mi.Float, table_c, k) < c)
    i = dr.clip(i, 1, n - 1)
    c0, c1 = dr.gather(mi.Float, table_c, i - 1), dr.gather(mi.Float, table_c, i)
    m0, m1 = dr.gather(mi.Float, table_m, i - 1), dr.gather(mi.Float, table_m, i)
    t = dr.clip((c - c0) / dr.maximum(c1 - c0, 1e-12), 0.0, 1.0)
    return dr.rcp(dr.maximum(dr.lerp(m0, m1, t), _EDGE_MASS[-1]))


def _in_plane(offset, valid, query_n, radius):
    """``valid``, but for candidates off the query's plane (``offset``: candidate
    position − query position)."""
    return valid & (dr.abs(dr.dot(offset, query_n)) < PLANE_TOLERANCE * radius)


def _facing(normal, valid, query_n):
    """``valid``, but for candidates whose ``normal`` is too far from the query's."""
    return valid & (dr.dot(normal, query_n) > NORMAL_COSINE)


def _compatible(photons: PhotonMap, index, offset, valid, query_n, radius):
    """Mask of candidate photons that lie on the query's surface, on its side
    (``offset``: photon position − query position)."""
    valid = _in_plane(offset, valid, query_n, radius)
    return _facing(dr.gather(mi.Vector3f, photons.normal, index, valid), valid, query_n)


def estimate_irradiance(photons: PhotonMap, grid, query_p: mi.Point3f,
                        query_n: mi.Vector3f, radius=None, max_depth=None, min_depth=None,
                        skip_specular_paths: bool = False, active=True,
                        boundary: bool = True, without_delta_direct: bool = False,
                        delta_scale: float = 1.0, nodelta_too: bool = False):
    """Irradiance at ``query_p`` from the photons within ``radius``.

    ``grid`` is a :class:`PointGridPyramid` (the radius then adapts to the local photon
    density, and ``radius`` is ignored) or a :class:`PointGrid` (fixed ``radius``).
    Uses the normalised Simpson kernel K(d) = 3/(π r²) (1 - d²/r²)², which weights
    close photons more and goes smoothly to zero at the radius (fewer blotches than a
    box kernel). ``query_n`` must face the side from which the surface is seen.
    ``min_depth``/``max_depth`` (scalars or per-lane arrays) restrict the photons by
    their number of surface interactions: ``min_depth=2`` excludes direct light.
    ``skip_specular_paths`` excludes photons of L S* D paths (what a caustic map and
    direct lighting already count); ``without_delta_direct`` the photons that came
    straight from a delta light (``photons.delta_light`` and depth 1). ``delta_scale``
    (≤ 1): photons whose path started at a delta light count with a kernel that many
    times narrower (as many times fewer photons: a sun's patch keeps its sharp edge
    where a sky's light through the same window needs more photons per estimate).
    ``boundary`` corrects for discs that run past the
    edge of their surface (see below): without it, a Cornell box came out 1.2 % dark.
    With ``nodelta_too``, returns ``(estimate, estimate without_delta_direct)`` from one
    walk over the photons (the same sums, term for term, as two calls: a sunlit
    scene's precomputation walked them twice, 0.10 of its 0.15 s).
    """
    query_n = mi.Vector3f(query_n)
    lanes = dr.width(query_p)
    active = mi.Bool(active)
    pyramid = isinstance(grid, PointGridPyramid)
    if pyramid:
        level, radius = grid.level_of(query_p, active)
    else:
        radius = dr.opaque(mi.Float, radius) if isinstance(radius, (int, float)) else mi.Float(radius)
    inv_r2 = dr.rcp(dr.maximum(radius * radius, 1e-30))
    narrow_delta = delta_scale < 1.0 and photons.delta_light is not None
    inv_s2 = opaque_float(1.0 / max(delta_scale, 1e-3) ** 2) if narrow_delta else None

    def sums(state, power, k, offset):
        total, moment, weight, weight2 = state
        total = dr.fma(power, k, total)
        if boundary:
            # Kernel-and-power-weighted moments of the photons' offsets in the plane.
            w = k * mi.luminance(power)
            tangent = offset - query_n * dr.dot(offset, query_n)
            moment = dr.fma(tangent, w, moment)
            weight += w
            weight2 = dr.fma(w * w, dr.squared_norm(tangent), weight2)
        return total, moment, weight, weight2

    packed = photons.packed

    def read(index, ok):
        """``(normal, power, depth, specular_path, from a delta light)`` of the photons
        at ``index`` (zeros where not ``ok``): one packet load where the map is packed
        (PhotonMap.pack), else a gather per field."""
        if packed is not None:
            photon = dr.gather(mi.ArrayXf, packed, index, ok, shape=(PhotonMap.PACKED_WIDTH, dr.width(index)))
            flags = dr.reinterpret_array(mi.UInt32, photon[7])
            return (mi.Vector3f(photon[0], photon[1], photon[2]), mi.Color3f(photon[3], photon[4], photon[5]),
                    dr.reinterpret_array(mi.UInt32, photon[6]), (flags & 1) != 0, (flags & 2) != 0)
        delta = dr.gather(mi.Bool, photons.delta_light, index, ok) if photons.delta_light is not None \
            else dr.zeros(mi.Bool, dr.width(index))
        return (dr.gather(mi.Vector3f, photons.normal, index, ok), dr.gather(mi.Color3f, photons.power, index, ok),
                dr.gather(mi.UInt32, photons.depth, index, ok),
                dr.gather(mi.Bool, photons.specular_path, index, ok), delta)

    def visit(state, index, dist2, valid, offset):
        whole = state[:4]
        ok = _in_plane(offset, valid, query_n, radius)
        normal, power, depth, specular, from_delta = read(index, ok)
        ok = _facing(normal, ok, query_n)
        if min_depth is not None:
            ok &= depth >= min_depth
        if max_depth is not None:
            ok &= depth <= max_depth
        if skip_specular_paths:
            ok &= ~specular
        if without_delta_direct:
            ok &= ~(from_delta & (depth == 1))
        power = dr.select(ok, power, 0.0)
        k = dr.square(1.0 - dist2 * inv_r2)
        if narrow_delta:
            # Kernel of radius s·r for delta lights' photons, normalised to it (1/s²).
            k_delta = dr.square(dr.maximum(1.0 - dist2 * inv_r2 * inv_s2, 0.0)) * inv_s2
            k = dr.select(from_delta & ok, k_delta, k)
        if not nodelta_too:
            return sums(whole, power, k, offset)
        # (A masked-out photon adds 0·k: the same sums as the separate walk.)
        direct = ok & from_delta & (depth == 1)
        return sums(whole, power, k, offset) + sums(state[4:], dr.select(direct, 0.0, power), k, offset)

    zero = (dr.zeros(mi.Color3f, lanes), dr.zeros(mi.Vector3f, lanes), dr.zeros(mi.Float, lanes),
            dr.zeros(mi.Float, lanes))
    if nodelta_too:
        zero = zero + tuple(type(z)(z) for z in zero)
    if pyramid:
        state = grid.for_each_neighbor(
            query_p, level, zero, visit, active=active, label="photon_density_estimate",
            with_offset=True, one_loop=False)
    else:
        state = grid.for_each_neighbor(
            query_p, radius, zero, visit, active=active, label="photon_density_estimate",
            with_offset=True, one_loop=False)
    if nodelta_too:
        return _density(state[:4], inv_r2, boundary), _density(state[4:], inv_r2, boundary)
    return _density(state, inv_r2, boundary)


def _density(state, inv_r2, boundary: bool) -> mi.Color3f:
    """The irradiance estimate from a walk's sums (:func:`estimate_irradiance`)."""
    total, moment, weight, weight2 = state
    estimate = total * (3.0 * dr.inv_pi) * inv_r2
    if boundary:
        # Where the disc runs past the surface's edge (walls meeting, a table's rim),
        # the photons' centroid moves away from the edge; its offset tells how much of
        # the kernel is off the surface (for a straight edge), and the estimate is
        # divided by the part that is on it. The centroid's own noise (its variance,
        # weight2 / weight²) is subtracted first, or every estimate would look cut.
        # A centroid within EDGE_SIGNIFICANCE standard deviations of the query is noise:
        # corrected anyway, a flat interior came out 1.5 % bright.
        inv_w2 = dr.square(dr.rcp(dr.maximum(weight, 1e-30)))
        measured = dr.squared_norm(moment) * inv_w2
        noise = weight2 * inv_w2
        centroid2 = dr.select(measured > EDGE_SIGNIFICANCE * noise, measured - noise, 0.0) * inv_r2
        estimate *= dr.select(weight > 0, _edge_correction(centroid2), 1.0)
    return estimate


def precompute_stride(photons_a: int) -> int:
    """One in how many of half A's ``photons_a`` photons get precomputed irradiance
    (:data:`PRECOMPUTE_STRIDE`, fewer where that would leave under MIN_PRECOMPUTED)."""
    return int(max(1, min(PRECOMPUTE_STRIDE, photons_a // MIN_PRECOMPUTED)))


def precompute_irradiance(photons: PhotonMap, radius: float, per_estimate: float,
                          max_depth: int | None = None, caustics=None,
                          other_paths: bool = True, surface=None) -> PhotonMap:
    """Irradiance at photons (stage 2 of the paper), free of the self-term bias.

    The photons of one in :func:`precompute_stride` of the even light paths (set A)
    get the irradiance estimated from the photons of every other path (set B: the odd
    paths, and at a stride above 1 the even ones not chosen too), which are
    independent of them; A is returned with ``irradiance`` filled in, for gather rays
    to read its nearest photon.

    Why not every photon estimated from the whole map, as Christensen (2000) does: a
    photon counting itself adds 3/(π r²) of its power, +3/k where k photons fall in
    the disc. That is small where photons are dense and huge where they are sparse
    (+55 % measured in a dim, indirectly lit room). Leaving the photon out is unbiased
    at the photon, but gather rays read the *nearest* photon, which picks photons with
    large Voronoi cells, i.e. with few neighbours: 1-20 % dark. With independent sets
    neither bias exists: which photon of A is nearest says nothing about B. B was the
    odd half only: at a stride of 8, 15/16 of the paths now, and where photons are
    sparse (a room lit through a door: a median of 2 photons of the odd half per disc)
    the estimates' noise is the image's, one seed to the next: the door-ajar proxy's
    mean moved by sd 0.94 % over 16 photon seeds (stride 4, odd half), 0.72 % with the
    rest at stride 4, now 0.50 %; relMSE 2.12e-3 -> 2.04e-3. With ``other_paths``
    False, B is the odd half only (open scenes, where bounced light is little of the
    image: the pipeline's choice, see ``pipeline.OTHER_PATHS_MIN_BOUNCED``).

    ``radius`` is the base radius of the estimates, which shrinks where photons are
    dense (:class:`PointGridPyramid`) so that a disc of B holds about ``per_estimate``
    times B's share of the paths. ``max_depth`` limits the photons counted (camera paths
    of bounded length). ``caustics`` (``(map, grid, radius, delta_scale)`` of the
    caustic map, or None): the caustic map's irradiance is estimated at A's photons too
    (``irradiance_caustic``), for gather rays that bounce on at a near hit
    (:func:`~pmic_integrator.gather.trace_gather_rays`).

    Where the even paths' photons are sparse (:data:`SPARSE_CELL_RADII`), every one of
    them is in A too, estimated from the odd half: one in ``stride`` left a dim room
    with a precomputed photon every few lookup radii.

    ``surface`` (``(scene, seed, ray offset)``, or None): each estimate is divided by
    the part of its disc that lies on its surface, measured by probes traced over it
    (:func:`~pmic_integrator.boundary.surface_mass`), instead of the photons' centroid
    (:func:`estimate_irradiance`'s ``boundary``), which misses discs cut on two sides.
    """
    if photons.count == 0:
        return PhotonMap.empty()
    half_a, half_b = photons.split_by_path()
    if half_a.count == 0 or half_b.count == 0 or half_b.paths_emitted == 0:
        return PhotonMap.empty()
    stride = precompute_stride(half_a.count)
    sparse = None
    if stride > 1:
        # Whole paths: one in ``stride`` of the even ones; with ``other_paths`` B is the
        # rest of the map, else it stays the odd half.
        even = (photons.path & 1) == 0
        chosen = even & ((photons.path >> 1) % opaque_u32(stride) == 0)
        sparse = even & ~chosen & _sparse_even(photons, even, radius, stride)
        half_a = photons.select(dr.compress(chosen))
        if other_paths:
            half_b = photons.select(dr.compress(~chosen))
            paths_a = -(-(photons.paths_emitted - photons.paths_emitted // 2) // stride)
            half_b.paths_emitted = photons.paths_emitted - paths_a
    delta = photons.delta_light is not None and bool(dr.any(photons.delta_light))
    settings = (photons.paths_emitted, radius, per_estimate, max_depth, caustics, surface, delta)
    half_a = _estimated_at(half_a, half_b, *settings)
    extra = dr.compress(sparse) if sparse is not None else None
    if extra is not None and dr.width(extra):
        # Where even photons are sparse, every one of them is precomputed too, from the
        # odd half only: B (the rest) would be thinned exactly there by taking them.
        odd = photons.select(dr.compress((photons.path & 1) == 1))
        odd.paths_emitted = photons.paths_emitted // 2
        half_a = half_a.joined(_estimated_at(photons.select(extra), odd, *settings))
        dr.eval(half_a)
    return half_a


#: Even photons in cells (two lookup radii wide) that hold fewer even photons than the
#: stride are all precomputed (precompute_irradiance): one in ``stride`` left such
#: cells mostly without a precomputed photon, and a gather hit there read the nearest
#: one, several radii off, where photons (and light) are denser. The door-ajar kind's
#: dim room came out 1-11 % bright (docs/results.md).
SPARSE_CELL_RADII = 2.0


def _sparse_even(photons: PhotonMap, even, radius: float, stride: int) -> mi.Bool:
    """Per photon: whether the even photons in its cell (:data:`SPARSE_CELL_RADII`) are
    fewer than ``stride`` (a test on the even half only, so the odd half that estimates
    those photons is independent of which are chosen)."""
    lanes = dr.compress(even)
    positions = dr.gather(mi.Point3f, photons.position, lanes)
    grid = PointGrid.build(positions, SPARSE_CELL_RADII * radius)
    count = dr.zeros(mi.UInt32, photons.count)
    dr.scatter(count, grid.occupancy(positions), lanes)
    return even & (count < stride)


def _estimated_at(half_a: PhotonMap, half_b: PhotonMap, paths: int, radius: float, per_estimate: float,
                  max_depth, caustics, surface, delta: bool) -> PhotonMap:
    """``half_a`` with its irradiance estimated from ``half_b`` (see
    :func:`precompute_irradiance`); ``paths``: the whole map's paths."""
    share = half_b.paths_emitted / paths
    grid_b, order = PointGridPyramid.build(half_b.position, radius, share * per_estimate)
    half_b = half_b.select(order).pack()
    # Opaque: it moves with the photon seed (a constant would compile a kernel per seed).
    scale = opaque_float(paths / half_b.paths_emitted)
    # Without the direct light of delta lights (a sun, a spot) too, where there are
    # any: gather rays and camera paths sample those themselves (GatherSource.irradiance_at).
    irradiance = estimate_irradiance(half_b, grid_b, half_a.position, half_a.normal,
                                     max_depth=max_depth, nodelta_too=delta, boundary=surface is None)
    if surface is not None:
        scene, seed, offset = surface
        mass = boundary.surface_mass(scene, half_a.position, half_a.normal,
                                     grid_b.level_of(half_a.position)[1], PLANE_TOLERANCE,
                                     NORMAL_COSINE, seed, offset)
        scale = scale * dr.rcp(dr.maximum(mass, boundary.MIN_SURFACE_MASS))
    if delta:
        irradiance, nodelta = irradiance[0] * scale, irradiance[1] * scale
        half_a.irradiance_nodelta = finite(nodelta)
    else:
        irradiance = irradiance * scale
    half_a.irradiance = finite(irradiance)
    if caustics is not None:
        caustic_map, caustic_grid, caustic_radius, delta_scale = caustics
        caustic = estimate_irradiance(caustic_map, caustic_grid, half_a.position, half_a.normal,
                                      caustic_radius, delta_scale=delta_scale)
        half_a.irradiance_caustic = finite(caustic)
    half_a.paths_emitted = paths
    dr.eval(half_a.irradiance, half_a.irradiance_nodelta, half_a.irradiance_caustic)
    return half_a


def nearest_photon(photons: PhotonMap, grid: PointGrid, query_p: mi.Point3f,
                   query_n: mi.Vector3f, radius, active=True, octant: bool = False):
    """Index of the nearest photon on the query's surface within ``radius``.

    Returns ``(index, found)``; ``found`` is False where no compatible photon is near.
    """
    lanes = dr.width(query_p)
    query_n = mi.Vector3f(query_n)
    # Opaque: a radius measured from the photons must not be baked into the kernel.
    radius = opaque_float(radius) if isinstance(radius, (int, float)) else radius

    def visit(state, index, dist2, valid, offset, normal=None):
        best_d2, best = state
        if normal is None:
            ok = _compatible(photons, index, offset, valid & (dist2 < best_d2), query_n, radius)
        else:  # (the normal read with the grid entry: PointGrid.pack)
            ok = _facing(normal, _in_plane(offset, valid & (dist2 < best_d2), query_n, radius), query_n)
        closer = ok & (dist2 < best_d2)
        return dr.select(closer, dist2, best_d2), dr.select(closer, index, best)

    init = (dr.full(mi.Float, dr.inf, lanes), dr.zeros(mi.UInt32, lanes))
    with_normal = isinstance(grid, PointGrid) and grid.packed is not None and grid.packed.has_normals
    best_d2, best = grid.for_each_neighbor(query_p, radius, init, visit, active=active,
                                           label="nearest_photon",
                                           with_offset="normal" if with_normal else True, octant=octant)
    return best, dr.isfinite(best_d2)


#: Caustic photons at which :func:`caustic_standout` measures (at most; evenly spread).
STANDOUT_QUERIES = 400


def caustic_sample(photons: PhotonMap) -> mi.UInt32:
    """Up to :data:`STANDOUT_QUERIES` of the map's caustic photons (L S+ D: light, then
    delta or glossy bounces only, then a diffuse surface), evenly spread over it."""
    chosen = dr.compress(photons.caustic)
    count = dr.width(chosen)
    if count == 0:
        return chosen
    return dr.gather(mi.UInt32, chosen, every_nth(count, -(-count // STANDOUT_QUERIES)))


def caustic_standout(photons: PhotonMap, radius: float, per_estimate: float) -> float:
    """How far the caustic light of a global map stands out from the light around it:
    at its :func:`caustic_sample`, the caustic share of the photons' irradiance
    estimate there, averaged with the photons' power as weights; 0 where it
    has none. About 0.5 for focused caustics (a glass sphere's spot, a sunlit glass
    cube), 0.1 where glass spreads a lamp's light through a room (the white room's, the
    stairwell kind's glass drop): where a render for a denoiser may trace them instead
    of mapping them (pipeline.CAUSTIC_MIN_STANDOUT). The global map samples light paths
    as a caustic pass does up to their first diffuse bounce, so this is known before
    that pass."""
    chosen = caustic_sample(photons)
    if dr.width(chosen) == 0:
        return 0.0
    query_p = dr.gather(mi.Point3f, photons.position, chosen)
    query_n = dr.gather(mi.Vector3f, photons.normal, chosen)
    weight = mi.luminance(dr.gather(mi.Color3f, photons.power, chosen))
    ordered, grid = sort_into_grid(photons, radius, per_estimate)

    def estimate(**which):
        return mi.luminance(estimate_irradiance(ordered, grid, query_p, query_n, boundary=False, **which))

    total = estimate()
    # Caustic: bounced (depth >= 2) and along a delta/glossy path all the way.
    caustic_part = estimate(min_depth=2) - estimate(min_depth=2, skip_specular_paths=True)
    share = dr.select(total > 0, dr.clip(caustic_part / dr.maximum(total, 1e-30), 0.0, 1.0), 0.0)
    weights = dr.sum(weight)[0]
    return float(dr.sum(share * weight)[0] / weights) if weights > 0 else 0.0


def sort_into_grid(photons, radius: float, per_estimate: float, levels: int | None = None):
    """``(photons reordered, PointGridPyramid)``: the map's grid pyramid for estimates
    of about ``per_estimate`` photons within ``radius``, and the photons in its order,
    so that a lookup reads neighbouring memory instead of jumping across the map.
    An empty map gives ``(photons, None)``."""
    if photons.count == 0:
        return photons, None
    grid, order = PointGridPyramid.build(photons.position, radius, per_estimate, levels)
    return photons.select(order).pack(), grid



#: Photon normals are put in 64 bins of the octahedral map (8 × 8 squares over the
#: unfolded octahedron). An estimate counts photons within acos(NORMAL_COSINE) = 36.9°
#: of the query normal: a bin all of whose normals are further off holds none it
#: counts (:func:`_bin_limits`: each bin's angular radius about its centre, measured
#: once with :func:`_normal_bin` itself).
_BIN_SIDE = 8
#: A bin is wanted where its centre is within 36.9° + its reach + this margin (the
#: reach is sampled, and float rounding) of the query normal.
_BIN_MARGIN = math.radians(3.0)


def _normal_bin(normal: mi.Vector3f) -> mi.UInt32:
    """Each normal's octahedral bin, in [0, ``_BIN_SIDE``²)."""
    d = normal / dr.maximum(dr.abs(normal.x) + dr.abs(normal.y) + dr.abs(normal.z), 1e-30)
    fold_u = (1.0 - dr.abs(d.y)) * dr.select(d.x >= 0, 1.0, -1.0)
    fold_v = (1.0 - dr.abs(d.x)) * dr.select(d.y >= 0, 1.0, -1.0)
    u = dr.select(d.z < 0, fold_u, d.x)
    v = dr.select(d.z < 0, fold_v, d.y)
    i = mi.UInt32(dr.clip(dr.floor((u + 1.0) * (0.5 * _BIN_SIDE)), 0, _BIN_SIDE - 1))
    j = mi.UInt32(dr.clip(dr.floor((v + 1.0) * (0.5 * _BIN_SIDE)), 0, _BIN_SIDE - 1))
    return j * _BIN_SIDE + i


def normal_bins(normal: mi.Vector3f) -> mi.UInt64:
    """The bit of each normal's octahedral bin (``_BIN_SIDE`` × ``_BIN_SIDE``)."""
    return mi.UInt64(1) << mi.UInt64(_normal_bin(normal))


@functools.lru_cache(maxsize=None)
def _bin_limits(samples: int = 1 << 18):
    """Per bin, its mean direction and the cosine above which a query normal may count
    one of its photons (36.9° + the largest angle of a normal in the bin from its
    centre + ``_BIN_MARGIN``), measured over ``samples`` random directions binned by
    :func:`_normal_bin`. Once per process, at the first use (not at import: 0.06 s)."""
    d = np.random.default_rng(7).normal(size=(samples, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = np.array(_normal_bin(mi.Vector3f(*(d[:, k].astype(np.float32) for k in range(3)))))
    centre = np.zeros((_BIN_SIDE ** 2, 3))
    np.add.at(centre, b, d)
    centre /= np.linalg.norm(centre, axis=1, keepdims=True)
    reach = np.zeros(_BIN_SIDE ** 2)
    np.maximum.at(reach, b, np.arccos(np.clip((d * centre[b]).sum(1), -1, 1)))
    limits = [math.cos(min(math.pi, math.acos(NORMAL_COSINE) + r + _BIN_MARGIN)) for r in reach]
    return [tuple(float(c) for c in row) for row in centre.astype(np.float32)], limits


#: The bins' own hash table holds this many buckets per photon: the 27 lookups of a
#: query meet another cell's bucket (a collision, whose bins count too) rarely.
BIN_TABLE_PER_PHOTON = 4


@dataclass
class NormalBins:
    """Per cell of a map's level-0 grid (hashed into a table of their own), the bins
    of its photons' normals: which estimates can count any (:func:`may_count_photons`)."""

    origin: mi.Point3f
    cell_size: float
    table_mask: int
    bins: mi.UInt64

    @staticmethod
    def build(photons: PhotonMap, grid) -> "NormalBins":
        table = _next_pow2(max(BIN_TABLE_PER_PHOTON * photons.count, 1024))
        bins = dr.zeros(mi.UInt64, table)
        cell = cell_of(photons.position, grid.origin, dr.opaque(mi.Float, 1.0 / grid.radius))
        bucket = hash_cell(cell, dr.opaque(mi.UInt32, table - 1))
        dr.scatter_reduce(dr.ReduceOp.Or, bins, normal_bins(photons.normal), bucket)
        dr.eval(bins)
        return NormalBins(grid.origin, float(grid.radius), table - 1, bins)


def may_count_photons(normal_bins_: NormalBins, p: mi.Point3f, n: mi.Vector3f, active=True) -> mi.Bool:
    """False where an estimate at (p, n) is certainly 0: no photon in the 3×3×3
    level-0 cells around p (which hold every photon a disc of any level reaches) has a
    normal the estimate could count (:func:`_bin_limits`). True may still estimate 0."""
    lanes = dr.width(p)
    wanted = mi.UInt64(0)
    centres, limits = _bin_limits()
    for b in range(_BIN_SIDE ** 2):
        near = dr.dot(n, mi.Vector3f(*centres[b])) > limits[b]
        wanted |= dr.select(near, mi.UInt64(1 << b), mi.UInt64(0))
    g = normal_bins_
    center = cell_of(p, g.origin, dr.opaque(mi.Float, 1.0 / g.cell_size))
    mask = dr.opaque(mi.UInt32, g.table_mask)
    found = dr.zeros(mi.UInt64, lanes)
    for j in range(27):
        cell = center + _neighbour_offset(mi.UInt32(j))
        found |= dr.gather(mi.UInt64, g.bins, hash_cell(cell, mask), active)
    return mi.Bool(active) & ((found & wanted) != 0)
