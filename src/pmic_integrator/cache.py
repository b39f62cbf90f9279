"""Stage 3: the irradiance cache — record placement, record computation, interpolation.

Placement follows the paper's Fig. 2 (walk the candidates in order; a candidate that no
existing record covers becomes a record) but runs as data-parallel rounds that give
*exactly* the sequential result: in each round, an undecided candidate becomes a
record when no undecided candidate before it in the order could cover it; then every
undecided candidate covered by a new record is dropped. A record's radius is known
before it is computed (a cheap pilot gather), so coverage is decided with the same
radius the record will have, and after placement every candidate is covered.

Records are computed by final gathering over an M×N stratified hemisphere and carry
rotational and translational irradiance gradients (Ward & Heckbert 1992, in the form
of Křivánek et al. 2005). Interpolation uses Ward's error metric with a weight shifted
to reach zero at the edge of a record's reach, so that records entering or leaving the
sum cause no brightness step (one of the paper's weak points).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import drjit as dr
import mitsuba as mi
import numpy as np

from . import streams
from . import skylight
from .gather import PAST_TARGET_LIFTS, GatherSource, gather_radiance, stratified_directions
from . import emission
from . import spectra
from ._jit import (ONE_MINUS_EPSILON, concat, finite, interleave, jittered, mean_value, mis_weight,
                   opaque_float, opaque_u32, rng as make_rng, scatter_min,
                   segment_blocked, shading_normal_on_side, surface_offset)
from .hashgrid import BallGrid, PointGrid
from .lights import RecordLights

# --- Internal tuning constants -------------------------------------------------------
#: Pilot gather for a candidate's radius: 4 × 4 strata give a harmonic mean distance
#: good to ~25 %, enough to size a record; the full gather then computes irradiance.
PILOT_STRATA = (4, 4)
#: Ward's error below this is treated as this (a record's own position has error 0).
MIN_ERROR = 1e-3
#: A record whose plane is this far (in units of R) in front of the query point is not
#: used: it sees the scene from the other side of a fold or a thin object.
IN_FRONT_TOLERANCE = 0.05
#: Where no record reaches a shading point (rare: a small gap between the records that
#: cover the photons and the pixel centres), interpolation falls back to the records
#: within BACKUP_REACH × their reach, with the same kind of weight.
BACKUP_REACH = 2.0
#: Ball-grid cell edge relative to the mean reach: smaller cells hold fewer balls per
#: query (each query scans one cell) at the price of more (cell, ball) entries.
CELL_PER_REACH = 0.5
#: Gradients are limited so that a first-order extrapolation over the record's reach
#: cannot go below zero or above twice the record's irradiance.
GRADIENT_LIMIT = 1.0
#: Emitter samples per record for its direct irradiance (final gather only): an area
#: light's irradiance varies by a few % over its solid angle, so 64 samples give ~1 %
#: where it is in full view; the error is read one diffuse bounce away from the camera.
RECORD_DIRECT_SAMPLES = 64
#: ...of which this fraction of the sky's samples, at a record whose gather saw the sky
#: (:meth:`RecordIndex.sees_sky`), follow the sky it saw (its ``sky_guide``), the rest
#: the whole sky's tables, all weighted by the mixture's density. Drawn over the whole
#: sky, a window-lit room's 64 samples met the window a few times each: a record's
#: direct light was a skewed draw, and the image moved by ±1 % from one scene seed to
#: the next (sd over 4 seeds 1.0 %, mean 0.988 of path's; 512 samples: 0.1 %, 0.998).
RECORD_SKY_GUIDE_FRACTION = 0.5
#: ...drawn from jittered strata of the sample square (the largest square grid that fits
#: the count), each warped by the emitter's sampling: the relative variance of a
#: record's direct light fell 22x in a Cornell box (the light's edge and its occluders
#: are met by strata, not by chance), 1.4x in a room lit through a window, 1.25x under
#: an open sky (64 samples, against a 4096-sample reference).
#: Guiding (final gather): each record keeps how its gather's radiance was spread over
#: directions, in equal-area bins of the whole sphere in world space (GUIDE_BANDS bands
#: of z = cos θ × GUIDE_SECTORS sectors of φ: no frame to match between a record and
#: the point it guides). 128 bins of 0.1 sr: fine enough to send rays towards a bright
#: opening or a lit lamp housing, coarse enough for 256 gather rays to fill.
GUIDE_BANDS = 8
GUIDE_SECTORS = 16
GUIDE_BINS = GUIDE_BANDS * GUIDE_SECTORS
GUIDE_BIN_SOLID_ANGLE = 4.0 * math.pi / GUIDE_BINS
#: Guiding is skipped in scenes where records covering less than this fraction of
#: the surface (records weighted by R²) owe at least GUIDE_BOUNCED_SHARE of their
#: irradiance to bounced light (an open ground under a sky): there a guided ray is
#: rarely drawn, and looking for the record to draw it from cost 37 % of the render
#: for no gain. By area, not by count: records crowd concave corners (the material
#: preview's object holds 41 % of its records, 10 % of its area), where a count of a
#: quarter said "pays" and guiding cost 9 % of the render for 3 % less error; by count
#: the bundled exterior sat at 0.244-0.251 and flipped from seed to seed, compiling a
#: second render kernel. By area the open scenes score 0.09-0.10 (material preview,
#: bundled exterior) and 0.14-0.17 (walled courtyards, whose sky guides pay: 27 % of
#: the overcast one's efficiency), every interior 0.90-0.99.
GUIDE_MIN_RECORDS = 0.125
GUIDE_BOUNCED_SHARE = 0.25
#: A record's guide holds the sky it saw (escaped_sky) only where at most this
#: fraction of its gather rays left the scene: the sky seen through an opening. At
#: 0.5, records in the gap under the material preview's object qualified too, and its
#: relMSE rose 2 % (4.20e-3 -> 4.27-4.30e-3); a window is a far smaller share.
SKY_GUIDE_OPENNESS = 0.25
#: ...unless the sky is even within the guide's bins (``SkySampler.even``: a constant
#: sky, an overcast one): then every record's guide holds the sky it saw. A guided
#: sample falls uniformly within its bin, which serves an even sky as well as its own
#: tables do, and the guide knows what walls and roofs hide (an overcast courtyard:
#: relMSE 1.43e-3 -> 1.16e-3). Over the material preview's studio sky (variation
#: within bins 0.71) it lost the sky's detail: +26 % relMSE at any openness.
EVEN_SKY_OPENNESS = 1.0
#: Interpolation walks a query's grid cell in two passes: the first only tests which
#: records reach the query (position, normal, radius) and keeps the first this many
#: of them; the second reads those whole (irradiance, gradients, direct light) and
#: tests their visibility. Only ~1 in 10 of the records a cell lists reaches a given
#: query (1.9 of 19.8 in the material preview), and a SIMD packet runs the loop body
#: as often as its busiest lane needs (33 times there): reading every listed record
#: whole cost three times the walk. Queries that more records reach walk the cell
#: again the old way; the sums are the same, term for term, either way.
INTERPOLATION_SLOTS = 8
#: Floats per record in RecordIndex.pack(): position, normal, radius, nearest hit; then
#: irradiance, direct light, translational and rotational gradients, the direct
#: light's rotational gradient relative to it, the shading normal (30, padded to a
#: power of two: Dr.Jit reads powers of two as packet loads).
PACKED_HEAD = 8
PACKED_BODY = 32


@dataclass
class CacheRecords:
    """Irradiance-cache records (structure of arrays, one entry per record)."""

    position: mi.Point3f  #: where the record was computed
    normal: mi.Vector3f  #: surface normal on the lit side
    radius: mi.Float  #: R: harmonic mean distance to the surrounding geometry, clamped
    irradiance: mi.Color3f  #: E at the record
    grad_t: tuple  #: translational gradient, world space: (∇E_r, ∇E_g, ∇E_b) Vector3f
    grad_r: tuple  #: rotational gradient, world space: (∇E_r, ∇E_g, ∇E_b) Vector3f
    obstacle: mi.Float = None  #: nearest hit of the record's gather (None: not known)
    #: Shading normal on the lit side, about which irradiance and its rotational
    #: gradient were gathered (None: ``normal``); see :func:`shading_normals`.
    shading_normal: mi.Vector3f = None
    #: Directional distribution of the gathered radiance (see :func:`guide_cdfs`):
    #: GUIDE_BINS cumulative probabilities per record, record-major; a record whose
    #: gather found no light has zeros (it guides nothing). None: not computed.
    guide: mi.Float = None
    #: The same over the sky its gather rays saw leave the scene (:func:`escaped_sky`),
    #: zeros where they saw none: a density for emitter samples of the sky.
    sky_guide: mi.Float = None
    #: The gather's nearest hit per azimuth sector of the record's (shading-normal)
    #: frame, OBSTACLE_SECTORS per record (None: only ``obstacle`` is known).
    obstacle_sectors: mi.Float = None
    #: Mean over the record's gather rays of their luminance squared (None: not known,
    #: 0 where filled in): with ``irradiance``, the relative variance of one
    #: cosine-sampled bounce at the record (:meth:`RecordIndex.bounce_variance`).
    ray_moment: mi.Float = None
    #: Per record, whether it gathered only the first round of its rays
    #: (pipeline.GATHER_BUDGET_RAYS; None: none did).
    partial: mi.Bool = None

    @property
    def count(self) -> int:
        return dr.width(self.radius)

    @staticmethod
    def empty() -> "CacheRecords":
        z = mi.Vector3f()
        return CacheRecords(mi.Point3f(), mi.Vector3f(), mi.Float(), mi.Color3f(), (z, z, z), (z, z, z))

    @staticmethod
    def geometry_only(p: mi.Point3f, n: mi.Vector3f, radius: mi.Float) -> "CacheRecords":
        """Records with position, normal and radius only: enough for coverage tests."""
        count = dr.width(radius)
        z = dr.zeros(mi.Vector3f, count)
        return CacheRecords(p, n, radius, dr.zeros(mi.Color3f, count), (z, z, z), (z, z, z))

    def _filled(self, name: str):
        """Optional field ``name``, or what records without it hold in its place (for
        :meth:`extend`): no nearest hit is known (+inf), the shading normal is the
        normal, a guide guides nothing (zeros), every sector's hit is the one known."""
        value = getattr(self, name)
        if value is not None:
            return value
        if name == "obstacle":
            return dr.full(mi.Float, dr.inf, self.count)
        if name == "shading_normal":
            return self.normal
        if name in ("guide", "sky_guide"):
            return dr.zeros(mi.Float, self.count * GUIDE_BINS)
        if name == "ray_moment":
            return dr.zeros(mi.Float, self.count)
        if name == "partial":
            return dr.zeros(mi.Bool, self.count)
        return dr.repeat(self._filled("obstacle"), OBSTACLE_SECTORS)  # obstacle_sectors

    def extend(self, other: "CacheRecords") -> "CacheRecords":
        """These records followed by ``other``'s, field by field (an optional field
        either holds is filled in for the other: :meth:`_filled`)."""
        if self.count == 0:
            return other
        if other.count == 0:
            return self
        joined = {}
        for f in fields(CacheRecords):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if isinstance(mine, tuple):
                joined[f.name] = tuple(concat([a, b], type(a)) for a, b in zip(mine, theirs))
            elif mine is None and theirs is None:
                joined[f.name] = None
            else:
                mine, theirs = self._filled(f.name), other._filled(f.name)
                joined[f.name] = concat([mine, theirs], type(mine))
        return CacheRecords(**joined)

    def blend(self, other: "CacheRecords", weight: float) -> "CacheRecords":
        """These records with a second, independent gather at the same places
        (``other``, from :func:`compute_records` with another stream) counted with
        ``weight`` (its share of the rays): irradiance and gradients are the weighted
        means, nearest hits the nearer, and each directional distribution the mixture
        (a record whose gather found no light in one part takes the other's)."""
        w = float(weight)

        def mean(a, b):
            return a * (1.0 - w) + b * w

        def nearer(a, b):
            return None if a is None or b is None else dr.minimum(a, b)

        return CacheRecords(
            self.position, self.normal, self.radius, mean(self.irradiance, other.irradiance),
            tuple(mean(a, b) for a, b in zip(self.grad_t, other.grad_t)),
            tuple(mean(a, b) for a, b in zip(self.grad_r, other.grad_r)),
            nearer(self.obstacle, other.obstacle), self.shading_normal,
            _mix_cdfs(self.guide, other.guide, w), _mix_cdfs(self.sky_guide, other.sky_guide, w),
            nearer(self.obstacle_sectors, other.obstacle_sectors),
            None if self.ray_moment is None or other.ray_moment is None else mean(self.ray_moment, other.ray_moment),
            partial=self.partial)

    def _per_record(self, value) -> int:
        """How many entries per record a field's ``value`` holds (a guide: GUIDE_BINS)."""
        return dr.width(value) // max(self.count, 1)

    def _entries(self, value, lanes: mi.UInt32) -> mi.UInt32:
        """The entries of a field's ``value`` that the records at ``lanes`` hold."""
        k = self._per_record(value)
        if k == 1:
            return lanes
        return dr.repeat(lanes * k, k) + dr.tile(dr.arange(mi.UInt32, k), dr.width(lanes))

    def take(self, lanes: mi.UInt32) -> "CacheRecords":
        """The records at ``lanes``, every field."""
        return self._mapped(lambda value: dr.gather(type(value), value, self._entries(value, lanes)))

    def put(self, lanes: mi.UInt32, part: "CacheRecords") -> "CacheRecords":
        """These records with those at ``lanes`` replaced by ``part``'s (same fields)."""
        def one(value, new):
            out = type(value)(value)
            dr.scatter(out, new, self._entries(value, lanes))
            return out
        return self._mapped(one, part)

    def _mapped(self, fn, other: "CacheRecords" = None) -> "CacheRecords":
        """Records whose every field (every item of a tuple field) is ``fn`` of this
        one's (and ``other``'s); fields that are None stay None."""
        def apply(mine, theirs):
            if mine is None:
                return None
            return fn(mine) if other is None else fn(mine, theirs)
        out = {}
        for f in fields(CacheRecords):
            mine = getattr(self, f.name)
            theirs = None if other is None else getattr(other, f.name)
            out[f.name] = tuple(apply(a, None if theirs is None else theirs[i]) for i, a in enumerate(mine)) \
                if isinstance(mine, tuple) else apply(mine, theirs)
        return CacheRecords(**out)

    def nbytes(self) -> int:
        return 4 * (3 + 3 + 1 + 3 + 18 + (self.obstacle is not None)
                    + 3 * (self.shading_normal is not None)
                    + GUIDE_BINS * (self.guide is not None)
                    + GUIDE_BINS * (self.sky_guide is not None)
                    + OBSTACLE_SECTORS * (self.obstacle_sectors is not None)
                    + (self.ray_moment is not None) + (self.partial is not None)) * self.count


def block_sum(values, block: int, op: str = "sum"):
    """Sums (or minima, ``op="min"``) of consecutive blocks of ``block`` entries, always
    taken in the same order.

    (``dr.block_sum`` may accumulate in a thread-dependent order; a record must come
    out bit-identical for the same seed.) ``values`` is a Float or a 3-vector array.
    """
    dtype = type(values)
    values = dr.detach(values)
    dr.eval(values)
    count = dr.width(values) // block
    limit = opaque_u32(block)
    first = dr.arange(mi.UInt32, count) * limit

    def body(i, total):
        value = dr.gather(dtype, values, first + i)
        return i + 1, (total + value) if op == "sum" else dr.minimum(total, value)

    start = dr.zeros(dtype, count) if op == "sum" else dr.full(dtype, dr.inf, count)
    _, total = dr.while_loop((dr.zeros(mi.UInt32, count), start),
                             lambda i, total: i < limit, body, label=f"block_{op}")
    return total


# --------------------------------------------------------------------------------------
# Ward's error metric and the interpolation weight
# --------------------------------------------------------------------------------------
def ward_error(x: mi.Point3f, n: mi.Vector3f, rec_p: mi.Point3f, rec_n: mi.Vector3f,
               rec_radius: mi.Float) -> mi.Float:
    """ε = |x − xᵢ| / Rᵢ + sqrt(1 − n·nᵢ) (Ward et al. 1988); Ward's weight is 1/ε."""
    return dr.norm(x - rec_p) / rec_radius + dr.safe_sqrt(1.0 - dr.dot(n, rec_n))


def covers(x, n, rec_p, rec_n, rec_radius, max_error) -> mi.Bool:
    """Record i may be used at (x, n): ε < a, facing the same way, not in front of x."""
    err = ward_error(x, n, rec_p, rec_n, rec_radius)
    in_front = dr.dot(x - rec_p, 0.5 * (n + rec_n)) < -IN_FRONT_TOLERANCE * rec_radius
    return (err < max_error) & (dr.dot(n, rec_n) > 0.0) & ~in_front


def interpolation_weight(err: mi.Float, max_error) -> mi.Float:
    """1/ε − 1/a: Ward's weight shifted to fall continuously to zero at ε = a."""
    return dr.maximum(dr.rcp(dr.maximum(err, MIN_ERROR)) - 1.0 / max_error, 0.0)


# --------------------------------------------------------------------------------------
# Placement (Fig. 2 of the paper, in data-parallel rounds)
# --------------------------------------------------------------------------------------
def _covered_by(records_p, records_n, records_r, grid: BallGrid, query_p, query_n,
                max_error, active, earlier_than=None, priority=None, visibility=None):
    """Mask of queries covered by some record in ``grid`` (optionally: only by records
    whose ``priority`` is smaller than the query's ``earlier_than``; with
    ``visibility`` = (scene, records, lift), only by records not hidden from it)."""

    def visit(found, index, valid):
        rp = dr.gather(mi.Point3f, records_p, index, valid)
        rn = dr.gather(mi.Vector3f, records_n, index, valid)
        rr = dr.gather(mi.Float, records_r, index, valid)
        ok = valid & covers(query_p, query_n, rp, rn, rr, max_error)
        if visibility is not None:
            ok &= ~hidden_record(visibility, index, rp, rn, rr * max_error, query_p, query_n, ok)
        if earlier_than is not None:
            ok &= dr.gather(mi.UInt32, priority, index, ok) < earlier_than
        return found | ok

    lanes = dr.width(query_p)
    return grid.for_each_ball(query_p, dr.zeros(mi.Bool, lanes), visit, active=active,
                              finished=lambda found: found, label="cache_coverage")


#: Points nearer a record than this fraction of its gather's nearest hit are taken as
#: visible without a shadow ray (the gather's rays sample directions, not all of them).
#: (A floor point d from a tall wall: the nearest of 16-256 cosine-distributed rays
#: meets the wall at 1.03-1.16 d.)
OBSTACLE_MARGIN = 0.8
#: Azimuth sectors of a record's frame that keep their own nearest gather hit
#: (CacheRecords.obstacle_sectors): a point is tested only past the nearest hit in its
#: own direction (its sector and the two beside it). The record's one nearest hit
#: made a box beside a record test every point the record reached, on the far side of
#: the record too.
OBSTACLE_SECTORS = 8  # (_obstacle_sector and the packed reads assume 8)


def _obstacle_sector(local: mi.Vector3f) -> mi.UInt32:
    """The azimuth sector (of OBSTACLE_SECTORS = 8) of the local direction ``local``:
    sector k holds the azimuths [k, k + 1) · 45°. By comparisons, not ``atan2``: it runs
    at every record a lookup reads (an atan2 there was ~5 % of a Cornell box's lookups)."""
    # Sectors 4-7 (φ in [π, 2π)) are those of the direction turned by 180°.
    lower = (local.y < 0) | ((local.y == 0) & (local.x < 0))
    x = dr.select(lower, -local.x, local.x)
    y = dr.select(lower, -local.y, local.y)
    sector = dr.select(x > y, 0, dr.select(x > 0, 1, dr.select(-x < y, 2, 3)))
    return mi.UInt32(sector) + dr.select(lower, 4, 0)


def obstacle_sectors(local: mi.Vector3f, distance: mi.Float, owner: mi.UInt32, count: int) -> mi.Float:
    """Per record (``owner`` of each gather ray; ``local``: the ray's direction in the
    record's frame), the nearest hit among its rays in each of OBSTACLE_SECTORS
    azimuth sectors (+inf where none hit)."""
    out = dr.full(mi.Float, dr.inf, count * OBSTACLE_SECTORS)
    scatter_min(out, distance, owner * OBSTACLE_SECTORS + _obstacle_sector(local))
    return out


def _nearest_of_sectors(sectors, sector: mi.UInt32) -> mi.Float:
    """The least of ``sectors`` (a record's OBSTACLE_SECTORS values) at ``sector`` and
    the two beside it."""
    nearest = mi.Float(dr.inf)
    for k in range(OBSTACLE_SECTORS):
        turn = (k + OBSTACLE_SECTORS - sector) % OBSTACLE_SECTORS  # k's place from sector
        beside = (turn <= 1) | (turn == OBSTACLE_SECTORS - 1)
        nearest = dr.select(beside, dr.minimum(nearest, sectors[k]), nearest)
    return nearest


def obstacle_towards(records: "CacheRecords", index: mi.UInt32, rec_p: mi.Point3f, x: mi.Point3f,
                     active, frame_normal: mi.Vector3f = None) -> mi.Float:
    """How far record ``index`` saw nothing in the direction of ``x``: its nearest hit
    in x's azimuth sector and the two beside it (``obstacle_sectors``, read as one
    packet), else its one nearest hit. ``frame_normal``: the record's shading normal,
    where the caller has read it already (:meth:`RecordIndex.pack`)."""
    if records.obstacle_sectors is None:
        return dr.gather(mi.Float, records.obstacle, index, active)
    if frame_normal is None:
        frame_n = records.shading_normal if records.shading_normal is not None else records.normal
        frame_normal = dr.gather(mi.Vector3f, frame_n, index, active)
    sectors = dr.gather(mi.ArrayXf, records.obstacle_sectors, index, active,
                        shape=(OBSTACLE_SECTORS, dr.width(index)))
    return _nearest_of_sectors(sectors, _obstacle_sector(_frame(frame_normal).to_local(x - rec_p)))


def hidden_from(scene, x, n, rec_p, rec_n, rec_reach, obstacle, lift, active) -> mi.Bool:
    """Is record i (reach a·R, nearest gather hit ``obstacle``: towards x, see
    :func:`obstacle_towards`) blocked from (x, n)?

    Only points beyond ``OBSTACLE_MARGIN`` of the nearest surface the record's gather
    met are tested (one shadow ray between the two points, lifted ``lift`` off their
    surfaces): nothing can stand between points closer than the nearest surface. (The
    margin applies to the record's reach too: a wall at d was met at 1.03-1.16 d, and
    a record that reached 1.05 d once went untested, lighting the far side of a 2 mm
    wall through the backup reach, 2 a·R.) A floor split by a thin wall has
    the same plane and normal on both sides; without the test, the lit side's records
    lit a strip of the dark side. Final-gather records, which hold direct light, once
    tested every record they read (a shadow ray for each of up to 8 records at every
    gather hit): 36 % of the render of an exterior lit by a sky, where the records
    reach past nothing; the gated test gives the same images (the thin-wall tests in
    ``tests/test_bias.py`` and ``test_records_reaching_across_a_thin_wall_are_not_read``).
    """
    if scene is None or obstacle is None:
        return dr.zeros(mi.Bool, dr.width(x))
    origin = x + n * lift
    target = rec_p + rec_n * lift
    margin = OBSTACLE_MARGIN * obstacle
    test = active & (rec_reach > margin) & (dr.norm(target - origin) > margin)
    return segment_blocked(scene, origin, target, test, past=PAST_TARGET_LIFTS * lift)


def hidden_record(visibility, index: mi.UInt32, rec_p, rec_n, rec_reach, x, n, active,
                  frame_normal: mi.Vector3f = None) -> mi.Bool:
    """:func:`hidden_from` for record ``index`` of ``visibility`` = (scene, records,
    lift) (:meth:`RecordIndex._visibility`), with its nearest gather hit towards x
    (:func:`obstacle_towards`): the test every reader of the records makes."""
    scene, records, lift = visibility
    obstacle = obstacle_towards(records, index, rec_p, x, active, frame_normal=frame_normal)
    return hidden_from(scene, x, n, rec_p, rec_n, rec_reach, obstacle, lift, active)


def placement_priority(index: mi.UInt32) -> mi.UInt32:
    """The position of each candidate in the walk: a bijective hash of its index.

    The photons arrive sorted by grid cell; walking them in that order would chain
    each decision to its spatial neighbour's and need many rounds. A pseudo-random
    order (as the photons had when emitted) keeps the chains short, O(log n) rounds.
    """
    h = mi.UInt32(index) * 0x9E3779B1  # odd multiplier: a bijection mod 2^32
    return h ^ (h >> 16)  # xor-shift: also a bijection


def place_records(cand_p: mi.Point3f, cand_n: mi.Vector3f, cand_r: mi.Float,
                  max_error: float, existing: "RecordIndex | None" = None):
    """Choose which candidates become records, walking them in the order of
    :func:`placement_priority` (Fig. 2 of the paper).

    ``cand_r`` is the radius R each candidate would have as a record. Candidates that a
    record of ``existing`` already covers are skipped. Returns ``(selected, rounds)``:
    the indices of the candidates that become records (ascending) and the number of
    data-parallel rounds used.
    """
    n = dr.width(cand_r)
    if n == 0:
        return mi.UInt32(), 0
    all_index = dr.arange(mi.UInt32, n)
    undecided = all_index
    if existing is not None and existing.records.count > 0:
        covered = existing.covered(cand_p, cand_n)
        undecided = dr.compress(~covered)
    selected = []
    rounds = 0
    while dr.width(undecided) > 0:
        rounds += 1
        if dr.width(undecided) <= PLACEMENT_TAIL:
            selected.append(_walk_tail(cand_p, cand_n, cand_r, undecided, max_error))
            break
        up = dr.gather(mi.Point3f, cand_p, undecided)
        un = dr.gather(mi.Vector3f, cand_n, undecided)
        ur = dr.gather(mi.Float, cand_r, undecided)
        # Would any earlier undecided candidate cover me? Then I must wait for it.
        grid = BallGrid.build(up, ur * max_error)
        priority = placement_priority(undecided)
        blocked = _covered_by(up, un, ur, grid, up, un, max_error, True,
                              earlier_than=priority, priority=priority)
        dr.eval(blocked)
        new_local = dr.compress(~blocked)
        new_index = dr.gather(mi.UInt32, undecided, new_local)
        selected.append(new_index)
        # Every undecided candidate that a new record covers is decided (not a record).
        np_ = dr.gather(mi.Point3f, cand_p, new_index)
        nn = dr.gather(mi.Vector3f, cand_n, new_index)
        nr = dr.gather(mi.Float, cand_r, new_index)
        new_grid = BallGrid.build(np_, nr * max_error)
        covered = _covered_by(np_, nn, nr, new_grid, up, un, max_error, True)
        # A new record covers itself (ε = 0), so this also removes the new records.
        is_new = dr.zeros(mi.Bool, dr.width(undecided))
        dr.scatter(is_new, True, new_local)
        remaining = dr.compress(~(covered | is_new))
        undecided = dr.gather(mi.UInt32, undecided, remaining)
        dr.eval(undecided)
    if not selected:
        return mi.UInt32(), rounds
    out = concat(selected, mi.UInt32)
    # Ascending candidate index, for reproducibility.
    out = dr.gather(mi.UInt32, out, dr.argsort(out)) if dr.width(out) > 1 else out
    return out, rounds


#: The last few undecided candidates of a placement are walked one by one on the CPU.
#: The rounds' kernels on 1-4 candidates differ from those on more (Dr.Jit treats
#: arrays of one element as scalars) and from seed to seed: a render whose placement
#: ended on other counts than its warm-up's compiled 20-30 small kernels, 0.17 s of the
#: material preview's 2.3 s on a machine whose kernel cache was empty.
PLACEMENT_TAIL = 32


def _walk_tail(cand_p, cand_n, cand_r, undecided: mi.UInt32, max_error) -> mi.UInt32:
    """The sequential walk (Fig. 2) over the few ``undecided`` candidates, in the
    order of :func:`placement_priority`: a candidate becomes a record unless one chosen
    before it covers it (:func:`covers`, in float32 as there). Returns the chosen
    indices (into the candidates)."""
    # Component by component, on the CPU: no kernel (a gather or a conversion of a
    # 3-vector would make one per count).
    index = np.array(undecided, dtype=np.uint32)
    p = np.stack([np.array(c, dtype=np.float32)[index] for c in (cand_p.x, cand_p.y, cand_p.z)], 1)
    n = np.stack([np.array(c, dtype=np.float32)[index] for c in (cand_n.x, cand_n.y, cand_n.z)], 1)
    r = np.array(cand_r, dtype=np.float32)[index]
    key = (index.astype(np.uint64) * np.uint64(0x9E3779B1)) & np.uint64(0xFFFFFFFF)
    key ^= key >> np.uint64(16)  # placement_priority, on the CPU
    a = np.float32(max_error)
    chosen: list[int] = []
    for i in np.argsort(key, kind="stable"):
        covered = False
        for j in chosen:
            offset = p[i] - p[j]
            cosine = np.float32(np.dot(n[i], n[j]))
            err = np.float32(np.linalg.norm(offset)) / r[j] + np.sqrt(max(np.float32(0), np.float32(1) - cosine))
            in_front = np.dot(offset, np.float32(0.5) * (n[i] + n[j])) < -IN_FRONT_TOLERANCE * r[j]
            if err < a and cosine > 0 and not in_front:
                covered = True
                break
        if not covered:
            chosen.append(int(i))
    return mi.UInt32(index[np.sort(np.array(chosen, dtype=np.int64))])


# --------------------------------------------------------------------------------------
# Record computation by final gathering
# --------------------------------------------------------------------------------------
def _frame(n: mi.Vector3f) -> mi.Frame3f:
    return mi.Frame3f(dr.normalize(n))


def shading_normals(scene: mi.Scene, p: mi.Point3f, n: mi.Vector3f, offset: float) -> mi.Vector3f:
    """The shading normal of the surface at each point ``p`` (geometric normal ``n``),
    turned to ``n``'s side: found by a ray from just off the surface back onto it.

    Mitsuba's BSDFs weigh light by the cosine to the shading normal; a record gathered
    about the geometric one holds other irradiance than ``path`` reflects. A floor
    whose vertex normals lean 20° towards a lamp at grazing incidence reflects
    several times what its geometric cosine says (the final gather read 0.86 of
    ``path`` there). Where the shading normal *is* the geometric one (flat shapes,
    spheres, meshes without vertex normals), or no surface is found, ``n`` is
    returned exactly, so those scenes are unchanged bit for bit.
    """
    count = dr.width(p.x)
    if count == 0:
        return mi.Vector3f(n)
    lift = surface_offset(p, offset)
    ray = mi.Ray3f(p + n * lift, -n)
    ray.maxt = 2.0 * lift
    si = scene.ray_intersect(ray, active=mi.Bool(True))
    # The hit's geometric normal, not n: a sphere's is recomputed from the hit point.
    geometric_n = dr.select(dr.dot(si.n, n) < 0, -si.n, si.n)
    shading_n = shading_normal_on_side(si, geometric_n)
    out = dr.select(si.is_valid() & dr.any(shading_n != geometric_n), shading_n, n)
    dr.eval(out)
    return out


def _stratified_rays(p, n, strata, seed, stream, offset, about=None):
    """M·N cosine-weighted stratified rays per point, in [point][j][k] order, about the
    normals ``about`` (default ``n``, the geometric normals). A ray that leaves below
    the geometric surface (possible about a shading normal) starts below it, as
    Mitsuba's ``spawn_ray`` does.

    Returns ``(ray, owner, local direction, j, k, rng)``; ``rng`` continues the
    rays' random streams (for glossy bounces along them)."""
    m_theta, n_phi = strata
    rays = m_theta * n_phi
    count = dr.width(p.x)
    lane = dr.arange(mi.UInt32, count * rays)
    owner = lane // rays
    rng = make_rng(count * rays, seed, stream=stream)
    local, j, k = stratified_directions(m_theta, n_phi, lane % rays, rng.next_float32(), rng.next_float32())
    on = dr.gather(mi.Vector3f, n, owner)
    origin = dr.gather(mi.Point3f, p, owner)
    if about is None:
        ray = mi.Ray3f(origin + on * surface_offset(origin, offset), _frame(on).to_world(local))
    else:
        d = _frame(dr.gather(mi.Vector3f, about, owner)).to_world(local)
        side = dr.select(dr.dot(d, on) < 0, -1.0, 1.0)
        ray = mi.Ray3f(origin + on * (surface_offset(origin, offset) * side), d)
    return ray, owner, local, j, k, rng


def _gather_rays(scene, source, p, n, strata, seed, offset, about=None,
                 stream: int = streams.RECORD_GATHER):
    """Trace M·N stratified rays per point (about the normals ``about``, default
    ``n``); return per-ray data in [point][j][k] order."""
    ray, owner, local, j, k, rng = _stratified_rays(p, n, strata, seed, stream, offset, about)
    if mi.is_spectral:  # each ray its own wavelengths; the records hold linear sRGB
        ray.wavelengths, wavelength_weight = spectra.sample_wavelengths(rng.next_float32())
    radiance, distance = gather_radiance(scene, source, ray, rng,
                                         sample_delta=source.photons.irradiance_nodelta is not None)
    if mi.is_spectral:
        radiance = spectra.to_rgb(radiance * wavelength_weight, ray.wavelengths)
    dr.eval(radiance, distance)
    return owner, j, k, local, radiance, distance


#: Rays per record of :func:`record_surroundings` (8 x 8 strata).
SURROUNDINGS_STRATA = (8, 8)


def record_surroundings(scene, source: GatherSource, records: "CacheRecords", seed: int,
                        offset: float):
    """``(glossy_share, photon_support, glossy_light)`` of each record, from
    SURROUNDINGS_STRATA cosine rays of its own (not its gather's):

    - the share of its rays whose first hit is a surface that its gather cannot read
      as diffuse (glass, metal, glossy or principled: no separable diffuse lobe;
      emitters aside);
    - of its rays that hit a diffuse surface, the share with a precomputed photon
      within one lookup radius of the hit (:meth:`GatherSource.photon_near`);
    - the share of the light reaching the record from those first hits that is
      emitters' light reflected by the glossy ones (one BSDF sample at each): light
      that its gather reads as if they were diffuse. The rest is the diffuse hits'
      albedo times their photon's irradiance.

    What the adaptive estimator asks of a record before reading it at a camera path's
    first hit (render.reads.survey_first_reads)."""
    from .bsdfs import lobe_flags, lobes_separable
    from .cases import lobes_of

    about = records.shading_normal
    ray, owner, _, _, _, rng = _stratified_rays(records.position, records.normal, SURROUNDINGS_STRATA,
                                                seed, streams.RECORD_SURROUNDINGS, offset, about)
    wavelengths, wavelength_weight = spectra.sample_wavelengths(rng.next_float32())
    if mi.is_spectral:  # (the albedo and the reflected light are read at them)
        ray.wavelengths = wavelengths
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    bsdf = si.bsdf(ray)
    lobes = lobes_of(lobe_flags(bsdf, source.diffuse_free))
    diffuse = valid & lobes.diffuse & lobes_separable(bsdf, si, valid & lobes.mixed)
    glossy = valid & ~diffuse & (si.shape.emitter() == None)  # noqa: E711
    n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
    irradiance, supported = source.photon_near(si.p, n, diffuse)
    albedo = mi.luminance(spectra.to_rgb(bsdf.eval_diffuse_reflectance(si, supported) * wavelength_weight,
                                         ray.wavelengths))
    diffuse_light = albedo * mi.luminance(irradiance)
    diffuse_light = dr.select(supported & dr.isfinite(diffuse_light), diffuse_light, 0.0)
    glossy_light = _reflected_emission(scene, si, bsdf, rng, glossy, wavelength_weight)
    rays = SURROUNDINGS_STRATA[0] * SURROUNDINGS_STRATA[1]

    def count(mask):
        return block_sum(dr.select(mask, mi.Float(1.0), mi.Float(0.0)), rays)

    glossy_share = count(glossy) * (1.0 / rays)
    support = count(supported) / dr.maximum(count(diffuse), 1.0)
    # (Sums over the same rays: π / rays cancels.)
    reflected = block_sum(glossy_light, rays)
    total = reflected + block_sum(diffuse_light / math.pi, rays)
    glossy_light_share = dr.select(total > 0, reflected / dr.maximum(total, 1e-30), 0.0)
    dr.eval(glossy_share, support, glossy_light_share)
    return glossy_share, support, glossy_light_share


def _reflected_emission(scene, si, bsdf, rng, active, wavelength_weight) -> mi.Float:
    """Luminance of the emitters' light that the BSDF at ``si`` reflects back along the
    ray that found it: one emitter sample (with its shadow ray), and one BSDF sample
    for delta lobes (glass, a mirror), which emitter samples cannot meet (an
    environment where it leaves the scene). The emitter sample is
    :func:`emission.sample_emitter_direction`'s, as everywhere else: the same choice of
    light whatever order Mitsuba loaded them in, and a sky's shadow rays unbounded."""
    ctx = mi.BSDFContext()
    ds, emitted = emission.sample_emitter_direction(scene, si, mi.Point2f(rng.next_float32(), rng.next_float32()),
                                                    True, active)
    light = bsdf.eval(ctx, si, si.to_local(ds.d), active) * emitted
    sample, weight = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
                                 active)
    delta = active & mi.has_flag(sample.sampled_type, mi.BSDFFlags.Delta) & (sample.pdf > 0)
    hit = scene.ray_intersect(si.spawn_ray(si.to_world(sample.wo)), delta)
    emitter = hit.emitter(scene, delta)
    light += dr.select(delta & (emitter != None), weight * emitter.eval(hit, delta), 0.0)  # noqa: E711
    light = mi.luminance(spectra.to_rgb(light * wavelength_weight, si.wavelengths))
    return dr.select(active & dr.isfinite(light), light, 0.0)


def harmonic_mean_distance(scene, p: mi.Point3f, n: mi.Vector3f, strata, seed: int,
                           offset: float):
    """R: the harmonic mean of the hit distances of M·N stratified rays (misses count
    as infinitely far), and the nearest hit. Returns ``(R, nearest)``. Only distances
    are needed, so no radiance is looked up."""
    if dr.width(p.x) == 0:
        return mi.Float(), mi.Float()
    rays = strata[0] * strata[1]
    ray = _stratified_rays(p, n, strata, seed, streams.PILOT_DISTANCE, offset)[0]
    # `active` by keyword: the second positional argument is `coherent`, and Embree's
    # coherent mode traced these scattered rays 5x slower (0.095 s against 0.018 s
    # for 262k rays in the Cornell box).
    si = scene.ray_intersect_preliminary(ray, active=mi.Bool(True))
    inv = dr.select(si.is_valid(), dr.rcp(dr.maximum(si.t, 1e-30)), 0.0)
    total = block_sum(inv, rays)
    nearest = block_sum(dr.select(si.is_valid(), si.t, dr.inf), rays, op="min")
    return rays / dr.maximum(total, 1e-30), nearest


def clamp_to_neighbours(p: mi.Point3f, n: mi.Vector3f, radius: mi.Float, step: float,
                        iterations: int) -> mi.Float:
    """Neighbour clamping (Křivánek et al.): Rᵢ ≤ Rⱼ + |xᵢ − xⱼ| for candidates facing
    the same way, so that a large record cannot reach over a small one's narrow space
    (the shadowed gap between a light and its ceiling, a corner).

    Exact clamping needs every pair within the largest radius; instead ``iterations``
    passes over neighbours within ``step`` propagate the bound over
    ``iterations × step``, with cheap fixed-radius queries.
    """
    if dr.width(radius) == 0 or iterations <= 0:
        return radius
    grid = PointGrid.build(p, step)
    order = grid.order
    sorted_p = dr.gather(mi.Point3f, p, order)
    sorted_n = dr.gather(mi.Vector3f, n, order)
    sorted_r = dr.gather(mi.Float, radius, order)
    # (Entries packed with their normals: the passes read each neighbour as one packet.)
    grid = grid.sorted_in_place().pack(sorted_n)
    for _ in range(iterations):
        previous = sorted_r

        def visit(bound, index, dist2, valid, offset, normal):
            ok = valid & (dr.dot(normal, sorted_n) > 0)
            neighbour = dr.gather(mi.Float, previous, index, ok) + dr.sqrt(dist2)
            return dr.select(ok, dr.minimum(bound, neighbour), bound)

        sorted_r = grid.for_each_neighbor(sorted_p, step, mi.Float(previous), visit,
                                          label="neighbour_clamping", with_offset="normal")
        dr.eval(sorted_r)
    out = dr.zeros(mi.Float, dr.width(radius))
    dr.scatter(out, sorted_r, order)
    return out


def clamp_records_to_points(index: "RecordIndex", p: mi.Point3f, n: mi.Vector3f,
                            radius: mi.Float, scene: mi.Scene | None = None, lift: float = 0.0):
    """New record radii with Rᵢ ≤ R(x) + |x − xᵢ| for every point x (radius R(x)) that
    record i covers; None if no record changes.

    With ``scene``, a record that covers x but cannot see it (a shadow ray between the
    two, both lifted ``lift`` off their surfaces, is blocked) shrinks until it no longer
    covers x: on a floor split by a thin wall, the lit side's records must not reach
    the dark side, which the same plane and normal tests cannot tell apart.
    """
    records = index.records
    if records.count == 0 or dr.width(radius) == 0:
        return None
    bound_r = dr.zeros(mi.Float, records.count) + records.radius
    dr.eval(bound_r)
    lift = opaque_float(lift)

    def visit(state, i, valid):
        rp = dr.gather(mi.Point3f, records.position, i, valid)
        rn = dr.gather(mi.Vector3f, records.normal, i, valid)
        rr = dr.gather(mi.Float, records.radius, i, valid)
        ok = valid & covers(p, n, rp, rn, rr, index.max_error)
        distance = dr.norm(p - rp)
        bound = radius + distance
        if scene is not None:
            hidden = segment_blocked(scene, p + n * lift, rp + rn * lift, ok,
                                     past=PAST_TARGET_LIFTS * lift)
            # Just outside the reach: ε = |x − xᵢ| / Rᵢ ≥ a.
            bound = dr.select(hidden, distance * (0.99 / index.max_error), bound)
        scatter_min(bound_r, bound, i, ok & (bound < rr))
        return state

    index.grid.for_each_ball(p, dr.zeros(mi.UInt32, dr.width(radius)), visit,
                             label="view_neighbour_clamping")
    dr.eval(bound_r)
    changed = dr.any(bound_r < records.radius)
    return bound_r if bool(changed[0] if dr.width(changed) else changed) else None


def compute_records(scene, source: GatherSource, p: mi.Point3f, n: mi.Vector3f,
                    radius: mi.Float, strata, seed: int, offset: float,
                    sky_openness: float = SKY_GUIDE_OPENNESS,
                    stream: int = streams.RECORD_GATHER) -> CacheRecords:
    """Final-gather irradiance and gradients at (p, n); ``radius`` is the record's R;
    ``sky_openness``: see :func:`escaped_sky`; ``stream``: of the gather's random
    numbers (another gives an independent gather at the same records).

    The gather (and so the irradiance and its gradients) is about the surface's
    shading normal (:func:`shading_normals`), the cosine Mitsuba's BSDFs use."""
    count = dr.width(p.x)
    if count == 0:
        return CacheRecords.empty()
    m_theta, n_phi = strata
    rays = m_theta * n_phi
    shading_n = shading_normals(scene, p, n, offset)
    owner, j, k, local, radiance, distance = _gather_rays(scene, source, p, n, strata, seed, offset,
                                                          shading_n, stream)
    # E = π/(MN) Σ L for cosine-weighted stratified sampling.
    irradiance = block_sum(radiance, rays) * (math.pi / rays)

    # Rotational gradient: ∂E/∂(rotation δ) = ∫ L sinθ v(φ) dω, v = n × (dir. of φ),
    # estimated with cosine-weighted samples as π/(MN) Σ L tanθ v(φ).
    cos_t = dr.maximum(local.z, 1e-4)
    sin_t = dr.safe_sqrt(1.0 - local.z * local.z)
    inv_sin = dr.rcp(dr.maximum(sin_t, 1e-6))
    v = mi.Vector3f(-local.y * inv_sin, local.x * inv_sin, 0.0)
    rot_w = (math.pi / rays) * sin_t / cos_t

    # Translational gradient (Ward & Heckbert 1992; Křivánek et al. 2005): changes of
    # the strata's projected solid angles as the point moves, weighted by radiance
    # differences across each stratum boundary and the nearer hit distance.
    lane_base = owner * rays
    jm = dr.maximum(mi.Int32(j) - 1, 0)
    prev_j = lane_base + mi.UInt32(jm) * n_phi + k
    prev_k = lane_base + j * n_phi + (k + n_phi - 1) % n_phi
    l_prev_j = dr.gather(mi.Color3f, radiance, prev_j)
    l_prev_k = dr.gather(mi.Color3f, radiance, prev_k)
    d_here = distance
    d_prev_j = dr.gather(mi.Float, distance, prev_j)
    d_prev_k = dr.gather(mi.Float, distance, prev_k)
    # Boundary between strata j-1 and j (at sin²θ = j/M), along the azimuth of stratum k.
    s_minus = mi.Float(j) / m_theta
    sin_minus = dr.sqrt(s_minus)
    phi_center = (mi.Float(k) + 0.5) * (2.0 * math.pi / n_phi)
    sc, cc = dr.sincos(phi_center)
    u_k = mi.Vector3f(cc, sc, 0.0)
    theta_term = (2.0 * math.pi / n_phi) * sin_minus * (1.0 - s_minus) \
        / dr.maximum(dr.minimum(d_here, d_prev_j), 1e-30)
    theta_term = dr.select(j > 0, theta_term, 0.0)  # stratum 0 has no inner boundary
    # Boundary between azimuth strata k-1 and k (at φ = 2πk/N), across all of stratum j.
    sin_plus = dr.sqrt((mi.Float(j) + 1.0) / m_theta)
    phi_minus = mi.Float(k) * (2.0 * math.pi / n_phi)
    sm, cm = dr.sincos(phi_minus)
    v_k = mi.Vector3f(-sm, cm, 0.0)
    phi_term = (sin_plus - sin_minus) / dr.maximum(dr.minimum(d_here, d_prev_k), 1e-30)

    frame = _frame(dr.gather(mi.Vector3f, shading_n, owner))
    grad_t, grad_r = [], []
    for c in range(3):
        dl_j = radiance[c] - l_prev_j[c]
        dl_k = radiance[c] - l_prev_k[c]
        gt_local = u_k * (theta_term * dl_j) + v_k * (phi_term * dl_k)
        gr_local = v * (rot_w * radiance[c])
        gt = block_sum(mi.Vector3f(frame.to_world(gt_local)), rays)
        gr = block_sum(mi.Vector3f(frame.to_world(gr_local)), rays)
        grad_t.append(gt)
        grad_r.append(gr)

    # Limit the gradients: over the record's reach, first-order extrapolation must not
    # change irradiance by more than GRADIENT_LIMIT × E (noisy gathers near corners).
    for c in range(3):
        limit = GRADIENT_LIMIT * irradiance[c] / dr.maximum(radius, 1e-30)
        norm_t = dr.norm(grad_t[c])
        grad_t[c] = grad_t[c] * dr.minimum(1.0, limit / dr.maximum(norm_t, 1e-30))
        limit_r = GRADIENT_LIMIT * irradiance[c]
        norm_r = dr.norm(grad_r[c])
        grad_r[c] = grad_r[c] * dr.minimum(1.0, limit_r / dr.maximum(norm_r, 1e-30))
    nearest = block_sum(distance, rays, op="min")
    sectors = obstacle_sectors(local, distance, owner, count)
    world = mi.Vector3f(frame.to_world(local))
    sky = escaped_sky(scene, world, distance, owner, rays, sky_openness)
    guide = guide_cdfs(owner, world, radiance + sky, count)
    ray_moment = block_sum(dr.square(mi.luminance(radiance)), rays) * (1.0 / rays)
    sky_guide = guide_cdfs(owner, world, sky, count) if scene.environment() is not None else None
    records = CacheRecords(mi.Point3f(p), mi.Vector3f(n), mi.Float(radius), mi.Color3f(irradiance),
                           tuple(grad_t), tuple(grad_r), nearest, shading_n, guide,
                           sky_guide=sky_guide, obstacle_sectors=sectors, ray_moment=ray_moment)
    dr.eval(records.irradiance, *records.grad_t, *records.grad_r, records.obstacle, records.obstacle_sectors,
            records.ray_moment)
    return records


# --------------------------------------------------------------------------------------
# Guiding: where a record's gathered light came from
# --------------------------------------------------------------------------------------
def guide_bin(d: mi.Vector3f) -> mi.UInt32:
    """The equal-area sphere bin of the world-space unit direction ``d``."""
    band = mi.UInt32(dr.clip((d.z + 1.0) * (0.5 * GUIDE_BANDS), 0.0, GUIDE_BANDS - 1))
    phi = dr.atan2(d.y, d.x)
    phi = dr.select(phi < 0, phi + 2.0 * math.pi, phi)
    sector = mi.UInt32(dr.clip(phi * (GUIDE_SECTORS / (2.0 * math.pi)), 0.0, GUIDE_SECTORS - 1))
    return band * GUIDE_SECTORS + sector


def escaped_sky(scene: mi.Scene, direction: mi.Vector3f, distance: mi.Float,
                owner: mi.UInt32, rays: int, openness_limit: float = SKY_GUIDE_OPENNESS) -> mi.Color3f:
    """The environment's radiance along the gather rays that left the scene (``distance``
    infinite), 0 along the others, for records that see the sky through an opening (at
    most ``openness_limit`` of their ``rays`` rays left; ``owner``: each ray's record):
    what a record saw of the sky. It goes into the record's guide only, not its irradiance (direct light is
    sampled at the shading point): a continuation guided by it goes out through the
    window a room is lit by, where the shading point's emitter samples, drawn over the
    whole sky, mostly meet the walls (in a room lit through a window, direct light was
    98 % of the noise). Under an open sky those samples do well, and the guide keeps to
    the bounced light it was made for (the material preview: +2 % relMSE with it)."""
    environment = scene.environment()
    escaped = ~dr.isfinite(distance)
    if environment is None or not dr.any(escaped):
        return dr.zeros(mi.Color3f, dr.width(distance))
    openness = block_sum(dr.select(escaped, 1.0, 0.0), rays) * (1.0 / rays)
    escaped &= dr.gather(mi.Float, openness, owner) <= opaque_float(openness_limit)
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(distance))
    si.wi = -direction
    if mi.is_spectral:  # wavelengths spread over the rays (a guide: its colour is noise)
        si.wavelengths, weight = spectra.sample_wavelengths(spectra.spread(dr.width(distance)))
        sky = spectra.to_rgb(environment.eval(si, escaped) * weight, si.wavelengths)
    else:
        sky = mi.Color3f(environment.eval(si, escaped))
    return finite(sky, escaped)


def _mix_cdfs(a, b, weight: float):
    """Per record, the mixture ``(1 - weight)·a + weight·b`` of two :func:`guide_cdfs`
    distributions (record-major, GUIDE_BINS each); where one of them is empty (all
    zeros: its gather found no light), the other alone. None if either is None."""
    if a is None or b is None:
        return None
    ca = np.array(a, dtype=np.float64).reshape(-1, GUIDE_BINS)
    cb = np.array(b, dtype=np.float64).reshape(-1, GUIDE_BINS)
    wa = np.where(ca[:, -1:] > 0, 1.0 - weight, 0.0)
    wb = np.where(cb[:, -1:] > 0, weight, 0.0)
    total = wa + wb
    cdf = np.where(total > 0, (wa * ca + wb * cb) / np.where(total > 0, total, 1.0), 0.0)
    cdf[:, -1] = np.where(total[:, 0] > 0, 1.0, 0.0)  # exactly 1, as guide_cdfs leaves it
    return mi.Float(cdf.astype(np.float32).ravel())


def guide_cdfs(owner: mi.UInt32, direction: mi.Vector3f, radiance: mi.Color3f, count: int) -> mi.Float:
    """Per record, the cumulative distribution over :func:`guide_bin` bins of its
    gather rays' luminance. The rays are cosine distributed, so a bin's sum is
    proportional to the irradiance arriving through it: the density a diffuse lobe
    would want to sample. Summed on the host with NumPy (a fixed order: the same
    records bit for bit; a parallel float scatter-add is not)."""
    import numpy as np

    lum = np.array(mi.luminance(radiance), dtype=np.float64)
    lum = np.where(np.isfinite(lum) & (lum > 0), lum, 0.0)
    slot = np.array(owner, dtype=np.int64) * GUIDE_BINS + np.array(guide_bin(direction), dtype=np.int64)
    hist = np.bincount(slot, weights=lum, minlength=count * GUIDE_BINS).reshape(count, GUIDE_BINS)
    cdf = np.cumsum(hist, axis=1)
    total = cdf[:, -1:]
    cdf = np.where(total > 0, cdf / np.where(total > 0, total, 1.0), 0.0)
    cdf[:, -1] = np.where(total[:, 0] > 0, 1.0, 0.0)  # exactly 1: u < 1 always finds a bin
    return mi.Float(cdf.astype(np.float32).ravel())


def direct_irradiance(scene: mi.Scene, position: mi.Point3f, normal: mi.Vector3f, samples: int,
                      seed: int, offset: float, shading_normal: mi.Vector3f = None, sky=None,
                      guides: "RecordIndex | None" = None) -> mi.Color3f:
    """Irradiance straight from the emitters at each (position, normal), from every
    light: the sum of :func:`direct_irradiance_parts`' two parts (same arguments)."""
    (soft, _), (delta, _) = direct_irradiance_parts(scene, position, normal, samples, seed, offset,
                                                    shading_normal, sky, guides)
    return soft + delta


def direct_irradiance_parts(scene: mi.Scene, position: mi.Point3f, normal: mi.Vector3f,
                            samples: int, seed: int, offset: float,
                            shading_normal: mi.Vector3f = None, sky=None,
                            guides: "RecordIndex | None" = None):
    """Irradiance straight from the emitters at each (position, normal), in two parts,
    each with its rotational gradient (of the mean of its channels: ∫ L (n × ω) dω from
    the same samples): ``((E, ∇ᵣE) from lights that are not delta, (E, ∇ᵣE) from delta
    lights)``; a part without lights is zero.

    Each is the mean of ``samples`` emitter samples with shadow rays (Mitsuba's emitter
    importance sampling, from jittered strata: :data:`RECORD_DIRECT_SAMPLES`), each
    non-finite sample counted as 0. The cosine is to ``shading_normal`` where given (as
    Mitsuba's BSDFs weigh light). With ``sky`` (a
    :class:`~pmic_integrator.skylight.SkySampler`), an environment is sampled by its
    radiance times the cosine. With ``guides`` (the index of these very records, one
    per position), :data:`RECORD_SKY_GUIDE_FRACTION` of the sky's samples at a record
    that saw the sky follow the sky its gather saw.

    In a scene with both kinds of light, the ``samples`` samples go to the lights
    that are not delta lights, and each delta light (a sun, a spot) gets one sample of
    its own (up to ``samples`` of them, in strata of the choice): one sample of a delta
    light is exact up to visibility, and a choice among all lights spent half of a
    sunlit sky's samples on the same shadow ray to the sun."""
    kinds = [(delta, n) for delta, n in ((False, samples), (True, min(samples, len(emission.emitter_subset(scene, True)))))
             if n and emission.emitter_subset(scene, delta)]
    soft = delta = (mi.Color3f(0.0), mi.Vector3f(0.0))
    for kind, count in kinds:
        part = _direct_irradiance_of(scene, position, normal, count, seed, offset, shading_normal,
                                     sky, kind, guides)
        if kind:
            delta = part
        else:
            soft = part
    return soft, delta


def _direct_irradiance_of(scene, position, normal, samples: int, seed: int, offset: float,
                          shading_normal, sky, delta: bool, guides=None):
    """:func:`direct_irradiance_parts`' part from the delta lights only (``delta``) or
    from the others only, with its rotational gradient: ``(E, ∇ᵣE)``."""
    count = dr.width(position)
    lanes = count * samples
    owner = dr.arange(mi.UInt32, lanes) // opaque_u32(samples)
    p = dr.gather(mi.Point3f, position, owner)
    n = dr.gather(mi.Vector3f, normal, owner)
    cos_n = n if shading_normal is None else dr.gather(mi.Vector3f, shading_normal, owner)
    ref = dr.zeros(mi.Interaction3f, lanes)
    ref.p = p + n * surface_offset(p, offset)
    ref.n = n
    rng = make_rng(lanes, seed, stream=streams.RECORD_DIRECT_DELTA if delta else streams.RECORD_DIRECT)
    within = dr.arange(mi.UInt32, lanes) % opaque_u32(samples)  # sample number
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    if mi.is_spectral:  # each sample its own wavelengths; the records hold linear sRGB
        ref.wavelengths, wavelength_weight = spectra.sample_wavelengths(rng.next_float32())
    guide = None
    if delta:  # strata of the choice of light: with even weights, each light once
        u.x = dr.minimum((mi.Float(within) + u.x) / samples, ONE_MINUS_EPSILON)
        ds, weight = emission.sample_emitter_direction(scene, ref, u, True, delta=True)
    else:
        u = jittered(u, within, samples)
        if guides is not None and sky is not None and guides.records.sky_guide is not None:
            fraction = dr.select(guides.sees_sky(owner), RECORD_SKY_GUIDE_FRACTION, 0.0)
            guide = skylight.SkyGuide(guides, owner, fraction)
        ds, weight = skylight.sample_emitter_direction(scene, sky, ref, cos_n, u, guide=guide,
                                                       delta=False)
        # Weighted against a cosine sample that counts the emission it meets: alone, an
        # emitter sample beside a lamp is unbounded (1/d²; a white-room record beside
        # its wall lamp held 4 105 where π L is 56), as the gathers' near bounces were.
        weight = weight * dr.select(ds.delta, 1.0, mis_weight(ds.pdf, dr.maximum(dr.dot(ds.d, cos_n), 0.0) / math.pi))
    if mi.is_spectral:
        weight = spectra.to_rgb(weight * wavelength_weight, ref.wavelengths)
    e, g = _irradiance_sample(weight, ds.d, ds.pdf > 0, cos_n)
    if not delta:
        met, d = _emission_by_cosine(scene, sky, ref, cos_n, rng, guide)
        if mi.is_spectral:
            met = spectra.to_rgb(met * wavelength_weight, ref.wavelengths)
        e2, g2 = _irradiance_sample(met, d, dr.max(met) > 0, cos_n)
        e, g = e + e2, g + g2
    return (mi.Color3f(block_sum(mi.Color3f(e), samples)) / samples,
            mi.Vector3f(block_sum(mi.Vector3f(g), samples)) / samples)


def _irradiance_sample(weight, d, valid, cos_n):
    """One sample's irradiance (``weight`` = L/pdf, times the cosine) and rotational
    gradient (L/pdf (n × ω), of the channels' mean, where the light is above the
    surface); 0 where not ``valid`` or not finite."""
    cosine = dr.dot(d, cos_n)
    e = weight * dr.maximum(cosine, 0.0)
    counted = valid & dr.all(dr.isfinite(e))
    e = dr.select(counted, e, 0.0)
    mean_weight = (weight.x + weight.y + weight.z) * (1.0 / 3.0)
    g = dr.select(counted & (cosine > 0) & dr.isfinite(mean_weight),
                  mean_weight * dr.cross(cos_n, d), 0.0)
    return e, g


def _emission_by_cosine(scene, sky, ref, cos_n, rng, guide):
    """A cosine-weighted direction about ``cos_n`` from ``ref`` and the emission it
    meets first (of lights that are not delta), as L/pdf weighted by MIS against the
    emitter samples of :func:`_direct_irradiance_of`: ``(L/pdf · w, direction)``."""
    local = mi.warp.square_to_cosine_hemisphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    d = mi.Frame3f(cos_n).to_world(local)
    active = dr.dot(d, ref.n) > 0
    si = scene.ray_intersect(ref.spawn_ray(d), active)
    emitter = si.emitter(scene, active)
    active &= emitter != None  # noqa: E711
    ds = mi.DirectionSample3f(scene, si=si, ref=ref)
    em_pdf = skylight.pdf_emitter_direction(scene, sky, ref, ds, cos_n, active, guide, delta=False)
    cos_pdf = dr.maximum(local.z, 1e-12) / math.pi
    radiance = emitter.eval(si, active)
    return dr.select(active, radiance * mis_weight(cos_pdf, em_pdf) / cos_pdf, 0.0), d


def _relative_rotation(direct: mi.Color3f, gradient: mi.Vector3f) -> mi.Vector3f:
    """A record's direct-light rotational ``gradient`` over the mean of its ``direct``
    light's channels (0 where it has no light or the ratio is not finite): the light
    read at a rotation δ is ``direct · max(0, 1 + relative · δ)``, spread over the
    channels as the light is, never negative."""
    mean = (direct.x + direct.y + direct.z) * (1.0 / 3.0)
    relative = gradient / dr.maximum(mean, 1e-30)
    return finite(relative, mean > 0)


# --------------------------------------------------------------------------------------
# Lookup structure and interpolation
# --------------------------------------------------------------------------------------
@dataclass
class RecordIndex:
    """Records plus a ball grid of their reach ``a·R``, for coverage and interpolation."""

    #: What an index keeps when :meth:`for_lookup` builds its lookup grids (the rest
    #: is built from the records).
    KEPT_BY_LOOKUP = ("direct", "direct_rotation", "direct_all", "holds_caustics", "lights")

    records: CacheRecords
    max_error: float
    grid: BallGrid  #: balls of radius a·R
    #: Balls of radius BACKUP_REACH·a·R, for gaps; None in the indices used while the
    #: cache is being built, which only test coverage.
    backup_grid: BallGrid | None
    scene: object = None  #: for visibility tests of records reaching past a surface
    lift: float = 0.0  #: how far those tests start off the surfaces
    #: What interpolation adds to the gathered light (final gather: a gather hit reflects
    #: all of its light): direct irradiance from the lights that are not delta (area
    #: lights, environments); the camera path samples delta lights itself, whose sharp
    #: shadows records would smear. None: not kept.
    direct: mi.Color3f = None
    #: The rotational gradient of ``direct``'s light from the emitters (of its channels'
    #: mean, about the record's shading normal): interpolation extrapolates ``direct``
    #: to the shading normal of the point read (a normal map's lean, a curved mesh), as
    #: it does the gathered light. None: not kept.
    direct_rotation: mi.Vector3f = None
    #: ``direct`` holds the caustic map's irradiance at each record too (light that
    #: reached the record through delta/glossy bounces): readers need no caustic lookup.
    holds_caustics: bool = False
    #: All direct irradiance at each record (delta lights too), for the share of
    #: bounced light in a record's light (guiding) and for the lights; not interpolated.
    direct_all: mi.Color3f = None
    #: The brightest records as spherical lights (final gather: continuation rays are drawn
    #: towards them, :mod:`pmic_integrator.lights`); None: no record stands out.
    lights: RecordLights | None = None
    #: What interpolation reads of each record, record by record (:meth:`pack`):
    #: PACKED_HEAD floats of geometry and PACKED_BODY of light. None: read field by
    #: field from ``records``.
    #: (Derived: not written to cache files.)
    packed_head: mi.Float = field(default=None, metadata={"derived": True})
    packed_body: mi.Float = field(default=None, metadata={"derived": True})
    #: :meth:`bounce_variance`, once computed (derived from the records).
    ray_variance: mi.Float = field(default=None, metadata={"derived": True})
    #: :meth:`left_out_error`, once computed (derived from the records).
    left_out: mi.Float = field(default=None, metadata={"derived": True})
    #: Per record, whether the adaptive estimator may read it at a camera path's first
    #: hit (:meth:`survey_first_reads`); None: not surveyed, none may.
    first_readable: mi.Bool = field(default=None, metadata={"derived": True})
    #: Per record, the sample count per pixel up to which such a read pays
    #: (:func:`~pmic_integrator.render.reads.survey_first_reads`; 0 where not readable).
    first_read_spp: mi.Float = field(default=None, metadata={"derived": True})

    @staticmethod
    def build(records: CacheRecords, max_error: float, scene=None, lift: float = 0.0,
              lookup: bool = True) -> "RecordIndex":
        """The index of ``records``. With ``lookup`` (for rendering: interpolation),
        grids of small cells and the backup grid; without, one grid of
        the default cells, which answers :meth:`covered` alike at a tenth of the cost
        (coverage is a yes/no test, whatever the cells; the interpolated sums follow
        the cells' order, so every rendered index is built with ``lookup``)."""
        def grid(reach):
            cell = CELL_PER_REACH * mean_value(reach) if records.count and lookup else None
            return BallGrid.build(records.position, reach, cell_size=cell)

        reach = records.radius * max_error
        backup = grid(reach * BACKUP_REACH) if lookup else None
        return RecordIndex(records, max_error, grid(reach), backup, scene, lift)

    def for_lookup(self) -> "RecordIndex":
        """This index with the lookup grids (see :meth:`build`); itself if it has them."""
        if self.backup_grid is not None:
            return self
        index = RecordIndex.build(self.records, self.max_error, self.scene, self.lift)
        for name in RecordIndex.KEPT_BY_LOOKUP:
            setattr(index, name, getattr(self, name))
        return index

    def pack(self) -> "RecordIndex":
        """Lay out what interpolation reads of each record contiguously, so that a
        lookup loads it with a few packet loads instead of a gather per float (a
        record's term read 37 floats, gathered one by one: half of a Cornell box's
        camera pass). Call it once the records and ``direct`` are final (the render
        does); the sums are those of the field-by-field reads but for rounding (the
        rotational gradient is kept as ``∇ᵣE × n_s``, read as one dot product).
        Returns ``self``."""
        r = self.records
        if r.count == 0:
            self.packed_head = self.packed_body = None
            return self
        zero = dr.zeros(mi.Float, r.count)
        rsn = r.shading_normal if r.shading_normal is not None else r.normal
        obstacle = r.obstacle if r.obstacle is not None else zero
        head = [r.position.x, r.position.y, r.position.z, r.normal.x, r.normal.y, r.normal.z,
                r.radius, obstacle]
        direct = self.direct if self.direct is not None else dr.zeros(mi.Color3f, r.count)
        body = [*r.irradiance, *direct]
        for c in range(3):
            body += [*r.grad_t[c]]
        for c in range(3):
            body += [*dr.cross(r.grad_r[c], rsn)]
        # The direct light's rotational gradient relative to it, so that a lookup
        # scales by max(0, 1 + q·n) without a division.
        relative = mi.Vector3f(zero) if self.direct_rotation is None else \
            _relative_rotation(direct, dr.cross(self.direct_rotation, rsn))
        body += [*relative, *rsn]
        self.packed_head = interleave(head, PACKED_HEAD)
        self.packed_body = interleave(body, PACKED_BODY)
        for grid in (self.grid, self.backup_grid):
            if grid is not None:
                grid.pack()
        return self

    def _require_lookup(self):
        if self.backup_grid is None:
            raise RuntimeError("RecordIndex built with lookup=False: call for_lookup() first")

    def _visibility(self):
        if self.scene is None or self.records.obstacle is None:
            return None
        return self.scene, self.records, opaque_float(self.lift)

    def sees(self, x, n, record: mi.UInt32, active=True) -> mi.Bool:
        """Whether ``record`` sees (x, n), tested as interpolation tests the records it
        reads (:func:`hidden_from`: a shadow ray only beyond the nearest surface the
        record's gather met, lifted ``lift`` off both surfaces)."""
        active = mi.Bool(active)
        visibility = self._visibility()
        if visibility is None:
            return active
        rp, rn, rr = self._record_geometry(record, active)
        return active & ~hidden_record(visibility, record, rp, rn, rr * self.max_error, x, n, active)

    def covered(self, x, n, active=True) -> mi.Bool:
        """Is (x, n) within the reach a·R of some record (Ward's test) that sees it?"""
        r = self.records
        return _covered_by(r.position, r.normal, r.radius, self.grid, x, n, self.max_error, active,
                           visibility=self._visibility())

    def _weighted_sum(self, grid: BallGrid, max_error: float, x, n, shading_n, active, label,
                      with_direct: bool = False, exclude: mi.UInt32 = None):
        """``(Σ wᵢ Eᵢ(x), Σ wᵢ, Σ wᵢ Rᵢ)`` over the records of ``grid`` that reach
        (x, n) with maximum error ``max_error`` and see x, in the grid's order (see
        :data:`INTERPOLATION_SLOTS`); with ``with_direct``, and ``Σ wᵢ Dᵢ``, the
        records' own direct light (part of Eᵢ(x)); but for record ``exclude`` of each
        lane (None: none)."""
        r = self.records
        lanes = dr.width(x)
        slots = INTERPOLATION_SLOTS

        def find(state, index, valid):
            count, *slot = state
            rp, rn, rr = self._record_geometry(index, valid)
            # (Ward's test implies a positive weight: the second pass tests that too.)
            ok = valid & covers(x, n, rp, rn, rr, max_error)
            if exclude is not None:
                ok &= index != exclude
            slot = [dr.select(ok & (count == k), index, slot[k]) for k in range(slots)]
            return (dr.select(ok, count + 1, count), *slot)

        zeros = dr.zeros(mi.UInt32, lanes)
        count, *slot = grid.for_each_ball(x, (zeros, *[mi.UInt32(zeros) for _ in range(slots)]),
                                          find, active=active, label=label + "_find")
        accumulate = self._record_term(max_error, x, n, shading_n, with_direct, exclude)

        def cond(k, state):
            return active & (k < dr.minimum(count, slots))

        def body(k, state):
            index = slot[slots - 1]
            for j in range(slots - 2, -1, -1):
                index = dr.select(k == j, slot[j], index)
            return k + 1, accumulate(state, index, mi.Bool(True))

        zero = dr.zeros(mi.Float, lanes)
        empty = (dr.zeros(mi.Color3f, lanes), zero, mi.Float(zero))
        if with_direct:
            empty += (dr.zeros(mi.Color3f, lanes),)
        _, state = dr.while_loop((mi.UInt32(zeros), empty), cond, body, label=label)
        # The rare queries that more records reach: the whole cell, every record read.
        crowded = active & (count > slots)
        whole = grid.for_each_ball(x, empty, accumulate, active=crowded, label=label + "_crowded")
        return tuple(dr.select(crowded, a, b) for a, b in zip(whole, state))

    def _record_geometry(self, index, valid):
        """Position, normal and radius of record ``index``."""
        if self.packed_head is None:
            r = self.records
            return (dr.gather(mi.Point3f, r.position, index, valid),
                    dr.gather(mi.Vector3f, r.normal, index, valid),
                    dr.gather(mi.Float, r.radius, index, valid))
        h = dr.gather(mi.ArrayXf, self.packed_head, index, valid, shape=(PACKED_HEAD, dr.width(index)))
        return mi.Point3f(h[0], h[1], h[2]), mi.Vector3f(h[3], h[4], h[5]), mi.Float(h[6])

    def _record_term(self, max_error: float, x, n, shading_n, with_direct: bool = False,
                     exclude: mi.UInt32 = None):
        """``visit(state, index, valid)`` adding record ``index``'s weighted,
        extrapolated irradiance at (x, n) to ``state = (Σ wE, Σ w, Σ wR)`` where it
        reaches and sees x (with ``with_direct``, also to Σ wD: its direct light)."""
        r = self.records
        record_shading_n = r.shading_normal if r.shading_normal is not None else r.normal
        visibility = self._visibility()
        direct = self.direct
        direct_rotation = self.direct_rotation if direct is not None else None
        packed = self.packed_body

        def visit(state, index, valid):
            total, weight_sum, radius_sum, *direct_sum = state
            rp, rn, rr = self._record_geometry(index, valid)
            ok = valid & covers(x, n, rp, rn, rr, max_error)
            if exclude is not None:
                ok &= index != exclude
            w = interpolation_weight(ward_error(x, n, rp, rn, rr), max_error)
            ok &= w > 0
            dx = x - rp
            d = None  # (the record's direct light, where kept)
            if packed is not None:  # (RecordIndex.pack: one packet load)
                b = dr.gather(mi.ArrayXf, packed, index, ok, shape=(PACKED_BODY, dr.width(index)))
                if visibility is not None:
                    ok &= ~hidden_record(visibility, index, rp, rn, rr * max_error, x, n, ok,
                                         frame_normal=mi.Vector3f(b[27], b[28], b[29]))
                ext = [b[c] + dr.dot(mi.Vector3f(b[6 + 3 * c], b[7 + 3 * c], b[8 + 3 * c]), dx)
                       + dr.dot(mi.Vector3f(b[15 + 3 * c], b[16 + 3 * c], b[17 + 3 * c]), shading_n)
                       for c in range(3)]
                d = mi.Color3f(b[3], b[4], b[5])
                if direct_rotation is not None:
                    d *= dr.maximum(1.0 + dr.dot(mi.Vector3f(b[24], b[25], b[26]), shading_n), 0.0)
            else:
                if visibility is not None:
                    ok &= ~hidden_record(visibility, index, rp, rn, rr * max_error, x, n, ok)
                e = dr.gather(mi.Color3f, r.irradiance, index, ok)
                # The rotational gradient was gathered about the record's shading normal:
                # it extrapolates to the query's (the plane and Ward tests above keep the
                # geometric ones, which say where the surfaces are).
                rot = dr.cross(dr.gather(mi.Vector3f, record_shading_n, index, ok), shading_n)
                ext = []
                for c in range(3):
                    gt = dr.gather(mi.Vector3f, r.grad_t[c], index, ok)
                    gr = dr.gather(mi.Vector3f, r.grad_r[c], index, ok)
                    ext.append(e[c] + dr.dot(gt, dx) + dr.dot(gr, rot))
                if direct is not None:
                    d = dr.gather(mi.Color3f, direct, index, ok)
                    if direct_rotation is not None:
                        relative = _relative_rotation(d, dr.gather(mi.Vector3f, direct_rotation, index, ok))
                        d *= dr.maximum(1.0 + dr.dot(relative, rot), 0.0)
            e_x = dr.maximum(mi.Color3f(*ext), 0.0)
            if d is not None:
                e_x += d
            total = dr.select(ok, total + w * e_x, total)
            weight_sum = dr.select(ok, weight_sum + w, weight_sum)
            radius_sum = dr.select(ok, radius_sum + w * rr, radius_sum)
            if with_direct:
                if d is None:
                    return total, weight_sum, radius_sum, direct_sum[0]
                return total, weight_sum, radius_sum, dr.select(ok, direct_sum[0] + w * d, direct_sum[0])
            return total, weight_sum, radius_sum

        return visit

    @property
    def light_direct(self) -> mi.Color3f:
        """All direct irradiance at each record (``direct_all``, else ``direct``)."""
        return self.direct if self.direct_all is None else self.direct_all

    def bounce_variance(self) -> mi.Float:
        """Per record, the relative variance of one cosine-sampled bounce's estimate of
        its bounced irradiance, π L: mean(L²) / mean(L)² - 1 over its gather's rays
        (0 where no light was found; +inf where the rays' moment is not known: such a
        record is never taken for smooth). Large where the light comes through a small
        part of the hemisphere (a lamp's shade seen from a wall): the record's own
        gather saw it with a few rays, and its irradiance is noisy
        (:func:`pmic_integrator.render.reads.first_read_pays` reads at the first hit only
        records where this is small). Computed once."""
        if self.ray_variance is None:
            r = self.records
            mean_l = mi.luminance(r.irradiance) * (1.0 / math.pi)
            moment = r._filled("ray_moment")
            variance = dr.select(moment > 0, moment / dr.maximum(dr.square(mean_l), 1e-30) - 1.0, dr.inf)
            self.ray_variance = dr.select(mean_l > 0, variance, 0.0)
            dr.eval(self.ray_variance)
        return self.ray_variance

    def left_out_error(self) -> mi.Float:
        """Per record, the squared relative error with which the other records predict
        its bounced irradiance where it lies (leave-one-out: interpolated as a camera
        vertex there would be, this record left out; luminance): an estimate of the
        error a read near it carries, its noise and the interpolation's together.
        +inf where no other record reaches it or it found no light. Computed once."""
        if self.left_out is None:
            r = self.records
            others, covered, direct = self.interpolate(
                r.position, r.normal, shading_n=r.shading_normal, with_direct=True,
                exclude=dr.arange(mi.UInt32, r.count))
            own = mi.luminance(r.irradiance)
            error = dr.square(mi.luminance(others - direct) - own) / dr.maximum(dr.square(own), 1e-30)
            self.left_out = dr.select(covered & (own > 0), error, dr.inf)
            dr.eval(self.left_out)
        return self.left_out

    @property
    def guides(self) -> bool:
        """The records carry directional distributions (:meth:`guide_record`)."""
        return self.records.guide is not None and self.records.count > 0

    def sky_guiding_pays(self) -> bool:
        """Did any record see the sky through an opening (:func:`escaped_sky`)? Then
        emitter samples of the sky at the points they guide may follow what it saw."""
        if self.records.sky_guide is None or self.records.count == 0:
            return False
        return self.remembered("sky_guiding_pays", lambda: bool(
            dr.any(self.sees_sky(dr.arange(mi.UInt32, self.records.count)))))

    def remembered(self, name: str, compute):
        """``compute()``, once per records of this index: a per-render decision read
        back from the device (a host read: a synchronisation on a GPU) is made at the
        first render and kept for the next ones (a fly-through's frames, a view's
        passes). Kept beside the fields (not copied by ``dataclasses.replace``), keyed
        by the records' identity."""
        memo = self.__dict__.setdefault("_remembered", {})
        key = (name, id(self.records))
        if key not in memo:
            memo[key] = compute()
        return memo[key]

    def sees_sky(self, record: mi.UInt32, active=True) -> mi.Bool:
        """Whether ``record``'s gather saw the sky through an opening."""
        return dr.gather(mi.Float, self.records.sky_guide, record * GUIDE_BINS + (GUIDE_BINS - 1),
                         active) > 0

    def guiding_pays(self) -> bool:
        """Do enough records owe enough of their light to bounces for guiding to be
        worth its lookups (:data:`GUIDE_MIN_RECORDS`)? A function of the cache only."""
        if not self.guides:
            return False
        return self.remembered("guiding_pays", self._guiding_pays)

    def _guiding_pays(self) -> bool:
        bounced = mi.luminance(self.records.irradiance)
        direct = self.light_direct
        total = bounced if direct is None else bounced + mi.luminance(direct)
        share = dr.select(total > 0, bounced / dr.maximum(total, 1e-30), 0.0)
        area = dr.square(self.records.radius)
        bounced_area = dr.sum(dr.select(share >= GUIDE_BOUNCED_SHARE, area, 0.0))
        return float(bounced_area[0]) >= GUIDE_MIN_RECORDS * float(dr.sum(area)[0])

    def guide_record(self, x: mi.Point3f, n: mi.Vector3f, active=True):
        """``(record, share)``: the first record in the grid cell of x that reaches
        (x, n) and gathered some light (its distribution guides the sampling at x;
        the walk stops at the first, not the nearest), and the share of bounced light
        in its irradiance (0 where no record was found). A deterministic function of
        (x, n), so that the guided density can be evaluated at any direction (MIS).
        No visibility test:
        a record behind a thin wall only guides worse, never wrongly (the BSDF
        density stays in the mixture)."""
        r = self.records
        lanes = dr.width(x)
        last = opaque_u32(GUIDE_BINS - 1)

        def visit(state, index, valid):
            best_w, best = state
            rp, rn, rr = self._record_geometry(index, valid)
            ok = valid & covers(x, n, rp, rn, rr, self.max_error)
            w = interpolation_weight(ward_error(x, n, rp, rn, rr), self.max_error)
            ok &= (w > 0) & (dr.gather(mi.Float, r.guide, index * GUIDE_BINS + last, ok) > 0)
            return dr.select(ok, w, best_w), dr.select(ok, index, best)

        if not self.guides:
            return dr.zeros(mi.UInt32, lanes), dr.zeros(mi.Float, lanes)
        self._require_lookup()
        best_w, best = self.grid.for_each_ball(
            x, (dr.zeros(mi.Float, lanes), dr.zeros(mi.UInt32, lanes)), visit,
            active=mi.Bool(active), finished=lambda state: state[0] > 0, label="cache_guide_record")
        found = mi.Bool(active) & (best_w > 0)
        # The share of bounced light in the record's irradiance: where direct light
        # is most of it (a sunlit ground), BSDF sampling also serves direct light
        # (MIS with the emitters) and keeps most of the rays.
        bounced = mi.luminance(dr.gather(mi.Color3f, r.irradiance, best, found))
        total = bounced
        direct = self.light_direct
        if direct is not None:
            total = total + mi.luminance(dr.gather(mi.Color3f, direct, best, found))
        share = dr.select(found & (total > 0), dr.clip(bounced / dr.maximum(total, 1e-30), 0.0, 1.0), 0.0)
        return best, share

    def sample_guide(self, record: mi.UInt32, u: mi.Point2f, active=True,
                     sky: bool = False) -> mi.Vector3f:
        """A world-space direction from ``record``'s distribution (``sky``: of the sky
        it saw): a bin by its probability (a binary search of the cumulative table),
        then uniformly within the bin's area on the sphere."""
        cdf = self.records.sky_guide if sky else self.records.guide
        start = record * GUIDE_BINS
        below = dr.zeros(mi.UInt32, dr.width(record))  # bins whose cumulative value < u.x
        step = GUIDE_BINS // 2
        while step >= 1:
            go = dr.gather(mi.Float, cdf, start + below + (step - 1), active) < u.x
            below = dr.select(go, below + step, below)
            step //= 2
        upper = dr.gather(mi.Float, cdf, start + below, active)
        lower = dr.select(below > 0, dr.gather(mi.Float, cdf, start + below - 1, active & (below > 0)), 0.0)
        t = dr.clip((u.x - lower) / dr.maximum(upper - lower, 1e-30), 0.0, 1.0)
        band = mi.Float(below // GUIDE_SECTORS)
        sector = mi.Float(below % GUIDE_SECTORS)
        z = dr.clip(-1.0 + (band + t) * (2.0 / GUIDE_BANDS), -1.0, 1.0)
        phi = (sector + u.y) * (2.0 * math.pi / GUIDE_SECTORS)
        sin_t = dr.safe_sqrt(1.0 - z * z)
        sp, cp = dr.sincos(phi)
        return mi.Vector3f(sin_t * cp, sin_t * sp, z)

    def guide_pdf(self, record: mi.UInt32, d: mi.Vector3f, active=True,
                  sky: bool = False) -> mi.Float:
        """Solid-angle density of :meth:`sample_guide` at world direction ``d``."""
        cdf = self.records.sky_guide if sky else self.records.guide
        b = guide_bin(d)
        slot = record * GUIDE_BINS + b
        upper = dr.gather(mi.Float, cdf, slot, active)
        lower = dr.select(b > 0, dr.gather(mi.Float, cdf, slot - 1, active & (b > 0)), 0.0)
        return dr.select(active, dr.maximum(upper - lower, 0.0) * (1.0 / GUIDE_BIN_SOLID_ANGLE), 0.0)

    def interpolate(self, x: mi.Point3f, n: mi.Vector3f, active=True, with_radius: bool = False,
                    shading_n: mi.Vector3f = None, with_direct: bool = False,
                    exclude: mi.UInt32 = None):
        """E(x) = Σ wᵢ Eᵢ(x) / Σ wᵢ with gradients; returns ``(E, covered)``, and with
        ``with_radius`` also the weighted mean record radius Σ wᵢ Rᵢ / Σ wᵢ (how far
        the geometry the records saw is: the final gather's trust test).

        wᵢ is :func:`interpolation_weight` with the maximum error a; lanes that no
        record reaches use the records within ``BACKUP_REACH`` × a instead.
        ``covered`` is False where no record is even within the backup reach.
        ``n`` is the geometric normal on the side seen from; ``shading_n`` (default
        ``n``) the shading normal on that side, for the rotational gradient. With
        ``with_direct``, last comes the part of E that is the records' own direct light
        (final gather: :attr:`direct`, with caustics where the records hold them).
        ``exclude``: a record each lane leaves out (:meth:`left_out_error`).
        """
        lanes = dr.width(x)
        shading_n = mi.Vector3f(n if shading_n is None else shading_n)
        if self.records.count == 0:
            zero = dr.zeros(mi.Color3f, lanes), dr.zeros(mi.Bool, lanes)
            zero += (dr.zeros(mi.Float, lanes),) if with_radius else ()
            return zero + (dr.zeros(mi.Color3f, lanes),) if with_direct else zero
        self._require_lookup()
        active = mi.Bool(active)
        sums = self._weighted_sum(self.grid, self.max_error, x, n, shading_n, active,
                                  "cache_interpolation", with_direct, exclude)
        gap = active & (sums[1] <= 0)
        backup = self._weighted_sum(self.backup_grid, self.max_error * BACKUP_REACH, x, n,
                                    shading_n, gap, "cache_interpolation_backup", with_direct, exclude)
        total, weight_sum, radius_sum, *direct_sum = (dr.select(gap, b, a) for a, b in zip(sums, backup))
        covered = weight_sum > 0
        safe_sum = dr.maximum(weight_sum, 1e-30)
        out = (dr.select(covered, total / safe_sum, 0.0), covered)
        if with_radius:
            out += (dr.select(covered, radius_sum / safe_sum, 0.0),)
        if with_direct:
            out += (dr.select(covered, direct_sum[0] / safe_sum, 0.0),)
        return out
