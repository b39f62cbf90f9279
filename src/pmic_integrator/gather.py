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
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .bsdfs import diffuse_response, lobes_separable, non_diffuse_context  # noqa: F401
from ._jit import opaque_float, segment_blocked, shading_normal_on_side
from .emission import sample_emitter_direction
from .hashgrid import PointGrid
from .irradiance import nearest_photon
from .photons import PhotonMap

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
#: ...and only below this throughput: a rough metal passes most of the light, so
#: roulette there saves little, and it made the records that see the lamp room's
#: shades noisier (its relMSE 0.211 -> 0.224).
GATHER_ROULETTE_BELOW = 0.5

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
        return GatherSource(coarse_photons, coarse, reach,
                            near_photons, near.sorted_in_place(),
                            mid_photons=photons.select(mid.order), mid_grid=mid.sorted_in_place(),
                            far_photons=far_photons, far_grid=far_grid,
                            wide_photons=wide_photons, wide_grid=wide_grid)

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

    def irradiance_at(self, scene: mi.Scene, si: mi.SurfaceInteraction3f, n: mi.Vector3f,
                      active, without_delta: bool = False, caustic=None) -> mi.Color3f:
        """Precomputed irradiance of the nearest photon on the surface at ``si`` that
        ``si`` can see (0 where there is none); with ``without_delta``, without the
        direct light of delta lights (the caller samples them itself). Lanes in the
        mask ``caustic`` read its caustic irradiance instead (``irradiance_caustic``):
        one search serves both kinds of lane."""
        if self.photons.count == 0:
            return dr.zeros(mi.Color3f, dr.width(si.p))
        active = mi.Bool(active)
        found = dr.zeros(mi.Bool, dr.width(si.p))
        result = dr.zeros(mi.Color3f, dr.width(si.p))
        position = dr.zeros(mi.Point3f, dr.width(si.p))
        for photons, grid, reach, octant in self._steps():
            retry = active & ~found
            index, hit = nearest_photon(photons, grid, si.p, n, reach, retry, octant=octant)
            hit &= retry
            values = photons.irradiance_nodelta if without_delta else photons.irradiance
            value = dr.gather(mi.Color3f, values, index, hit if caustic is None else hit & ~caustic)
            if caustic is not None:
                value = dr.select(caustic, dr.gather(mi.Color3f, photons.irradiance_caustic, index,
                                                     hit & caustic), value)
            result = dr.select(hit, value, result)
            position = dr.select(hit, dr.gather(mi.Point3f, photons.position, index, hit), position)
            found |= hit
        # The nearest photon may lie across a thin wall (same plane, same normal): the
        # floor on the lit side of a 2 mm partition lit the dark side. One shadow ray
        # between the two points, both lifted off the surface, tells them apart.
        lift = n * opaque_float(VISIBILITY_LIFT * self.radius / self.SEARCH_REACH)
        blocked = segment_blocked(scene, si.p + lift, position + lift, found)
        return dr.select(found & ~blocked, result, 0.0)


@dr.syntax
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
    the continuation meets is then counted unless the bounce sampled a non-delta lobe
    (the emitter sample holds that light); light reaching the bounced point through
    delta/glossy bounces is counted as at the record: by gathering where there is no
    caustic map, else from the caustic map's irradiance precomputed at the nearest
    photon (``irradiance_caustic``). (Found by the continuation instead, a caustic
    under a glass sphere came out 0.4 % dark over a Cornell box: one cosine sample
    rarely finds a light through a sphere, and the specular-bounce budget ran out on
    the way. Estimated from the caustic map at each near hit, it cost 0.6 s of a
    textured room's 1.6 s cache stage, whose rough-plastic floor spreads caustic
    photons everywhere.)

    Returns ``(radiance, distance)``; ``distance`` is +inf for rays that leave the scene.
    """
    ray = mi.Ray3f(ray)
    active = mi.Bool(active)
    radiance = dr.zeros(mi.Color3f, dr.width(ray.o))
    throughput = dr.full(mi.Color3f, 1.0, dr.width(ray.o))
    distance = dr.full(mi.Float, dr.inf, dr.width(ray.o))
    bounce = dr.zeros(mi.UInt32, dr.width(ray.o))
    ctx_specular = non_diffuse_context()
    ctx_all = mi.BSDFContext()
    caustics = source.caustics_by_gathering
    near_on = source.near_hit_distance > 0
    near_distance = opaque_float(source.near_hit_distance)
    near_bounces = dr.zeros(mi.UInt32, dr.width(ray.o))
    # Emission met next is counted after a delta/glossy bounce without a caustic map,
    # and right after a near bounce's delta sample (its emitter sample holds the rest).
    count_emission = dr.zeros(mi.Bool, dr.width(ray.o))
    crossed = dr.zeros(mi.Bool, dr.width(ray.o))  # went through an inseparable BSDF
    while dr.hint(active, label="gather_ray",
                  max_iterations=GATHER_SPECULAR_BOUNCES + NEAR_HIT_BOUNCES + 1):
        si = scene.ray_intersect(ray, active)
        if dr.hint(caustics | near_on | source.crossing, mode="scalar"):
            # Light reaching the record through delta/glossy bounces (no caustic map)
            # or through an inseparable BSDF, or reaching a near bounce's point past
            # its emitter sample.
            seen = active & count_emission
            emitted = throughput * si.emitter(scene, seen).eval(si, seen)
            radiance += dr.select(seen & dr.all(dr.isfinite(emitted)), emitted, 0.0)
        active &= si.is_valid()
        distance = dr.select(active & (bounce == 0), si.t, distance)
        bsdf = si.bsdf(ray)
        flags = bsdf.flags()
        # Normal on the side the ray arrives from, to match photon normals.
        n = mi.Vector3f(si.n)
        n = dr.select(dr.dot(n, ray.d) > 0, -n, n)
        diffuse = active & mi.has_flag(flags, mi.BSDFFlags.Diffuse)
        response = diffuse_response(bsdf, si, diffuse)
        # No lookup where nothing is reflected (the back of a one-sided surface, a
        # black texel): the searches there are the slowest (no photon is near).
        lit = diffuse & (dr.max(response) > 0)
        near = mi.Bool(False)
        # Lanes that read a photon: its irradiance, or at a near hit its caustics only.
        lookup, caustic_lanes = mi.Bool(lit), None
        if dr.hint(near_on, mode="scalar"):
            near = lit & (si.t < near_distance) & (near_bounces < NEAR_HIT_BOUNCES)
            lit &= ~near
            u_em = mi.Point2f(rng.next_float32(), rng.next_float32())
            ds_near, em_near = sample_emitter_direction(scene, si, u_em, True, near)
            f_near = bsdf.eval(ctx_all, si, si.to_local(ds_near.d), near & (ds_near.pdf > 0))
            lit_near = throughput * f_near * em_near
            radiance += dr.select(near & (ds_near.pdf > 0) & dr.all(dr.isfinite(lit_near)), lit_near, 0.0)
            if dr.hint(source.photons.irradiance_caustic is not None, mode="scalar"):
                caustic_lanes = near
            else:
                lookup = lit
        irradiance = source.irradiance_at(scene, si, n, lookup, without_delta=sample_delta,
                                          caustic=caustic_lanes)
        if dr.hint(sample_delta, mode="scalar"):
            u = mi.Point2f(rng.next_float32(), rng.next_float32())
            ds, em_weight = sample_emitter_direction(scene, si, u, True, lit, delta=True)
            cos_n = dr.maximum(dr.dot(ds.d, shading_normal_on_side(si, n)), 0.0)
            direct = mi.Color3f(em_weight) * cos_n
            irradiance += dr.select(lit & (ds.pdf > 0) & dr.all(dr.isfinite(direct)), direct, 0.0)
        reflected = throughput * response * irradiance
        radiance += dr.select(diffuse & dr.all(dr.isfinite(reflected)), reflected, 0.0)
        rest = active & ~near & (mi.has_flag(flags, mi.BSDFFlags.Delta) | mi.has_flag(flags, mi.BSDFFlags.Glossy))
        rest &= bounce < GATHER_SPECULAR_BOUNCES
        # A BSDF that ignores lobe masks (principled) gave its reflection above as a
        # diffuse response; what it transmits (glass, a thin leaf) comes from the other
        # side, which that response cannot see: a sample of the whole BSDF goes on
        # where it crosses the surface, and ends where it reflects.
        separable = lobes_separable(bsdf, si, rest & diffuse) if source.inseparable else mi.Bool(True)
        through = rest & diffuse & ~separable
        rest &= separable
        u1 = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        bs, weight = bsdf.sample(ctx_specular, si, u1, u2, rest)
        if dr.hint(source.crossing, mode="scalar"):
            bs_through, weight_through = bsdf.sample(ctx_all, si, u1, u2, through)
            through &= mi.Frame3f.cos_theta(si.wi) * mi.Frame3f.cos_theta(bs_through.wo) < 0
            bs[through] = bs_through
            weight[through] = weight_through
            # Photons through such a surface are global-map photons (not caustic ones),
            # so no caustic map holds the emitters seen through it: count them.
            crossed |= through
            rest |= through
        if dr.hint(near_on, mode="scalar"):
            bs_near, weight_near = bsdf.sample(ctx_all, si, u1, u2, near)
            bs[near] = bs_near
            weight[near] = weight_near
            count_emission = dr.select(near, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
                                       mi.Bool(caustics) | crossed)
            near_bounces[near] = near_bounces + 1
        else:
            count_emission = mi.Bool(caustics) | crossed
        throughput *= weight
        active = (rest | near) & (bs.pdf > 0) & (dr.max(throughput) > 0) & dr.all(dr.isfinite(throughput))
        if dr.hint(GATHER_ROULETTE, mode="scalar"):
            roulette = active & rest & ~count_emission & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Glossy)
            survive = dr.minimum(dr.max(throughput), 1.0)
            roulette &= survive < GATHER_ROULETTE_BELOW
            throughput[roulette] = throughput * dr.rcp(survive)
            active &= ~roulette | (rng.next_float32(roulette) < survive)
        ray = si.spawn_ray(si.to_world(bs.wo))
        bounce += 1
    return radiance, distance
