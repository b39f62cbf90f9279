"""How a camera path goes on from a vertex: the directions a traced vertex draws from
the records (guiding, bright records) beside BSDF sampling, the lobe a rough
plastic's sample counts as, and the roulettes."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .._jit import ONE_MINUS_EPSILON, only_where
from ..bsdfs import diffuse_context, non_diffuse_context
from ..cases import CAMERA_COAT_ROULETTE_BELOW
from .config import PathContext
from .state import PathState, PreviousVertex
from .vertex import Guides, Reads, Vertex

#: Guiding (``guiding``): at a traced diffuse vertex that a record reaches, this
#: fraction, times the share of bounced light in the record's irradiance, of the
#: continuation rays is drawn from the record's directional distribution of gathered
#: light, the rest by BSDF sampling, weighted by the mixture's density (one-sample
#: MIS, unbiased whatever the distribution). At most half: the BSDF's density stays at
#: least 1/2 of its own everywhere (never worse than 2× its variance), while a bright
#: source of bounced light (a lit ceiling, a door to a lit room) is met far more often
#: than cosine sampling meets it. Scaled by the bounced share because where direct
#: light is most of the irradiance, BSDF samples also serve it (MIS with the emitters).
GUIDE_FRACTION = 0.5
#: ...and where bright records (:mod:`pmic_integrator.lights`: a lamp's shade lit from
#: inside) face the traced vertex, this fraction of its continuation rays is drawn
#: towards them, the rest as above, all weighted by the three-way mixture's density.
#: A quarter: such a source sends most of the bounced light there, while the BSDF and
#: guide strategies keep 3/4 of their own density (at most 4/3 their variance). Half
#: measured worse in the lamp room (relMSE 0.36-0.76 against 0.30-0.45 over render
#: seeds) for 1.5× the render time (rays into the cone that meet the shade's glossy
#: outside go on bouncing).
LIGHT_FRACTION = 0.25
#: ...and where that record saw the sky through an opening (a window), this fraction
#: of the vertex's emitter samples of the sky follow the sky it saw (chosen from each
#: sample's own square), the rest the whole sky's tables, all weighted by the
#: mixture's density (as are the continuation's emitter hits there). The tables'
#: samples mostly meet the walls of a room lit through a window.
SKY_EMITTER_FRACTION = 0.5


def choose_guides(ctx: PathContext, v: Vertex, reads: Reads) -> Guides:
    """Where a record reaches a traced vertex, part of its continuation follows the
    record's distribution of gathered light (GUIDE_FRACTION), part goes towards the
    bright records that face it (LIGHT_FRACTION), and part of its sky samples follow
    the sky the record saw (SKY_EMITTER_FRACTION)."""
    config, index, si, n = ctx.config, ctx.view.index, v.si, v.n
    lanes = dr.width(si.p)
    traced_on = reads.traced_here & v.active_next  #: traced, and the path goes on
    # (a first read's sky samples follow the record too; the first-read test found it)
    first_on = reads.first_read & v.active_next
    guided = traced_on | first_on
    record, fraction = mi.UInt32(0), mi.Float(0.0)
    if config.guiding:
        record, bounced_share = only_where(
            traced_on, lambda: index.guide_record(si.p, n, traced_on),
            lambda: (dr.zeros(mi.UInt32, lanes), dr.zeros(mi.Float, lanes)), label="guide_record")
        record = dr.select(first_on, reads.first_record, record)
        fraction = GUIDE_FRACTION * dr.select(first_on, reads.first_share, bounced_share)
    sky_fraction = mi.Float(0.0)
    if config.sky_guided:
        sees = index.sees_sky(record, guided & (fraction > 0))
        sky_fraction = dr.select(guided & (fraction > 0) & sees,
                                 SKY_EMITTER_FRACTION, 0.0)
    light_total, light_fraction = mi.Float(0.0), mi.Float(0.0)
    if config.lit:
        light_total = only_where(traced_on, lambda: index.lights.total_weight(si.p, n, traced_on),
                                 lambda: dr.zeros(mi.Float, lanes), label="record_lights")
        light_fraction = dr.select(light_total > 0, LIGHT_FRACTION, 0.0)
    return Guides(record=record, fraction=fraction, sky_fraction=sky_fraction,
                  light_total=light_total, light_fraction=light_fraction)


def _pick_strategy(config, guides: Guides, u1, active):
    """``(pick_light, u_light, pick_guide, u1)``: which lanes draw towards a bright
    record (u1 < α_light: u1 / α_light then picks the record) or from the guide record
    (u1 < α_guide of what is left), and u1 stretched back to [0, 1) for the BSDF
    sample (its lobe)."""
    pick_light, u_light, pick_guide = mi.Bool(False), mi.Float(0.0), mi.Bool(False)
    if config.lit:
        pick_light = active & (u1 < guides.light_fraction)
        u_light = dr.minimum(u1 / LIGHT_FRACTION, ONE_MINUS_EPSILON)
        u1 = dr.select(guides.light_fraction > 0,
                       dr.clip((u1 - guides.light_fraction) / (1.0 - guides.light_fraction),
                               0.0, ONE_MINUS_EPSILON), u1)
    if config.guiding:
        pick_guide = active & (u1 < guides.fraction) & ~pick_light
        u1 = dr.select(guides.fraction > 0,
                       dr.clip((u1 - guides.fraction) / (1.0 - guides.fraction), 0.0, ONE_MINUS_EPSILON),
                       u1)
    return pick_light, u_light, pick_guide, u1


def mixed_continuation(ctx: PathContext, v: Vertex, bs, weight, u2, active, picks, guides: Guides):
    """One-sample MIS of up to three strategies for a traced vertex's continuation:
    towards a bright record (:meth:`RecordLights.sample`, where ``pick_light``,
    probability α_l = ``light_fraction``), from the guide record's distribution
    (:meth:`RecordIndex.sample_guide`, where ``pick_guide``, probability (1-α_l)·α_g),
    else the BSDF sample ``bs``. Either way the weight is f·cos / p_mix with p_mix =
    α_l p_light + (1-α_l)((1-α_g) p_bsdf + α_g p_guide) (a strategy the scene does not
    use has α 0). A delta lobe's sample keeps its weight over (1-α_l)(1-α_g).

    Also returns the density that emitter hits are MIS-weighted with: the mixture
    without the bright-record strategy. MIS weights need only sum to one over the
    strategies (emitter sampling and this continuation), which they do when both use
    the same density, so the emitter samples need not evaluate the lights' density (a
    loop over the lights per sample): unbiased either way."""
    config, index, si, n = ctx.config, ctx.view.index, v.si, v.n
    pick_light, u_light, pick_guide = picks
    alpha_g = guides.fraction if config.guiding else mi.Float(0.0)
    alpha_l = guides.light_fraction if config.lit else mi.Float(0.0)
    mixing = active & ((alpha_g > 0) | (alpha_l > 0))
    picked = mi.Bool(False)
    wo_picked = mi.Vector3f(0.0, 0.0, 1.0)
    if config.guiding:
        picked |= pick_guide
        wo_picked = dr.select(pick_guide, index.sample_guide(guides.record, u2, pick_guide), wo_picked)
    if config.lit:
        picked |= pick_light
        wo_picked = dr.select(pick_light, index.lights.sample(si.p, n, guides.light_total, u_light, u2,
                                                              pick_light), wo_picked)
    wo_picked_local = si.to_local(wo_picked)
    f_picked, pdf_bsdf_picked = v.bsdf.eval_pdf(mi.BSDFContext(), si, wo_picked_local, picked)
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) & ~picked
    wo_world = dr.select(picked, wo_picked, si.to_world(bs.wo))
    pdf_bsdf = dr.select(picked, pdf_bsdf_picked, bs.pdf)
    mixed = mixing & ~delta
    pdf_mix = pdf_bsdf
    if config.guiding:
        pdf_mix = (1.0 - alpha_g) * pdf_mix + alpha_g * index.guide_pdf(
            guides.record, wo_world, mixed & (alpha_g > 0))
    pdf_mis = dr.select(mixed, pdf_mix, bs.pdf)
    if config.lit:
        pdf_mix = (1.0 - alpha_l) * pdf_mix + alpha_l * index.lights.pdf(
            si.p, n, guides.light_total, wo_world, mixed & (alpha_l > 0))
    safe = dr.maximum(pdf_mix, 1e-30)
    weight = dr.select(mixed & ~picked, weight * (bs.pdf / safe), weight)
    weight = dr.select(mixing & delta, weight / ((1.0 - alpha_g) * (1.0 - alpha_l)), weight)
    weight = dr.select(picked, mi.Spectrum(f_picked) / safe, weight)
    weight = dr.select(mixed & ~(pdf_mix > 0), 0.0, weight)
    bs.pdf = dr.select(mixed, pdf_mix, bs.pdf)
    bs.wo = dr.select(picked, wo_picked_local, bs.wo)
    bs.eta = dr.select(picked, 1.0, bs.eta)
    bs.sampled_type = dr.select(picked, mi.UInt32(+mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
    bs.sampled_component = dr.select(picked, mi.UInt32(0), bs.sampled_component)
    return bs, weight, pdf_mis


def split_lobes(sampler, v: Vertex, bs, bsdf_weight, sampled_diffuse, split):
    """``(bsdf_weight, sampled_diffuse)`` where a rough plastic's sample of its whole
    BSDF (``split``: traced where it reads the caustic map, or once armed) must say
    which lobe it counts as: light that leaves by its diffuse lobe after a coat's
    reflection of the lights is a caustic the map holds (not counted again past it),
    light that leaves by the coat is the path's. A sample of the whole BSDF carries both
    lobes' values (f_all / p, guided or not), whichever lobe drew it: counted by the
    lobe drawn, a box of strong rough plastic (index 2.5) came out 2.5 % dark on its
    floor, and a window-lit room 1 % bright. The sample belongs to the diffuse lobe with
    probability f_d / (f_d + f_rest) at its direction, to the rest otherwise, with
    weight f_lobe / (p · that probability): each lobe's light, unbiased, and guiding
    kept. (Armed vertices sampled the lobes apart before, half and half, unguided: a
    door-lit room of rough plastic's relMSE 9.5e-4 -> 9.0e-4 at 16 spp, the same
    time.)"""
    f_lobe_d = mi.Spectrum(v.bsdf.eval(diffuse_context(), v.si, bs.wo, split))
    f_lobe_rest = mi.Spectrum(v.bsdf.eval(non_diffuse_context(), v.si, bs.wo, split))
    share_d = dr.max(f_lobe_d) / dr.maximum(dr.max(f_lobe_d) + dr.max(f_lobe_rest), 1e-30)
    as_diffuse = sampler.next_1d() < share_d
    part = dr.select(as_diffuse, f_lobe_d / dr.maximum(share_d, 1e-30),
                     f_lobe_rest / dr.maximum(1.0 - share_d, 1e-30))
    f_sum = f_lobe_d + f_lobe_rest
    bsdf_weight[split] = mi.Spectrum(dr.select(f_sum > 0, bsdf_weight * part / dr.maximum(f_sum, 1e-30), 0.0))
    return bsdf_weight, dr.select(split, as_diffuse, sampled_diffuse)


def sample_continuation(ctx: PathContext, sampler, state: PathState, v: Vertex, reads: Reads,
                        guides: Guides, whole):
    """``(bs, bsdf_weight, mis_pdf, sampled_diffuse)``: the direction the path goes on
    in, through the lobes left after the reads (all lobes where ``whole``: inseparable
    or traced), its weight, the density emitter hits there are MIS-weighted with, and
    whether it counts as the diffuse lobe's."""
    config, si, bsdf = ctx.config, v.si, v.bsdf
    u1, u2 = sampler.next_1d(), sampler.next_2d()
    pick_light, u_light, pick_guide, u1 = _pick_strategy(config, guides, u1, v.active_next & whole)
    bs, bsdf_weight = bsdf.sample(non_diffuse_context(), si, u1, u2, v.active_next & ~whole)
    bs_all, weight_all = bsdf.sample(mi.BSDFContext(), si, u1, u2,
                                     v.active_next & whole & ~pick_guide & ~pick_light)
    bs[whole] = bs_all
    bsdf_weight[whole] = weight_all
    mis_pdf = mi.Float(bs.pdf)
    if config.guiding or config.lit:
        bs, bsdf_weight, mis_pdf = mixed_continuation(ctx, v, bs, bsdf_weight, u2, v.active_next & whole,
                                                      (pick_light, u_light, pick_guide), guides)
    sampled_diffuse = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
    if config.lobes_split:
        split = v.active_next & reads.traced_here & (reads.read_caustic | state.armed) & \
            v.separable & v.lobes.rough_coat & (bs.pdf > 0)
        bsdf_weight, sampled_diffuse = split_lobes(sampler, v, bs, bsdf_weight, sampled_diffuse, split)
    return bs, bsdf_weight, mis_pdf, sampled_diffuse


def _coat_roulette(sampler, state: PathState, active_next, whole, bs, bsdf_weight):
    """Behind a traced vertex, a vertex that reads the cache and goes on through a weak
    glossy lobe alone (a rough plastic's coat: its sample weight is the few per cent the
    coat reflects) survives with probability weight / CAMERA_COAT_ROULETTE_BELOW
    (unbiased), as gather rays do. Mitsuba's roulette waits for ``rr_depth``: until then
    such paths went on as chains of weak coat bounces, each vertex reading the cache,
    sampling the lights and evaluating the BSDF again."""
    weak = active_next & ~whole & (state.traced > 0) & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Glossy)
    survival = dr.minimum(dr.max(bsdf_weight) * (1.0 / CAMERA_COAT_ROULETTE_BELOW), 1.0)
    weak &= survival < 1.0
    bsdf_weight[weak] = bsdf_weight / dr.maximum(survival, 1e-8)
    # (drawn for those lanes only: the others' random streams are unchanged)
    return active_next & (~weak | (sampler.next_1d(weak) < survival)), bsdf_weight


def continue_path(ctx: PathContext, sampler, state: PathState, v: Vertex, reads: Reads,
                  guides: Guides, coat) -> None:
    """Advance ``state`` past ``v``: sample the continuation, update the caustic
    bookkeeping (``armed``, ``crossed``, ``coat_counted``), apply the roulettes, and find
    the next vertex."""
    config, si = ctx.config, v.si
    whole = ~v.separable | reads.traced_here  # all lobes sampled, not those left after reads
    bs, bsdf_weight, mis_pdf, sampled_diffuse = sample_continuation(ctx, sampler, state, v, reads, guides,
                                                                    whole)
    # A traced vertex sampling its diffuse lobe starts a new chain; an inseparable one
    # (no caustic photon is stored behind it) ends the old one; any other continues it
    # through a delta/glossy lobe.
    active_next = v.active_next
    restart = reads.traced_here & sampled_diffuse
    ended = active_next & v.lobes.diffuse & ~v.separable
    state.crossed = dr.select(restart | ended, False, state.crossed | state.armed)
    state.armed = dr.select(restart, reads.read_caustic, state.armed & ~ended)
    state.traced[reads.traced_here | reads.traced_whole | reads.first_read] = state.traced + 1
    state.coat_counted = coat & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    if config.coat_reads:
        active_next, bsdf_weight = _coat_roulette(sampler, state, active_next, whole, bs, bsdf_weight)
    state.β *= bsdf_weight
    state.η *= bs.eta
    state.prev = PreviousVertex(si=dr.detach(si, True), bsdf_pdf=mis_pdf,
                                bsdf_delta=mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
                                normal=mi.Vector3f(v.shading_n), sky_record=mi.UInt32(guides.record),
                                sky_fraction=mi.Float(guides.sky_fraction))
    state.ray = si.spawn_ray(si.to_world(bs.wo))
    # Russian roulette, as Mitsuba's path tracers (η² keeps it unitless).
    β_max = dr.max(state.β)
    active_next &= (β_max > 0) & (bs.pdf > 0) & dr.all(dr.isfinite(state.β)) & ~reads.trusted_whole
    rr_prob = dr.minimum(β_max * dr.square(state.η), 0.95)
    rr_active = state.depth + 1 >= config.rr_depth
    state.β[rr_active] *= dr.rcp(dr.maximum(rr_prob, 1e-8))
    active_next &= ~rr_active | (sampler.next_1d() < rr_prob)
    state.pi = ctx.scene.ray_intersect_preliminary(state.ray, coherent=False, active=active_next)
    state.depth += 1
    state.active = active_next
