"""How much of a density estimate's disc lies on the surface it estimates (stage 2).

An estimate at a photon divides the power of the photons it counts by the area of its
disc. Where the disc runs past the surface's edge (a pillar narrower than the disc, a
ledge, a column curving away, a window frame), the photons it counts fall on less area
than that, and the estimate comes out dark. :func:`irradiance.estimate_irradiance`
corrects a straight edge from the photons' centroid, which moves away from the edge; a
strip cut on both sides leaves the centroid in place and went uncorrected: photons whose
disc lay less than 0.6 on their surface held 0.54 of the irradiance `path` traces
there, 13 % of Sponza's light. Probes traced over the disc measure the surface under it
instead, whatever its shape (docs/tuning.md, ``SURFACE_PROBED_ESTIMATES``).

Where something stands on the surface (a wall on a floor: a concave corner) the disc
is not corrected: the light there dips towards the wall, which hides half the scene
from the floor at its foot, and an estimate scaled up to the even field of a free
edge came out too bright (a classroom kind lit through its windows: 1.06 of `path`
corrected there too, 1.014 not).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import streams
from ._jit import channel_mean, opaque_u32, rng as make_rng, surface_offset

#: Probes per estimate: SURFACE_PROBE_STRATA² stratified over the disc.
SURFACE_PROBE_STRATA = 8
#: An estimate is divided by its disc's mass on the surface, but by no less than this:
#: at most four times brighter (a disc that barely touches surface is mostly noise).
MIN_SURFACE_MASS = 0.25


def surface_mass(scene: mi.Scene, p: mi.Point3f, n: mi.Vector3f, radius: mi.Float,
                 plane_tolerance: float, normal_cosine: float, seed: int,
                 offset: float) -> mi.Float:
    """The mass of the normalised Simpson kernel of ``radius`` about ``p`` that lies on
    surface an estimate at ``(p, n)`` counts photons of (within ``plane_tolerance``
    radii of the plane, facing within ``normal_cosine`` of ``n``) or behind something
    standing on it: 1 for an open plane and at a wall's foot, 0.5 at a free straight
    edge, the strip's share for a strip narrower than the disc.

    Each probe is a point of the disc, lifted off the plane. Where the lifted segment
    from ``p`` to it is blocked (a wall), it counts whole; else a ray down from it must
    meet a surface within the tolerance below the plane. The lift is the tolerance, or
    half the room above ``p`` where something overhangs it (the narrow gap between a
    ceiling light and the ceiling)."""
    lanes = dr.width(p.x)
    if lanes == 0:
        return mi.Float()
    p, n, radius = mi.Point3f(p), mi.Vector3f(n), mi.Float(radius)
    frame = mi.Frame3f(n)
    tolerance = plane_tolerance * radius
    start = p + n * surface_offset(p, offset)
    overhang = scene.ray_intersect_preliminary(_segment(start, n, tolerance), active=mi.Bool(True))
    lift = dr.select(overhang.is_valid(), 0.5 * overhang.t, tolerance)
    origin = p + n * lift
    strata = SURFACE_PROBE_STRATA
    probes = strata * strata
    inv_r2 = dr.rcp(dr.maximum(radius * radius, 1e-30))

    def probe(i, mass, rng):
        # A point of the disc drawn from the kernel itself (s = ρ²/r² has density
        # 3(1 - s)²): an open plane gives 1 with no noise.
        u = mi.Point2f((mi.Float(i % strata) + rng.next_float32()) * (1.0 / strata),
                       (mi.Float(i // strata) + rng.next_float32()) * (1.0 / strata))
        s = 1.0 - dr.cbrt(1.0 - u.x)
        sin_phi, cos_phi = dr.sincos(2.0 * dr.pi * u.y)
        across = frame.to_world(mi.Vector3f(cos_phi, sin_phi, 0.0)) * (dr.sqrt(s) * radius)
        length = dr.norm(across)
        blocked = _opaque_hit(scene, _segment(origin, across * dr.rcp(dr.maximum(length, 1e-30)), length),
                              length > 0).is_valid()
        below = _opaque_hit(scene, _segment(origin + across, -n, lift + tolerance), ~blocked)
        cosine = dr.abs(dr.dot(below.n, n))
        on = ~blocked & below.is_valid() & (cosine > normal_cosine)
        # The kernel at the surface point over the kernel at the probe (the point lies
        # off the plane), over the cosine (a surface tilted to the plane holds more of
        # the kernel than its shadow on the plane).
        d2 = dr.minimum(dr.squared_norm(below.p - p) * inv_r2, 1.0)
        weight = dr.square((1.0 - d2) * dr.rcp(dr.maximum(1.0 - s, 1e-6))) \
            * dr.rcp(dr.maximum(cosine, normal_cosine))
        counted = dr.select(on, dr.minimum(weight, 1.0 / normal_cosine), dr.select(blocked, 1.0, 0.0))
        return i + 1, mass + counted, rng

    _, mass, _ = dr.while_loop((dr.zeros(mi.UInt32, lanes), dr.zeros(mi.Float, lanes),
                                make_rng(lanes, seed, stream=streams.SURFACE_MASS)),
                               lambda i, mass, rng: i < opaque_u32(probes), probe,
                               label="surface_mass")
    return mass * (1.0 / probes)


def _segment(origin: mi.Point3f, direction: mi.Vector3f, length: mi.Float) -> mi.Ray3f:
    """A ray that ends after ``length`` (``mi.Ray3f``'s third positional argument is
    its time, not its end)."""
    ray = mi.Ray3f(origin, direction)
    ray.maxt = length
    return ray


def _opaque_hit(scene: mi.Scene, ray: mi.Ray3f, active) -> mi.SurfaceInteraction3f:
    """The first hit along ``ray`` but where a surface's opacity mask is clear (a
    ``mask`` BSDF: the gaps of blinds, around a leaf): photons cross it there, so it
    neither ends a surface nor holds one. One such hit is passed over."""
    si = scene.ray_intersect(ray, active)
    bsdf = si.bsdf()
    see_through = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Null)
    see_through &= channel_mean(mi.Spectrum(bsdf.eval_null_transmission(si, see_through))) > 0.5
    beyond = si.spawn_ray(ray.d)
    beyond.maxt = ray.maxt - si.t
    second = scene.ray_intersect(beyond, see_through & (ray.maxt > si.t))
    si[see_through] = second
    return si
