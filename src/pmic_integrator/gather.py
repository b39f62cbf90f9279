"""Final gathering: radiance arriving at a point over stratified hemisphere rays.

A gather ray that reaches a surface with a diffuse lobe takes that surface's outgoing
diffuse radiance ``f_d · E``, where ``E`` is the precomputed irradiance of the nearest
global photon on the same surface (Christensen 2000): no density estimate per ray.
Rays that reach delta or glossy lobes continue by sampling those lobes (a few bounces).
Light arriving straight from emitters is *not* counted: the renderer computes direct
light at the shading point, and the caustic map carries light → specular → point.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi

from .cases import GATHER_PEAK_RATIO, GATHER_ROULETTE_BELOW, lobes_of
from .bsdfs import (diffuse_response, lobe_flags, lobes_separable,  # noqa: F401
                    near_diffuse, non_diffuse_context, response_azimuths)
from ._jit import concat, finite, mis_weight, opaque_float, opaque_u32, segment_blocked, shading_normal_on_side
from .emission import sample_emitter_direction
from .hashgrid import PointGrid
from .irradiance import nearest_photon
from .photons import PhotonMap
from .spectra import from_rgb

# --- Internal tuning constants -------------------------------------------------------
#: Specular/glossy bounces a gather ray may follow before it gives up (glass needs two
#: to get through a sphere; four covers a reflection of a refraction).
GATHER_SPECULAR_BOUNCES = 4
#: A gather ray that meets a diffuse surface closer than this many lookup radii is
#: continued one bounce (an emitter sample and a sample of the whole BSDF there)
#: instead of reading the photon there: a hit that close lies in a corner, a contact
#: or a narrow gap, where the photons' estimate, blurred over a lookup radius across
#: the surfaces meeting there, is far off (27 % dark on the inner faces of the material
#: preview's arms, a hand's width from the sphere, at one indirect bounce; the records
#: there and the renders that read them came out 2-7 % dark).
NEAR_HIT_LOOKUPS = 2.0
#: At most this many such bounces per gather ray; a hit still near after them reads
#: its photon.
NEAR_HIT_BOUNCES = 4
#: The visibility test between a gather hit and its nearest photon starts and ends
#: this fraction of a lookup radius off the surface (clear of it, well under the width
#: of any gap that photons could not cross).
VISIBILITY_LIFT = 0.02
#: Both ends of that test are lifted, besides, by this many times the photon's height
#: off the query's plane (which the plane test lets reach a quarter of the search
#: reach): the chord between two points of a convex surface runs under it by up to a
#: quarter of that height, and a step between them as high as it is cleared wherever
#: it stands. With the fixed lift alone, 26 % of the white room's records' lookups
#: (8 % of Sponza's; mouldings, sofas, columns) found their nearest photon hidden by
#: the very surface they lay on and read 0: images 0.986 / 0.984 of the references.
#: docs/tuning.md (final gathering) has the measurement.
VISIBILITY_LIFT_PER_HEIGHT = 1.0
#: ... but by no more than this many lookup radii: where photons are sparse a wide
#: search step accepts photons far off the plane, and lifted by their whole height the
#: ends passed over what lay between (the lamp room at 30k photons read its shade's
#: inside through the shade's base: 1.17 of path, first-hit).
VISIBILITY_LIFT_MAX = 1.0
#: Visibility rays between lifted points go on this many lifts past their target
#: (:func:`~pmic_integrator._jit.segment_blocked`'s ``past``): a target on the plane of a
#: wall standing on its surface counts as behind the wall.
PAST_TARGET_LIFTS = 0.5
#: A gather ray continued through a glossy lobe whose next hit can only read photons
#: (its emission is not counted: a caustic map holds it) survives with probability
#: min(1, its throughput) (Russian roulette, unbiased). A rough plastic's coat passes
#: ~5 % of the light: every gather ray in a room of rough plastic followed it up to
#: GATHER_SPECULAR_BOUNCES times, each bounce a photon search, for a few per cent of
#: its value (a door-lit room's cache stage 0.5 s diffuse, 2.2 s rough plastic, 0.8 s
#: now). Not where emission is counted next (a light met through the coat would be a
#: firefly in the record), nor after delta lobes: glass and mirrors pass most of the
#: light, and a mirror sphere's 10 % loss, played by roulette, made the records that
#: see it noisier (the bundled caustics box's relMSE +7 %) for no time saved.
GATHER_ROULETTE = True
#: Records' gathers of at least this many rays answer their photon lookups after the
#: rays' walk, together (:func:`gather_radiance`): in-process A/B of the cache stage,
#: Cornell box at 1M photons 0.48-0.60 -> 0.40-0.53 s, the bundled window-lit
#: interior 0.65-0.89 -> 0.53-0.67 s (a 183k-ray gather 150-180 -> 88-99 ms). Smaller
#: batches run as one loop: the split costs a few ms of tracing and launches whatever
#: the batch (6.8k rays: 12-16 ms as one loop, 15-19 ms split).
SPLIT_GATHER_MIN_RAYS = 1 << 14
#: The records' gathers answer lookups that no photon answers with one more traced
#: bounce (:func:`_trace_unanswered`), not with 0; their batches then take the split
#: path whatever their size (the one loop answers lookups in place).
TRACE_UNANSWERED = True
#: A traced answer's ray that lands near its start (a corner: where lookups go
#: unanswered) reads the photons there, as any other: bounced on as a gather ray's near
#: hit (an emitter sample and up to NEAR_HIT_BOUNCES more, each read in place) it cost
#: the white room's cache 1.59 s instead of 0.56 s, Sponza's 0.59 s instead of 0.36 s,
#: for the same means (`python benchmarks/gather_visibility.py --modes on near zero
#: --stem gather_visibility_near`, bounced on / read where it lands: white room
#: 0.9946 / 0.9954, Sponza 0.9936 / 0.9932).
TRACED_NEAR_HITS = False

def stratified_directions(strata_theta: int, strata_phi: int, sample_index: mi.UInt32,
                          u1: mi.Float, u2: mi.Float):
    """Cosine-weighted direction in stratum (j, k) of an M×N grid (local frame).

    Returns ``(direction, j, k)`` with ``j`` the cos²θ stratum and ``k`` the azimuth.
    """
    j = sample_index // strata_phi
    k = sample_index % strata_phi
    s = (mi.Float(j) + u1) / strata_theta
    phi = (mi.Float(k) + u2) * (2.0 * math.pi / strata_phi)
    sin_theta = dr.sqrt(s)
    cos_theta = dr.safe_sqrt(1.0 - s)
    sp, cp = dr.sincos(phi)
    return mi.Vector3f(sin_theta * cp, sin_theta * sp, cos_theta), j, k


@dataclass
class GatherSource:
    """What gather rays read at a diffuse hit: the precomputed-irradiance photons.

    The nearest compatible photon is searched in rings that double, each only for the
    lanes the previous ones left without a photon:

    1. half the lookup radius, in the 2×2×2 nearest cells of ``near_grid`` (cell =
       the radius);
    2. one radius, in the 3×3×3 cells of ``near_grid`` around the query;
    3. two radii, in ``mid_grid`` (cell = two radii);
    4. ``SEARCH_REACH`` radii, in ``wide_grid`` (a spread subset of each of its cells,
       ``WIDE_CELL_PHOTONS``);
    5. ``FAR_REACH`` radii, in ``far_grid``: a grid over the *sparse* photons only
       (those with at most ``SPARSE_CELL_PHOTONS`` in their ``near_grid`` cell). The
       lookup radius follows the photons' density where most of them are; where they
       cluster (the inside of a lamp shade, with 3/4 of the map) the rest of the room
       is far sparser, and 87 % of the gather hits there found no photon within step
       4's reach and read zero: 4 % dark overall, 17 % at lookup_size 16. Leaving the
       dense photons out of step 5 bounds what its large cells hold: a query beside
       the cluster does not scan the cluster. It too keeps a spread subset of each cell.

    The nearest photon within a ring is the nearest of all (a nearer one would lie in
    the ring too; only the plane test, which scales with the reach, is stricter in
    the narrow rings), so the rings save work and change next to nothing: a SIMD packet pays for its slowest
    lane, and a lane of step 4 scans ~30 times the photons of a lane of step 1 (64
    times the volume of step 2). Without steps 2 and 3 the record gathers took 1.9-2.0
    s of a 2.1 s cache stage in the lamp room and 0.9 of 1.05 s in the material
    preview, against 1.2-1.35 s and 0.55-0.75 s with them. With step 1 a quarter of the
    radius wide, 18 % of the gather hits in a Cornell box went on to the wide search
    and record gathers took 2.7× as long.
    """

    photons: PhotonMap  #: global map with ``irradiance`` filled in (stage 2), ``grid`` order
    grid: PointGrid  #: hash grid over ``photons`` (cell = ``radius``)
    radius: float  #: how far to look for the nearest compatible photon (the coarse cell)
    near_photons: PhotonMap | None = None  #: the same photons in ``near_grid`` order
    near_grid: PointGrid | None = None  #: hash grid with cell = the lookup radius
    far_photons: PhotonMap | None = None  #: the sparse photons (step 5), ``far_grid`` order
    far_grid: PointGrid | None = None  #: hash grid over ``far_photons``, cell = FAR_REACH radii
    mid_photons: PhotonMap | None = None  #: the same photons in ``mid_grid`` order
    mid_grid: PointGrid | None = None  #: hash grid with cell = two lookup radii
    #: Step 4's photons: at most ``WIDE_CELL_PHOTONS`` of ``photons`` per ``grid``
    #: bucket (:meth:`PointGrid.spread_subset`), ``wide_grid`` order (None: step 4
    #: searches ``photons`` whole).
    wide_photons: PhotonMap | None = None
    wide_grid: PointGrid | None = None  #: hash grid over ``wide_photons`` (cell = ``radius``)
    #: No caustic map: gather rays count emitters met after delta/glossy bounces.
    caustics_by_gathering: bool = False
    #: Diffuse hits closer than this are bounced on (:data:`NEAR_HIT_LOOKUPS`); 0: never
    #: (a bounded ``max_depth``, whose photons' depth limit leaves no segment for it).
    near_hit_distance: float = 0.0
    #: Some BSDF has a diffuse lobe and transmits (SceneInfo.has_diffuse_transmission):
    #: gather rays go on through those whose lobes cannot be taken apart (principled).
    crossing: bool = False
    #: Some BSDF ignores lobe masks (SceneInfo.has_inseparable): each hit is tested.
    inseparable: bool = True
    #: Some BSDF's response leans (SceneInfo.has_leaning_lobes): responses at three
    #: azimuths per level, else one (bsdfs.response_azimuths).
    leaning: bool = True
    #: The scene's BSDFs whose flags list a diffuse lobe they never have (principled
    #: metals and glass: bsdfs.diffuse_free_table), or None. Derived from the scene, not stored in
    #: cache files (registry indices are the process's).
    diffuse_free: mi.Bool = field(default=None, metadata={"derived": True})

    #: The full search reaches this many lookup radii: the precomputed photons are a
    #: fraction of the map (:func:`~pmic_integrator.irradiance.precompute_stride`), and
    #: where light is sparse (a room lit through a door) the nearest one is often
    #: beyond one radius. A ray that found none read zero: 10 % dark at lookup_size 8
    #: in such a room.
    SEARCH_REACH = 4.0
    #: Step 3 reaches this many lookup radii (16 made the lamp-shade room right: 1.003
    #: of path's mean, against 0.957 with steps 1-2 alone)...
    FAR_REACH = 16.0
    #: ...among the photons with at most this many in their near cell (a disc of one
    #: radius holds ~lookup_size / 2 photons of the map where the radius fits the density,
    #: ~lookup_size / 8 or / 16 of the precomputed ones).
    SPARSE_CELL_PHOTONS = 2
    #: Steps 4 and 5 search at most this many photons of each of their cells, spread
    #: through it. A lane there found no photon within two radii, but its 27 wide cells
    #: may hold a cluster: in the material preview 14 % of the gather hits went on to
    #: steps 4-5 and scanned whole clusters (the sparse photons of a 2 m far cell:
    #: thousands each), 0.22 s of a 0.48 s record gather. Their nearest photon is then
    #: the nearest of a spread subset, a little further off than the nearest of all,
    #: in light of the same cluster. (16 → 4: the material preview's cache stage
    #: 0.56 → 0.52 s, the lamp room's 0.87 → 0.84 s, with the same relMSE and mean
    #: (the lamp room's, fireflies, 0.30-0.41 → 0.21-0.44 over three seeds); the
    #: bundled scenes' images to 4 digits of relMSE.)
    WIDE_CELL_PHOTONS = 4

    @staticmethod
    def build(photons: PhotonMap, radius: float) -> "GatherSource":
        """Grids over ``photons`` (with ``irradiance`` filled in: the result of
        :func:`~pmic_integrator.irradiance.precompute_irradiance`)."""
        if photons.count == 0:
            return GatherSource(photons, PointGrid.build(mi.Point3f(), radius), radius)
        reach = radius * GatherSource.SEARCH_REACH
        coarse = PointGrid.build(photons.position, reach)
        coarse_photons, coarse = photons.select(coarse.order), coarse.sorted_in_place()
        near = PointGrid.build(photons.position, radius)
        near_photons = photons.select(near.order)
        # Photons in each photon's near cell (near.positions is in near order).
        sparse = dr.compress(near.occupancy(near.positions) <= GatherSource.SPARSE_CELL_PHOTONS)
        far_photons = far_grid = None
        if dr.width(sparse):
            far_photons = near_photons.select(sparse)
            far = PointGrid.build(far_photons.position, radius * GatherSource.FAR_REACH)
            far_photons, far_grid = GatherSource._spread(far_photons.select(far.order),
                                                         far.sorted_in_place())
        mid = PointGrid.build(photons.position, 2.0 * radius)
        # Step 4 searches the coarse grid itself where no cell needs thinning.
        wide_photons, wide_grid = GatherSource._spread(coarse_photons, coarse)
        source = GatherSource(coarse_photons, coarse, reach,
                              near_photons, near.sorted_in_place(),
                              mid_photons=photons.select(mid.order), mid_grid=mid.sorted_in_place(),
                              far_photons=far_photons, far_grid=far_grid,
                              wide_photons=wide_photons, wide_grid=wide_grid)
        return source.pack()

    def pack(self) -> "GatherSource":
        """Lay out its grids' entries for the searches (:meth:`PointGrid.pack`)."""
        for photons, grid in ((self.photons, self.grid), (self.near_photons, self.near_grid),
                              (self.mid_photons, self.mid_grid), (self.far_photons, self.far_grid),
                              (self.wide_photons, self.wide_grid)):
            if grid is not None:
                grid.pack(photons.normal)
        return self

    @staticmethod
    def _spread(photons: PhotonMap, grid: PointGrid):
        """``(photons, grid)`` (photons in the order of ``grid``, sorted in place) kept
        to at most ``WIDE_CELL_PHOTONS`` per bucket: the same pair where none has more,
        else the kept photons and a grid of the same edge rebuilt over them."""
        spread = grid.spread_subset(GatherSource.WIDE_CELL_PHOTONS)
        if dr.width(spread) == photons.count:
            return photons, grid
        kept = photons.select(spread)
        thin = PointGrid.build(kept.position, grid.cell_size)
        return kept.select(thin.order), thin.sorted_in_place()

    def nbytes(self) -> int:
        """Bytes of the other photon copies and their grids (the first copy is the
        map's own half, counted with the map)."""
        if self.near_grid is None:
            return 0
        far = 0 if self.far_grid is None else self.far_photons.nbytes() + self.far_grid.nbytes()
        mid = 0 if self.mid_grid is None else self.mid_photons.nbytes() + self.mid_grid.nbytes()
        wide = 0 if self.wide_grid is None or self.wide_grid is self.grid else \
            self.wide_photons.nbytes() + self.wide_grid.nbytes()
        return self.near_photons.nbytes() + self.near_grid.nbytes() + mid + far + wide

    def _steps(self):
        """(photons, grid, reach, octant) of each search step, narrowest first."""
        steps = []
        if self.near_grid is not None:
            steps.append((self.near_photons, self.near_grid, 0.5 * self.near_grid.cell_size, True))
            steps.append((self.near_photons, self.near_grid, self.near_grid.cell_size, False))
        if self.mid_grid is not None:
            steps.append((self.mid_photons, self.mid_grid, self.mid_grid.cell_size, False))
        if self.wide_grid is not None:
            steps.append((self.wide_photons, self.wide_grid, self.radius, False))
        else:
            steps.append((self.photons, self.grid, self.radius, False))
        if self.far_grid is not None:
            steps.append((self.far_photons, self.far_grid, self.far_grid.cell_size, False))
        return steps

    @property
    def lookup_radius(self) -> float:
        """The global map's lookup radius (``radius`` spans SEARCH_REACH of them)."""
        return self.radius / self.SEARCH_REACH

    def photon_near(self, p: mi.Point3f, n: mi.Vector3f, active):
        """``(irradiance, found)``: whether a precomputed photon on the surface at ``p``
        lies within one lookup radius (search steps 1-2: hits whose gather reads light
        from where it arrives, not from a photon the wider steps found far off), and
        the nearest one's precomputed irradiance (0 where none; no visibility test)."""
        near = self.near_grid is not None
        photons, grid = (self.near_photons, self.near_grid) if near else (self.photons, self.grid)
        index, found = nearest_photon(photons, grid, p, n, self.lookup_radius, active)
        found &= active
        return dr.gather(mi.Color3f, photons.irradiance, index, found), found

    def _read(self, photons: PhotonMap, index, hit, caustic, without_delta: bool) -> mi.Color3f:
        """Irradiance of photon ``index`` where ``hit``: its caustic irradiance in the
        lanes of ``caustic`` (None: none), else its whole (without the direct light of
        delta lights with ``without_delta``)."""
        values = photons.irradiance_nodelta if without_delta else photons.irradiance
        value = dr.gather(mi.Color3f, values, index, hit if caustic is None else hit & ~caustic)
        if caustic is not None:
            value = dr.select(caustic, dr.gather(mi.Color3f, photons.irradiance_caustic, index,
                                                 hit & caustic), value)
        return value

    def _visible(self, scene: mi.Scene, p: mi.Point3f, n: mi.Vector3f, position: mi.Point3f,
                 found) -> mi.Bool:
        """``found``, but for photons across a thin wall from the query. The nearest
        photon may lie there (same plane, same normal): the floor on the lit side of a
        2 mm partition lit the dark side. One shadow ray between the two points, both
        lifted off the surface (:data:`VISIBILITY_LIFT`, more where the photon lies off
        the query's plane, up to a bound: :data:`VISIBILITY_LIFT_PER_HEIGHT`), tells
        them apart."""
        radius = self.lookup_radius
        height = VISIBILITY_LIFT * radius
        extra = dr.minimum(dr.abs(dr.dot(position - p, n)) * VISIBILITY_LIFT_PER_HEIGHT,
                           opaque_float(VISIBILITY_LIFT_MAX * radius))
        lift = n * (extra + opaque_float(height))
        # (Past the photon by half the fixed lift: a photon stored at the foot of a wall
        # is on the wall's plane, and was read through it from inside a closed box
        # standing on the floor: 3.7e-4 where path is black.)
        return found & ~segment_blocked(scene, p + lift, position + lift, found,
                                        past=opaque_float(PAST_TARGET_LIFTS * height))

    def irradiance_at(self, scene: mi.Scene, p: mi.Point3f, n: mi.Vector3f,
                      active, without_delta: bool = False, caustic=None) -> mi.Color3f:
        """Precomputed irradiance of the nearest photon on the surface at ``p`` (normal
        ``n``, on the side it is seen from) that ``p`` can see (0 where there is none);
        with ``without_delta``, without the direct light of delta lights (the caller
        samples them itself). Lanes in the mask ``caustic`` read its caustic irradiance
        instead (``irradiance_caustic``): one search serves both kinds of lane. For use
        inside a symbolic loop; :meth:`irradiance_of` for evaluated batches."""
        if self.photons.count == 0:
            return dr.zeros(mi.Color3f, dr.width(p))
        active = mi.Bool(active)
        found = dr.zeros(mi.Bool, dr.width(p))
        result = dr.zeros(mi.Color3f, dr.width(p))
        position = dr.zeros(mi.Point3f, dr.width(p))
        for photons, grid, reach, octant in self._steps():
            retry = active & ~found
            index, hit = nearest_photon(photons, grid, p, n, reach, retry, octant=octant)
            hit &= retry
            result = dr.select(hit, self._read(photons, index, hit, caustic, without_delta), result)
            position = dr.select(hit, dr.gather(mi.Point3f, photons.position, index, hit), position)
            found |= hit
        return dr.select(self._visible(scene, p, n, position, found), result, 0.0)

    def irradiance_of(self, scene: mi.Scene, p: mi.Point3f, n: mi.Vector3f,
                      without_delta: bool = False, caustic=None, with_seen: bool = False):
        """:meth:`irradiance_at` for every lane of an evaluated batch (not inside a
        symbolic loop): the same photons and values, but each wider step searches only
        the queries that the narrower ones left without a photon, gathered together.
        Inside one kernel a SIMD packet runs a step for all of its lanes when one of
        them needs it: in a Cornell box at 1M photons, 19 % of the gather hits go on
        to step 2 and 1.6 % to step 3, which then ran in nearly every packet (the
        search was 0.13 s of a 0.21 s record-gather kernel; compacted, 0.09 s)."""
        count = dr.width(p)
        result = dr.zeros(mi.Color3f, count)
        if self.photons.count == 0 or count == 0:
            return (result, dr.zeros(mi.Bool, count)) if with_seen else result
        position = dr.zeros(mi.Point3f, count)
        found = dr.zeros(mi.Bool, count)
        pending = dr.arange(mi.UInt32, count)
        for photons, grid, reach, octant in self._steps():
            index, hit = nearest_photon(photons, grid, dr.gather(mi.Point3f, p, pending),
                                        dr.gather(mi.Vector3f, n, pending), reach, True,
                                        octant=octant)
            asked = None if caustic is None else dr.gather(mi.Bool, caustic, pending)
            dr.scatter(result, self._read(photons, index, hit, asked, without_delta), pending, hit)
            dr.scatter(position, dr.gather(mi.Point3f, photons.position, index, hit), pending, hit)
            dr.scatter(found, True, pending, hit)
            dr.eval(result, position, found, hit)
            pending = dr.gather(mi.UInt32, pending, dr.compress(~hit))
            if not dr.width(pending):
                break
        seen = self._visible(scene, p, n, position, found)
        result = dr.select(seen, result, 0.0)
        return (result, seen) if with_seen else result


@dataclass
class GatherWalk:
    """Gather rays on their way through delta/glossy bounces and near hits: the state
    of :func:`trace_gather_rays` and :func:`gather_radiance`, advanced one vertex at a
    time by :func:`_gather_vertex`."""

    ray: mi.Ray3f
    rng: mi.PCG32
    active: mi.Bool
    radiance: mi.Spectrum  #: gathered so far, but for the photons' irradiance (GatherLookup)
    throughput: mi.Spectrum
    distance: mi.Float  #: distance to the first hit (+inf: none)
    bounce: mi.UInt32
    near_bounces: mi.UInt32
    #: Emission met next is counted: after a delta/glossy bounce without a caustic map,
    #: and right after a near bounce (weighted against its emitter sample: ``near_pdf``).
    count_emission: mi.Bool
    crossed: mi.Bool  #: went through an inseparable BSDF
    #: Where a near bounce sampled a non-delta lobe: the emission met next is weighted
    #: against that vertex's emitter sample (MIS), from its position and the BSDF
    #: sample's density (0: no weighting).
    near_p: mi.Point3f
    near_pdf: mi.Float

    @staticmethod
    def start(ray: mi.Ray3f, rng: mi.PCG32, active) -> "GatherWalk":
        lanes = dr.width(ray.o)
        return GatherWalk(ray=mi.Ray3f(ray), rng=rng, active=mi.Bool(active),
                          radiance=dr.zeros(mi.Spectrum, lanes),
                          throughput=dr.full(mi.Spectrum, 1.0, lanes),
                          distance=dr.full(mi.Float, dr.inf, lanes),
                          bounce=dr.zeros(mi.UInt32, lanes), near_bounces=dr.zeros(mi.UInt32, lanes),
                          count_emission=dr.zeros(mi.Bool, lanes), crossed=dr.zeros(mi.Bool, lanes),
                          near_p=dr.zeros(mi.Point3f, lanes), near_pdf=dr.zeros(mi.Float, lanes))


@dataclass
class GatherLookup:
    """The photon lookups one vertex of a :class:`GatherWalk` asks for: in the lanes of
    ``mask``, ``weight`` times the precomputed irradiance of the nearest photon at
    ``(p, n)`` (its caustic irradiance in the lanes of ``caustic``; None: none)."""

    mask: mi.Bool
    p: mi.Point3f
    n: mi.Vector3f
    weight: mi.Spectrum
    caustic: mi.Bool | None = None
    #: The walk's wavelengths (spectral variants; None in RGB ones): ``weight`` is at
    #: them, the photons' irradiance is linear sRGB (spectra.from_rgb).
    wavelengths: mi.Spectrum | None = None
    #: Where each lookup came from in the arrays it was gathered from (:meth:`select`):
    #: the rays of a first vertex, the (ray, vertex) slots of the rest.
    lanes: mi.UInt32 | None = None

    def reflected(self, irradiance: mi.Color3f) -> mi.Spectrum:
        """What the lookup adds to the walk's radiance."""
        return finite(self.weight * from_rgb(irradiance, self.wavelengths), self.mask)

    def select(self, lanes: mi.UInt32) -> "GatherLookup":
        """The lookups of ``lanes`` (all asked for: ``mask`` true), kept as ``lanes``."""
        return GatherLookup(mask=dr.full(mi.Bool, True, dr.width(lanes)),
                            p=dr.gather(mi.Point3f, self.p, lanes),
                            n=dr.gather(mi.Vector3f, self.n, lanes),
                            weight=dr.gather(mi.Spectrum, self.weight, lanes),
                            caustic=None if self.caustic is None else dr.gather(mi.Bool, self.caustic, lanes),
                            wavelengths=None if self.wavelengths is None else
                            dr.gather(mi.Spectrum, self.wavelengths, lanes),
                            lanes=mi.UInt32(lanes))

    @staticmethod
    def joined(parts: list) -> "GatherLookup":
        """The lookups of ``parts`` (all asked for) one after the other."""
        first = parts[0]
        return GatherLookup(mask=concat([p.mask for p in parts], mi.Bool),
                            p=concat([p.p for p in parts], mi.Point3f),
                            n=concat([p.n for p in parts], mi.Vector3f),
                            weight=concat([p.weight for p in parts], mi.Spectrum),
                            caustic=None if first.caustic is None else concat([p.caustic for p in parts], mi.Bool),
                            wavelengths=None if first.wavelengths is None else
                            concat([p.wavelengths for p in parts], mi.Spectrum))

    def write(self, asked: "GatherLookup", slot: mi.UInt32) -> None:
        """Store the lookups ``asked`` for at ``slot`` of these arrays (where asked)."""
        dr.scatter(self.mask, asked.mask, slot, asked.mask)
        dr.scatter(self.p, asked.p, slot, asked.mask)
        dr.scatter(self.n, asked.n, slot, asked.mask)
        dr.scatter(self.weight, asked.weight, slot, asked.mask)
        if self.caustic is not None:
            dr.scatter(self.caustic, asked.caustic, slot, asked.mask)
        if self.wavelengths is not None:
            dr.scatter(self.wavelengths, asked.wavelengths, slot, asked.mask)


def _gather_vertex(scene: mi.Scene, source: GatherSource, walk: GatherWalk, sample_delta: bool,
                   near_distance: mi.Float, emission: bool = False):
    """One vertex of the gather rays of ``walk`` (see :func:`trace_gather_rays`): returns
    the walk past it and the photon lookups it asks for (:class:`GatherLookup`), which
    the caller answers in place or later. ``emission``: some walk may count emission
    (``count_emission``) though the source's switches would not (:func:`_trace_unanswered`)."""
    ray, rng, throughput, bounce = walk.ray, walk.rng, walk.throughput, walk.bounce
    radiance, near_bounces, crossed = mi.Spectrum(walk.radiance), walk.near_bounces, walk.crossed
    ctx_specular = non_diffuse_context()
    ctx_all = mi.BSDFContext()
    caustics = source.caustics_by_gathering
    near_on = source.near_hit_distance > 0
    si = scene.ray_intersect(ray, walk.active)
    if emission or caustics or near_on or source.crossing or source.inseparable:
        # Light reaching the record through delta/glossy bounces (no caustic map) or
        # through an inseparable BSDF, or reaching a near bounce's point past its
        # emitter sample.
        seen = walk.active & walk.count_emission
        emitted = throughput * si.emitter(scene, seen).eval(si, seen)
        if near_on:
            emitted *= _after_near_bounce(scene, si, walk, seen)
        radiance += finite(emitted, seen)
    active = walk.active & si.is_valid()
    distance = dr.select(active & (bounce == 0), si.t, walk.distance)
    bsdf = si.bsdf(ray)
    lobes = lobes_of(lobe_flags(bsdf, source.diffuse_free))  # (the vertex cases: pmic_integrator.cases)
    # Normal on the side the ray arrives from, to match photon normals.
    n = mi.Vector3f(si.n)
    n = dr.select(dr.dot(n, ray.d) > 0, -n, n)
    diffuse = active & lobes.diffuse
    glossy = lobes.specular
    # A BSDF that ignores lobe masks (principled) reflects the photon's irradiance with
    # its whole response only where it is nearly diffuse for this ray (as camera
    # vertices read the cache; GATHER_PEAK_RATIO); elsewhere (a glossy metal) the
    # ray goes on through a sample of the whole BSDF, reading nothing here.
    whole, separable = mi.Bool(False), mi.Bool(True)
    if source.inseparable:
        whole = diffuse & glossy & (bounce < GATHER_SPECULAR_BOUNCES)
        separable = lobes_separable(bsdf, si, whole)
        whole &= ~separable
        whole &= ~near_diffuse(bsdf, si, whole, GATHER_PEAK_RATIO)
        diffuse &= ~whole
    response = diffuse_response(bsdf, si, diffuse,
                                azimuths=response_azimuths(source.leaning))
    # No lookup where nothing is reflected (the back of a one-sided surface, a black
    # texel): the searches there are the slowest (no photon is near).
    lit = diffuse & (dr.max(response) > 0)
    near = mi.Bool(False)
    # Lanes that read a photon: its irradiance, or at a near hit its caustics only.
    lookup, caustic_lanes = mi.Bool(lit), None
    if near_on:
        near = lit & (si.t < near_distance) & (near_bounces < NEAR_HIT_BOUNCES)
        lit &= ~near
        u_em = mi.Point2f(rng.next_float32(), rng.next_float32())
        ds_near, em_near = sample_emitter_direction(scene, si, u_em, True, near)
        f_near, pdf_near = bsdf.eval_pdf(ctx_all, si, si.to_local(ds_near.d), near & (ds_near.pdf > 0))
        # Weighted against the continuation's BSDF sample, which counts the emission it
        # meets (_after_near_bounce): alone, a sample from a hit millimetres from a lamp
        # is unbounded (docs/tuning.md, "near bounces' MIS").
        mis = dr.select(ds_near.delta, 1.0, mis_weight(ds_near.pdf, pdf_near))
        lit_near = throughput * f_near * em_near * mis
        radiance += finite(lit_near, near & (ds_near.pdf > 0))
        if source.photons.irradiance_caustic is not None:
            caustic_lanes = near
        else:
            lookup = lit
    if sample_delta:
        # (Lanes going on through the whole BSDF cannot meet a delta light either: they
        # reflect the sample by the BSDF itself.)
        sampled = lit | whole
        u = mi.Point2f(rng.next_float32(), rng.next_float32())
        ds, em_weight = sample_emitter_direction(scene, si, u, True, sampled, delta=True)
        cos_n = dr.maximum(dr.dot(ds.d, shading_normal_on_side(si, n)), 0.0)
        direct = throughput * response * mi.Spectrum(em_weight) * cos_n
        if source.inseparable:
            f_whole = bsdf.eval(ctx_all, si, si.to_local(ds.d), whole & (ds.pdf > 0))
            direct = dr.select(whole, throughput * f_whole * mi.Spectrum(em_weight), direct)
        radiance += finite(direct, sampled & (ds.pdf > 0))
    asked = GatherLookup(mask=lookup, p=si.p, n=n, weight=throughput * response, caustic=caustic_lanes,
                         wavelengths=ray.wavelengths if mi.is_spectral else None)
    rest = active & ~near & ~whole & glossy
    rest &= bounce < GATHER_SPECULAR_BOUNCES
    # A BSDF that ignores lobe masks (principled), nearly diffuse here, gave its
    # reflection above as a diffuse response; what it transmits (glass, a thin leaf)
    # comes from the other side, which that response cannot see: a sample of the whole
    # BSDF goes on where it crosses the surface, and ends where it reflects.
    through = rest & diffuse & ~separable
    rest &= separable
    u1 = rng.next_float32()
    u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
    bs, weight = bsdf.sample(ctx_specular, si, u1, u2, rest)
    if source.crossing or source.inseparable:
        # ``through`` (nearly diffuse: its reflection read above) goes on where it
        # crosses the surface only; ``whole`` goes on either way.
        bs_through, weight_through = bsdf.sample(ctx_all, si, u1, u2, through | whole)
        through &= mi.Frame3f.cos_theta(si.wi) * mi.Frame3f.cos_theta(bs_through.wo) < 0
        through = (through & mi.Bool(source.crossing)) | whole
        bs[through] = bs_through
        weight[through] = weight_through
        # Photons through or off such a surface are global-map photons (not caustic
        # ones), so no caustic map holds the emitters seen through it: count them.
        crossed = crossed | through
        rest |= through
    if near_on:
        bs_near, weight_near = bsdf.sample(ctx_all, si, u1, u2, near)
        bs[near] = bs_near
        weight[near] = weight_near
        count_emission = near | mi.Bool(caustics) | crossed
        near_pdf = dr.select(near & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta), bs.pdf, 0.0)
        near_bounces = dr.select(near, near_bounces + 1, near_bounces)
    else:
        count_emission = mi.Bool(caustics) | crossed
        near_pdf = mi.Float(0.0)
    throughput = throughput * weight
    active = (rest | near) & (bs.pdf > 0) & (dr.max(throughput) > 0) & dr.all(dr.isfinite(throughput))
    if GATHER_ROULETTE:
        roulette = active & rest & ~count_emission & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Glossy)
        survive = dr.minimum(dr.max(throughput), 1.0)
        roulette &= survive < GATHER_ROULETTE_BELOW
        throughput = dr.select(roulette, throughput * dr.rcp(survive), throughput)
        active &= ~roulette | (rng.next_float32(roulette) < survive)
    walk = GatherWalk(ray=si.spawn_ray(si.to_world(bs.wo)), rng=rng, active=active,
                      radiance=radiance, throughput=throughput, distance=distance,
                      bounce=bounce + 1, near_bounces=near_bounces,
                      count_emission=count_emission, crossed=crossed, near_p=mi.Point3f(si.p),
                      near_pdf=near_pdf)
    return walk, asked


def _after_near_bounce(scene: mi.Scene, si: mi.SurfaceInteraction3f, walk: GatherWalk, seen) -> mi.Float:
    """MIS weight of the emission met at ``si`` by the lanes of ``seen``: against the
    emitter sample of the near bounce that sampled the ray (``walk.near_pdf`` > 0),
    else 1."""
    weighted = seen & (walk.near_pdf > 0)
    ref = dr.zeros(mi.Interaction3f, dr.width(walk.near_pdf))
    ref.p = walk.near_p
    ds = mi.DirectionSample3f(scene, si=si, ref=ref)
    emitter_pdf = scene.pdf_emitter_direction(ref, ds, weighted)
    return dr.select(weighted, mis_weight(walk.near_pdf, emitter_pdf), 1.0)


def _answer_lookups(scene: mi.Scene, source: GatherSource, lookups: "GatherLookup", states: mi.UInt64,
                    sample_delta: bool) -> mi.Spectrum:
    """What each of ``lookups`` (all asked for) adds to its ray's radiance: its weight
    times the irradiance of the nearest photon it sees, or, where it sees none (none
    near enough, or the nearest across a wall: :meth:`GatherSource.irradiance_of`), a
    traced answer (:func:`_trace_unanswered`; not for near hits' caustic reads, whose
    other light their emitter sample and continuation carry). ``states``: each
    lookup's random state."""
    irradiance, seen = source.irradiance_of(scene, lookups.p, lookups.n, without_delta=sample_delta,
                                            caustic=lookups.caustic, with_seen=True)
    reflected = lookups.reflected(irradiance)
    if not TRACE_UNANSWERED:
        return reflected
    unanswered = ~seen if lookups.caustic is None else ~seen & ~lookups.caustic
    lanes = dr.compress(unanswered)
    if dr.width(lanes):
        traced = _trace_unanswered(scene, source, lookups.select(lanes),
                                   dr.gather(mi.UInt64, states, lanes), sample_delta)
        dr.scatter(reflected, traced, lanes)
    return reflected


def _trace_unanswered(scene: mi.Scene, source: GatherSource, lookups: "GatherLookup", states: mi.UInt64,
                      sample_delta: bool) -> mi.Spectrum:
    """For lookups that no photon answers: the irradiance the photon would have held,
    from one cosine-distributed ray (E = π L) that counts the emission it meets first
    (a photon's irradiance holds the direct light of area lights and skies; a delta
    light's the walk sampled at the lookup already) and reads the photons where it
    lands, near or far (:data:`TRACED_NEAR_HITS`). Measured in docs/tuning.md
    (``TRACE_UNANSWERED``, ``TRACED_NEAR_HITS``)."""
    lanes = dr.width(lookups.p)
    rng = mi.PCG32(size=lanes, initstate=states, initseq=dr.arange(mi.UInt64, lanes))
    local = mi.warp.square_to_cosine_hemisphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    origin = dr.zeros(mi.Interaction3f, lanes)
    origin.p, origin.n = lookups.p, lookups.n
    if mi.is_spectral:
        origin.wavelengths = lookups.wavelengths
    ray = origin.spawn_ray(mi.Frame3f(lookups.n).to_world(local))
    walk = GatherWalk.start(ray, rng, True)
    walk.count_emission = dr.full(mi.Bool, True, lanes)
    if not TRACED_NEAR_HITS:
        source = replace(source, near_hit_distance=0.0)
    walk = _walk_on(scene, source, walk, sample_delta, emission=True)
    return finite(lookups.weight * walk.radiance * math.pi, True)


#: A gather ray's vertices: delta/glossy bounces, near-hit bounces and the last hit.
GATHER_VERTICES = GATHER_SPECULAR_BOUNCES + NEAR_HIT_BOUNCES + 1


def trace_gather_rays(scene: mi.Scene, source: GatherSource, ray: mi.Ray3f,
                      rng: mi.PCG32, active: mi.Bool, sample_delta: bool = False):
    """Radiance arriving along ``ray`` from the first diffuse surface it meets (through
    delta/glossy bounces), and the first hit distance. Emission met directly is not
    counted (the renderer samples direct light itself); emission met after a delta or
    glossy bounce is counted only when ``source.caustics_by_gathering``.

    With ``sample_delta``, the direct light of delta lights (a sun, a spot) at a diffuse
    hit comes from one sample of them (a shadow ray: exact up to visibility), and the
    photons give the rest: the photons' estimate of a sunlit patch blurs its sharp
    edge over a lookup radius and shares one error over the whole patch.

    A diffuse hit closer than ``source.near_hit_distance`` to where its segment started
    (a corner, a contact, a narrow gap: :data:`NEAR_HIT_LOOKUPS`) reads no photon: its
    light is one emitter sample (all emitters, all lobes, a shadow ray) and the
    continuation samples its whole BSDF, up to :data:`NEAR_HIT_BOUNCES` times. Emission
    the continuation meets is then counted, weighted against the emitter sample by MIS
    where the bounce sampled a non-delta lobe; light reaching the bounced point through
    delta/glossy bounces is counted as at the record: by gathering where there is no
    caustic map, else from the caustic map's irradiance precomputed at the nearest
    photon (``irradiance_caustic``). (Found by the continuation instead, a caustic
    under a glass sphere came out 0.4 % dark over a Cornell box: one cosine sample
    rarely finds a light through a sphere, and the specular-bounce budget ran out on
    the way. Estimated from the caustic map at each near hit, it cost 0.6 s of a
    textured room's 1.6 s cache stage, whose rough-plastic floor spreads caustic
    photons everywhere.)

    One symbolic loop, photon searches inside it (for camera paths);
    :func:`gather_radiance` is the same for evaluated batches of rays.

    Returns ``(radiance, distance)``; ``distance`` is +inf for rays that leave the scene.
    """
    walk = _walk_on(scene, source, GatherWalk.start(ray, rng, active), sample_delta)
    return walk.radiance, walk.distance


def _walk_on(scene: mi.Scene, source: GatherSource, walk: GatherWalk, sample_delta: bool,
             emission: bool = False) -> GatherWalk:
    """``walk`` to its end in one symbolic loop, each vertex's photon lookups answered
    in place. (``dr.while_loop`` with the state named: ``@dr.syntax`` traces a loop's
    body twice to find its state, and this body holds five nested searches.)"""
    near_distance = opaque_float(source.near_hit_distance)

    def vertex(walk):
        walk, asked = _gather_vertex(scene, source, walk, sample_delta, near_distance, emission)
        irradiance = source.irradiance_at(scene, asked.p, asked.n, asked.mask,
                                          without_delta=sample_delta, caustic=asked.caustic)
        walk.radiance = walk.radiance + asked.reflected(irradiance)
        return (walk,)

    return dr.while_loop((walk,), lambda walk: walk.active, vertex, label="gather_ray",
                         max_iterations=GATHER_VERTICES)[0]


def _walk_on_deferred(scene: mi.Scene, source: GatherSource, walk: GatherWalk, sample_delta: bool,
                      near_distance: mi.Float):
    """``walk`` to its end in one symbolic loop, each vertex's photon lookups written
    to slot ``(ray, vertex)`` of a :class:`GatherLookup` of ``GATHER_VERTICES`` slots
    per ray, to be answered after the loop. Returns ``(walk, lookups)``."""
    rays = dr.width(walk.active)
    slots = rays * GATHER_VERTICES
    deferred = GatherLookup(mask=dr.zeros(mi.Bool, slots), p=dr.zeros(mi.Point3f, slots),
                            n=dr.zeros(mi.Vector3f, slots), weight=dr.zeros(mi.Spectrum, slots),
                            caustic=None if source.photons.irradiance_caustic is None else
                            dr.zeros(mi.Bool, slots),
                            wavelengths=dr.zeros(mi.Spectrum, slots) if mi.is_spectral else None)
    dr.make_opaque(deferred.mask, deferred.p, deferred.n, deferred.weight, deferred.caustic,
                   deferred.wavelengths)
    first_slot = dr.arange(mi.UInt32, rays) * GATHER_VERTICES

    def vertex(walk):
        slot = first_slot + dr.minimum(walk.bounce, GATHER_VERTICES - 1)
        walk, asked = _gather_vertex(scene, source, walk, sample_delta, near_distance)
        deferred.write(asked, slot)
        return (walk,)

    walk = dr.while_loop((walk,), lambda walk: walk.active, vertex, label="gather_ray_deferred",
                         max_iterations=GATHER_VERTICES)[0]
    return walk, deferred


def gather_radiance(scene: mi.Scene, source: GatherSource, ray: mi.Ray3f, rng: mi.PCG32,
                    sample_delta: bool = False):
    """:func:`trace_gather_rays` for an evaluated batch of rays (the records' gathers),
    with the same rays, random numbers and photons, up to float rounding: the photon
    lookups are answered after the rays' walk, all together
    (:meth:`GatherSource.irradiance_of`: each wider search step only for the lookups
    the narrower ones left without a photon). In one kernel a SIMD packet paid for its
    slowest lane's search at every vertex. The first vertex of every ray is evaluated
    on its own, and the rays that go on (glossy and delta bounces, near hits: 7 % in
    a Cornell box, 30-60 % in a room with a glossy floor) finish in one symbolic loop
    over those rays only, writing their lookups to slots of their own. (Every vertex
    evaluated on its own cost more than it saved: each is a few ms of tracing and
    launches, for a few hundred rays.) Without :data:`TRACE_UNANSWERED`, batches under
    :data:`SPLIT_GATHER_MIN_RAYS` rays run as one loop.

    Returns ``(radiance, distance)``."""
    if dr.width(ray.o) < SPLIT_GATHER_MIN_RAYS and not TRACE_UNANSWERED:
        # (One loop answers its lookups in place: it cannot trace the unanswered ones.)
        return trace_gather_rays(scene, source, ray, rng, mi.Bool(True), sample_delta)
    near_distance = opaque_float(source.near_hit_distance)
    walk = GatherWalk.start(ray, rng, True)
    walk, asked = _gather_vertex(scene, source, walk, sample_delta, near_distance)
    dr.eval(walk, asked.mask, asked.p, asked.n, asked.weight, asked.caustic, asked.wavelengths)
    radiance = mi.Spectrum(walk.radiance)
    first = asked.select(dr.compress(asked.mask))  # at most one per ray
    going = dr.compress(walk.active)
    later = None
    if dr.width(going):
        rest, deferred = _walk_on_deferred(scene, source, dr.gather(GatherWalk, walk, going),
                                           sample_delta, near_distance)
        dr.eval(rest.radiance, deferred.mask, deferred.p, deferred.n, deferred.weight, deferred.caustic,
                deferred.wavelengths)
        dr.scatter(radiance, rest.radiance, going)
        later = deferred.select(dr.compress(deferred.mask))
    parts = [part for part in (first, later) if part is not None and dr.width(part.lanes)]
    if not parts:
        return radiance, walk.distance
    # Each lookup's random stream for a traced answer: its ray's, after the walk.
    states = [dr.gather(mi.UInt64, walk.rng.state, first.lanes) if part is first else
              dr.gather(mi.UInt64, rest.rng.state, later.lanes // GATHER_VERTICES) for part in parts]
    reflected = _answer_lookups(scene, source, GatherLookup.joined(parts), concat(states, mi.UInt64),
                                sample_delta)
    dr.eval(reflected)
    # The sums below add each ray's lookups in the order of its vertices, whatever the
    # order of the threads. (Atomic adds, each ray's once per sum: Dr.Jit's default on
    # the CPU reduces into a copy per thread and writes the rays' count into the
    # kernel, which was compiled anew for every record count: _jit.scatter_min.)
    done = dr.width(first.lanes)
    if done:
        dr.scatter_add(radiance, dr.gather(mi.Spectrum, reflected, dr.arange(mi.UInt32, done)), first.lanes,
                       mode=dr.ReduceMode.Direct)
    if later is not None and dr.width(later.lanes):
        count = dr.width(later.lanes)
        part = dr.gather(mi.Spectrum, reflected, dr.arange(mi.UInt32, count) + opaque_u32(done))
        by_slot = dr.zeros(mi.Spectrum, dr.width(going) * GATHER_VERTICES)
        dr.scatter(by_slot, part, later.lanes)
        dr.eval(by_slot)
        first_slot = dr.arange(mi.UInt32, dr.width(going)) * GATHER_VERTICES
        total = dr.zeros(mi.Spectrum, dr.width(going))
        for vertex in range(GATHER_VERTICES):
            total += dr.gather(mi.Spectrum, by_slot, first_slot + vertex)
        dr.scatter_add(radiance, total, going, mode=dr.ReduceMode.Direct)
    return radiance, walk.distance
