"""A camera vertex: the surface met, its BSDF's case (:mod:`pmic_integrator.cases`),
and what the path decided to read there (:class:`Reads`) and to follow (:class:`Guides`).
Built anew at each vertex; none of it is loop state."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .._jit import shading_normal_on_side
from ..cases import Lobes, lobes_of
from ..bsdfs import lobe_flags, lobes_separable
from .config import PathConfig
from .state import PathState


def no_light(si):
    """The ``zeros`` of :func:`~pmic_integrator._jit.only_where` for a light estimate at
    ``si``'s lanes (with or without the sampler)."""
    return lambda *sampler: dr.zeros(mi.Spectrum, dr.width(si.p))


@dataclass
class Vertex:
    """The surface a camera path meets and its BSDF's structure there."""

    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDF
    lobes: Lobes
    n: mi.Vector3f  #: geometric normal on the side the path arrives from
    shading_n: mi.Vector3f  #: shading normal on that side
    active_next: mi.Bool  #: the path may go on from here
    separable: mi.Bool  #: its lobes can be taken apart (bsdfs.lobes_separable)
    lit_diffuse: mi.Bool  #: it has a diffuse lobe that can be read or traced alone

    @staticmethod
    def meet(state: PathState, config: PathConfig, diffuse_free=None) -> "Vertex":
        """The surface ``state``'s ray meets (``diffuse_free``: the scene's
        :func:`~pmic_integrator.bsdfs.diffuse_free_table`)."""
        si = state.pi.compute_surface_interaction(state.ray, ray_flags=mi.RayFlags.All,
                                                  active=state.active)
        bsdf = si.bsdf(state.ray)
        lobes = lobes_of(lobe_flags(bsdf, diffuse_free))
        active_next = state.active & si.is_valid() & (state.depth + 1 < config.max_depth)
        separable = mi.Bool(True)
        if config.inseparable_bsdfs:
            separable = lobes_separable(bsdf, si, active_next & lobes.mixed)
        n = mi.Vector3f(si.n)
        n = dr.select(dr.dot(n, state.ray.d) > 0, -n, n)
        return Vertex(si=si, bsdf=bsdf, lobes=lobes, n=n, shading_n=shading_normal_on_side(si, n),
                      active_next=active_next, separable=separable,
                      lit_diffuse=active_next & lobes.diffuse & separable)


@dataclass
class Reads:
    """Where a vertex's diffuse lobe reads the cache or the photon maps, and where it
    is traced instead (:func:`~pmic_integrator.render.reads.where_read`)."""

    trust: mi.Bool  #: reads its diffuse (or whole) light here
    traced_here: mi.Bool  #: a diffuse vertex path-traced (final gather)
    traced_whole: mi.Bool  #: an inseparable BSDF traced whole
    trusted_whole: mi.Bool  #: an inseparable BSDF read whole (the path ends)
    cached: mi.Color3f  #: the records' irradiance where ``covered``
    covered: mi.Bool
    cached_direct: mi.Color3f  #: the records' direct part of ``cached`` (coat reads)
    records_here: mi.Bool  #: first hit: the records serve this depth
    read_caustic: mi.Bool  #: reads the caustic map
    response: mi.Spectrum  #: the diffuse lobe's (or whole BSDF's) response
    coat_read: mi.Bool  #: a rough plastic's coat reads the records too
    coat_response: mi.Spectrum
    #: Final gather: a trusted vertex reads all its light from the cache, direct light
    #: included: only its other lobes need emitter samples.
    from_records: mi.Bool
    #: Adaptive estimator: a first diffuse vertex that reads the records' bounced light
    #: (part of ``trust``, not ``from_records``: its direct light is sampled).
    first_read: mi.Bool
    #: There: the record that guides its continuation and that record's bounced share
    #: (``RecordIndex.guide_record``, found by the first-read test).
    first_record: mi.UInt32
    first_share: mi.Float


@dataclass
class Guides:
    """How a traced vertex's continuation (and its emitter samples of a sky) are
    drawn beside BSDF sampling (:mod:`~pmic_integrator.render.continuation`)."""

    record: mi.UInt32  #: the record whose distribution of gathered light guides
    fraction: mi.Float  #: of the continuation drawn from it
    sky_fraction: mi.Float  #: of the sky's emitter samples following the sky it saw
    light_total: mi.Float  #: weight of the bright records facing the vertex
    light_fraction: mi.Float  #: of the continuation drawn towards them
