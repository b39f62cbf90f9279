"""Every seed and random stream pmic draws from, named in one place.

A generator here is a PCG32 keyed by ``(seed, stream)`` (:func:`pmic_integrator._jit.rng`);
different streams of one seed are independent. Two seeds exist:

* the **scene seed**, the ``seed`` parameter: it alone drives the photons and the
  cache, so the cache is a pure function of (scene, settings, seed) and a cache file
  can be reused by any render;
* the **render seed**, ``mi.render(..., seed=)``: it drives Mitsuba's sampler, and
  through it every random number of the camera paths (:func:`render_rng` derives a
  generator from the sampler where a camera-path stage needs one of its own).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

# --- Scene seed: photons ---------------------------------------------------------------
#: Photon batch ``b`` of a map is traced with seed ``seed·PHOTON_SEED_STRIDE + 2b + k``
#: (``k`` = 1 for the caustic map, 0 for the global one) and stream = the index of its
#: first light path, so the two maps and all batches are independent.
PHOTON_SEED_STRIDE = 7919


def photon_batch_seed(seed: int, batch: int, caustic: bool) -> int:
    return seed * PHOTON_SEED_STRIDE + batch * 2 + int(bool(caustic))


# --- Scene seed: the cache (streams of _jit.rng) -----------------------------------------
RECORD_GATHER = 1  #: a record's stratified gather rays (and glossy bounces along them)
PILOT_DISTANCE = 2  #: pilot rays measuring a candidate's harmonic mean distance
RECORD_DIRECT = 11  #: emitter samples of a record's direct irradiance
RECORD_DIRECT_DELTA = 12  #: ...and its samples of the delta lights (a sun, a spot)
RECORD_GATHER_REST = 13  #: the rest of a record's gather rays (pipeline.FIRST_GATHER_SHARE)
RECORD_SURROUNDINGS = 14  #: rays that survey what surrounds each record (cache.record_surroundings)
CAUSTIC_PILOT = 15  #: rays that trace caustic light from caustic photons (pipeline.traced_caustics_moment)
CAMERA_POINTS = 101  #: ``irradiance_cache`` only: the camera rays that seed its records
SURFACE_PROBES = 103  #: the view-independent probes sampled on every surface by area
SURFACE_MASS = 107  #: probes of the surface under a precomputed estimate's disc (boundary.py)

# Seed offsets (added to the scene seed) of the cache stage's passes, so that the pilot
# rays of placement, of the probes and the records' own gathers never share numbers.
PLACEMENT_PILOT = 17  #: pilot radii of placement candidates
PROBE_PILOT = 23  #: pilot radii of the surface probes (neighbour clamping)
RECORDS = 31  #: record gathers; plus the number of records placed before this batch


def render_rng(sampler: mi.Sampler, lanes: int) -> mi.PCG32:
    """A generator per camera lane, seeded from Mitsuba's ``sampler``: it follows the
    render seed (and the sample index), unlike a generator keyed by the scene seed."""
    state = mi.UInt64(mi.UInt32(sampler.next_1d() * 4294967040.0))
    return mi.PCG32(size=lanes, initstate=state, initseq=dr.arange(mi.UInt64, lanes))


def render_pass_seed(seed, pass_index: int):
    """The sampler seed of render pass ``pass_index`` (:func:`camera.pass_counts`: more
    than one only past 2^32 camera samples): the render seed itself (an ``int`` or a
    ``mi.UInt32``, as Mitsuba passes it) for the first, a hash of both after, so that
    no pass repeats another render seed's numbers."""
    if pass_index == 0:
        return seed
    v0, _ = mi.sample_tea_32(mi.UInt32(seed), mi.UInt32(pass_index))
    return v0
