"""Small Dr.Jit helpers shared by the stages.

Dr.Jit bakes Python numbers into the kernels it compiles, so a value that changes from
run to run (a seed, a radius derived from the photon count, a batch offset) would make
every run compile new kernels. These helpers pass such values as *opaque* variables:
one kernel serves every value.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

_GOLDEN = 0x9E3779B97F4A7C15
#: The largest float32 below 1 (a sample in [0, 1) stays there after stretching).
ONE_MINUS_EPSILON = 0.99999994


def mis_weight(pdf_a, pdf_b):
    """The power heuristic's weight of a sample drawn with density ``pdf_a`` against
    one of density ``pdf_b``: Mitsuba's own (``mitsuba.ad.integrators.common``),
    imported on first use, since that module needs a variant set and this one is
    imported before."""
    from mitsuba.ad.integrators.common import mis_weight as power_heuristic

    return power_heuristic(pdf_a, pdf_b)


def opaque_float(value: float) -> mi.Float:
    return dr.opaque(mi.Float, float(value))


def mean_value(values) -> float:
    """The mean of a Dr.Jit array as a Python float. ``dr.mean`` multiplies by 1/width
    as a constant: a kernel per width, and widths (records, photons) move with the seed."""
    width = dr.width(values)
    return float(dr.sum(values)[0]) / width if width else 0.0


def channel_mean(spectrum):
    """The mean of a spectrum's channels, lane by lane. (``dr.mean`` of a Color3f
    folds its width into a constant: one 10 000-operation kernel of the surface
    probes was compiled anew (5 s on two cores) for every photon count.)"""
    return dr.sum(spectrum, axis=0) * (1.0 / dr.size_v(type(spectrum)))


def opaque_u32(value: int) -> mi.UInt32:
    return dr.opaque(mi.UInt32, int(value) & 0xFFFFFFFF)


def concat(parts, dtype):
    """Join 1-D arrays of ``dtype`` (e.g. several batches of Point3f) end to end.

    (``dr.concat`` joins nested arrays along their first, component axis, so this
    scatters each part at its offset; offsets are opaque, see above.)
    """
    if not parts:
        return dtype()
    if len(parts) == 1:
        return parts[0]
    out = dr.zeros(dtype, sum(dr.width(p) for p in parts))
    offset = 0
    for p in parts:
        n = dr.width(p)
        if n:
            dr.scatter(out, p, dr.arange(mi.UInt32, n) + opaque_u32(offset))
        offset += n
    return out


def interleave(columns, width: int) -> mi.Float:
    """Equal-length arrays laid out element by element, ``width`` floats each (the
    columns first, zeros after; integer columns as the bits of a float, see
    ``dr.reinterpret_array``): what ``dr.gather(mi.ArrayXf, ..., shape=(width, n))``
    reads back with packet loads when ``width`` is a power of two."""
    count = dr.width(columns[0])
    out = dr.zeros(mi.Float, count * width)
    base = dr.arange(mi.UInt32, count) * width
    for j, column in enumerate(columns):
        if not dr.is_float_v(column):
            column = dr.reinterpret_array(mi.Float, column)
        dr.scatter(out, column, base + j)
    dr.eval(out)
    return out


def scatter_min(target, value, index, active=True) -> None:
    """``target[index] = min(target[index], value)`` by atomics (min is order free).
    Not Dr.Jit's default on the CPU, which reduces into a copy of ``target`` per thread
    and writes ``target``'s size into the kernel: a kernel per size (per record count,
    so per seed), compiled again by a render whose warm-up had other counts."""
    dr.scatter_reduce(dr.ReduceOp.Min, target, value, index, active, mode=dr.ReduceMode.Direct)


def scatter_count(counts: mi.UInt32, index: mi.UInt32, active=True) -> None:
    """``counts[index] += 1`` by atomics (see :func:`scatter_min`: the default writes
    the table's size into the kernel, a kernel per size)."""
    dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.UInt32(1), index, active, mode=dr.ReduceMode.Direct)


def every_nth(count: int, stride: int) -> mi.UInt32:
    """Indices 0, stride, 2·stride, … below ``count``."""
    return dr.arange(mi.UInt32, -(-count // stride)) * opaque_u32(stride)


def rng(size: int, seed: int, stream: int = 0) -> mi.PCG32:
    """``size`` independent PCG32 streams for (``seed``, ``stream``), without baking
    either number into kernels."""
    state = (int(seed) * _GOLDEN + 0x853C49E6748FEA9B) % (1 << 64)
    sequence = (int(stream) * _GOLDEN + 0xDA3E39CB94B95BDB) % (1 << 64)
    return mi.PCG32(size=size, initstate=dr.opaque(mi.UInt64, state),
                    initseq=dr.opaque(mi.UInt64, sequence))


#: Relative part of a ray offset: ~30 float ulps of the point's largest coordinate.
RAY_OFFSET_RELATIVE = 2e-6


def surface_offset(p: mi.Point3f, offset: float) -> mi.Float:
    """How far to push a ray origin at ``p`` off its surface: ``offset`` (a world-space
    length) plus enough to clear float rounding at ``p``'s distance from the origin."""
    return opaque_float(offset) + dr.max(dr.abs(mi.Vector3f(p))) * RAY_OFFSET_RELATIVE


def segment_blocked(scene: mi.Scene, origin: mi.Point3f, target: mi.Point3f, active,
                    past=None) -> mi.Bool:
    """Does a surface lie between ``origin`` and ``target``? (One shadow ray; zero-length
    segments are never blocked.) Without ``past`` the ray stops just short of the target;
    with it, it goes on ``past`` beyond the target, so that a target lying on a
    surface's plane (a photon stored at a wall's foot, lifted along the floor's normal:
    it stays on the wall's plane, within rounding of either side) counts as behind
    that surface, whichever side rounding put it on. Callers whose endpoints are lifted
    off their own surfaces pass a fraction of the lift: nothing else lies that close
    beyond the target."""
    offset = target - origin
    length = dr.norm(offset)
    ray = mi.Ray3f(origin, offset / dr.maximum(length, 1e-30))
    ray.maxt = length * 0.999 if past is None else length + past
    return scene.ray_test(ray, mi.Bool(active) & (length > 0))


#: Shading normals within this cosine of the geometric normal (0.08°) are taken as the
#: geometric normal itself: Mitsuba's ``cube`` and merged meshes carry vertex normals
#: equal to their faces' up to rounding, and a factor of 1 ± 1e-7 would still change
#: which photons Russian roulette keeps (another noise, not a better image).
FLAT_SHADING_COSINE = 1.0 - 1e-6


def shading_normal_on_side(si: mi.SurfaceInteraction3f, n: mi.Vector3f) -> mi.Vector3f:
    """``si``'s shading normal turned to the side of ``n`` (its geometric normal on the
    side that matters), or ``n`` itself, exactly, where the two agree
    (:data:`FLAT_SHADING_COSINE`) or the shading normal is not finite."""
    shading_n = mi.Vector3f(si.sh_frame.n)
    cosine = dr.dot(shading_n, n)
    shading_n = dr.select(cosine < 0, -shading_n, shading_n)
    bent = (dr.abs(cosine) < FLAT_SHADING_COSINE) & dr.all(dr.isfinite(shading_n))
    return dr.select(bent, shading_n, n)


def jittered(u: mi.Point2f, index: mi.UInt32, count: int) -> mi.Point2f:
    """The uniform sample ``u`` moved into stratum ``index`` of a side × side grid over
    [0, 1)² (side = ⌊√count⌋): jittered stratification of ``count`` samples numbered
    ``index``. Samples numbered side² and beyond (``count`` not a square) keep ``u``."""
    side = math.isqrt(count)
    if side < 2:
        return mi.Point2f(u)
    cell = mi.Point2f(mi.Float(index % side), mi.Float(index // side))
    moved = dr.minimum((cell + u) * (1.0 / side), ONE_MINUS_EPSILON)
    return dr.select(index < side * side, moved, u)


def finite(value, active=True):
    """``value`` where ``active`` and every channel is finite, else 0: a NaN or Inf from
    one emitter, texel or sample must cost that sample only."""
    return dr.select(mi.Bool(active) & dr.all(dr.isfinite(value)), value, 0.0)


def only_where(mask, compute, zeros, sampler=None, label: str = "only_where"):
    """``compute()`` on the lanes of ``mask`` and ``zeros()`` on the others, as a
    symbolic conditional: the LLVM backend then skips ``compute``'s code for every
    SIMD packet with no lane in ``mask``. Masked code outside a conditional runs for
    every packet (a 16-lane packet pays for it even with no lane active): in the
    camera loop, most of a vertex's work is for some of the lanes only (the cache
    read behind a traced vertex, emitter samples at traced ones, the rare fallback
    to the photons).

    ``compute`` must have no side effects but on ``sampler`` (given: ``compute`` and
    ``zeros`` take it, its state advances on the lanes of ``mask`` only).
    Returns what ``compute`` does. ``zeros`` should make new values: passing values of
    the enclosing loop through it unchanged (a BSDFSample3f, in the camera loop) made
    Dr.Jit 1.5 emit LLVM IR that failed verification ("Instruction does not dominate
    all uses").
    """
    mask = mi.Bool(mask)
    if sampler is None:
        return dr.if_stmt((), mask, true_fn=compute, false_fn=zeros, label=label)
    _, result = dr.if_stmt((sampler,), mask,
                           true_fn=lambda s: (s, compute(s)),
                           false_fn=lambda s: (s, zeros(s)), label=label)
    return result
