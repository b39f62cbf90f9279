"""Direct light from an environment sampled by its radiance times the cosine.

Mitsuba's ``envmap`` samples directions by radiance alone: on a surface a quarter of
the samples (the material preview's ground) fall below the horizon and the rest ignore
the cosine, and a ``constant`` sky is sampled uniformly over the whole sphere. Direct
light from a sky was then most of the noise left on such scenes.

:class:`SkySampler` tabulates, for each of ``NORMAL_BINS`` bins of surface normals, the
sky's radiance times the cosine to the bin's normal over equal-area cells of the
sphere, and samples a cell by that table, then a direction uniformly within it. A
sample for a point of normal ``n`` is drawn, with probability ``PRODUCT_FRACTION``, from
the table of ``n``'s bin, else by the emitter's own sampling, and weighted by the
mixture of the two densities (one-sample MIS): unbiased whatever the tables hold (the
emitter's own density covers every direction it lights). Cells holding a peak finer
than themselves (a sun in an HDR sky, which uniform sampling within the cell would
rarely hit) are left out of the tables, and the emitter's own sampling, which
resolves its texels, gets their share of the samples back (:data:`PEAK_RATIO`).

Directions are in world space; a cell is a band of ``z`` times a sector of ``φ``
(equal solid angles, ``4π / cells`` each); normal bins are the cells of an octahedral
map.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from . import emission
from ._jit import ONE_MINUS_EPSILON
from .emission import choose_emitter, emission_sphere, emitter_order, emitter_pmf
from . import spectra

# --- Internal tuning constants -------------------------------------------------------
#: Cells of the sky tables: bands of z × sectors of φ (~1.4° × 1.4° at the horizon).
#: Half as fine (64 × 128), the material preview's relMSE at 16 spp was 11 % higher
#: (4.81e-3 against 4.33e-3): a cell's sky varied within it. The tables hold
#: NORMAL_BINS × cells floats (32 MB).
SKY_BANDS = 128
SKY_SECTORS = 256
#: Solid-angle density of a direction drawn uniformly within a cell: cells / 4π.
CELL_DENSITY = SKY_BANDS * SKY_SECTORS / (4.0 * math.pi)
#: Normal bins: an octahedral map of the sphere of normals, this many bins a side
#: (bins ~15° wide). Each table uses the cosine to its bin's centre (widened by the
#: cell's own angular radius): a point whose normal lies off the centre meets a few
#: directions near its horizon that its table leaves out, which the emitter's own
#: sampling covers (unbiased). Widening by the bin's radius as well (so that no
#: direction was left out) put up to 9 % of the table's samples below the horizon and
#: oversampled the rest of it: the variance of one sky sample was 1.3-1.6× this one's,
#: relMSE 9 % higher on the overcast courtyard and 8 % on the material preview.
NORMAL_RES = 16
NORMAL_BINS = NORMAL_RES * NORMAL_RES
#: Radiance of a cell: the mean of this many × this many stratified evaluations (4 × 4
#: with the coarser cells above gave the same relMSE, and four times the evaluations).
CELL_SAMPLES = 2
#: Fraction of a cell's width kept clear on each side by sample() (see there).
CELL_MARGIN = 1e-4
#: Each table's guide (Chen and Asau's cutpoints): for each of this many equal slices
#: of [0, 1], the first cell whose cumulative value passes the slice's start, so that
#: sample() searches only the cells between two cutpoints (a few) instead of all of a
#: table's 32768 (15 dependent reads across its 128 KB; the overcast courtyard's render
#: -6 %, of the ~20 % that the tables' sampling takes there). A power of two: u·K is
#: then exact in float32. 4 MB in all.
GUIDE_SLOTS = 4096
#: Probability that a sky sample is drawn from the product tables (the rest: the
#: emitter's own sampling; see the module's docstring), times the share of the sky's
#: power that the tables resolve (below). Relative to 0.75, with the tables as they are
#: now (1.4° cells, the cosine to the bin's centre), relMSE at 16 spp over three seeds:
#: overcast courtyard -21 %, interior_window -4 %, courtyard with a sun -2 %,
#: material preview -2 %, exterior_envmap +1 %; 0.95 went further (-27 % overcast)
#: but +3 % on exterior_envmap, whose large bright patch the emitter's own sampling
#: serves better.
PRODUCT_FRACTION = 0.9
#: A sky is even (``SkySampler.even``) when its radiance varies within the records'
#: guide bins by at most this (:func:`_variation_within_guide_bins`): 0 for a constant
#: sky, 0.7-0.95 for the environment maps tried; records may then hold it everywhere.
EVEN_SKY_VARIATION = 0.25
#: A cell whose environment density somewhere exceeds this many times the density of
#: its power spread evenly over it holds a peak finer than the cell (a sun in an HDR
#: sky): uniform sampling within the cell would rarely hit it, so the tables leave such
#: cells to the emitter's own sampling. A 0.7° sun holding 57 % of a sky's power had
#: doubled the noise of its direct light (2.27e-2 against 1.13e-2 without tables);
#: 3 also caught the material preview's bright texels (+6 % relMSE there), 8 missed
#: the sun where the cells are narrow (near the poles of the cells' grid). (Measured
#: with 2.8° cells; with today's 1.4° cells that sun fills its cells and is sampled
#: well by the tables, within 1.02× of the noise without them: the test uses a 0.35°
#: sun.)
PEAK_RATIO = 6.0
#: Samples of the emitter's own sampling that find such cells.
PEAK_PROBE_SAMPLES = 1 << 16
#: The tables' share of the samples is PRODUCT_FRACTION × (1 − peaked share) ** this:
#: the peaks' own share goes back to the emitter's sampling, and more, since a peak
#: is all the emitter's sampling is good at and most of where the light comes from
#: (the 0.7° sun: 1.37e-2 with 1, 1.23e-2 with 2).
PEAK_EXPONENT = 2


def _cell_of(d: mi.Vector3f, bands: int, sectors: int):
    """(band, sector) of world direction ``d`` on the equal-area z × φ grid."""
    band = mi.UInt32(dr.clip((d.z + 1.0) * (0.5 * bands), 0.0, bands - 1))
    phi = dr.atan2(d.y, d.x)
    phi = dr.select(phi < 0, phi + 2.0 * math.pi, phi)
    sector = mi.UInt32(dr.clip(phi * (sectors / (2.0 * math.pi)), 0.0, sectors - 1))
    return band, sector


def _direction(band, sector, u, v, bands: int, sectors: int):
    """The direction at (u, v) ∈ [0, 1)² within cell (band, sector) (NumPy or Dr.Jit)."""
    if isinstance(band, np.ndarray):
        z = np.clip(-1.0 + (band + u) * (2.0 / bands), -1.0, 1.0)
        phi = (sector + v) * (2.0 * math.pi / sectors)
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)
    z = dr.clip(-1.0 + (mi.Float(band) + u) * (2.0 / bands), -1.0, 1.0)
    phi = (mi.Float(sector) + v) * (2.0 * math.pi / sectors)
    s = dr.safe_sqrt(1.0 - z * z)
    sp, cp = dr.sincos(phi)
    return mi.Vector3f(s * cp, s * sp, z)


def _octahedral_inverse(uv):
    """Unit vectors (NumPy, rows) of points of [0, 1]² of the octahedral map."""
    p = uv * 2.0 - 1.0
    z = 1.0 - np.abs(p).sum(1)
    t = np.maximum(-z, 0.0)
    xy = p - t[:, None] * np.where(p >= 0, 1.0, -1.0)
    v = np.concatenate([xy, z[:, None]], 1)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def normal_bin(n: mi.Vector3f) -> mi.UInt32:
    """Bin of unit vector ``n`` in the NORMAL_RES² octahedral map (Dr.Jit)."""
    inv = dr.rcp(dr.maximum(dr.abs(n.x) + dr.abs(n.y) + dr.abs(n.z), 1e-30))
    px, py = n.x * inv, n.y * inv
    fx = (1.0 - dr.abs(py)) * dr.select(px >= 0, 1.0, -1.0)
    fy = (1.0 - dr.abs(px)) * dr.select(py >= 0, 1.0, -1.0)
    below = n.z < 0
    px, py = dr.select(below, fx, px), dr.select(below, fy, py)
    i = mi.UInt32(dr.clip((px * 0.5 + 0.5) * NORMAL_RES, 0.0, NORMAL_RES - 1))
    j = mi.UInt32(dr.clip((py * 0.5 + 0.5) * NORMAL_RES, 0.0, NORMAL_RES - 1))
    return i * NORMAL_RES + j


@functools.lru_cache(maxsize=1)
def _tables_geometry():
    """What the tables share whatever the sky (computed once per process): the
    CELL_SAMPLES² stratified directions of every cell, and for each normal bin and cell
    the cosine between the bin's centre and the cell, widened by the cell's angular
    radius (the largest cosine between the centre and any direction of the cell)."""
    cells = SKY_BANDS * SKY_SECTORS
    k = CELL_SAMPLES
    cell = np.repeat(np.arange(cells), k * k)
    sub = np.tile(np.arange(k * k), cells)
    directions = _direction((cell // SKY_SECTORS).astype(np.float64), (cell % SKY_SECTORS).astype(np.float64),
                            (sub // k + 0.5) / k, (sub % k + 0.5) / k, SKY_BANDS, SKY_SECTORS)
    res = NORMAL_RES
    centres_uv = np.stack(np.meshgrid((np.arange(res) + 0.5) / res, (np.arange(res) + 0.5) / res,
                                      indexing="ij"), -1).reshape(-1, 2)
    normals = _octahedral_inverse(centres_uv)
    cell_ids = np.arange(cells)
    band, sector = (cell_ids // SKY_SECTORS).astype(np.float64), (cell_ids % SKY_SECTORS).astype(np.float64)
    centres = _direction(band, sector, np.full(cells, 0.5), np.full(cells, 0.5), SKY_BANDS, SKY_SECTORS)
    cell_radius = np.zeros(cells)
    for cu in (0.0, 1.0):
        for cv in (0.0, 1.0):
            corner = _direction(band, sector, np.full(cells, cu), np.full(cells, cv), SKY_BANDS, SKY_SECTORS)
            cell_radius = np.maximum(cell_radius, np.arccos(np.clip((corner * centres).sum(1), -1, 1)))
    # cos(max(angle - r, 0)) = cos a cos r + sin a sin r where a > r, else 1; in float32
    # without arccos (bins × cells = 8M: 0.1 s instead of 0.45 s; kept, at half the memory).
    cos_a = np.clip(normals.astype(np.float32) @ centres.T.astype(np.float32), -1.0, 1.0)
    cos_r, sin_r = np.cos(cell_radius).astype(np.float32), np.sin(cell_radius).astype(np.float32)
    sin_a = np.sqrt(np.maximum(1.0 - cos_a * cos_a, 0.0))
    cosine = np.where(cos_a >= cos_r[None, :], np.float32(1.0),
                      np.maximum(cos_a * cos_r[None, :] + sin_a * sin_r[None, :], 0.0))
    directions.setflags(write=False)
    cosine.setflags(write=False)
    return directions, cosine


def _peaked_cells(emitter):
    """``(mask over the cells, share of the sky's power in them)``: the cells holding a
    peak finer than themselves (:data:`PEAK_RATIO`), found with PEAK_PROBE_SAMPLES
    stratified samples of the emitter's own sampling (which resolves its texels): a
    cell's power is Σ L/p over the samples in it, and its peak the largest density p
    met there."""
    cells = SKY_BANDS * SKY_SECTORS
    n = PEAK_PROBE_SAMPLES
    side = int(round(math.sqrt(n)))
    # Built in Dr.Jit, not from NumPy: an array that wraps NumPy's memory is aligned as
    # NumPy allocated it, and Dr.Jit compiles a kernel per alignment (a cold cache then
    # compiled the emitter's sampling again in a later render: 0.09 s).
    i = dr.arange(mi.UInt32, side * side)
    u = mi.Point2f((mi.Float(i // side) + 0.5) / side, (mi.Float(i % side) + 0.5) / side)
    def sampled(wavelengths):
        it = dr.zeros(mi.Interaction3f, side * side)
        if wavelengths is not None:
            it.wavelengths = wavelengths
        return emitter.sample_direction(it, u)

    ds, _ = sampled(spectra.reference_wavelengths(side * side))
    band, sector = _cell_of(ds.d, SKY_BANDS, SKY_SECTORS)
    cell = np.array(band * SKY_SECTORS + sector, dtype=np.int64)
    pdf = np.array(ds.pdf, dtype=np.float64)
    weight = spectra.rgb_of(lambda wavelengths: sampled(wavelengths)[1], side * side)
    power = np.array(mi.luminance(weight), dtype=np.float64)  # L / p
    pdf, power = (np.broadcast_to(a, cell.shape) for a in (pdf, power))  # a constant: one value
    ok = np.isfinite(pdf) & (pdf > 0) & np.isfinite(power) & (power > 0)
    if not ok.any():
        return np.zeros(cells, bool), 0.0
    cell, pdf, power = cell[ok], pdf[ok], power[ok]
    cell_power = np.bincount(cell, weights=power, minlength=cells)
    total = cell_power.sum()
    peak = np.zeros(cells)
    np.maximum.at(peak, cell, pdf)
    # The density of a cell's power spread evenly over its solid angle.
    even = cell_power / total * CELL_DENSITY
    peaked = (cell_power > 0) & (peak > PEAK_RATIO * even)
    return peaked, float(cell_power[peaked].sum() / total)


def _variation_within_guide_bins(directions: np.ndarray, radiance: np.ndarray) -> float:
    """√(Σ (L - L̄_bin)²) / √(Σ L²) over ``directions`` (equal solid angles), L̄_bin the
    mean over each direction's guide bin (cache.guide_bin): 0 for a constant sky; 0.7-0.95
    for the bundled and public environment maps (a sun or studio lights in them)."""
    from .cache import GUIDE_BINS, guide_bin  # (cache imports this module)

    bins = np.array(guide_bin(mi.Vector3f(directions.T.astype(np.float32))), dtype=np.int64)
    count = np.bincount(bins, minlength=GUIDE_BINS)
    mean = np.bincount(bins, radiance, minlength=GUIDE_BINS) / np.maximum(count, 1)
    total = float((radiance ** 2).sum())
    return float(np.sqrt(((radiance - mean[bins]) ** 2).sum() / total)) if total > 0 else 0.0


@dataclass
class SkySampler:
    """Sky radiance × cosine tables for one environment emitter (see the module)."""

    emitter: object  #: the environment emitter (``scene.emitters()[emitter_index]``)
    emitter_index: int  #: its index in ``scene.emitters()``
    pmf: float  #: the probability that an emitter sample picks it (emission.emitter_pmf)
    #: Probability that a sky sample comes from the tables: PRODUCT_FRACTION times the
    #: share of the sky's power outside cells with finer peaks (PEAK_RATIO).
    product_fraction: float
    #: How far a sample's point lies from the shading point: beyond all the geometry
    #: (twice the radius of emission.emission_sphere), for its shadow ray.
    distance: float
    cdf: mi.Float  #: per normal bin, the cumulative distribution over the sky cells
    #: per normal bin, GUIDE_SLOTS + 1 cutpoints: the number of cells whose cumulative
    #: value is at most j / GUIDE_SLOTS
    guide: mi.UInt32
    #: The sky's radiance varies little within the records' guide bins (a constant or
    #: overcast sky; :data:`EVEN_SKY_VARIATION`): guides may hold it everywhere
    #: (cache.EVEN_SKY_OPENNESS).
    even: bool = False

    @staticmethod
    def build(scene: mi.Scene) -> "SkySampler | None":
        """Tables for the scene's environment (``envmap``, ``constant``: an infinite
        emitter that is not a delta), or None if it has none or more than one."""
        infinite = [i for i in emitter_order(scene)
                    if mi.has_flag(scene.emitters()[i].flags(), mi.EmitterFlags.Infinite)
                    and not mi.has_flag(scene.emitters()[i].flags(), mi.EmitterFlags.Delta)]
        if len(infinite) != 1:
            return None
        index = infinite[0]
        emitter = scene.emitters()[index]
        directions, cosine = _tables_geometry()
        # Mean luminance of each cell from CELL_SAMPLES² stratified directions.
        si = dr.zeros(mi.SurfaceInteraction3f, len(directions))
        si.wi = -mi.Vector3f(directions.T.astype(np.float32))

        def evaluate(wavelengths):
            if wavelengths is not None:
                si.wavelengths = wavelengths
            return emitter.eval(si)

        radiance = np.array(mi.luminance(spectra.rgb_of(evaluate, len(directions))), dtype=np.float64)
        radiance = np.broadcast_to(radiance, (len(directions),))  # a constant sky gives one value
        radiance = np.where(np.isfinite(radiance) & (radiance > 0), radiance, 0.0)
        even = _variation_within_guide_bins(directions, radiance) <= EVEN_SKY_VARIATION
        radiance = radiance.reshape(SKY_BANDS * SKY_SECTORS, -1).mean(1)
        if not radiance.sum() > 0:
            return None
        peaked, peaked_share = _peaked_cells(emitter)
        radiance = np.where(peaked, 0.0, radiance)
        if not radiance.sum() > 0:
            return None
        # In float32 and in place: the tables are NORMAL_BINS × cells (8M) and rebuilt
        # for every scene (float64 with copies took 0.13 s, this 0.04 s).
        cdf = np.cumsum(cosine * radiance.astype(np.float32)[None, :], 1, dtype=np.float32)
        dark = ~(cdf[:, -1] > 0)
        if dark.any():  # a bin that sees no sky (a black upper half): radiance alone
            cdf[dark] = np.cumsum(radiance, dtype=np.float64).astype(np.float32)[None, :]
        cdf /= cdf[:, -1:]
        cdf[:, -1] = 1.0
        cuts = (np.arange(GUIDE_SLOTS + 1) / GUIDE_SLOTS).astype(np.float32)  # exact
        guide = np.stack([np.searchsorted(row, cuts, side="right") for row in cdf]).astype(np.uint32)
        return SkySampler(emitter, index, emitter_pmf(scene, index),
                          PRODUCT_FRACTION * (1.0 - peaked_share) ** PEAK_EXPONENT, 2.0 * emission_sphere(scene)[1],
                          mi.Float(cdf.ravel()), mi.UInt32(guide.ravel()), even)

    def _bin(self, n: mi.Vector3f) -> mi.UInt32:
        return normal_bin(n)

    def sample(self, n: mi.Vector3f, u: mi.Point2f, active=True):
        """A world direction from the table of ``n``'s bin and its solid-angle density."""
        cells = SKY_BANDS * SKY_SECTORS
        active = mi.Bool(active)
        bin_ = self._bin(n)
        start = bin_ * cells
        # The cell is the first whose cumulative value exceeds u.x: between the
        # cutpoints of u.x's slice (the last cell's value is 1).
        slot = bin_ * (GUIDE_SLOTS + 1) + mi.UInt32(u.x * GUIDE_SLOTS)
        lo = dr.gather(mi.UInt32, self.guide, slot, active)
        hi = dr.minimum(dr.gather(mi.UInt32, self.guide, slot + 1, active), cells - 1)

        def halve(lo, hi):
            mid = (lo + hi) >> 1
            past = dr.gather(mi.Float, self.cdf, start + mid, active) <= u.x
            return dr.select(past, mid + 1, lo), dr.select(past, hi, mid)
        lo, hi = dr.while_loop((lo, hi), lambda lo, hi: active & (lo < hi), halve,
                               label="sky_table_search")
        cell = lo
        upper = dr.gather(mi.Float, self.cdf, start + cell, active)
        lower = dr.select(cell > 0, dr.gather(mi.Float, self.cdf, start + cell - 1, active & (cell > 0)), 0.0)
        t = dr.clip((u.x - lower) / dr.maximum(upper - lower, 1e-30), 0.0, 1.0)
        # A margin of CELL_MARGIN of the cell is left on each side, so that rounding
        # never puts the direction in a neighbouring cell (whose density pdf() would
        # give): the interior is the cell up to a measure of 4e-4 of it.
        inner = 1.0 - 2.0 * CELL_MARGIN
        d = _direction(cell // SKY_SECTORS, cell % SKY_SECTORS, CELL_MARGIN + inner * t,
                       CELL_MARGIN + inner * u.y, SKY_BANDS, SKY_SECTORS)
        return d, (upper - lower) * CELL_DENSITY

    def pdf(self, n: mi.Vector3f, d: mi.Vector3f, active=True) -> mi.Float:
        """Solid-angle density of :meth:`sample` at world direction ``d``."""
        band, sector = _cell_of(d, SKY_BANDS, SKY_SECTORS)
        slot = self._bin(n) * (SKY_BANDS * SKY_SECTORS) + band * SKY_SECTORS + sector
        upper = dr.gather(mi.Float, self.cdf, slot, active)
        first = (band == 0) & (sector == 0)
        lower = dr.select(first, 0.0, dr.gather(mi.Float, self.cdf, slot - 1, active & ~first))
        return dr.select(active, dr.maximum(upper - lower, 0.0) * CELL_DENSITY, 0.0)


def _is_sky(sky: SkySampler, emitter) -> mi.Bool:
    return emitter == mi.EmitterPtr(sky.emitter)


def _mixture_pdf(sky: SkySampler, pmf: float, table_pdf, env_pdf):
    """Density of a sky sample (emitter choice included: ``pmf``), given the tables'
    density ``table_pdf`` and the emitter's own ``env_pdf`` (emitter choice included)."""
    fraction = sky.product_fraction
    return fraction * pmf * table_pdf + (1.0 - fraction) * env_pdf


def _sky_pmf(scene: mi.Scene, sky: SkySampler, delta: bool | None) -> float:
    """Probability that an emitter sample picks the sky: among all lights (``delta``
    None) or among the lights that are not delta lights (False)."""
    return sky.pmf if delta is None else sky.pmf * emission.soft_pdf_scale(scene)


@dataclass
class SkyGuide:
    """Emitter samples of the sky that follow, with probability ``fraction`` (per lane;
    0: never), the sky that ``record`` of ``index`` saw through an opening
    (:meth:`~pmic_integrator.cache.RecordIndex.sample_guide` with ``sky``)."""

    index: object  #: the RecordIndex
    record: mi.UInt32
    fraction: mi.Float

    def mix(self, other_pdf, pmf: float, d: mi.Vector3f, active) -> mi.Float:
        """The strategy's density at ``d``: the guide's share and the rest's."""
        guide_pdf = self.index.guide_pdf(self.record, d, active & (self.fraction > 0), sky=True)
        return (1.0 - self.fraction) * other_pdf + self.fraction * pmf * guide_pdf


def sample_emitter_direction(scene: mi.Scene, sky: SkySampler | None, ref, normal: mi.Vector3f,
                             sample: mi.Point2f, active=True, guide: SkyGuide | None = None,
                             delta: bool | None = None):
    """:func:`pmic_integrator.emission.sample_emitter_direction` (with a shadow ray),
    except that the sky is sampled by the mixture of the module's docstring about the
    surface normal ``normal`` (world space, on the side the light arrives from), and,
    with ``guide``, with probability ``guide.fraction`` by the sky a record saw (decided
    by the sample itself, like the rest of the mixture: a fixed map of the square, so
    that jittered strata stay unbiased; lanes whose fraction is 0 draw exactly what
    they drew without a guide).
    ``ds.pdf`` is the density of the whole strategy (emitter choice included), as
    :func:`pdf_emitter_direction` gives it for a direction met by other means.
    ``delta``: the emitters chosen from, as in
    :func:`pmic_integrator.emission.choose_emitter` (False: all but the delta lights,
    which are then sampled apart)."""
    if sky is None:
        return emission.sample_emitter_direction(scene, ref, sample, True, active, delta)
    active = mi.Bool(active)
    sample = mi.Point2f(sample)
    pmf = _sky_pmf(scene, sky, delta)
    index, weight, sample.x = choose_emitter(scene, sample.x, active, delta)
    is_sky = active & (index == sky.emitter_index)
    guided = mi.Bool(False)
    if guide is not None:
        g = guide.fraction
        guided = is_sky & (sample.x < g)
        rest = (sample.x - g) / dr.maximum(1.0 - g, 1e-30)
        sample.x = dr.select(is_sky, dr.clip(dr.select(guided, sample.x / dr.maximum(g, 1e-30), rest),
                                             0.0, ONE_MINUS_EPSILON), sample.x)
    fraction = sky.product_fraction
    product = is_sky & ~guided & (sample.x < fraction)
    stretched = dr.select(product, sample.x / fraction, (sample.x - fraction) / (1.0 - fraction))
    sample.x = dr.select(is_sky & ~guided, dr.clip(stretched, 0.0, ONE_MINUS_EPSILON), sample.x)
    own = active & ~product & ~guided
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), index, own)
    ds, spectrum = emitter.sample_direction(ref, sample, own)
    if len(emission.emitter_subset(scene, delta)) > 1:
        ds.pdf *= dr.rcp(weight)
        spectrum *= weight
    # Sky lanes: the direction drawn from the tables where ``product``, the radiance
    # and the mixture's density for both kinds.
    d, sampled_table_pdf = sky.sample(normal, sample, product)
    if guide is not None:  # the record's sky, from its bins
        d = dr.select(guided, guide.index.sample_guide(guide.record, sample, guided, sky=True), d)
    mine = product | guided  # directions drawn here, not by the emitter
    dist = dr.select(mine, sky.distance, ds.dist)
    ds.d = dr.select(mine, d, ds.d)
    ds.dist = dist
    ds.p = dr.select(mine, ref.p + d * dist, ds.p)
    ds.n = dr.select(mine, -d, ds.n)
    ds.delta = dr.select(mine, False, ds.delta)
    ds.emitter = dr.select(mine, mi.EmitterPtr(sky.emitter), ds.emitter)
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ds.d))
    si.wi = -ds.d
    if mi.is_spectral:
        si.wavelengths = ref.wavelengths
    radiance = sky.emitter.eval(si, is_sky)
    env_pdf = dr.select(mine, pmf * sky.emitter.pdf_direction(ref, ds, mine), ds.pdf)
    table_pdf = dr.select(product & ~guided, sampled_table_pdf,
                          sky.pdf(normal, ds.d, is_sky & ~(product & ~guided)))
    pdf = _mixture_pdf(sky, pmf, table_pdf, env_pdf)
    if guide is not None:
        pdf = guide.mix(pdf, pmf, ds.d, is_sky)
    ds.pdf = dr.select(is_sky, pdf, ds.pdf)
    spectrum = dr.select(is_sky, radiance * dr.rcp(dr.maximum(pdf, 1e-30)), spectrum)
    ok = active & (ds.pdf != 0.0)
    spectrum = dr.select(ok, spectrum, 0.0)
    blocked = scene.ray_test(emission.shadow_ray(ref, ds), ok)
    return ds, dr.select(blocked, 0.0, spectrum)


def pdf_emitter_direction(scene: mi.Scene, sky: SkySampler | None, ref, ds: mi.DirectionSample3f,
                          normal: mi.Vector3f, active=True, guide: SkyGuide | None = None,
                          delta: bool | None = None) -> mi.Float:
    """Density with which :func:`sample_emitter_direction` about ``normal`` (with
    ``guide`` and ``delta``) draws the direction ``ds`` of an emitter that is not a
    delta light (``scene.pdf_emitter_direction`` without a sky and ``delta``)."""
    pdf = scene.pdf_emitter_direction(ref, ds, active)
    if delta is False:
        pdf *= emission.soft_pdf_scale(scene)
    if sky is None:
        return pdf
    pmf = _sky_pmf(scene, sky, delta)
    is_sky = mi.Bool(active) & _is_sky(sky, ds.emitter)
    mixture = _mixture_pdf(sky, pmf, sky.pdf(normal, ds.d, is_sky), pdf)
    if guide is not None:
        mixture = guide.mix(mixture, pmf, ds.d, is_sky)
    return dr.select(is_sky, mixture, pdf)

