"""The vertex cases: one table of how the camera walk and the gather walk treat each
structure of BSDF they meet, and the per-lane classification both walks read.

A BSDF's flags give its **structure** (:class:`Lobes`, from :func:`lobes_of`; the walks
read them through :func:`~pmic_integrator.bsdfs.lobe_flags`, which drops the diffuse lobe
a principled metal's or glass's flags list but it does not have); two
**modifiers** change how a structure is read: a diffuse lobe that *leans* off the
shading normal (normal maps) and *transmission*. For each case :data:`VERTEX_CASES`
gives, per walk, what is read there, which lobes take emitter samples, how the walk
goes on, and its Russian roulette, and where the walks differ, why. The thresholds
the walks test (:data:`CAMERA_PEAK_RATIO`, :data:`GATHER_PEAK_RATIO`, the roulette
bounds) live in the table's rows; the measurements behind them are in the docs'
tuning page.

Adding a case: a row here, its mask in :class:`Lobes`, a ``SceneInfo`` flag that turns
its code on (:mod:`pmic_integrator.pipeline`), then the camera path's reads
(:mod:`pmic_integrator.render.reads`) and the gather vertex
(:func:`pmic_integrator.gather._gather_vertex`), which both read the row.
"""
from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi

from .bsdfs import glossy_beside_diffuse


@dataclass
class Lobes:
    """A BSDF's structure at each lane (from its flags)."""

    diffuse: mi.Bool  #: has a diffuse lobe
    specular: mi.Bool  #: has a delta or a glossy lobe
    glossy: mi.Bool  #: has a glossy lobe
    delta: mi.Bool  #: has a delta lobe
    transmits: mi.Bool  #: has a transmission lobe
    flags: mi.UInt32

    @property
    def mixed(self) -> mi.Bool:
        """A diffuse lobe beside delta or glossy ones (plastics, principled)."""
        return self.diffuse & self.specular

    @property
    def smooth_coat(self) -> mi.Bool:
        """Delta lobes over a diffuse one and no glossy lobe (a smooth plastic)."""
        return self.diffuse & self.delta & ~self.glossy

    @property
    def rough_coat(self) -> mi.Bool:
        """A glossy lobe beside a diffuse one (a rough plastic, principled)."""
        return glossy_beside_diffuse(self.flags)


def lobes_of(flags) -> Lobes:
    """The structure of a BSDF of ``flags`` (``bsdf.flags()``)."""
    delta = mi.has_flag(flags, mi.BSDFFlags.Delta)
    glossy = mi.has_flag(flags, mi.BSDFFlags.Glossy)
    return Lobes(diffuse=mi.has_flag(flags, mi.BSDFFlags.Diffuse), specular=glossy | delta,
                 glossy=glossy, delta=delta,
                 transmits=mi.has_flag(flags, mi.BSDFFlags.Transmission), flags=flags)


@dataclass(frozen=True)
class WalkRule:
    """What one walk does at a vertex of one case."""

    read: str  #: what it reads there (cache, photons, maps)
    direct: str  #: which lobes take emitter samples
    continuation: str  #: how the walk goes on
    roulette: str  #: its Russian roulette beyond Mitsuba's


@dataclass(frozen=True)
class VertexCase:
    name: str
    structure: str
    camera: WalkRule
    gather: WalkRule
    differs: str = ""  #: where the walks differ, and why


#: A BSDF whose lobes cannot be taken apart (principled) reads the cache at a camera
#: vertex with its whole response only where it is this close to diffuse for the
#: incident direction: its value at the mirror direction at most this many times its
#: cosine-weighted mean (:func:`~pmic_integrator.bsdfs.near_diffuse`; gather hits have their own bound,
#: GATHER_PEAK_RATIO). Read wherever a diffuse lobe would be, a
#: Cornell box of principled walls came out 3-8 % off in places at roughness 0.5,
#: 10-20 % with metallic 0.5 and roughness 0.3 (glossy reflections of the light
#: averaged away); at 2, within 1.4 % and 0.7 % (the metallic walls never read: they
#: are traced as before); at 4, 3 % and 3 %. In a dim room lit through a door
#: (benchmarks/scene_kinds.py's door_principled) it left the image ~2 % dark for most
#: photon seeds (a quadrant 5 %), mostly from the gathers' even-light approximation at
#: principled hits (README, limits; 0.987 -> 0.993 of path once gathers went on through
#: the glossiest hits); at 1.2 it is unbiased but reads too rarely to pay (0.39x path's
#: speed there, against 1.87x).
CAMERA_PEAK_RATIO = 2.0
#: A gather hit on a BSDF whose lobes cannot be taken apart (principled) reflects the
#: photon's irradiance with the whole BSDF's response (as if lit evenly) where its
#: value at the mirror direction is at most this many times its cosine-weighted mean
#: (:func:`~pmic_integrator.bsdfs.near_diffuse`); beyond, the gather ray goes on through
#: a sample of the whole BSDF. (The camera's CAMERA_PEAK_RATIO is 2.) Read everywhere,
#: a glossy metal floor (metallic 0.86, roughness 0.13: a peak ratio in the tens) read
#: 76 % too bright along the gather rays that met it (a random room's first-hit image
#: +12 %, 12 seeds); at 4, 0.96-1.05 of path's radiance along the same rays (three
#: seeds; at 8, 1.07), and the door-lit room of Blender-default principled (roughness
#: 0.5: 1.3 at normal incidence, 6 at 66°) 0.987 -> 0.993 of path, its cache stage
#: 0.44-0.49 -> 0.55-0.59 s (two interleaved rounds).
GATHER_PEAK_RATIO = 4.0
#: A camera vertex behind a traced one that goes on through a weak glossy lobe alone
#: survives with probability weight / this (the same bound as the gather's).
CAMERA_COAT_ROULETTE_BELOW = 0.5
#: A gather ray's roulette through a glossy lobe (``gather.GATHER_ROULETTE``) plays
#: only below this throughput: a rough metal passes most of the light, so roulette
#: there saves little, and it made the records that see the lamp room's
#: shades noisier (its relMSE 0.211 -> 0.224).
GATHER_ROULETTE_BELOW = 0.5

#: What a gather reads under a coat and which lights it samples there.
_COATED_DIFFUSE = ("the diffuse lobe as 'diffuse'", "delta lights on the diffuse lobe")

VERTEX_CASES: tuple[VertexCase, ...] = (
    VertexCase(
        "diffuse", "a diffuse lobe only",
        camera=WalkRule("first hit: the cache (else the global map); final gather: traced at the "
                        "first diffuse vertex, the cache behind it (traced again nearer than a "
                        "record radius, up to 3 times); the caustic map where traced",
                        "all emitter samples (MIS with the traced continuation; with BSDF "
                        "sampling of the diffuse lobe under a sky)",
                        "ends where read; traced: a sample of the BSDF, guided where records reach",
                        "Mitsuba's, from rr_depth"),
        gather=WalkRule("the nearest photon's precomputed irradiance (near hits: one bounce more)",
                        "delta lights only (the photons smear their shadows)",
                        "ends", "none")),
    VertexCase(
        "smooth_coat", "delta lobes over a diffuse one (smooth plastic)",
        camera=WalkRule("the diffuse lobe as 'diffuse'",
                        "the diffuse lobe; traced vertices trace the coat's reflection of the "
                        "lights (a ray of its own, coat_emission)",
                        "the delta lobes (all lobes where traced)", "Mitsuba's"),
        gather=WalkRule(*_COATED_DIFFUSE, "the delta lobes, up to GATHER_SPECULAR_BOUNCES",
                        "none after delta lobes"),
        differs="the camera's image shows the coat's reflection of the lights, which gathers "
                "leave to the caustic map"),
    VertexCase(
        "rough_coat", "a glossy lobe beside a diffuse one (rough plastic)",
        camera=WalkRule("the diffuse lobe as 'diffuse'; behind a traced vertex, where the whole "
                        "BSDF is nearly diffuse (CAMERA_PEAK_RATIO), the coat reads the records "
                        "too and the path ends (coat_reads)",
                        "the glossy lobe shares emitter samples with the continuation",
                        "the glossy lobe; at and past a traced vertex that read the caustic map "
                        "each sample is split between the lobes (lobes_split)",
                        "behind a traced vertex, weight / CAMERA_COAT_ROULETTE_BELOW"),
        differs="the camera weighs its roulette by the sample's weight, the gather by its "
                "throughput: a camera path's weight is already in β",
        gather=WalkRule(*_COATED_DIFFUSE, "the glossy lobe",
                        "min(1, throughput) below GATHER_ROULETTE_BELOW")),
    VertexCase(
        "inseparable", "lobes a context cannot take apart (principled)",
        camera=WalkRule("traced whole at the first vertex; behind a traced one read whole where "
                        "its peak is within CAMERA_PEAK_RATIO of its mean, and the path ends",
                        "the whole BSDF", "a sample of the whole BSDF", "Mitsuba's"),
        gather=WalkRule("read whole where its peak is within GATHER_PEAK_RATIO of its mean",
                        "delta lights with the whole BSDF", "else a sample of the whole BSDF",
                        "none"),
        differs="a camera read shows directly (a glossy reflection averaged away is seen: 2), "
                "a gather read is averaged over a record's rays (4)"),
    VertexCase(
        "specular_only", "delta or glossy lobes only (glass, metal, a principled metal or glass: "
                         "bsdfs.diffuse_free)",
        camera=WalkRule("nothing", "glossy lobes share emitter samples with the continuation",
                        "a sample of the BSDF", "Mitsuba's"),
        gather=WalkRule("nothing", "none", "a sample, up to GATHER_SPECULAR_BOUNCES",
                        "glossy: min(1, throughput) below GATHER_ROULETTE_BELOW"),
        differs="emission met past such lobes is the caustic map's in gathers (when it exists)"),
)

#: Modifiers of the cases above.
MODIFIERS: dict[str, str] = {
    "leaning": "a diffuse lobe leaning off the shading normal (normal map): both walks take "
               "its response at three azimuths per level; the camera reads the cache about the "
               "normal it leans to",
    "transmission": "a diffuse lobe that transmits (principled glass, a thin leaf): never read "
                    "whole by the camera (that light comes from behind); a gather ray goes on "
                    "where it crosses the surface",
}
