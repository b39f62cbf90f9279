"""The camera path's loop state: what each lane carries from one vertex to the next."""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi


@dataclass
class CausticRead:
    """One deferred caustic-map read of each lane (:mod:`.caustics`): whether it was
    made, where, and its weight (throughput times the diffuse response)."""

    made: mi.Bool
    p: mi.Point3f
    n: mi.Vector3f
    weight: mi.Spectrum

    @staticmethod
    def none() -> "CausticRead":
        return CausticRead(mi.Bool(False), mi.Point3f(0.0), mi.Vector3f(0.0), mi.Spectrum(0.0))


@dataclass
class PreviousVertex:
    """What emission met at the next vertex needs of the one before (its MIS weight
    against that vertex's emitter samples)."""

    si: mi.SurfaceInteraction3f
    bsdf_pdf: mi.Float
    bsdf_delta: mi.Bool
    normal: mi.Vector3f  #: shading normal of ``si``, on its lit side
    #: The record whose sky this vertex's emitter samples followed, and how often (0: never).
    sky_record: mi.UInt32
    sky_fraction: mi.Float

    @staticmethod
    def camera() -> "PreviousVertex":
        return PreviousVertex(dr.zeros(mi.SurfaceInteraction3f), mi.Float(1.0), mi.Bool(True),
                              mi.Vector3f(0.0, 0.0, 1.0), mi.UInt32(0), mi.Float(0.0))


@dataclass
class PathState:
    """One camera path between vertices."""

    ray: mi.Ray3f
    pi: mi.PreliminaryIntersection3f  #: where ``ray`` meets the scene
    depth: mi.UInt32
    active: mi.Bool
    L: mi.Spectrum
    β: mi.Spectrum
    η: mi.Float
    prev: PreviousVertex
    valid: mi.Bool
    traced: mi.UInt32  #: diffuse vertices path-traced so far (final gather)
    # ``armed``: the last traced diffuse vertex read the caustic map and every vertex
    # since continued through a delta/glossy lobe; ``crossed``: armed, and at least one
    # such lobe lies behind. Light reaching the path through a delta/glossy lobe once
    # armed (emitter samples through this vertex's lobes), or by emission once crossed,
    # is a caustic that map already holds.
    armed: mi.Bool
    crossed: mi.Bool
    #: The last vertex traced its coat's reflection of the lights (direct.coat_emission)
    #: and the continuation took a delta lobe: emission met now is counted there.
    coat_counted: mi.Bool
    # AOVs (width-1 constants when not asked for).
    L_direct: mi.Spectrum
    L_indirect: mi.Spectrum
    L_caustic: mi.Spectrum
    coverage: mi.Float
    unread: mi.Bool  #: no vertex has read the cache yet (coverage AOV)
    #: The caustic-map reads made after the loop (one slot per traced vertex, only
    #: where the config defers them).
    reads: list = field(default_factory=list)

    @staticmethod
    def start(ray: mi.Ray3f, pi, active, deferred_slots: int) -> "PathState":
        return PathState(ray=ray, pi=pi, depth=mi.UInt32(0), active=active, L=mi.Spectrum(0.0),
                         β=mi.Spectrum(1.0), η=mi.Float(1.0), prev=PreviousVertex.camera(),
                         valid=mi.Bool(False), traced=mi.UInt32(0), armed=mi.Bool(False),
                         crossed=mi.Bool(False), coat_counted=mi.Bool(False),
                         L_direct=mi.Spectrum(0.0), L_indirect=mi.Spectrum(0.0),
                         L_caustic=mi.Spectrum(0.0), coverage=mi.Float(0.0), unread=mi.Bool(True),
                         reads=[CausticRead.none() for _ in range(deferred_slots)])
