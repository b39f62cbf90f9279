"""What the stages need to know about a BSDF's lobes: the diffuse lobe's response to
irradiance, and whether the lobes can be taken apart at all.

pmic splits every BSDF into its diffuse lobes (lit from the cache, the caustic map and
emitter sampling) and the rest (followed by sampling). That split relies on
``BSDFContext`` lobe masks, which some BSDFs ignore; :func:`lobes_separable` finds them
per lane so that they are treated as one lobe instead of being counted twice.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ._jit import ONE_MINUS_EPSILON, finite
from .spectra import channel_mean, reference_wavelengths, spread

#: Outgoing directions at which :func:`diffuse_response` evaluates the lobes: the
#: response is (1/π) ∫ f(wo) cos θ dω over the hemisphere, integrated in cos θ (uniform
#: in solid angle) by 3-point Gauss-Legendre, at 3 azimuths per level, each level
#: turned by a third of their spacing. Exact for Lambertian lobes; coated ones
#: (plastic), which fall towards grazing angles through their coating's Fresnel
#: transmittance, within 0.2 %. The azimuths matter where the lobe is not symmetric
#: about the shading normal: a ``normalmap`` or ``bumpmap`` tilts it. The directions
#: used before, one azimuth per level (four levels of sin²θ), read a normal map's
#: diffuse wall tilted 30° as 0.72-1.05 of its true response, by the tilt's azimuth
#: (a Cornell box of such walls came out 5-12 % dark, tests/test_bias.py); these give
#: 0.99-1.02 up to 30°,
#: 0.95-1.05 at 50° (a dense quadrature of the same integral, tests/test_bsdfs.py).
#: Plastic's: +1.6 % before, -0.2 % now. Where no lobe of the scene leans
#: (:func:`lobes_lean`), one azimuth per level is exact in azimuth: 3 evaluations,
#: not 9, at every vertex and gather hit that reads light.
RESPONSE_LEVELS = 3
RESPONSE_AZIMUTHS = 3


def response_azimuths(leaning: bool) -> int:
    """Azimuths per level of :func:`diffuse_response` in a scene where some lobe leans
    (``leaning``: :func:`lobes_lean`) or none does: :data:`RESPONSE_AZIMUTHS`, or one
    (exact for lobes symmetric about the shading normal). The camera path and the
    gather rays ask it alike."""
    return RESPONSE_AZIMUTHS if leaning else 1


def _gauss_legendre_unit(count: int):
    """Nodes and weights of ``count``-point Gauss-Legendre quadrature on [0, 1]."""
    nodes, weights = np.polynomial.legendre.leggauss(count)
    return [float(0.5 * (x + 1.0)) for x in nodes], [float(0.5 * w) for w in weights]


_RESPONSE_NODES = _gauss_legendre_unit(RESPONSE_LEVELS)


def _response_directions(side: mi.Float, azimuths: int):
    """Local directions and weights of :data:`RESPONSE_LEVELS` × ``azimuths`` on the
    hemisphere ``side`` (+1 or -1: the side of the incident direction, so that the back
    of a ``twosided`` surface responds as its front does). The weights sum to 2 (the
    hemisphere's 2π over π)."""
    out = []
    nodes, weights = _RESPONSE_NODES
    for level, (cos_t, weight) in enumerate(zip(nodes, weights)):
        sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
        for k in range(azimuths):
            phi = 2.0 * math.pi * (k + level / RESPONSE_AZIMUTHS) / azimuths
            out.append((mi.Vector3f(sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t * side),
                        2.0 * weight / azimuths))
    return out


#: A lobe's tilt (tangent of its lean, :func:`diffuse_response`) below this counts as
#: none: a symmetric lobe's is zero up to rounding (its three azimuths cancel), and
#: reading it as zero keeps such a surface's image unchanged to the bit.
TILT_MIN = 1e-4
#: ...and above this (45°) is capped: the records' rotational gradients extrapolate
#: to first order only.
TILT_MAX = 1.0
#: A BSDF whose diffuse-only and non-diffuse evaluations add up to more than this
#: times its full evaluation ignores the lobe mask of its BSDFContext (Mitsuba 3.9's
#: ``principled`` does, in ``eval`` and ``sample``): its lobes cannot be split.
MASK_IGNORED_RATIO = 1.5


def diffuse_response(bsdf, si: mi.SurfaceInteraction3f, active,
                     ctx: mi.BSDFContext | None = None, with_tilt: bool = False,
                     azimuths: int = RESPONSE_AZIMUTHS):
    """``f_d``: the diffuse lobe's cosine-weighted mean BSDF value for the incident
    direction ``si.wi``, so that outgoing radiance is f_d · E.

    Exact (ρ/π) for Lambertian surfaces, on either face of a ``twosided`` one; it
    includes the Fresnel losses of plastic-like coatings, which ρ alone does not.
    ``ctx`` (default: diffuse lobes only) selects the lobes averaged. ``azimuths`` per
    level: 1 is exact for lobes symmetric about the shading normal (:func:`lobes_lean`
    false), and cannot tell a lean (no ``with_tilt`` then).

    With ``with_tilt``, returns ``(f_d, tilt)``: ``tilt`` (world space, tangent to the
    shading frame) is where a lobe that is not symmetric about the shading normal (a
    ``normalmap``'s, a ``bumpmap``'s) leans, so that irradiance read about
    :func:`tilted_normal` (the records' rotational gradients extrapolate it there)
    weighs the incident light as the lobe does (see :data:`TILT_MIN`).
    """
    if ctx is None:
        ctx = diffuse_context()
    side = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
    total = dr.zeros(mi.Spectrum, dr.width(si.p))
    moment = dr.zeros(mi.Vector2f, dr.width(si.p))
    if with_tilt and azimuths < 3:
        raise ValueError(f"diffuse_response: a tilt needs at least 3 azimuths, got {azimuths}")
    for wo, weight in _response_directions(side, azimuths):
        value = mi.Spectrum(bsdf.eval(ctx, si, wo, active)) * weight
        total += value
        if with_tilt:
            moment += mi.Vector2f(wo.x, wo.y) * channel_mean(value)
    response = finite(total)
    if not with_tilt:
        return response
    # The lobe's best linear fit, f(wo) ≈ c · wo, has c = (3 / 2π) ∫ f wo dω; its
    # tangential part over the response (1/π ∫ f dω, the normal part for uniform
    # light) is the tilt of the normal about which to read the irradiance.
    mean = channel_mean(response)
    tilt = 1.5 * moment / dr.maximum(mean, 1e-30)
    length = dr.norm(tilt)
    tilt *= dr.minimum(1.0, TILT_MAX / dr.maximum(length, 1e-30))
    keep = (mean > 0) & (length > TILT_MIN) & dr.all(dr.isfinite(tilt))
    tilt = dr.select(keep, tilt, 0.0)
    return response, si.sh_frame.s * tilt.x + si.sh_frame.t * tilt.y


def tilted_normal(shading_n: mi.Vector3f, tilt: mi.Vector3f) -> mi.Vector3f:
    """``shading_n`` leant by ``tilt`` (:func:`diffuse_response`); exactly
    ``shading_n`` where there is no tilt."""
    return dr.select(dr.any(tilt != 0), dr.normalize(shading_n + tilt), shading_n)


def dark_side(bsdf, si: mi.SurfaceInteraction3f, active) -> mi.Bool:
    """True where light arrives at the back of the shading frame (``si.wi`` below it)
    and the diffuse lobe reflects nothing towards that side: the back of a one-sided
    surface (a thin wall of ``diffuse`` rectangles, seen or lit from outside). Not the
    back of a ``twosided`` surface, nor a black texel on a front (whose photons still
    count in the density estimates of the texels beside it). One evaluation, only for
    light arriving from behind: a photon tracer's every hit asks."""
    behind = mi.Bool(active) & (mi.Frame3f.cos_theta(si.wi) < 0)
    reflected = mi.Spectrum(bsdf.eval(diffuse_context(), si, mi.Vector3f(0.0, 0.0, -1.0), behind))
    return behind & ~(dr.max(reflected) > 0)


def lobes_separable(bsdf, si: mi.SurfaceInteraction3f, active) -> mi.Bool:
    """False where the BSDF ignores its context's lobe mask (see
    :data:`MASK_IGNORED_RATIO`): there the diffuse lobe cannot be taken apart from the
    others, and the camera path treats the whole BSDF as one lobe."""
    side = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
    wo = mi.Vector3f(0.0, 0.0, side)
    f_d = dr.max(mi.Spectrum(bsdf.eval(diffuse_context(), si, wo, active)))
    f_r = dr.max(mi.Spectrum(bsdf.eval(non_diffuse_context(), si, wo, active)))
    f_all = dr.max(mi.Spectrum(bsdf.eval(mi.BSDFContext(), si, wo, active)))
    return ~(active & (f_all > 0) & (f_d + f_r > MASK_IGNORED_RATIO * f_all))


def scene_bsdfs(scene: mi.Scene) -> list:
    """The shapes' BSDFs, each once, and where some shape is an instance (of a
    ``shapegroup``) every BSDF in the scene graph: an instance reports a default diffuse
    BSDF of its own, not those of the shapes it holds (a glass sphere held in one left
    the scene without a caustic map, its caustic 0.7-0.9 % of the image dark at 64 spp,
    and a rough plastic there would not have had its lobes sampled apart)."""
    found = {}
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None:
            found.setdefault(id(bsdf), bsdf)
    if any(shape.class_name() == "Instance" for shape in scene.shapes()):
        for node in mi.traverse(scene).hierarchy:
            if isinstance(node, mi.BSDF):
                found.setdefault(id(node), node)
    return list(found.values())


#: BSDFs that hold others and add no lobe of their own (Mitsuba's class names):
#: their lobes are those they hold.
LOBE_WRAPPERS = ("TwoSidedBRDF", "NormalMap", "BumpMap")


def diffuse_free(bsdf: mi.BSDF) -> bool:
    """Does ``bsdf``'s flags list a diffuse lobe it never has? A ``principled`` metal
    (``metallic`` a constant 1) or glass (``spec_trans`` 1 and no ``sheen``): Mitsuba
    weighs its diffuse and subsurface terms by (1 - metallic)(1 - spec_trans) and its
    sheen by 1 - metallic, and its flags do not change with the values. Such a BSDF is
    read as its lobes are, glossy only (:func:`lobe_flags`), as a rough conductor or a
    rough dielectric: photons it reflects or transmits onto diffuse surfaces are
    caustic photons, and camera paths that meet it behind a traced vertex leave its
    reflection of the lights to the caustic map. Read as an inseparable BSDF (a diffuse
    lobe that cannot be taken apart), the glossy Cornell box's brass block lit the
    ceiling only through traced paths that found the light in it: 40 % of that image's
    noise at 16 spp (docs/tuning.md, "Principled metals"). Textured values are not
    read: they may be under 1 somewhere. A ``twosided``, ``normalmap`` or ``bumpmap``
    BSDF is diffuse free where the BSDFs it holds are (:data:`LOBE_WRAPPERS`)."""
    if bsdf.class_name() in LOBE_WRAPPERS:
        held = [node for node in mi.traverse(bsdf).hierarchy
                if isinstance(node, mi.BSDF) and node.class_name() not in LOBE_WRAPPERS]
        return bool(held) and all(diffuse_free(inner) for inner in held)
    if bsdf.class_name() != "Principled":
        return False
    params = mi.traverse(bsdf)

    def constant(name):  # a parameter's value where it is one constant, else None
        value = params[f"{name}.value"] if f"{name}.value" in params else None
        return float(dr.ravel(value)[0]) if value is not None and dr.width(value) == 1 else None

    metal = constant("metallic") == 1.0
    glass = constant("spec_trans") == 1.0 and constant("sheen") == 0.0
    return metal or glass


def diffuse_free_table(bsdfs: list) -> mi.Bool | None:
    """Per BSDF registry index (the value of a ``BSDFPtr`` lane), whether that BSDF is
    :func:`diffuse_free`; None where none of ``bsdfs`` is (walks then read the flags as
    they are, and compile nothing of this)."""
    ids = [int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(bsdf))[0]) for bsdf in bsdfs if diffuse_free(bsdf)]
    if not ids:
        return None
    table = dr.zeros(mi.Bool, max(ids) + 1)
    dr.scatter(table, True, mi.UInt32(ids))
    dr.eval(table)
    return table


def scene_diffuse_free(scene: mi.Scene) -> mi.Bool | None:
    """:func:`diffuse_free_table` of ``scene``'s BSDFs (:func:`scene_bsdfs`)."""
    return diffuse_free_table(scene_bsdfs(scene))


def lobe_flags(bsdf, free: mi.Bool | None) -> mi.UInt32:
    """``bsdf.flags()`` at each lane, without the diffuse lobe where the BSDF is
    :func:`diffuse_free` (``free``: :func:`diffuse_free_table`, or None)."""
    flags = bsdf.flags()
    if free is None:
        return flags
    index = dr.reinterpret_array(mi.UInt32, bsdf)
    known = index < dr.width(free)
    no_diffuse = dr.gather(mi.Bool, free, index, known)
    return dr.select(no_diffuse, flags & ~mi.UInt32(int(mi.BSDFFlags.Diffuse)), flags)


def scene_flags(bsdf: mi.BSDF) -> int:
    """``bsdf``'s flags as the walks read them (:func:`lobe_flags`), for one BSDF."""
    flags = int(bsdf.flags())
    return flags & ~int(mi.BSDFFlags.Diffuse) if diffuse_free(bsdf) else flags


#: Configurations at which :func:`ignores_lobe_masks` evaluates a BSDF (incident
#: directions spread over the hemisphere, texture coordinates over the unit square).
MASK_PROBE_LANES = 64


def _probe_interactions() -> mi.SurfaceInteraction3f:
    """:data:`MASK_PROBE_LANES` interactions on a flat surface at which a BSDF is probed
    once per scene: incident directions spread over the hemisphere, texture
    coordinates over the unit square."""
    lanes = MASK_PROBE_LANES
    u = (dr.arange(mi.Float, lanes) + 0.5) / lanes
    v = spread(lanes)
    si = dr.zeros(mi.SurfaceInteraction3f, lanes)
    si.n = mi.Vector3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(si.n)
    si.uv = mi.Point2f(u, v)
    si.wi = mi.warp.square_to_cosine_hemisphere(mi.Point2f(v, u))
    si.dp_du, si.dp_dv = mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0)
    si.t = 1.0
    if mi.is_spectral:
        si.wavelengths = reference_wavelengths(lanes)
    return si


def ignores_lobe_masks(bsdf: mi.BSDF) -> bool:
    """Does ``bsdf`` ignore its context's lobe mask anywhere (:func:`lobes_separable`
    false)? Mitsuba's ``principled`` and ``principledthin`` do, by name; any other
    (a blend holding one) is found by evaluating it at :data:`MASK_PROBE_LANES`
    incident directions and texture coordinates. Scenes without one skip the per-vertex
    test (three BSDF evaluations at every vertex of a mixed BSDF: a fifth of a rough
    plastic room's camera pass)."""
    flags = scene_flags(bsdf)
    if not (flags & int(mi.BSDFFlags.Diffuse)) or \
            not (flags & (int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta))):
        return False  # nothing to take apart
    if bsdf.class_name() in ("Principled", "PrincipledThin"):
        return True
    return bool(dr.any(~lobes_separable(bsdf, _probe_interactions(), mi.Bool(True))))


def lobes_lean(bsdf: mi.BSDF) -> bool:
    """Is ``bsdf``'s diffuse response not symmetric about the shading normal
    somewhere: a ``normalmap``'s, a ``bumpmap``'s, a principled BSDF's (which ignores
    the diffuse context: its whole lobe)? By name (also nested, as its description
    lists them), and by the tilt of :func:`diffuse_response` at
    :data:`MASK_PROBE_LANES` incident directions and texture coordinates. Scenes
    without one evaluate the diffuse response at one azimuth per level."""
    flags = scene_flags(bsdf)
    if not flags & int(mi.BSDFFlags.Diffuse):
        return False
    if any(name in str(bsdf) for name in ("NormalMap", "BumpMap", "Principled")):
        return True
    _, tilt = diffuse_response(bsdf, _probe_interactions(), mi.Bool(True), with_tilt=True)
    return bool(dr.any(dr.any(tilt != 0)))


def near_diffuse(bsdf, si: mi.SurfaceInteraction3f, active, peak_ratio: float) -> mi.Bool:
    """True where the whole BSDF, for the incident direction ``si.wi``, is within
    ``peak_ratio`` of diffuse: its value at the mirror direction at most that many
    times its cosine-weighted mean (:func:`diffuse_response` over every lobe). A
    Lambertian surface has 1; Mitsuba's ``principled`` at roughness 0.5 has 1.3 at
    normal incidence and 6 at 66° (Fresnel), at roughness 0.3 3.7 and 51."""
    active = mi.Bool(active)
    mean = dr.max(diffuse_response(bsdf, si, active, mi.BSDFContext()))
    return peak_within(bsdf, si, active, mean, peak_ratio)


def peak_within(bsdf, si: mi.SurfaceInteraction3f, active, mean: mi.Float,
                peak_ratio: float) -> mi.Bool:
    """:func:`near_diffuse` given ``mean``, the whole BSDF's cosine-weighted mean value
    (a caller that has its lobes' means adds them up)."""
    active = mi.Bool(active)
    wo = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
    cos_o = dr.abs(mi.Frame3f.cos_theta(wo))
    peak = dr.max(mi.Spectrum(bsdf.eval(mi.BSDFContext(), si, wo, active))) / dr.maximum(cos_o, 1e-6)
    return active & (mean > 0) & (peak <= peak_ratio * mean)




#: Probability of the glossy lobes where a BSDF's diffuse and glossy lobes are
#: sampled apart (:func:`sample_lobes_apart`).
GLOSSY_LOBE_PROBABILITY = 0.5


def glossy_beside_diffuse(flags) -> mi.Bool:
    """A diffuse lobe beside a glossy one (rough plastic): where Mitsuba's sampling of
    the whole BSDF does not tell which lobe carried the light (see
    :func:`sample_lobes_apart`)."""
    return mi.has_flag(flags, mi.BSDFFlags.Diffuse) & mi.has_flag(flags, mi.BSDFFlags.Glossy)


def sample_lobes_apart(bsdf, si: mi.SurfaceInteraction3f, u1: mi.Float, u2: mi.Point2f, active,
                       mode=mi.TransportMode.Radiance):
    """``(bs, weight)``: the lobes other than the diffuse one with probability
    :data:`GLOSSY_LOBE_PROBABILITY` q, else the diffuse lobe, each sampled alone;
    ``weight`` = f_lobe / (q_lobe p_lobe) and ``bs.pdf`` = q_lobe p_lobe.

    Mitsuba samples the whole of a rough plastic and weighs every sample by
    f_all / p_all, whichever lobe it took: a photon whose bounce took the glossy lobe
    carries some of the diffuse lobe's light too, and one that took the diffuse lobe
    some of the glossy's. A caustic map keeps the first kind only, while the camera
    path counts the diffuse lobe's light itself and leaves out the light its glossy
    lobe brings: a window-lit room with a rough plastic floor came out 1 % too bright
    in its bounced light. Sampled apart, each lobe's light is its own."""
    q = GLOSSY_LOBE_PROBABILITY
    active = mi.Bool(active)
    glossy = u1 < q
    u_glossy = dr.minimum(u1 * (1.0 / q), ONE_MINUS_EPSILON)
    u_diffuse = dr.clip((u1 - q) * (1.0 / (1.0 - q)), 0.0, ONE_MINUS_EPSILON)
    bs, weight = bsdf.sample(non_diffuse_context(mode), si, u_glossy, u2, active & glossy)
    bs_d, weight_d = bsdf.sample(diffuse_context(mode), si, u_diffuse, u2, active & ~glossy)
    bs[~glossy] = bs_d
    weight = dr.select(glossy, weight * (1.0 / q), weight_d * (1.0 / (1.0 - q)))
    bs.pdf = bs.pdf * dr.select(glossy, q, 1.0 - q)
    return bs, dr.select(active, weight, 0.0)


def diffuse_context(mode=mi.TransportMode.Radiance) -> mi.BSDFContext:
    """A context that samples/evaluates the diffuse lobes only."""
    return mi.BSDFContext(mode, int(mi.BSDFFlags.Diffuse), None)


def non_diffuse_context(mode=mi.TransportMode.Radiance) -> mi.BSDFContext:
    """A context that samples/evaluates every lobe but the diffuse ones."""
    mask = int(mi.BSDFFlags.All) & ~int(mi.BSDFFlags.Diffuse)
    return mi.BSDFContext(mode, mask, None)
