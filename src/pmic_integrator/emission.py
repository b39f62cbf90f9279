"""Emission of light-path (photon) rays that is correct for rotated environment maps.

Mitsuba 3.9's ``envmap`` emitter places the origin of a ray from ``sample_ray`` on a
disk that is perpendicular to the sampled direction *in the emitter's local frame*
(``Frame3f(d)`` with the un-rotated ``d``), while the ray itself travels along the
rotated (world-space) direction. As soon as ``to_world`` contains a rotation, the disk
is tilted against the ray: rays cross the scene with a density that is ``1/|cos a|``
too high (``a`` is the angle between the local and the world direction) inside an
ellipse of minor axis ``R |cos a|``, and not at all outside it, while the weight still
assumes an untilted disk of area ``pi R^2``. Light tracing (``ptracer``) and photon
emission through ``scene.sample_emitter_ray`` are then too bright (and very noisy, the
``1/|cos a|`` factor has no finite variance). See ``validation/envmap_emission_check.py``.

:func:`sample_emitter_rays` is a drop-in replacement for ``scene.sample_emitter_ray``.
For every *infinite* emitter (``envmap``, ``constant``, ``directional``) it samples the
direction with the emitter's own ``sample_direction`` (which handles ``to_world``
correctly and is what ``path`` uses) and puts the origin on the rectangle, perpendicular
to the world-space direction, that bounds the projection of the scene's bounding box
along it, behind the bounding sphere, with weight ``(L / pdf(direction)) * A`` (for
``directional``: ``E * A``), ``A`` the rectangle's area. Every other emitter (area,
point, spot, ...) uses Mitsuba's own ``sample_ray`` unchanged.

Mitsuba shoots from the bounding sphere's disk (``pi R^2``), which any direction sees
whole; the box's projection is smaller, the more so for flat scenes: in the material
preview (a 12 m backdrop) 89 % of the disk's rays met nothing. Both are unbiased:
every ray that can reach the geometry starts inside either.
"""
from __future__ import annotations

from typing import NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np

from . import spectra
from ._jit import ONE_MINUS_EPSILON

__all__ = ["sample_emitter_rays", "sample_emitter_direction", "choose_emitter", "emitter_order", "emitter_pmf",
           "emitter_subset", "soft_pdf_scale", "is_delta",
           "emission_sphere", "emission_bounds", "scene_bbox", "focus_box", "focus_rings", "shape_boxes", "EmissionBounds"]

#: The rectangle that infinite emitters shoot from is widened by this fraction of the
#: bounding sphere's radius on each side: rounding must not cut off a ray that would
#: graze the box.
RECTANGLE_MARGIN = 1e-4
#: Infinite emitters (skies, suns) of a scene whose geometry but one shape fits in a box
#: under this fraction of the whole scene's diagonal (a building on a ground plane 20-30
#: times its size: the public classroom's 221 m ground; the classroom kind 0.035) shoot
#: part of their rays (:data:`FOCUS_SHARE`) across that box, the *focus*
#: (:func:`focus_box`). Shot across the whole box, 5 of 50 000 photons landed in the
#: classroom kind's room, lit through its windows. Scenes at 0.15-0.18 (the material
#: preview's and the torus's floors, the bundled exterior) are left as they were.
#: docs/tuning.md ("Photons and emission") has the measurement.
FOCUS_MAX_RATIO = 0.1
#: ...this share of those rays; the rest cross rings round the focus and the whole box
#: (:data:`FOCUS_RING_WIDENING`), so that every ray that can reach the geometry keeps
#: some density. The lookup radius is set by the focus's photons alone
#: (pipeline._in_focus), not by the sparser ones outside. One half: over the classroom
#: kind's photon seeds 0-127 the spread of the photon power landing in its room was
#: 4.7 % of its mean at 0.5, 4.8 % at 0.45, 9.6 % at 0.55, 34 % at 0.6 (one path from
#: the far ground) and 17 % at 0.3; its images' (photon seeds 0-15) 1.4 % at 0.5,
#: 3.0 % at 0.45, 4.4 % at 0.6. docs/tuning.md, "Photons and emission", has the
#: measurement (``benchmarks/focus_spread.py``).
FOCUS_SHARE = 0.5
#: ...and the focus box is the box of the rest of the geometry widened on every side by
#: this fraction of its diagonal: the ground beside a building is what its windows see.
FOCUS_MARGIN = 0.25
#: The rest of the rays cross *rings*: the focus widened FOCUS_RING_WIDENING, its
#: square, ... times about its centre (within the whole box), while a ring's diagonal
#: is under FOCUS_RING_MAX_RATIO of the whole's, and the whole box last, each level with
#: FOCUS_RING_GROWTH times the share of the one before (the classroom kind: one ring,
#: 55 × 46 m, 0.4 of the rays, the whole 220 m ground 0.1). Why: with the focus alone
#: (three quarters of the rays, the rest across the whole box) a photon from the ground
#: beyond the focus that bounced in through a window carried ~700x the median power of
#: the room's photons, one such photon up to 28 % of the room's photon power, and that
#: power moved by 13.6 % of its mean from one photon seed to the next (4.7 % with the
#: rings; the images' 1.8 % → 1.4 %, default photon seed 0.981 → 0.992 of the
#: reference). Shares growing outwards (√W per level: a model of the sun's light that the
#: ground sends through the windows puts its variance lowest there) measured no better
#: (room 5.0 %, images 2.0 %) and placed 40 % more records; docs/tuning.md.
FOCUS_RING_WIDENING = 4.0
FOCUS_RING_GROWTH = 0.25
FOCUS_RING_MAX_RATIO = 0.5


def scene_bbox(scene: mi.Scene) -> mi.ScalarBoundingBox3f:
    """The scene's bounding box, from its shapes; meshes are bounded by their vertices.

    Neither ``scene.bbox()`` nor a mesh's own ``bbox()`` is enough: Mitsuba 3.9 merges
    shapes of one material loaded with ``load_dict`` into one mesh, and that mesh's
    box is either invalid (then ``scene.bbox()`` leaves it out: a room of six walls
    around a 6 cm lamp had a "diagonal" of 0.10 instead of 5.6, records 100 times too
    small, a 44 s cache stage) or spans only some of the merged parts (an 8 m ground
    merged with two 2.4 m boxes reported 2.4 m: sunlight reached the ground within 2 m
    of the centre only, and indirect light came out half of ``path``'s).
    """
    return _union(shape_boxes(scene))


def _union(boxes: list) -> mi.ScalarBoundingBox3f:
    whole = mi.ScalarBoundingBox3f()
    for box in boxes:
        whole.expand(box)
    return whole


def shape_boxes(scene: mi.Scene) -> list:
    """The valid bounding boxes of the scene's shapes (meshes bounded by their vertices:
    see :func:`scene_bbox`)."""
    boxes = []
    for shape in scene.shapes():
        if shape.is_mesh():
            if shape.vertex_count() == 0:
                continue
            v = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
            v = v[np.all(np.isfinite(v), axis=1)]
            if len(v):
                box = mi.ScalarBoundingBox3f(mi.ScalarPoint3f(*v.min(0)), mi.ScalarPoint3f(*v.max(0)))
                boxes.append(box)
        else:
            part = shape.bbox()
            if part.valid():
                boxes.append(part)
    return boxes


def _diagonal(box) -> float:
    return float(dr.norm(box.extents())) if box.valid() else 0.0


def focus_box(scene: mi.Scene, boxes: list | None = None):
    """Where infinite emitters shoot :data:`FOCUS_SHARE` of their rays: the box of every
    shape but the one of the largest box, widened by :data:`FOCUS_MARGIN`, where it is
    under :data:`FOCUS_MAX_RATIO` of the scene's diagonal (a building on a vast ground);
    else None. (Shapes Mitsuba merged into one mesh count as one: a ground merged with
    the building leaves no focus.)"""
    boxes = shape_boxes(scene) if boxes is None else boxes
    if len(boxes) < 2:
        return None
    whole = _union(boxes)
    largest = max(range(len(boxes)), key=lambda i: _diagonal(boxes[i]))
    rest = mi.ScalarBoundingBox3f()
    for i, box in enumerate(boxes):
        if i != largest:
            rest.expand(box)
    diagonal = _diagonal(rest)
    if not diagonal > 0 or diagonal >= FOCUS_MAX_RATIO * _diagonal(whole):
        return None
    margin = mi.ScalarVector3f(FOCUS_MARGIN * diagonal)
    # (Within the whole box: its projection then lies within the whole's rectangle.)
    return mi.ScalarBoundingBox3f(dr.maximum(rest.min - margin, whole.min),
                                  dr.minimum(rest.max + margin, whole.max))


def emission_sphere(scene: mi.Scene) -> tuple[mi.ScalarPoint3f, float]:
    """Centre and radius of the disk that infinite emitters shoot their rays from.

    Mitsuba's choice for its infinite emitters, the bounding sphere of the scene's
    bounding box enlarged by ``RayEpsilon`` (or a tiny sphere at the origin for a scene
    without geometry), but of the box of :func:`scene_bbox`: ``scene.bbox()`` leaves
    out merged meshes, and a ground merged with the rest of a scene got sunlight only
    within 2 m of its centre (indirect light half of ``path``'s). Any sphere that
    contains the geometry gives an unbiased result.
    """
    bounds = emission_bounds(scene)
    return bounds.center, bounds.radius


class EmissionBounds(NamedTuple):
    """What infinite emitters shoot their rays from (:func:`emission_bounds`)."""

    center: mi.ScalarPoint3f  #: of :func:`emission_sphere`
    radius: float
    box: object  #: ``ScalarBoundingBox3f`` whose projection they cross (None: no geometry)
    focus: object = None  #: :func:`focus_box` (None: none)
    rings: tuple = ()  #: :func:`focus_rings`


def emission_bounds(scene: mi.Scene) -> EmissionBounds:
    """:func:`emission_sphere`, the box whose projection infinite emitters shoot their
    rays across and the focus box (:func:`focus_box`), from one pass over the meshes."""
    eps = float(mi.math.RayEpsilon)
    boxes = shape_boxes(scene)
    bbox = _union(boxes)
    if not bbox.valid():
        return EmissionBounds(mi.ScalarPoint3f(0.0), eps, None)
    bsphere = bbox.bounding_sphere()
    focus = focus_box(scene, boxes)
    return EmissionBounds(mi.ScalarPoint3f(bsphere.center), max(eps, float(bsphere.radius) * (1.0 + eps)),
                          bbox, focus, focus_rings(focus, bbox))


def focus_rings(focus, whole) -> tuple:
    """The boxes between ``focus`` and ``whole`` that infinite emitters shoot part of
    their rays across (:data:`FOCUS_RING_WIDENING`); () without a focus."""
    if focus is None:
        return ()
    center, half = (focus.min + focus.max) * 0.5, (focus.max - focus.min) * 0.5
    rings = []
    for level in range(1, 32):  # (a bound: the whole box is reached long before)
        widening = FOCUS_RING_WIDENING ** level
        ring = mi.ScalarBoundingBox3f(dr.maximum(center - half * widening, whole.min),
                                      dr.minimum(center + half * widening, whole.max))
        if not _diagonal(ring) < FOCUS_RING_MAX_RATIO * _diagonal(whole):
            break
        rings.append(ring)
    return tuple(rings)


def _box_rectangle(d: mi.Vector3f, center: mi.Point3f, radius: float, box):
    """The frame (s, t) of ``d`` and the bounds of the box's projection on it,
    relative to ``center``, widened by RECTANGLE_MARGIN: ``(s, t, s_lo, s_hi, t_lo, t_hi)``."""
    frame = mi.Frame3f(d)
    s_lo = t_lo = mi.Float(dr.inf)
    s_hi = t_hi = mi.Float(-dr.inf)
    for k in range(8):
        corner = box.corner(k)
        rel = mi.Vector3f(corner[0], corner[1], corner[2]) - center
        ps, pt = dr.dot(frame.s, rel), dr.dot(frame.t, rel)
        s_lo, s_hi = dr.minimum(s_lo, ps), dr.maximum(s_hi, ps)
        t_lo, t_hi = dr.minimum(t_lo, pt), dr.maximum(t_hi, pt)
    margin = RECTANGLE_MARGIN * radius
    return frame.s, frame.t, s_lo - margin, s_hi + margin, t_lo - margin, t_hi + margin


def _area(rectangle) -> mi.Float:
    s_lo, s_hi, t_lo, t_hi = rectangle
    return (s_hi - s_lo) * (t_hi - t_lo)


def _levels(box, focus, rings) -> list:
    """``(box, share)`` of each rectangle an infinite emitter's rays cross: the focus
    (:data:`FOCUS_SHARE`), then its rings and the whole box last, each with
    :data:`FOCUS_RING_GROWTH` times the share of the one before; or the whole box alone."""
    if focus is None:
        return [(box, 1.0)]
    parts = [FOCUS_RING_GROWTH ** k for k in range(len(rings) + 1)]
    rest = [(1.0 - FOCUS_SHARE) * part / sum(parts) for part in parts]
    return [(focus, FOCUS_SHARE)] + list(zip(list(rings) + [box], rest))


def _rectangle_origin(d: mi.Vector3f, center: mi.Point3f, radius: float, levels: list,
                      sample: mi.Point2f):
    """``(origin, 1 / density)`` of an infinite emitter's ray along ``d``, behind the
    bounding sphere, on one of the rectangles bounding the projections of ``levels``'s
    boxes (:func:`_levels`: the whole box last), chosen by ``sample.x`` with the
    levels' shares. The density is the mixture's (one sample of it; unbiased: the whole
    rectangle keeps a share, and every other box lies within it)."""
    s, t, *whole = _box_rectangle(d, center, radius, levels[-1][0])
    if len(levels) == 1:
        s_lo, s_hi, t_lo, t_hi = whole
        return center + s * dr.lerp(s_lo, s_hi, sample.x) + t * dr.lerp(t_lo, t_hi, sample.y) - d * radius, \
            _area(whole)
    rectangles = [_box_rectangle(d, center, radius, box)[2:] for box, _ in levels[:-1]] + [whole]
    ps = pt = mi.Float(0.0)
    start = 0.0
    for k, ((_, share), (s_lo, s_hi, t_lo, t_hi)) in enumerate(zip(levels, rectangles)):
        chosen = sample.x >= start
        if k < len(levels) - 1:
            chosen &= sample.x < start + share
        u = dr.minimum((sample.x - start) / share, ONE_MINUS_EPSILON)
        ps = dr.select(chosen, dr.lerp(s_lo, s_hi, u), ps)
        pt = dr.select(chosen, dr.lerp(t_lo, t_hi, sample.y), pt)
        start += share
    density = levels[-1][1] / _area(whole)  # (every origin lies within the whole)
    for (_, share), rectangle in zip(levels[:-1], rectangles):
        s_lo, s_hi, t_lo, t_hi = rectangle
        inside = (ps >= s_lo) & (ps <= s_hi) & (pt >= t_lo) & (pt <= t_hi)
        density += dr.select(inside, share / _area(rectangle), 0.0)
    return center + s * ps + t * pt - d * radius, dr.rcp(density)


def emitter_order(scene: mi.Scene) -> list[int]:
    """Indices into ``scene.emitters()`` sorted by what each emitter is (id, kind,
    parameters, the shape of an area light), not by the order Mitsuba loaded them in:
    that order changes from one process to the next (seen: the lamp room's two lamps
    swapped in a quarter of the loads), and with it which light a random number picks.
    (The key reads each area light's bounding box back from the device: with one
    emitter there is nothing to sort, and a render of the Cornell box made 248 such
    reads, 112 of them in its camera pass: ``benchmarks/kernel_report.py``.)"""
    if len(scene.emitters()) < 2:
        return list(range(len(scene.emitters())))

    def key(i):
        emitter = scene.emitters()[i]
        shape = emitter.get_shape()
        geometry = () if shape is None else (tuple(shape.bbox().min), tuple(shape.bbox().max),
                                             shape.primitive_count())
        return (emitter.id(), emitter.class_name(), str(emitter), geometry)
    return sorted(range(len(scene.emitters())), key=key)


def is_delta(emitter) -> bool:
    """A point, spot or directional light (a delta in position or direction): its
    shadows are sharp, and one sample of it is exact up to visibility."""
    return mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)


def choose_emitter(scene: mi.Scene, sample, active=True, delta: bool | None = None):
    """``scene.sample_emitter`` over the emitters in :func:`emitter_order`: Mitsuba's
    rule (uniform, or by ``sampling_weight``); with ``delta`` True, over the delta
    lights only (:func:`is_delta`), with ``delta`` False over the others only (there
    must be one such light). Returns ``(index into scene.emitters(), 1/pmf, the sample
    reused)``. With one emitter to choose from, ``sample`` is returned as it is (as
    Mitsuba does)."""
    sample = mi.Float(sample)
    active = mi.Bool(active)
    order = emitter_subset(scene, delta)
    count = len(order)
    if count == 1:
        return dr.full(mi.UInt32, order[0], dr.width(sample)), dr.ones(mi.Float, dr.width(sample)), sample
    weights = _choice_weights(scene, order)
    if weights is None:
        scaled = sample * float(count)
        pick = dr.minimum(mi.UInt32(scaled), count - 1)
        weight, sample = dr.full(mi.Float, float(count), dr.width(sample)), scaled - mi.Float(pick)
    else:
        pick, sample, pmf = mi.DiscreteDistribution(weights).sample_reuse_pmf(sample, active)
        weight = dr.rcp(pmf)
    return dr.gather(mi.UInt32, mi.UInt32(order), pick), weight, sample


def emitter_subset(scene: mi.Scene, delta: bool | None = None) -> list[int]:
    """The emitters of :func:`emitter_order` that :func:`choose_emitter` chooses from:
    all (``delta`` None), the delta lights (True) or the others (False)."""
    order = emitter_order(scene)
    if delta is None:
        return order
    return [i for i in order if is_delta(scene.emitters()[i]) == delta]


def _choice_weights(scene: mi.Scene, order: list[int]) -> list[float] | None:
    """The ``sampling_weight`` of each emitter in ``order``, or None where Mitsuba's
    rule chooses uniformly (all equal, or none positive)."""
    weights = [float(scene.emitters()[i].sampling_weight()) for i in order]
    return None if min(weights) == max(weights) or sum(weights) <= 0 else weights


def emitter_pmf(scene: mi.Scene, index: int, delta: bool | None = None) -> float:
    """Probability that :func:`choose_emitter` (with ``delta``) picks emitter ``index``
    of ``scene.emitters()`` (0 if it is not of that kind)."""
    order = emitter_subset(scene, delta)
    if index not in order:
        return 0.0
    weights = _choice_weights(scene, order)
    return 1.0 / len(order) if weights is None else weights[order.index(index)] / sum(weights)


def soft_pdf_scale(scene: mi.Scene) -> float:
    """The factor from ``scene.pdf_emitter_direction`` (an emitter chosen among all)
    to the density of a sample whose emitter is chosen among the lights that are not
    delta lights (``choose_emitter(delta=False)``), for an emitter of that kind: the
    same for all of them (Mitsuba's pmf is each one's share of the weights). 1 in a
    scene without delta lights, or without other lights."""
    soft = emitter_subset(scene, False)
    if not soft or len(soft) == len(scene.emitters()):
        return 1.0
    everywhere = emitter_pmf(scene, soft[0])
    return emitter_pmf(scene, soft[0], False) / everywhere if everywhere > 0 else 1.0


def sample_emitter_direction(scene: mi.Scene, ref, sample: mi.Point2f, test_visibility: bool,
                             active=True, delta: bool | None = None):
    """``scene.sample_emitter_direction`` with the emitter chosen by
    :func:`choose_emitter` (what Mitsuba's does, step for step: the emitter's own
    ``sample_direction``, its pmf folded into the density and the weight, a shadow ray
    to the sampled point), so that the same seed gives the same samples whatever order
    Mitsuba loaded the lights in. ``scene.pdf_emitter_direction`` stays its density.
    With ``delta`` True, only the delta lights are sampled, with False only the others
    (the scene must have one such light): ``ds.pdf`` and the weight then hold the pmf
    of that choice."""
    active = mi.Bool(active)
    lanes = dr.width(ref.p)
    if not scene.emitters():
        return dr.zeros(mi.DirectionSample3f, lanes), dr.zeros(mi.Spectrum, lanes)
    sample = mi.Point2f(sample)
    index, weight, sample.x = choose_emitter(scene, sample.x, active, delta)
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), index, active)
    ds, spectrum = emitter.sample_direction(ref, sample, active)
    if len(emitter_subset(scene, delta)) > 1:
        ds.pdf *= dr.rcp(weight)
        spectrum *= weight
    active &= ds.pdf != 0.0
    if test_visibility:
        blocked = scene.ray_test(shadow_ray(ref, ds), active)
        spectrum = dr.select(blocked, 0.0, spectrum)
    return ds, spectrum


def shadow_ray(ref, ds: mi.DirectionSample3f) -> mi.Ray3f:
    """The visibility ray of an emitter sample: to the sampled point, or, for an
    infinite emitter (an environment, a directional sun), unbounded along its direction.

    Mitsuba places an infinite emitter's sample at twice the radius of the scene's
    bounding sphere, and takes that sphere from ``scene.bbox()``, which Mitsuba 3.9
    leaves invalid or too small when it merges shapes of one material loaded with
    ``load_dict`` (see :func:`scene_bbox`): in a room of such walls the sky's shadow
    rays stopped 1.6 m out, short of the 2.5 m ceiling, and lit the floor as if
    there were no roof (Mitsuba's own ``path`` does this too)."""
    to_point = ref.spawn_ray_to(ds.p)
    along = ref.spawn_ray(ds.d)
    infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
    ray = mi.Ray3f(to_point)
    ray.o = dr.select(infinite, along.o, to_point.o)
    ray.d = dr.select(infinite, along.d, to_point.d)
    ray.maxt = dr.select(infinite, along.maxt, to_point.maxt)
    return ray


def _finite(weight) -> mi.Bool:
    """Lanes whose every spectral channel is finite (not NaN, not +-inf)."""
    ok = mi.Bool(True)
    for i in range(len(weight)):
        ok &= dr.isfinite(weight[i])
    return ok


def _finite_rays_one_by_one(scene: mi.Scene, index, time, sample1, sample2, sample3, active):
    """The finite emitters' rays, emitter by emitter: each its own ``sample_ray``, or
    :func:`_sample_ray_by_evaluation` where that raises.

    Mitsuba's ``sample_ray`` needs the emitter's texture to be sampled
    (``sample_spectrum``, ``sample_position``), which procedural textures do not
    implement: an area light, a spot or a projector with a ``checkerboard`` raised
    "not implemented" (``path`` renders them: it only evaluates). One such emitter
    fails the call over all of them (a Dr.Jit call traces every emitter), hence the
    loop, taken only then."""
    n = dr.width(active)
    ray = dr.zeros(mi.Ray3f, n)
    weight = dr.zeros(mi.Spectrum, n)
    for i, emitter in enumerate(scene.emitters()):
        if mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite):
            continue
        mine = active & (index == i)
        try:
            ray_i, weight_i = emitter.sample_ray(time, sample1, sample2, sample3, mine)
        except RuntimeError:
            ray_i, weight_i = _sample_ray_by_evaluation(emitter, time, sample1, sample2, sample3, mine)
        ray = dr.select(mine, ray_i, ray)
        weight = dr.select(mine, mi.Spectrum(weight_i), weight)
    return ray, weight


def _infinite_wavelengths(scene: mi.Scene, index, si, sample1, infinite):
    """Spectral variants: the wavelengths of the lanes of ``infinite`` (emitter ``index``
    an environment or a sun), drawn by that emitter's ``sample_wavelengths`` at ``si``,
    and their weight. One call per infinite emitter, not one through the emitter
    pointers: that call traces every emitter's, and an area light of a ``spectrum``
    texture could not be traced so (Mitsuba raised "jit_var_schedule(): not permitted")."""
    lanes = dr.width(infinite)
    wavelengths, weight = dr.zeros(mi.Spectrum, lanes), dr.zeros(mi.Spectrum, lanes)
    for i, emitter in enumerate(scene.emitters()):
        if not mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite):
            continue
        mine = infinite & (index == i)
        wavelengths_i, weight_i = emitter.sample_wavelengths(si, sample1, mine)
        wavelengths = dr.select(mine, wavelengths_i, wavelengths)
        weight = dr.select(mine, mi.Spectrum(weight_i), weight)
    return wavelengths, weight


def _sample_ray_by_evaluation(emitter, time, sample1, sample2, sample3, active):
    """A ray of ``emitter`` sampled without its texture's sampling: uniform over the
    geometry and evaluated (unbiased; noisier where the texture varies).

    * On a shape (an area light): a point by the shape's ``sample_position`` (density
      p_A), a cosine-weighted direction, weight ``L(x, ω) π / p_A``.
    * A spot or projector: from its position, a direction uniform in the spot's cone
      (else over the sphere), weight ``I(ω) / p_ω``; ``I(ω)`` is what the emitter's
      ``sample_direction`` returns towards a point at distance 1 along ω.

    Spectral variants draw the wavelengths from ``sample1`` as a sensor does (the
    weight includes their ``1/pdf``).
    """
    wavelengths, wavelength_weight = spectra.sample_wavelengths(sample1)
    shape = emitter.get_shape()
    if shape is not None:
        ps = shape.sample_position(time, sample2, active)
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ps.pdf))
        si.p, si.n, si.uv, si.time = ps.p, ps.n, ps.uv, time
        si.sh_frame = mi.Frame3f(ps.n)
        local = mi.warp.square_to_cosine_hemisphere(sample3)
        si.wi = local  # eval reads the emitted direction in the local frame
        if wavelengths is not None:
            si.wavelengths = wavelengths
        radiance = emitter.eval(si, active) * wavelength_weight
        weight = radiance * dr.select(ps.pdf > 0, dr.pi / ps.pdf, 0.0)
        direction = mi.Frame3f(ps.n).to_world(local)
        return mi.Ray3f(ps.p, direction, time, si.wavelengths), weight
    params = mi.traverse(emitter)
    to_world = mi.Transform4f(params["to_world"]) if "to_world" in params else mi.Transform4f()
    if "cutoff_angle" in params:
        cos_cutoff = dr.cos(dr.deg2rad(mi.Float(params["cutoff_angle"])))
        local = mi.warp.square_to_uniform_cone(sample3, cos_cutoff)
        pdf = mi.warp.square_to_uniform_cone_pdf(local, cos_cutoff)
    else:
        local = mi.warp.square_to_uniform_sphere(sample3)
        pdf = mi.warp.square_to_uniform_sphere_pdf(local)
    origin = to_world @ mi.Point3f(0.0, 0.0, 0.0)
    direction = dr.normalize(to_world @ mi.Vector3f(local))
    it = dr.zeros(mi.Interaction3f, dr.width(pdf))
    it.p, it.time = origin + direction, time
    if wavelengths is not None:
        it.wavelengths = wavelengths
    ds, intensity = emitter.sample_direction(it, sample2, active)
    weight = intensity * wavelength_weight * dr.select(pdf > 0, dr.rcp(pdf), 0.0)
    return mi.Ray3f(origin, direction, time, it.wavelengths), weight


def sample_emitter_rays(scene: mi.Scene, time, sample1, sample2, sample3, active=True,
                        bounds: tuple | None = None):
    """Sample emitted rays; same meaning and return value as ``scene.sample_emitter_ray``.

    ``bounds`` is :func:`emission_bounds` for ``scene``, computed here when not given
    (callers that sample in batches compute it once: it reads every mesh's vertices).

    Returns ``(ray, weight, emitter)``: ``weight`` is the flux carried by the sample
    (emitted radiance over the spatio-directional density, including ``1/pmf`` of the
    emitter choice, :func:`choose_emitter`). Lanes that are
    inactive, that pick no valid sample, or whose weight is not finite (NaN, inf) get
    weight 0 and a finite ray with ``maxt = 0`` that hits nothing.

    Vectorised (one Dr.Jit wavefront, no Python loop over lanes); scenes with several
    emitters of mixed kinds are fine. RGB and monochromatic variants use the weight
    returned by ``sample_direction``; spectral variants sample the wavelengths with the
    emitter's ``sample_wavelengths`` as Mitsuba does. Polarised variants are not
    supported.
    """
    n = max(dr.width(time), dr.width(sample1), dr.width(sample2), dr.width(sample3),
            dr.width(active))
    time = mi.Float(time)
    active = mi.Bool(active)
    if scene.emitters() is None or len(scene.emitters()) == 0:
        ray = dr.zeros(mi.Ray3f, n)
        return ray, dr.zeros(mi.Spectrum, n), dr.zeros(mi.EmitterPtr, n)

    # Emitter choice by Mitsuba's rule (uniform, or by `sampling_weight`), with 1/pmf,
    # over the emitters in a fixed order (see emitter_order).
    index, selection_weight, sample1 = choose_emitter(scene, sample1, active)
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), index, active)
    infinite = active & mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite)
    finite_kind = active & ~infinite

    # Area / point / spot / ...: Mitsuba's own sample_ray (correct), unless some
    # emitter's cannot run (below).
    try:
        ray_f, weight_f = emitter.sample_ray(time, sample1, sample2, sample3, finite_kind)
    except RuntimeError:
        ray_f, weight_f = _finite_rays_one_by_one(scene, index, time, sample1, sample2, sample3,
                                                  finite_kind)

    # Infinite emitters: direction from sample_direction, origin on the rectangle that
    # bounds the box's projection, perpendicular to the *world-space* direction, placed
    # outside the bounding sphere.
    center, radius, box, focus, rings = emission_bounds(scene) if bounds is None else bounds
    levels = _levels(box, focus, rings)
    center_v = mi.Point3f(center)
    it = dr.zeros(mi.Interaction3f, n)
    it.p = center_v
    it.time = time
    spectral = mi.is_spectral
    if spectral:
        # Any wavelengths will do for the direction; the real ones are sampled below.
        it.wavelengths = it.wavelengths + 550.0
    ds, dir_weight = emitter.sample_direction(it, sample3, infinite)
    d = -ds.d                                   # the ray travels away from the emitter
    if box is None:  # no geometry: the sphere's disk
        offset = mi.warp.square_to_uniform_disk_concentric(sample2)
        perp = mi.Frame3f(d).to_world(mi.Vector3f(offset.x, offset.y, 0.0))
        origin = center_v + (perp - d) * radius
        area = mi.Float(dr.pi * radius * radius)
    else:
        origin, area = _rectangle_origin(d, center_v, radius, levels, sample2)
    if spectral:
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.p, si.uv, si.time = origin, ds.uv, time
        si.wi = -ds.d  # (a sky's spectrum depends on the direction: sunsky's is 0 without)
        wavelengths, wav_weight = _infinite_wavelengths(scene, index, si, sample1, infinite)
        pdf = dr.select(ds.delta, 1.0, ds.pdf)
        weight_i = mi.Spectrum(wav_weight) * (area / pdf)
        weight_i = dr.select(infinite & (pdf > 0), weight_i, 0.0)
    else:
        wavelengths = ray_f.wavelengths
        weight_i = mi.Spectrum(dir_weight) * area
    ray_i = mi.Ray3f(origin, d, time, wavelengths)

    ray = mi.Ray3f(dr.select(infinite, ray_i.o, ray_f.o),
                   dr.select(infinite, ray_i.d, ray_f.d), time)
    ray.maxt = dr.select(infinite, ray_i.maxt, ray_f.maxt)
    if spectral:
        ray.wavelengths = dr.select(infinite, ray_i.wavelengths, ray_f.wavelengths)
    weight = dr.select(infinite, weight_i, mi.Spectrum(weight_f)) * selection_weight
    alive = active & _finite(weight) & (dr.max(dr.abs(weight)) > 0)
    weight = dr.select(alive, weight, 0.0)
    # Dead lanes (weight 0) can carry NaN origins/directions (e.g. an envmap with a NaN
    # texel): give them a harmless ray that hits nothing.
    ray.o = dr.select(alive, ray.o, center_v)
    ray.d = dr.select(alive, ray.d, mi.Vector3f(0.0, 0.0, 1.0))
    ray.maxt = dr.select(alive, ray.maxt, 0.0)
    return ray, weight, emitter
