"""Direct light at a camera vertex: emission met by the path (MIS-weighted), emitter
samples (shadow rays), BSDF samples of the diffuse lobe that meet an emitter, a
smooth coat's reflection of the lights, and delta lights where the cache is read."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .. import emission, skylight
from .._jit import ONE_MINUS_EPSILON, finite, jittered, mis_weight, only_where
from ..bsdfs import diffuse_context, non_diffuse_context
from .config import PathContext
from .state import PathState
from .vertex import Guides, Reads, Vertex, no_light


def emission_met(ctx: PathContext, state: PathState, si, shown):
    """Emission met at ``si`` (the lanes of ``shown``), MIS-weighted against the emitter
    samples of the previous vertex unless a delta lobe led here."""
    scene, prev = ctx.scene, state.prev
    shown = shown & (si.emitter(scene) != None)  # noqa: E711
    sky_fraction = prev.sky_fraction if ctx.config.sky_guided else None

    def compute():
        ds = mi.DirectionSample3f(scene, si=si, ref=prev.si)
        em_pdf = emitter_pdf(ctx, prev.si, ds, prev.normal, shown & ~prev.bsdf_delta,
                             prev.sky_record, sky_fraction)
        mis = dr.select(prev.bsdf_delta, 1.0,
                        mis_weight(prev.bsdf_pdf, ctx.config.emitter_samples * em_pdf))
        return finite(state.β * mis * ds.emitter.eval(si, shown), shown)
    return only_where(shown, compute, no_light(si), label="emission")


def emitter_pdf(ctx: PathContext, ref, ds, normal, active, sky_record=None, sky_fraction=None):
    """Density of the emitter samples of :func:`direct_light` at ``ref`` (shading normal
    ``normal``; ``sky_record``, ``sky_fraction``: the sky guide they followed) for the
    emitter direction ``ds`` (MIS)."""
    guide = None if sky_fraction is None else skylight.SkyGuide(ctx.view.index, sky_record, sky_fraction)
    return skylight.pdf_emitter_direction(ctx.scene, ctx.view.sky, ref, ds, normal, active, guide,
                                          delta=False)


def _emitter_sample(ctx: PathContext, sampler, v: Vertex, active, fate, guides, k, delta):
    """Sample ``k`` of :func:`direct_light`'s emitter samples (``delta``: of the delta
    lights), weighted by MIS against the continuation (``fate``: traced, armed,
    no_diffuse; ``guides``: the continuation's guide, or None)."""
    config, scene, si, bsdf = ctx.config, ctx.scene, v.si, v.bsdf
    traced, armed, no_diffuse = fate
    if delta:  # sample k of the delta lights, in its own stratum of the choice
        u = sampler.next_2d()
        u.x = dr.minimum((mi.Float(k) + u.x) / _delta_samples(ctx), ONE_MINUS_EPSILON)
        ds, em_weight = emission.sample_emitter_direction(scene, si, u, True, active, delta=True)
    else:
        # Sample k of direct_samples, in its own jittered stratum of the square. (The
        # strategy is chosen from u itself, as the rest of the mixture is: choosing it
        # by sample number, every other one, gave each strategy only its samples'
        # strata of the square: 11 % dark in a window-lit room.)
        u = jittered(sampler.next_2d(), mi.UInt32(k), config.direct_samples)
        sky_guide = None if not config.sky_guided else \
            skylight.SkyGuide(ctx.view.index, guides.record, guides.sky_fraction)
        ds, em_weight = skylight.sample_emitter_direction(scene, ctx.view.sky, si, v.shading_n, u,
                                                          active, sky_guide, delta=False)
    ok = active & (ds.pdf != 0.0)
    wo = si.to_local(ds.d)
    separable = v.separable
    # A traced vertex weighs both parts alike (the continuation samples the whole
    # BSDF): unless armed, one evaluation of the whole serves (its three evaluations
    # were a fifth of the material preview's direct light).
    split = separable & ~(traced & ~armed)
    # (Only where there is a diffuse lobe: a principled metal or glass, which has none, ignores
    # the context's mask and would give its whole value twice: bsdfs.diffuse_free.)
    f_diffuse, pdf_diffuse_lobe = bsdf.eval_pdf(diffuse_context(), si, wo, ok & split & v.lobes.diffuse)
    f_rest, pdf_rest_lobe = bsdf.eval_pdf(non_diffuse_context(), si, wo, ok & split)
    f_all, pdf_all = bsdf.eval_pdf(mi.BSDFContext(), si, wo, ok & (~separable | traced))
    if config.guiding:  # the pdf with which the continuation would sample this direction
        pdf_all = (1.0 - guides.fraction) * pdf_all + guides.fraction * ctx.view.index.guide_pdf(
            guides.record, ds.d, ok & (guides.fraction > 0))
    pdf_rest = dr.select(separable & ~traced, pdf_rest_lobe, pdf_all)
    pdf_diffuse = dr.select(traced, pdf_all, pdf_diffuse_lobe)
    f_rest = dr.select(split, f_rest, f_all)
    f_rest = dr.select(separable & armed, 0.0, f_rest)
    f_diffuse = dr.select(split & ~no_diffuse, f_diffuse, 0.0)
    em_pdf = config.emitter_samples * ds.pdf
    w_rest = dr.select(ds.delta, 1.0, mis_weight(em_pdf, pdf_rest))
    w_diffuse = dr.select(ds.delta | ~(traced | config.diffuse_mis), 1.0, mis_weight(em_pdf, pdf_diffuse))
    return finite(em_weight * (f_diffuse * w_diffuse + f_rest * w_rest), ok)


def _delta_samples(ctx: PathContext) -> int:
    return min(ctx.config.direct_samples, len(emission.emitter_subset(ctx.scene, True)))


def direct_light(ctx: PathContext, sampler, v: Vertex, active, fate, guides: Guides):
    """Direct light at ``v``: the mean of ``direct_samples`` emitter samples (shadow
    rays) of the lights that are not delta lights, plus one sample of each delta light
    (a sun, a spot: exact up to visibility; up to ``direct_samples`` of them, in strata
    of the choice). Chosen among all lights, half of a sunlit sky's samples went to the
    sun, each the same shadow ray, and the sun's light at a point came from 0 to 4 of
    them: the noise left in a sunlit courtyard.

    Separable BSDFs: the diffuse lobe takes emitter samples alone (or shares them by MIS
    with :func:`diffuse_emitter_hit`), the other lobes share them with the
    continuation's BSDF sampling. Inseparable ones share them as a whole, and so do
    traced vertices (whose continuation samples the whole BSDF). ``fate`` is (traced,
    armed, no_diffuse): where ``armed``, light through the delta/glossy lobes is left
    out (a caustic the map holds); where ``no_diffuse``, the diffuse lobe is (the cache
    holds its direct light). Where the continuation is guided the MIS weights use its
    guided mixture density (:func:`~.continuation.mixed_continuation`: without its
    bright-record strategy, as the continuation's own emitter hits do); where
    ``guides.sky_fraction`` > 0, every other sample of the sky follows the sky the
    guide record saw (:data:`~.continuation.SKY_EMITTER_FRACTION`)."""
    soft_samples = ctx.config.direct_samples if emission.emitter_subset(ctx.scene, False) else 0

    def mean(count, delta):
        if count == 0:
            return mi.Spectrum(0.0)
        if count == 1:
            return only_where(active, lambda sampler: _emitter_sample(ctx, sampler, v, active, fate,
                                                                      guides, 0, delta),
                              no_light(v.si), sampler, label="pmic_direct_light")

        def body(k, total, sampler):
            return k + 1, total + _emitter_sample(ctx, sampler, v, active, fate, guides, k, delta), sampler

        _, total, _ = dr.while_loop(
            (dr.zeros(mi.UInt32, dr.width(v.si.p)), dr.zeros(mi.Spectrum, dr.width(v.si.p)), sampler),
            lambda k, total, sampler: active & (k < count), body, label="pmic_direct_light")
        return total / count

    return mean(soft_samples, False) + mean(_delta_samples(ctx), True)


def coat_emission(ctx: PathContext, sampler, v: Vertex, active):
    """Emission that a smooth coat (the delta lobes over a diffuse one: a smooth
    plastic) reflects at a traced vertex, along one sample of those lobes (for one delta
    lobe, its only direction): a ray of its own. The continuation samples the whole
    BSDF and takes the coat only now and then (a smooth plastic of IOR 1.9 one time in
    six, its reflection of a sky then weighted ×6); the emission it meets through a
    delta lobe is not counted again (``coat_counted``), so this replaces that estimate
    by its mean over the choice of lobe. In the material preview the coat's reflection
    of the sky was half the noise left on the object."""
    scene, si, bsdf = ctx.scene, v.si, v.bsdf

    def compute(sampler):
        bs, weight = bsdf.sample(non_diffuse_context(), si, sampler.next_1d(), sampler.next_2d(), active)
        ok = active & (bs.pdf > 0) & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        hit = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), ok)
        return finite(weight * hit.emitter(scene, ok).eval(hit, ok), ok)
    return only_where(active, compute, no_light(si), sampler, label="coat_emission")


def trusted_direct(ctx: PathContext, sampler, v: Vertex, active, lobe_context):
    """Direct light on a lobe of a vertex that reads the cache (final gather) from the
    delta lights (a sun, a spot), which neither the records nor the photons it may read
    instead hold (their sharp shadows would be smeared): one sample of them, a shadow
    ray, exact up to visibility. No MIS: a delta light cannot be hit, and the lobe does
    not continue."""
    scene, si = ctx.scene, v.si

    def compute(sampler):
        ds, em_weight = emission.sample_emitter_direction(scene, si, sampler.next_2d(), True, active,
                                                          delta=True)
        ok = mi.Bool(active) & (ds.pdf != 0.0)
        f = v.bsdf.eval(lobe_context, si, si.to_local(ds.d), ok)
        return finite(em_weight * f, ok)
    return only_where(active, compute, no_light(si), sampler, label="trusted_direct")


def diffuse_emitter_hit(ctx: PathContext, sampler, v: Vertex, active):
    """Direct light on the diffuse lobe from one BSDF-sampled ray that meets an emitter
    (an area light or the environment), MIS-weighted against the ``direct_samples``
    emitter samples of :func:`direct_light`."""
    scene, si = ctx.scene, v.si

    def compute(sampler):
        bs, weight = v.bsdf.sample(diffuse_context(), si, sampler.next_1d(), sampler.next_2d(), active)
        ok = active & (bs.pdf > 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        hit = scene.ray_intersect(ray, mi.RayFlags.All, coherent=False, active=ok)
        ds = mi.DirectionSample3f(scene, si=hit, ref=si)
        em_pdf = emitter_pdf(ctx, si, ds, v.shading_n, ok)
        emitted = ds.emitter.eval(hit, ok)
        return finite(weight * emitted * mis_weight(bs.pdf, ctx.config.emitter_samples * em_pdf), ok)
    return only_where(active, compute, no_light(si), sampler, label="diffuse_emitter_hit")


def direct_at_vertex(ctx: PathContext, sampler, state: PathState, v: Vertex, reads: Reads,
                     guides: Guides):
    """``(direct, coat)``: all the direct light a vertex adds (times the path's
    throughput), and the lanes that traced their smooth coat's reflection of the lights
    (emission their continuation meets through the coat is counted here)."""
    config, β, flags = ctx.config, state.β, v.lobes.flags
    from_records, traced_here, armed = reads.from_records, reads.traced_here, state.armed
    # (Where the cache gives the diffuse lobe's light, only a glossy lobe is left for
    # emitter samples: a delta one, a smooth plastic's coat, cannot be sampled. Its
    # wasted samples were 9 % of the material preview's render, 1.84 -> 1.68 s.)
    active_em = v.active_next & mi.has_flag(flags, mi.BSDFFlags.Smooth) & \
        ~(from_records & ~mi.has_flag(flags, mi.BSDFFlags.Glossy)) & ~reads.trusted_whole
    direct = β * direct_light(ctx, sampler, v, active_em, (traced_here, armed, from_records), guides)
    if config.diffuse_mis:  # the diffuse lobe's direct light by BSDF sampling too (MIS)
        direct += β * diffuse_emitter_hit(ctx, sampler, v, v.lit_diffuse & ~traced_here & ~from_records)
    if config.gather_first and config.delta_lights:
        # ...and where it reads the cache, from the lights records do not hold
        direct += β * trusted_direct(ctx, sampler, v, from_records & (v.lit_diffuse | reads.trusted_whole),
                                     diffuse_context())
        if config.coat_reads:
            # (their reflection in the coat too, unless the caustic map holds it)
            direct += β * trusted_direct(ctx, sampler, v, reads.coat_read & ~armed, non_diffuse_context())
    coat = mi.Bool(False)
    if config.coat_rays:  # a smooth coat's reflection of the lights, traced
        coat = traced_here & v.active_next & v.separable & v.lobes.mixed & ~armed & ~v.lobes.glossy
        direct += β * coat_emission(ctx, sampler, v, coat)
    return direct, coat
