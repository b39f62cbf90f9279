"""Hash grids built and queried in Dr.Jit kernels.

Two structures, both built by sorting entries into hash buckets (bucket counts and
an exclusive prefix sum give each bucket's range; a stable radix sort, O(N), gives the
order, so that a grid never depends on thread timing):

* :class:`PointGrid` stores points (photons) in cells whose size is the largest query
  radius; a query visits the 27 cells around the query point. Used for density
  estimates, nearest-photon lookups and record placement.
* :class:`BallGrid` stores balls of varying radius (irradiance-cache records with their
  reach ``a·R``) by inserting each ball into every cell its bounding box overlaps; a
  query visits only the one cell that contains the query point. Used for cache
  interpolation and coverage tests, where queries vastly outnumber records.

Queries are symbolic Dr.Jit loops that call a user ``visit`` function for every
candidate, so one traversal serves sums, counts, minima and early-exit searches. Two
cells that share a hash bucket are told apart by recomputing (points) or storing
(balls) each entry's own cell, so no entry is ever visited twice.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import drjit as dr
import mitsuba as mi

from ._jit import concat, interleave, mean_value, opaque_u32, scatter_count

#: Cell coordinates are clamped to this range so that a far-away query cannot overflow
#: the int32 cell arithmetic; entries never live there, so clamped cells find nothing.
CELL_COORD_LIMIT = 1 << 20

#: Large primes of Teschner et al. 2003, "Optimized spatial hashing for collision
#: detection of deformable objects".
_HASH_PRIMES = (73856093, 19349663, 83492791)


def _next_pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def cell_of(p: mi.Point3f, origin: mi.Point3f, inv_cell_size) -> mi.Vector3i:
    """Integer cell coordinates of ``p``, clamped to ±``CELL_COORD_LIMIT``."""
    c = dr.floor((p - origin) * inv_cell_size)
    c = dr.clip(c, -CELL_COORD_LIMIT, CELL_COORD_LIMIT)
    return mi.Vector3i(c)


def hash_cell(c: mi.Vector3i, mask) -> mi.UInt32:
    """Bucket index of integer cell ``c`` in a table of ``mask + 1`` buckets."""
    u = mi.Vector3u(c)
    h = (u.x * _HASH_PRIMES[0]) ^ (u.y * _HASH_PRIMES[1]) ^ (u.z * _HASH_PRIMES[2])
    return h & mask


def cell_key(c: mi.Vector3i) -> mi.UInt32:
    """The cell's coordinates modulo 1024, packed into 30 bits.

    Two cells with the same key are at least 1024 cells apart on some axis, so among
    the 27 cells around a query all keys differ: comparing keys tells a candidate of
    the visited cell from one of another cell in the same bucket, as comparing the
    full coordinates would (a far-away cell's points fail the distance test anyway).
    """
    u = mi.Vector3u(c) & 0x3FF
    return u.x | (u.y << 10) | (u.z << 20)


def _bucket_sort(bucket: mi.UInt32, table_size: int):
    """Sort entries by bucket. Returns (start offset of each bucket [table_size + 1],
    order: the entry at each sorted position).

    Counting gives the bucket offsets; the order comes from a stable radix sort rather
    than from the slots of ``scatter_inc``, whose order within a bucket depends on
    thread timing: the same photons must always give the same grid, cache and image.
    """
    counts = dr.zeros(mi.UInt32, table_size)
    scatter_count(counts, bucket)
    starts = dr.prefix_sum(counts)  # exclusive
    cell_start = dr.zeros(mi.UInt32, table_size + 1)
    dr.scatter(cell_start, starts, dr.arange(mi.UInt32, table_size))
    dr.scatter(cell_start, opaque_u32(dr.width(bucket)), opaque_u32(table_size))
    order = dr.argsort(bucket)
    dr.eval(cell_start, order)
    return cell_start, order


def _bucket_count(cell_start: mi.UInt32, bucket: mi.UInt32, active=True) -> mi.UInt32:
    """Entries in each hash ``bucket``."""
    return dr.gather(mi.UInt32, cell_start, bucket + 1, active) - \
        dr.gather(mi.UInt32, cell_start, bucket, active)


def _bucket_occupancy(cell_start: mi.UInt32, table_mask: int, origin: mi.Point3f,
                      cell_size: float, query: mi.Point3f, active=True) -> mi.UInt32:
    """Entries in the hash bucket of each query's cell (its cell's points, plus any
    that share the bucket)."""
    inv = dr.opaque(mi.Float, 1.0 / cell_size)
    bucket = hash_cell(cell_of(query, origin, inv), dr.opaque(mi.UInt32, table_mask))
    return _bucket_count(cell_start, bucket, active)


#: The key of an empty bucket: no cell key (30 bits) equals it.
NO_KEY = 0xFFFFFFFF


def _neighbourhood_occupancy(cell_start: mi.UInt32, middle_key: mi.UInt32, table_mask: int,
                             origin: mi.Point3f, cell_size: float, query: mi.Point3f,
                             active=True) -> mi.UInt32:
    """The largest occupancy among the 3×3×3 cells around each query's cell: what the
    densest cell that a 27-cell scan visits holds.

    A bucket's count is taken as a neighbour's only if the bucket's middle entry
    (``middle_key``) belongs to that cell: a sparse cell whose bucket a dense cell
    shares (a hash collision) would otherwise count as dense, and 27 buckets per
    query meet such collisions 27 times as often as the query's own bucket."""
    inv = dr.opaque(mi.Float, 1.0 / cell_size)
    mask = dr.opaque(mi.UInt32, table_mask)
    center = cell_of(query, origin, inv)
    densest = mi.UInt32(0)
    for j in range(27):
        cell = center + _neighbour_offset(mi.UInt32(j))
        bucket = hash_cell(cell, mask)
        count = _bucket_count(cell_start, bucket, active)
        if j != 13:  # the query's own cell counts as it is, as before
            count = dr.select(dr.gather(mi.UInt32, middle_key, bucket, active) == cell_key(cell),
                              count, 0)
        densest = dr.maximum(densest, count)
    return densest


def _visit_entry(keys, positions, index_of, entry, present, key, query, radius2, state, visit,
                 with_offset):
    """``visit`` one grid entry (where ``present``): it counts if it belongs to the
    visited cell (``keys`` equal to ``key``) and lies within the squared radius.
    ``positions`` may be :class:`PackedEntries` (then ``keys`` and ``index_of`` are
    read from it: one packet load per entry)."""
    packed = isinstance(positions, PackedEntries)
    if packed:
        packet = dr.gather(mi.ArrayXf, positions.data, entry, present,
                           shape=(PackedEntries.WIDTH, dr.width(entry)))
        same_cell = dr.reinterpret_array(mi.UInt32, packet[3]) == key
    else:
        same_cell = dr.gather(mi.UInt32, keys, entry, present) == key
    if present is not True:
        same_cell &= present
    p = mi.Point3f(packet[0], packet[1], packet[2]) if packed else \
        dr.gather(mi.Point3f, positions, entry, same_cell)
    d = p - query
    dist2 = dr.fma(d.x, d.x, dr.fma(d.y, d.y, d.z * d.z))
    valid = same_cell & (dist2 < radius2)
    index = dr.select(valid, dr.reinterpret_array(mi.UInt32, packet[4]), 0) if packed else \
        index_of(entry, valid)
    if with_offset == "normal":
        # (The visitor reads the point's normal from the entry: PackedEntries.of.)
        return visit(state, index, dist2, valid, d, mi.Vector3f(packet[5], packet[6], packet[7]))
    return visit(state, index, dist2, valid, d) if with_offset else visit(state, index, dist2, valid)


@dataclass
class PackedEntries:
    """A grid's entries laid out entry by entry, ``WIDTH`` floats each: the point's
    position, its cell key and its index (both as the bits of a float), and the
    point's normal where given (``has_normals``). A query reads an entry with one
    packet load instead of five to eight gathers."""

    data: mi.Float
    has_normals: bool = False
    WIDTH = 8

    @staticmethod
    def of(positions: mi.Point3f, keys: mi.UInt32, index: mi.UInt32,
           normals: mi.Vector3f | None = None) -> "PackedEntries":
        columns = [positions.x, positions.y, positions.z, mi.UInt32(keys), mi.UInt32(index)]
        if normals is not None:
            columns += [normals.x, normals.y, normals.z]
        return PackedEntries(interleave(columns, PackedEntries.WIDTH), normals is not None)


def _scan_cells(cell_start, keys, positions, index_of, cell, cells: int, query, radius2,
                state, visit, active, finished, with_offset, label):
    """Call ``visit`` for the entries within the squared radius of ``cells`` grid
    cells, one cell after the other: ``cell(j)`` gives the bucket and the key of each
    lane's j-th cell, and only entries of a bucket whose ``keys`` equal the cell's are
    visited. ``index_of(entry, valid)`` turns an entry into the index reported to
    ``visit``.

    One loop walks all the cells: each lane moves on to its next cell as soon as it
    is done with one (a loop per cell made every lane wait for the slowest at each of
    them), and the loop is traced once instead of once per cell (tracing 27 loops per
    lookup was most of the fixed cost of a record gather). Entries are visited in the
    same order either way."""
    def load(j, mask):
        bucket, key = cell(j)
        return (dr.gather(mi.UInt32, cell_start, bucket, mask),
                dr.gather(mi.UInt32, cell_start, bucket + 1, mask), key)

    entry, end, key = load(dr.zeros(mi.UInt32, dr.width(active)), active)
    limit = opaque_u32(cells)
    following = dr.full(mi.UInt32, 1, dr.width(active))

    def cond(following, entry, end, key, state):
        running = active & ((entry < end) | (following < limit))
        if finished is not None:
            running &= ~finished(state)
        return running

    def body(following, entry, end, key, state):
        in_cell = entry < end
        state = _visit_entry(keys, positions, index_of, entry, in_cell, key, query, radius2,
                             state, visit, with_offset)
        entry = dr.select(in_cell, entry + 1, entry)
        move_on = (entry >= end) & (following < limit)
        next_entry, next_end, next_key = load(following, move_on)
        entry = dr.select(move_on, next_entry, entry)
        end = dr.select(move_on, next_end, end)
        key = dr.select(move_on, next_key, key)
        following = dr.select(move_on, following + 1, following)
        return following, entry, end, key, state

    state = dr.while_loop(state=(following, entry, end, key, state), cond=cond, body=body,
                          label=label)[-1]
    return state


def _scan_cell(cell_start, keys, positions, index_of, bucket, visited_key, query, radius2,
               state, visit, active, finished, with_offset, label):
    """:func:`_scan_cells` for one cell (``bucket`` and ``visited_key`` given): a loop
    of its own, whose body holds only the per-candidate work."""
    entry = dr.gather(mi.UInt32, cell_start, bucket, active)
    end = dr.gather(mi.UInt32, cell_start, bucket + 1, active)

    def cond(entry, end, state):
        running = active & (entry < end)
        if finished is not None:
            running &= ~finished(state)
        return running

    def body(entry, end, state):
        return entry + 1, end, _visit_entry(keys, positions, index_of, entry, True, visited_key,
                                            query, radius2, state, visit, with_offset)

    return dr.while_loop(state=(entry, end, state), cond=cond, body=body, label=label)[-1]


def _walk(cell_start, keys, positions, index_of, cell, cells: int, query, radius2, state,
          visit, active, finished, with_offset, label, one_loop: bool, reaches=None):
    """Visit the ``cells`` cells: in one loop (:func:`_scan_cells`), or with a loop per
    cell unrolled here. The same entries in the same order either way; one loop is
    traced once and lets each lane move on by itself (cheap to build, best for small
    batches and lookups that stop early), a loop per cell carries no bookkeeping per
    candidate (best for dense sums: density estimates over hundreds of photons).
    ``reaches(j)`` (unrolled walk only): the lanes whose ball reaches cell j at all;
    the others skip it (no entry of it could be visited)."""
    if one_loop:
        return _scan_cells(cell_start, keys, positions, index_of, cell, cells, query, radius2,
                           state, visit, active, finished, with_offset, label)
    for j in range(cells):
        bucket, key = cell(mi.UInt32(j))
        lanes = active if reaches is None else active & reaches(j)
        state = _scan_cell(cell_start, keys, positions, index_of, bucket, key, query, radius2,
                           state, visit, lanes, finished, with_offset, f"{label}_cell{j}")
    return state


def _reaches_neighbour(query: mi.Point3f, origin: mi.Point3f, inv_cell, center: mi.Vector3i,
                       radius2_cells):
    """``reaches(j)`` for :func:`_walk`: does the ball (squared radius in cell units
    ``radius2_cells``) around each query reach the j-th of the 3×3×3 cells around
    ``center``? The distance from the query to that cell's box: on each axis where
    the cell lies beside the query's own, the way to the shared face. (A disc of one
    cell's radius on a plane reaches ~4 of the 8 corner cells and ~9 of the 12 edge
    cells.) With a margin for rounding: a cell it cannot quite tell is scanned."""
    local = (query - origin) * inv_cell - mi.Vector3f(center)  # in [0, 1) per axis
    # (A query whose cell was clamped, far outside the grid, scans every cell.)
    unsure = dr.any((local < -0.01) | (local > 1.01))

    def reaches(j: int):
        offset = (j % 3 - 1, (j // 3) % 3 - 1, j // 9 - 1)
        gap2 = mi.Float(0.0)
        for axis, o in enumerate(offset):
            if o < 0:
                gap2 += dr.square(local[axis])
            elif o > 0:
                gap2 += dr.square(1.0 - local[axis])
        return unsure | (gap2 <= radius2_cells * 1.0001 + 1e-6)

    return reaches


def _neighbour_offset(j: mi.UInt32) -> mi.Vector3i:
    """The j-th of the 3×3×3 cells around a cell (x fastest), as an offset."""
    j = mi.Int32(j)
    return mi.Vector3i(j % 3 - 1, (j // 3) % 3 - 1, j // 9 - 1)


@dataclass
class PointGrid:
    """Points sorted into a uniform hash grid.

    Build with :meth:`build`. Queries with radius up to ``cell_size`` are exact.
    """

    origin: mi.Point3f  #: lower corner of the grid (width 1)
    cell_size: float  #: edge of a cell = the largest supported query radius
    table_mask: int  #: number of hash buckets minus one (a power of two minus one)
    cell_start: mi.UInt32  #: first sorted entry of each bucket; entry table_size = N
    order: mi.UInt32 | None  #: original index of the i-th sorted point (None: identity)
    positions: mi.Point3f  #: sorted point positions (a copy, for coherent gathers)
    count: int  #: number of points
    keys: mi.UInt32 = None  #: :func:`cell_key` of each sorted point's cell
    #: ``positions``, ``keys`` and the points' indices entry by entry (:meth:`pack`);
    #: derived (not stored in cache files). None: queries read the arrays.
    packed: "PackedEntries" = field(default=None, metadata={"derived": True})

    def pack(self, normals: mi.Vector3f | None = None) -> "PointGrid":
        """Lay the entries out for queries that read many of them (one packet load per
        entry: :class:`PackedEntries`), with each point's normal from ``normals``
        (indexed as the points) if given. Returns ``self``."""
        if self.count and self.packed is None:
            index = self.order if self.order is not None else dr.arange(mi.UInt32, self.count)
            if normals is not None:
                normals = dr.gather(mi.Vector3f, normals, index)
            self.packed = PackedEntries.of(self.positions, self.keys, index, normals)
        return self

    @staticmethod
    def build(positions: mi.Point3f, cell_size: float, origin=None) -> "PointGrid":
        """Sort ``positions`` into cells of edge ``cell_size`` (> 0, finite)."""
        cell_size = float(cell_size)
        if not (cell_size > 0 and dr.isfinite(cell_size)):
            raise ValueError(f"PointGrid: cell_size must be finite and > 0, got {cell_size}")
        n = dr.width(positions) if dr.width(positions.x) > 0 else 0
        if origin is None:
            origin = mi.Point3f(dr.min(positions.x), dr.min(positions.y), dr.min(positions.z)) \
                if n > 0 else mi.Point3f(0.0)
        origin = mi.Point3f(origin)
        table_size = _next_pow2(max(n, 1))
        if n == 0:
            return PointGrid(origin, cell_size, table_size - 1,
                             dr.zeros(mi.UInt32, table_size + 1), mi.UInt32(),
                             mi.Point3f(), 0)
        inv = dr.opaque(mi.Float, 1.0 / cell_size)
        bucket = hash_cell(cell_of(positions, origin, inv), opaque_u32(table_size - 1))
        cell_start, order = _bucket_sort(bucket, table_size)
        sorted_positions = dr.gather(mi.Point3f, positions, order)
        keys = cell_key(cell_of(sorted_positions, origin, inv))
        dr.eval(order, sorted_positions, keys)
        return PointGrid(origin, cell_size, table_size - 1, cell_start, order,
                         sorted_positions, n, keys)

    def nbytes(self) -> int:
        """Memory held by the grid's own arrays."""
        per_point = 12 + 4 + (4 if self.order is not None else 0)
        packed = 4 * dr.width(self.packed.data) if self.packed is not None else 0
        return per_point * self.count + 4 * (self.table_mask + 2) + packed

    def occupancy(self, query: mi.Point3f, active=True) -> mi.UInt32:
        """Points in each query's cell (hash collisions add their buckets' others)."""
        return _bucket_occupancy(self.cell_start, self.table_mask, self.origin, self.cell_size,
                                 query, active)

    def sorted_in_place(self) -> "PointGrid":
        """The same grid for data already permuted by ``order`` (queries then report
        sorted indices, and every gather they lead to is cache-coherent)."""
        return PointGrid(self.origin, self.cell_size, self.table_mask, self.cell_start, None,
                         self.positions, self.count, self.keys)

    def spread_subset(self, per_bucket: int) -> mi.UInt32:
        """Sorted positions of at most ``per_bucket`` entries of each hash bucket,
        evenly spaced through it (every ⌈n / per_bucket⌉-th): a bucket's entries keep
        the order they had (a spatially sorted map lists them cell by cell), so every
        k-th spreads over the bucket instead of bunching in one corner of it."""
        entry = dr.arange(mi.UInt32, self.count)
        inv = dr.opaque(mi.Float, 1.0 / self.cell_size)
        bucket = hash_cell(cell_of(self.positions, self.origin, inv),
                           dr.opaque(mi.UInt32, self.table_mask))
        start = dr.gather(mi.UInt32, self.cell_start, bucket)
        size = dr.gather(mi.UInt32, self.cell_start, bucket + 1) - start
        stride = dr.maximum((size + (per_bucket - 1)) // per_bucket, 1)
        return dr.compress((entry - start) % stride == 0)

    def for_each_neighbor(self, query: mi.Point3f, radius, state: Any,
                          visit: Callable[[Any, mi.UInt32, mi.Float, mi.Bool], Any],
                          active=True, finished: Callable[[Any], mi.Bool] | None = None,
                          label: str = "point_grid_query", with_offset: bool = False,
                          octant: bool = False, one_loop: bool = True):
        """Call ``visit(state, index, dist2, valid)`` for every point within ``radius``.

        ``index`` is the point's original index, ``dist2`` its squared distance to
        ``query``, and ``valid`` the mask of lanes for which the candidate is really
        inside the radius (``dist2 < radius²``). ``visit`` returns the new state.
        ``radius`` (scalar or per lane) must not exceed ``cell_size``. ``finished``, if
        given, stops a lane early (e.g. once a covering record was found). With
        ``with_offset``, ``visit`` also receives ``point - query`` (already at hand, so
        the visitor need not gather the position again). With ``octant`` the radius
        must not exceed half a cell, and only the 2×2×2 cells nearest the query are
        visited (instead of 3×3×3). ``one_loop``: how the cells are walked (see
        :func:`_walk`; the result is the same).
        """
        query = mi.Point3f(query)
        n_lanes = dr.width(query.x)
        if self.count == 0 or n_lanes == 0:
            return state
        active = mi.Bool(active)
        radius = dr.opaque(mi.Float, radius) if isinstance(radius, (int, float)) else mi.Float(radius)
        radius2 = radius * radius
        inv = dr.opaque(mi.Float, 1.0 / self.cell_size)
        origin = self.origin
        center = cell_of(query, origin, inv)
        mask = dr.opaque(mi.UInt32, self.table_mask)
        if octant:
            # Towards the nearer face on each axis: a ball of radius <= cell/2 around
            # the query lies in the query's cell and those neighbours.
            frac = (query - origin) * inv - mi.Vector3f(center)
            toward = mi.Vector3i(dr.select(frac >= 0.5, 1, -1))

            def offset(j):
                j = mi.Int32(j)
                return mi.Vector3i(toward.x * (j & 1), toward.y * ((j >> 1) & 1), toward.z * (j >> 2))
        else:
            offset = _neighbour_offset

        def cell(j):
            visited = center + offset(j)
            return hash_cell(visited, mask), cell_key(visited)

        if self.order is None:
            index_of = lambda entry, valid: entry  # noqa: E731
        else:
            index_of = lambda entry, valid: dr.gather(mi.UInt32, self.order, entry, valid)  # noqa: E731
        return _walk(self.cell_start, self.keys, self.packed if self.packed is not None else self.positions,
                     index_of, cell,
                     8 if octant else 27, query, radius2, state, visit, active, finished,
                     with_offset, label, one_loop)


@dataclass
class BallGrid:
    """Balls (centre, radius) inserted into every grid cell their bounding box overlaps.

    A point query then needs to scan only the one cell that contains it.
    """

    origin: mi.Point3f  #: lower corner of the grid (width 1)
    cell_size: float  #: edge of a cell
    table_mask: int  #: number of hash buckets minus one
    cell_start: mi.UInt32  #: first entry of each bucket; entry table_size = entries
    ball: mi.UInt32  #: ball index of each (cell, ball) entry, sorted by bucket
    cell: mi.Vector3i  #: cell of each entry, to reject other cells sharing the bucket
    count: int  #: number of balls
    entries: int  #: number of (cell, ball) pairs
    #: ``cell`` and ``ball`` entry by entry (4 floats' bits each, :meth:`pack`): one
    #: packet load per visited entry instead of four gathers. Derived; None: unpacked.
    packed: mi.Float = field(default=None, metadata={"derived": True})

    def pack(self) -> "BallGrid":
        """Lay the entries out for grids that many queries walk (the records' lookup
        grids at render). Returns ``self``."""
        if self.entries and self.packed is None:
            self.packed = interleave([mi.Int32(self.cell.x), mi.Int32(self.cell.y),
                                      mi.Int32(self.cell.z), mi.UInt32(self.ball)], 4)
        return self

    #: Upper bound on cells per axis that one ball may span; a larger ball makes the
    #: grid use bigger cells instead of exploding the entry count.
    MAX_SPAN = 16

    @staticmethod
    def build(centers: mi.Point3f, radii: mi.Float, cell_size: float | None = None) -> "BallGrid":
        n = dr.width(centers.x)
        radii = mi.Float(radii)
        if n == 0:
            return BallGrid(mi.Point3f(0.0), 1.0, 0, dr.zeros(mi.UInt32, 2), mi.UInt32(),
                            mi.Vector3i(), 0, 0)
        r_max = float(dr.max(radii)[0]) if dr.width(radii) > 0 else 0.0
        if cell_size is None:
            # The mean diameter keeps entries per ball near 8 for typical radii.
            cell_size = 2.0 * mean_value(radii)
        cell_size = max(float(cell_size), 2.0 * r_max / BallGrid.MAX_SPAN, 1e-30)
        lo = centers - radii
        origin = mi.Point3f(dr.min(lo.x), dr.min(lo.y), dr.min(lo.z))
        inv = dr.opaque(mi.Float, 1.0 / cell_size)
        cmin = cell_of(centers - radii, origin, inv)
        cmax = cell_of(centers + radii, origin, inv)
        span = cmax - cmin + 1
        per_ball = mi.UInt32(span.x * span.y * span.z)
        first = dr.prefix_sum(per_ball)
        dr.eval(first, cmin, span)
        total = int(dr.sum(per_ball)[0])
        # Expand balls into (cell, ball) pairs: pair p belongs to the last ball whose
        # first pair is <= p.
        pair = dr.arange(mi.UInt32, total)
        # Every ball has >= 1 pair, so first[] is strictly increasing: mark each ball's
        # first pair with the ball's index, and a running maximum gives every pair its
        # owner (a prefix reduction, which bakes no array size into the kernel).
        marks = dr.zeros(mi.UInt32, total)
        dr.scatter(marks, dr.arange(mi.UInt32, n), first)
        owner = dr.prefix_reduce(dr.ReduceOp.Max, marks, exclusive=False)
        local = pair - dr.gather(mi.UInt32, first, owner)
        # max(., 1): integer division by a zero in an unused tail lane of a SIMD packet
        # would raise SIGFPE on x86.
        sx = dr.maximum(dr.gather(mi.Int32, span.x, owner), 1)
        sy = dr.maximum(dr.gather(mi.Int32, span.y, owner), 1)
        li = mi.Int32(local)
        cell = dr.gather(mi.Vector3i, cmin, owner) + mi.Vector3i(li % sx, (li // sx) % sy, li // (sx * sy))
        table_size = _next_pow2(max(total, 1))
        bucket = hash_cell(cell, opaque_u32(table_size - 1))
        cell_start, order = _bucket_sort(bucket, table_size)
        ball = dr.gather(mi.UInt32, owner, order)
        sorted_cell = dr.gather(mi.Vector3i, cell, order)
        dr.eval(ball, sorted_cell)
        return BallGrid(origin, cell_size, table_size - 1, cell_start, ball, sorted_cell, n, total)

    def for_each_ball(self, query: mi.Point3f, state: Any,
                      visit: Callable[[Any, mi.UInt32, mi.Bool], Any], active=True,
                      finished: Callable[[Any], mi.Bool] | None = None,
                      label: str = "ball_grid_query"):
        """Call ``visit(state, ball_index, valid)`` for every ball whose cell set
        contains the query's cell. ``visit`` must test the ball itself (distance,
        normal): this only guarantees that no ball containing ``query`` is missed and
        none is visited twice."""
        query = mi.Point3f(query)
        if self.count == 0 or dr.width(query.x) == 0:
            return state
        inv = dr.opaque(mi.Float, 1.0 / self.cell_size)
        c = cell_of(query, self.origin, inv)
        bucket = hash_cell(c, dr.opaque(mi.UInt32, self.table_mask))
        active = mi.Bool(active)
        entry = dr.gather(mi.UInt32, self.cell_start, bucket, active)
        end = dr.gather(mi.UInt32, self.cell_start, bucket + 1, active)

        def cond(entry, end, active, state):
            running = active & (entry < end)
            if finished is not None:
                running &= ~finished(state)
            return running

        packed = self.packed

        def body(entry, end, active, state):
            if packed is not None:
                packet = dr.gather(mi.ArrayXf, packed, entry, shape=(4, dr.width(entry)))
                same = (dr.reinterpret_array(mi.Int32, packet[0]) == c.x) & \
                    (dr.reinterpret_array(mi.Int32, packet[1]) == c.y) & \
                    (dr.reinterpret_array(mi.Int32, packet[2]) == c.z)
                index = dr.select(same, dr.reinterpret_array(mi.UInt32, packet[3]), 0)
            else:
                same = dr.all(dr.gather(mi.Vector3i, self.cell, entry) == c)
                index = dr.gather(mi.UInt32, self.ball, entry, same)
            state = visit(state, index, same)
            return entry + 1, end, active, state

        _, _, _, state = dr.while_loop(state=(entry, end, active, state),
                                       cond=cond, body=body, label=label)
        return state



@dataclass
class PointGridPyramid:
    """Points in grids with cells of r, r/2, r/4, r/8, all in one hash table, for
    density estimates whose radius adapts to the local photon density.

    One radius for the whole map is wrong twice where photons cluster (the inside of a
    lamp shade, a caustic): each query scans thousands of candidates (30 s of 40 in a
    lamp room), and the disc blurs detail that those photons resolve. A query picks
    its level from the photon count of the densest of the 27 level-0 cells around it,
    so that a disc there would hold about ``per_estimate`` photons, and scans the 27
    cells of that level around it. Every
    point is entered once per level; the level is part of each entry's hash and key,
    so one table (and one 27-cell scan per query) serves every level.

    The photon arrays must be reordered by the ``order`` that :meth:`build` returns
    (level-0 grid order): queries report indices into the reordered arrays.
    """

    origin: mi.Point3f  #: lower corner shared by every level
    radius: float  #: level-0 radius (= its cell size)
    per_estimate: float  #: photons a disc should hold
    levels: int  #: number of levels
    table_mask: int  #: buckets minus one
    cell_start: mi.UInt32  #: first entry of each bucket; entry table_size = entries
    index: mi.UInt32  #: point index (in level-0 order) of each entry
    positions: mi.Point3f  #: position of each entry's point (coherent reads)
    keys: mi.UInt32  #: cell key of each entry's cell, with the level in bits 30-31
    count: int  #: number of points
    level0_start: mi.UInt32  #: level-0 point grid's bucket starts (occupancy lookups)
    level0_mask: int
    #: cell key of each level-0 bucket's middle point (``NO_KEY``: empty bucket)
    level0_key: mi.UInt32
    #: ``positions``, ``keys`` and ``index`` entry by entry (:class:`PackedEntries`),
    #: what queries read (derived: rebuilt, not stored, by :meth:`pack`).
    packed: PackedEntries = field(default=None, metadata={"derived": True})

    def pack(self) -> "PointGridPyramid":
        """Lay the entries out for the queries (:class:`PackedEntries`). Returns ``self``."""
        if self.packed is None and self.count:
            self.packed = PackedEntries.of(self.positions, self.keys, self.index)
        return self

    #: Levels: radius / 2^(LEVELS-1) is the smallest radius used, so a cluster
    #: 4^(LEVELS-1) = 64× denser than the base still costs the same per query.
    LEVELS = 4
    #: A query moves one level finer only when its disc would hold more than this many
    #: times ``per_estimate`` (each level quarters the count).
    DENSE_FACTOR = 2.0
    #: Level bits of an entry's key (bits 29-31: up to 8 levels); the cell key keeps 29.
    #: (Bits 30-31 held levels 0-3 only: the caustic map's six levels put levels 4
    #: and 5 on 0 and 1's keys, so a scan could take a bucket-mate of another level's
    #: cell for its own; the distance test then rejected its points, at a cost.)
    LEVEL_SHIFT = 29

    @staticmethod
    def _bucket(cell: mi.Vector3i, level, mask):
        return (hash_cell(cell, 0xFFFFFFFF) ^ (mi.UInt32(level) * 0x9E3779B1)) & mask

    @staticmethod
    def _key(cell: mi.Vector3i, level):
        """An entry's key: the cell's (modulo 1024 on x and y, 512 on z: among the 27
        cells of a scan all still differ) and the level in the top three bits."""
        return (cell_key(cell) & 0x1FFFFFFF) | (mi.UInt32(level) << PointGridPyramid.LEVEL_SHIFT)

    @staticmethod
    def build(positions: mi.Point3f, radius: float, per_estimate: float, levels: int | None = None):
        """Returns ``(pyramid, order)``; reorder the point data by ``order``."""
        levels = levels or PointGridPyramid.LEVELS
        if levels > 8:
            raise ValueError(f"PointGridPyramid: at most 8 levels, got {levels}")
        base = PointGrid.build(positions, radius)
        order = base.order
        n = base.count
        if n == 0:
            empty = PointGridPyramid(
                origin=base.origin, radius=float(radius), per_estimate=float(per_estimate),
                levels=levels, table_mask=0, cell_start=dr.zeros(mi.UInt32, 2), index=mi.UInt32(),
                positions=mi.Point3f(), keys=mi.UInt32(), count=0, level0_start=base.cell_start,
                level0_mask=base.table_mask,
                level0_key=dr.full(mi.UInt32, NO_KEY, base.table_mask + 1))
            return empty, order
        sorted_p = base.positions
        table = _next_pow2(n * levels)
        buckets, keys = [], []
        for level in range(levels):
            inv = dr.opaque(mi.Float, (1 << level) / radius)
            cell = cell_of(sorted_p, base.origin, inv)
            buckets.append(PointGridPyramid._bucket(cell, opaque_u32(level), opaque_u32(table - 1)))
            keys.append(PointGridPyramid._key(cell, opaque_u32(level)))
        bucket = concat(buckets, mi.UInt32)
        key = concat(keys, mi.UInt32)
        cell_start, entry_order = _bucket_sort(bucket, table)
        point = entry_order % opaque_u32(n)
        # Each level-0 bucket's middle entry (level 0's keys are in base order): where a
        # dense cell shares its bucket with a sparse one, it is the dense cell's.
        level0_buckets = dr.arange(mi.UInt32, base.table_mask + 1)
        first = dr.gather(mi.UInt32, base.cell_start, level0_buckets)
        end = dr.gather(mi.UInt32, base.cell_start, level0_buckets + 1)
        filled = first < end
        middle = first + (end - first) // 2
        level0_key = dr.select(filled, dr.gather(mi.UInt32, base.keys, middle, filled),
                               opaque_u32(NO_KEY))
        pyramid = PointGridPyramid(
            origin=base.origin, radius=float(radius), per_estimate=float(per_estimate),
            levels=levels, table_mask=table - 1, cell_start=cell_start, index=point,
            positions=dr.gather(mi.Point3f, sorted_p, point),
            keys=dr.gather(mi.UInt32, key, entry_order), count=n,
            level0_start=base.cell_start, level0_mask=base.table_mask, level0_key=level0_key)
        dr.eval(pyramid.index, pyramid.positions, pyramid.keys, pyramid.level0_key)
        return pyramid.pack(), order

    def nbytes(self) -> int:
        packed = 4 * dr.width(self.packed.data) if self.packed is not None else 0
        return (12 + 4 + 4) * dr.width(self.index) + 4 * (self.table_mask + 2) \
            + 4 * (self.level0_mask + 2) + 4 * (self.level0_mask + 1) + packed

    def level_of(self, query: mi.Point3f, active=True):
        """The level each query should search (see the class docs) and its radius."""
        query = mi.Point3f(query)
        lanes = dr.width(query.x)
        if self.count == 0 or self.levels == 1:
            return dr.zeros(mi.UInt32, lanes), dr.full(mi.Float, self.radius, lanes)
        # The densest cell of the scan, not the query's own: beside a caustic's focus
        # (a glass sphere's, on the floor) a query in a sparse cell scanned the focus
        # in the next one, thousands of photons whose kernel weights smeared it over
        # the disc: 5 % too bright round the focus, and the packet waited for those
        # lanes (1.2 s of a 4.6 s render in a glossy room; 0.4 s this way).
        occupancy = mi.Float(_neighbourhood_occupancy(self.level0_start, self.level0_key,
                                                      self.level0_mask, self.origin, self.radius,
                                                      query, active))
        # ~π c / 1.25 photons per level-0 disc; each level down divides that by 4.
        per_disc = occupancy * (math.pi / 1.25)
        ratio = per_disc / dr.opaque(mi.Float, self.DENSE_FACTOR * max(self.per_estimate, 1.0))
        level = mi.UInt32(dr.clip(dr.floor(0.5 * dr.log2(dr.maximum(ratio, 1.0))),
                                  0, self.levels - 1))
        return level, dr.opaque(mi.Float, self.radius) * dr.exp2(-mi.Float(level))

    def for_each_neighbor(self, query: mi.Point3f, level: mi.UInt32, state, visit, active=True,
                          label="pyramid_query", with_offset: bool = False, one_loop: bool = True):
        """Call ``visit(state, index, dist2, valid[, offset])`` for every point within the
        radius of each query's ``level`` (from :meth:`level_of`); as
        :meth:`PointGrid.for_each_neighbor`."""
        query = mi.Point3f(query)
        if self.count == 0 or dr.width(query.x) == 0:
            return state
        active = mi.Bool(active)
        level = mi.UInt32(level)
        radius = dr.opaque(mi.Float, self.radius) * dr.exp2(-mi.Float(level))
        radius2 = radius * radius
        inv = dr.rcp(radius)
        center = cell_of(query, self.origin, inv)
        mask = dr.opaque(mi.UInt32, self.table_mask)

        def cell(j):
            visited = center + _neighbour_offset(j)
            return self._bucket(visited, level, mask), self._key(visited, level)

        # (Cells are one radius wide: the ball's squared radius is 1 cell².)
        return _walk(self.cell_start, self.keys, self.packed if self.packed is not None else self.positions,
                     lambda entry, valid: dr.gather(mi.UInt32, self.index, entry, valid),
                     cell, 27, query, radius2, state, visit, active, None, with_offset, label,
                     one_loop, _reaches_neighbour(query, self.origin, inv, center, 1.0))
