"""Stage 1: trace photons from the emitters and store them (Jensen 1996).

Photons are traced as a wavefront: one Dr.Jit kernel per bounce over all live paths,
with dead paths compacted away between bounces. Emission runs in batches until the
requested number of photons is *stored* (or a bound on emitted paths is hit), and the
last batch is cut at a whole path so that the stored photons stay an unbiased sample of
exactly ``paths_emitted`` light paths.

Two maps are made:

* the **global map**: a photon at every hit on a surface with a diffuse lobe, the first
  hit included (it becomes the precomputed irradiance that final-gather rays read);
* the **caustic map**: photons of paths light → one or more specular or glossy bounces
  → a surface with a diffuse lobe (L S+ D). Caustic passes stop a path at its first
  non-specular bounce, since it can no longer produce a caustic photon. The global
  pass's own L S+ D photons join it (:func:`merge_caustic_photons`).
"""
from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi

from ._jit import (ONE_MINUS_EPSILON, concat, interleave, opaque_float, opaque_u32, rng as make_rng, scatter_count,
                   shading_normal_on_side)
from .bsdfs import dark_side, lobe_flags, lobes_separable, sample_lobes_apart, scene_diffuse_free
from .cases import lobes_of
from .emission import choose_emitter, emission_bounds, sample_emitter_rays
from .streams import photon_batch_seed
from .spectra import to_rgb

log = logging.getLogger("pmic")

GLOBAL = "global"
CAUSTIC = "caustic"

# --- Internal tuning constants -------------------------------------------------------
#: First batch of emitted paths; later batches are sized from the measured yield.
FIRST_BATCH_PATHS = 1 << 16
#: Largest batch: bounds the wavefront's memory (~100 bytes of state per path).
MAX_BATCH_PATHS = 1 << 22
#: A pass that must store ``give_up_below`` photons (:func:`trace_photons`) stops once
#: its count so far plus this many Poisson deviations, carried on to its path bound,
#: stays under that: a map that would have reached it is given up with a chance
#: under 0.2 %.
GIVE_UP_SIGMAS = 3.0
#: A batch's paths go on in one symbolic loop once no more than this many are left
#: (:func:`_trace_tail`), for as many bounces as fill this many photon slots (a slot
#: per path and bounce, 39 bytes: 82 MB; 32 bounces for 65 536 paths, the rest of
#: them for 2 000). Measured in docs/tuning.md (``TAIL_LOOP_PATHS``).
TAIL_LOOP_PATHS = 1 << 16
TAIL_LOOP_SLOTS = 1 << 21
#: Photon paths are cut at this many bounces even when max_depth is unbounded; by then
#: Russian roulette has ended all but ~0.95^64 ≈ 4 % of paths in a white furnace.
MAX_PHOTON_BOUNCES = 64
#: Russian roulette keeps a photon with probability min(albedo of the bounce, this):
#: photons keep roughly equal power, which is what density estimation wants.
MAX_SURVIVAL = 0.95
#: Photon maps smaller than this fraction of the request trigger a warning.
LOW_YIELD_FRACTION = 0.5
#: Emission guiding (:class:`EmissionGuide`; global passes with no caustic pass to
#: come, see ``guide_emission``): a pass whose first batch, lit by an environment,
#: stores fewer photons than this per emitted path (a room lit through a window: 0.01,
#: 88 paths per photon, most of them meeting the outside walls or shot where the sun
#: cannot enter) draws its later emission samples where the first batch's paths
#: stored photons. Open scenes store 0.5-2 per path and are left alone.
EMISSION_GUIDE_BELOW = 0.1
#: Cells per side of each of the two sample squares guided (the emission origin's and
#: the direction's): 256 cells, ~256 first-batch paths each.
EMISSION_GUIDE_CELLS = 16
#: Share of each guided square's density kept uniform (defensive mixture: a cell where
#: the first batch stored nothing is still sampled, its photons at most 1/0.5 = 2x
#: the power per square, 4x for both, where they would otherwise be shot and lost).
EMISSION_GUIDE_UNIFORM = 0.5
#: ...and no cell more than this many times the uniform density before the mixture
#: (so at most 2.5x after it): photons' powers stay within 5x of one another per
#: square. Unbounded, they spread over a factor of ~100 per square, and the
#: density estimates of a window-lit room with a glass sphere (the bundled
#: interior_window) came out noisier (relMSE 3.1e-3 -> 3.3e-3).
EMISSION_GUIDE_CAP = 4.0
#: Bound on each cosine ratio of the shading-normal correction (see
#: :func:`shading_normal_factors`): the ratio grows without bound at grazing geometric
#: angles, and its variance diverges (logarithmically). 100 (a geometric angle of
#: 89.4°) changed no mean measured: a floor whose normals lean 50° towards a grazing
#: lamp was 3 % dark with 10, and the lamp room within 0.03 %.
MAX_SHADING_RATIO = 100.0


@dataclass
class PhotonMap:
    """Photons stored at surface hits, one entry per photon (structure of arrays)."""

    position: mi.Point3f  #: where the photon hit the surface
    normal: mi.Vector3f  #: geometric normal, flipped to the side the photon came from
    #: flux [W] over ``paths_emitted``, times the arrival factor of
    #: :func:`shading_normal_factors` (the irradiance the BSDF sees)
    power: mi.Color3f
    depth: mi.UInt32  #: surface interactions since the emitter (1 = direct light)
    specular_path: mi.Bool  #: every earlier bounce was delta/glossy (L S* D: direct or caustic)
    path: mi.UInt32 = None  #: index of the light path that stored the photon, in [0, paths_emitted)
    paths_emitted: int = 0  #: light paths traced to make this map
    irradiance: mi.Color3f = field(default=None)  #: stage 2 result, None until computed
    #: stage 2: ``irradiance`` without the direct light of delta lights (what gather
    #: rays and camera paths sample themselves); None: the scene has no delta light
    irradiance_nodelta: mi.Color3f = field(default=None)
    #: the photon's light path started at a delta light (point, spot, directional)
    delta_light: mi.Bool = field(default=None)
    #: stage 2: the caustic map's irradiance at the photon (what a gather ray that
    #: bounces on at a near hit reads for its caustics); None: no caustic map
    irradiance_caustic: mi.Color3f = field(default=None)
    #: stage 1 only (None once the maps are merged, :func:`merge_caustic_photons`): no
    #: bounce of the photon's path sampled lobes apart (:func:`sample_lobes_apart`), so
    #: the global and caustic passes sampled it alike
    shared_path: mi.Bool = field(default=None)
    #: What density estimates read of each photon, photon by photon (:meth:`pack`);
    #: derived (rebuilt, not stored in cache files), None until packed.
    packed: mi.Float = field(default=None, metadata={"derived": True})

    #: Floats per photon in ``packed``: normal, power, depth and flags (specular_path,
    #: delta_light) as the bits of a float.
    PACKED_WIDTH = 8

    def pack(self) -> "PhotonMap":
        """Lay out the normal, power, depth and flags photon by photon, so that a
        density estimate reads a candidate with one packet load (:data:`PACKED_WIDTH`)
        instead of eight gathers. Call it once the photons are final (sorted into their
        grid: :func:`~pmic_integrator.irradiance.sort_into_grid`). Returns ``self``."""
        if self.count == 0:
            return self
        flags = mi.UInt32(dr.select(self.specular_path, 1, 0))
        if self.delta_light is not None:
            flags |= mi.UInt32(dr.select(self.delta_light, 2, 0))
        columns = [self.normal.x, self.normal.y, self.normal.z, *self.power, mi.UInt32(self.depth), flags]
        self.packed = interleave(columns, self.PACKED_WIDTH)
        return self

    @property
    def count(self) -> int:
        return dr.width(self.depth) if self.depth is not None else 0

    @property
    def caustic(self) -> mi.Bool:
        """Per photon: a caustic photon (L S+ D: light, then delta or glossy bounces only,
        then this diffuse surface)."""
        return self.specular_path & (self.depth >= 2)

    def joined(self, other: "PhotonMap") -> "PhotonMap":
        """These photons, then ``other``'s (each field where both have it; this map's
        ``paths_emitted``)."""
        def both(name, dtype):
            x, y = getattr(self, name), getattr(other, name)
            return None if x is None or y is None else concat([x, y], dtype)

        return PhotonMap(both("position", mi.Point3f), both("normal", mi.Vector3f), both("power", mi.Color3f),
                         both("depth", mi.UInt32), both("specular_path", mi.Bool), both("path", mi.UInt32),
                         self.paths_emitted, irradiance=both("irradiance", mi.Color3f),
                         irradiance_nodelta=both("irradiance_nodelta", mi.Color3f),
                         delta_light=both("delta_light", mi.Bool),
                         irradiance_caustic=both("irradiance_caustic", mi.Color3f),
                         shared_path=both("shared_path", mi.Bool))

    def bounced_share(self) -> float:
        """The share of the photons' power (luminance) that bounced off a surface
        before landing (depth 2 and more): how much of a scene's light is indirect
        (0 for an empty map)."""
        if self.count == 0:
            return 0.0
        power = mi.luminance(self.power)
        total = float(dr.sum(power)[0])
        bounced = float(dr.sum(dr.select(self.depth >= 2, power, 0.0))[0])
        return bounced / total if total > 0 else 0.0

    @staticmethod
    def empty() -> "PhotonMap":
        return PhotonMap(mi.Point3f(), mi.Vector3f(), mi.Color3f(), mi.UInt32(), mi.Bool(), mi.UInt32(), 0)

    def select(self, index: mi.UInt32) -> "PhotonMap":
        """The photons at ``index`` (same ``paths_emitted``)."""
        irr = None if self.irradiance is None else dr.gather(mi.Color3f, self.irradiance, index)
        nodelta = None if self.irradiance_nodelta is None else \
            dr.gather(mi.Color3f, self.irradiance_nodelta, index)
        delta = None if self.delta_light is None else dr.gather(mi.Bool, self.delta_light, index)
        caustic = None if self.irradiance_caustic is None else \
            dr.gather(mi.Color3f, self.irradiance_caustic, index)
        shared = None if self.shared_path is None else dr.gather(mi.Bool, self.shared_path, index)
        out = PhotonMap(dr.gather(mi.Point3f, self.position, index),
                        dr.gather(mi.Vector3f, self.normal, index),
                        dr.gather(mi.Color3f, self.power, index),
                        dr.gather(mi.UInt32, self.depth, index),
                        dr.gather(mi.Bool, self.specular_path, index),
                        dr.gather(mi.UInt32, self.path, index),
                        self.paths_emitted, irr, nodelta, delta, caustic, shared)
        # Evaluated now: left lazy, every kernel reading the map would redo the gathers
        # (random memory access) instead of reading the reordered arrays.
        dr.eval(out.position, out.normal, out.power, out.depth, out.specular_path, out.path,
                out.irradiance, out.irradiance_nodelta, out.delta_light, out.irradiance_caustic,
                out.shared_path)
        return out

    def split_by_path(self):
        """Two independent halves: photons of even light paths and of odd ones, each
        with ``paths_emitted`` set to its own number of paths (powers unchanged: scale
        an estimate from a half by ``paths_emitted / half.paths_emitted``)."""
        odd = (self.path & 1) == 1
        halves = []
        for want_odd, paths in ((False, self.paths_emitted - self.paths_emitted // 2),
                                (True, self.paths_emitted // 2)):
            keep = dr.compress(odd if want_odd else ~odd)
            half = self.select(keep) if dr.width(keep) else PhotonMap.empty()
            half.paths_emitted = paths
            halves.append(half)
        return halves[0], halves[1]

    def nbytes(self) -> int:
        """Bytes held per the arrays above (positions, normals, powers, depths, E, flags)."""
        per = 4 * (3 + 3 + 3 + 1 + 1 + (3 if self.irradiance is not None else 0)
                   + (3 if self.irradiance_nodelta is not None else 0)
                   + (3 if self.irradiance_caustic is not None else 0)) + 1 \
            + (1 if self.delta_light is not None else 0)
        packed = 4 * dr.width(self.packed) if self.packed is not None else 0
        return per * self.count + packed


def shading_normal_factors(si: mi.SurfaceInteraction3f, n: mi.Vector3f, to_light: mi.Vector3f,
                           wo_local: mi.Vector3f | None = None):
    """Factors that make photons agree with ``path`` on meshes with shading normals.

    Mitsuba's BSDFs weight light by the cosine to the *shading* normal, while photon
    flux lands on the *geometric* surface. Light arriving from ``to_light`` (world
    space; ``n`` the geometric normal on its side) is therefore reflected
    cos_s/cos_g times what its flux says: ``arrival`` = |ω·n_s| / |ω·n_g| (0 where the
    shading hemisphere has ω below it, as the BSDF has). Stored photons carry it, so
    that density estimates give the irradiance the BSDF sees. The lamp shades of
    Veach's lamp room (smooth normals on a coarse cone, lit at grazing angles)
    reflect 1.67x what their flux says: without it that room was 4 % dark.

    With ``wo_local`` (a sampled scattering direction in the shading frame), also the
    factor a photon's flux takes on scattering, Veach's adjoint-BSDF correction
    (thesis, sec. 5.3): ``arrival`` × |ωₒ·n_g| / |ωₒ·n_s|. Both are exactly 1 where the
    shading normal is the geometric one (flat shapes, spheres, meshes without vertex
    normals: :func:`shading_normal_on_side`), so those scenes are unchanged.
    """
    shading_n = shading_normal_on_side(si, n)
    cos_g_in = dr.abs(dr.dot(n, to_light))
    arrival = dr.minimum(dr.maximum(dr.dot(shading_n, to_light), 0.0) / dr.maximum(cos_g_in, 1e-8),
                         MAX_SHADING_RATIO)
    flat = dr.all(shading_n == n)
    arrival = dr.select(flat, 1.0, arrival)
    if wo_local is None:
        return arrival
    cos_g_out = dr.abs(dr.dot(n, si.to_world(wo_local)))
    cos_s_out = dr.abs(mi.Frame3f.cos_theta(wo_local))
    leaving = dr.minimum(cos_g_out / dr.maximum(cos_s_out, 1e-8), MAX_SHADING_RATIO)
    return arrival, arrival * dr.select(flat, 1.0, leaving)


@dataclass
class EmissionGuide:
    """Where a pass's emitted paths store photons, learned from its first batch: a
    piecewise-constant density over each of the two squares that emission samples
    (``origin``: a ray's origin, ``direction``: its direction, as
    :func:`~pmic_integrator.emission.sample_emitter_rays` uses them), mixed with the
    uniform density (:data:`EMISSION_GUIDE_UNIFORM`). A path drawn from it carries
    its flux over the two densities: unbiased wherever the first batch stored nothing.

    In a room lit by a sky through a window most emitted paths meet the room's outside
    (no photon is stored on the dark side of a one-sided wall) or are shot from where
    a sun cannot enter: 17.5M paths for 200k photons, 6-8 s of a 9-13 s render at
    160x120."""

    origin: mi.DiscreteDistribution
    direction: mi.DiscreteDistribution

    @staticmethod
    def learn(u_origin: mi.Point2f, u_direction: mi.Point2f, environment: mi.Bool,
              stored: mi.UInt32) -> "EmissionGuide":
        """From uniformly drawn samples, whether an environment emitted each path, and
        the photons each path stored."""
        stored = dr.select(environment, mi.Float(stored), 0.0)

        def density(u):
            cells = EMISSION_GUIDE_CELLS
            index = EmissionGuide._cell(u)
            per_cell = dr.zeros(mi.Float, cells * cells)
            dr.scatter_reduce(dr.ReduceOp.Add, per_cell, stored, index)
            # Density over the uniform one, at most EMISSION_GUIDE_CAP.
            relative = per_cell * (cells * cells) / dr.maximum(dr.sum(per_cell), 1e-30)
            relative = dr.minimum(relative, EMISSION_GUIDE_CAP)
            return mi.DiscreteDistribution(EMISSION_GUIDE_UNIFORM + (1.0 - EMISSION_GUIDE_UNIFORM) * relative)
        return EmissionGuide(density(u_origin), density(u_direction))

    @staticmethod
    def _cell(u: mi.Point2f) -> mi.UInt32:
        cells = EMISSION_GUIDE_CELLS
        i = mi.UInt32(dr.clip(u.x * cells, 0, cells - 1))
        j = mi.UInt32(dr.clip(u.y * cells, 0, cells - 1))
        return j * cells + i

    @staticmethod
    def _warp(distribution: mi.DiscreteDistribution, u: mi.Point2f):
        """(sample, its density on the square)."""
        cells = EMISSION_GUIDE_CELLS
        index, reused, pmf = distribution.sample_reuse_pmf(u.x)
        i, j = index % cells, index // cells
        x = dr.minimum((mi.Float(i) + reused) / cells, ONE_MINUS_EPSILON)
        y = dr.minimum((mi.Float(j) + u.y) / cells, ONE_MINUS_EPSILON)
        return mi.Point2f(x, y), pmf * (cells * cells)

    def warp(self, u_origin: mi.Point2f, u_direction: mi.Point2f):
        """``(u_origin', u_direction', 1 / density)`` of uniform samples drawn anew."""
        origin, p_origin = self._warp(self.origin, u_origin)
        direction, p_direction = self._warp(self.direction, u_direction)
        return origin, direction, dr.rcp(dr.maximum(p_origin * p_direction, 1e-30))


def _emit_batch(scene: mi.Scene, first_path: int, n_paths: int, seed: int, bounds: tuple,
                guide: EmissionGuide | None, samples: list | None):
    """``(rng, path_id, ray, flux, emitter)`` of ``n_paths`` light paths leaving the
    emitters (see :func:`_trace_batch`)."""
    rng = make_rng(n_paths, seed, stream=first_path)
    path_id = dr.arange(mi.UInt32, n_paths) + opaque_u32(first_path)
    u_choice = rng.next_float32()
    u_origin = mi.Point2f(rng.next_float32(), rng.next_float32())
    u_direction = mi.Point2f(rng.next_float32(), rng.next_float32())
    guided_weight = None
    if guide is not None or samples is not None:
        # Environment paths only: a sun's or a lamp's do not miss a window the same way,
        # and a density they do not need only adds noise to their photons' power (a
        # directional light ignores the direction square: its weight would be noise
        # alone).
        chosen = dr.gather(mi.EmitterPtr, scene.emitters_dr(), choose_emitter(scene, u_choice)[0])
        environment = mi.has_flag(chosen.flags(), mi.EmitterFlags.Infinite)
    if guide is not None:
        origin, direction, weight = guide.warp(u_origin, u_direction)
        u_origin = dr.select(environment, origin, u_origin)
        u_direction = dr.select(environment, direction, u_direction)
        guided_weight = dr.select(environment, weight, 1.0)
    if samples is not None:
        samples.extend([u_origin, u_direction, environment])
    # Not scene.sample_emitter_ray: Mitsuba 3.9 places a rotated envmap's ray origins
    # on a disk tilted against the rays (too bright by up to 1.8x); see emission.py.
    ray, flux, emitter = sample_emitter_rays(scene, mi.Float(0.0), u_choice, u_origin, u_direction,
                                             mi.Bool(True), bounds=bounds)
    if guided_weight is not None:
        flux = flux * guided_weight
    return rng, path_id, ray, flux, emitter


@dataclass
class PhotonWalk:
    """The light paths of a batch still on their way (:func:`_trace_batch`)."""

    ray: mi.Ray3f
    flux: mi.Spectrum
    rng: mi.PCG32
    path_id: mi.UInt32
    specular_so_far: mi.Bool  #: every bounce so far sampled a delta or glossy lobe
    shared: mi.Bool  #: no bounce sampled lobes apart (yet): see merge_caustic_photons
    from_delta: mi.Bool  #: emitted by a delta light

    def survivors(self, alive: mi.Bool) -> "PhotonWalk":
        """The paths of ``alive``, their arrays and random states gathered in place."""
        keep = dr.compress(alive)
        lone = dr.width(keep) == 1
        if lone:
            # One photon left: it goes on beside a dead twin (zero flux: not stored, not
            # continued). Dr.Jit compiles one-element arrays as scalars: a lone photon
            # made its own kernels (a whole bounce's, 0.1 s), whenever a seed left one.
            keep = dr.gather(mi.UInt32, keep, mi.UInt32(0, 0))
        walk = dr.gather(PhotonWalk, self, keep)
        if lone:
            walk.flux = dr.select(dr.arange(mi.UInt32, 2) == 0, walk.flux, 0.0)
        return walk


@dataclass
class PhotonBounce:
    """The photons one bounce of a :class:`PhotonWalk` stores: in the lanes of
    ``store`` (one per path; :func:`_trace_tail` keeps one per path and bounce)."""

    store: mi.Bool
    position: mi.Point3f
    normal: mi.Vector3f  #: towards the side the photon arrived from
    power: mi.Color3f  #: linear sRGB (spectra.to_rgb: the photon's wavelengths projected)
    specular: mi.Bool  #: the path's specular_so_far at the photon
    shared: mi.Bool


#: The :class:`PhotonBounce` fields a stored photon keeps as they are.
STORED_FIELDS = ("position", "normal", "power", "specular", "shared")


def _photon_bounce(scene: mi.Scene, walk: PhotonWalk, caustic: bool, first: bool, inseparable: bool,
                   diffuse_free=None):
    """One bounce of every path of ``walk``: the photon it stores where it hits, and
    the walk advanced past it (a BSDF sample, Russian roulette). Returns
    ``(PhotonBounce, alive, walk)`` (``alive``: the paths that go on), for one
    evaluation: evaluated in two parts (the photons,
    then the sample), the second kernel traced the bounce's ray again (the white
    room's photon stage 4.0 -> 3.4 s, the same photons; docs/tuning.md)."""
    ray, flux, rng = walk.ray, walk.flux, walk.rng
    si = scene.ray_intersect(ray, mi.Bool(True))
    # A NaN or Inf flux (a NaN emitter, an Inf texel on the way) ends that photon
    # only: it must not poison the estimates around it.
    valid = si.is_valid() & (dr.max(flux) > 0) & dr.all(dr.isfinite(flux))
    bsdf = si.bsdf(ray)
    # (the vertex cases: pmic_integrator.cases; a principled metal's or glass's flags list a
    # diffuse lobe it does not have: bsdfs.diffuse_free)
    lobes = lobes_of(lobe_flags(bsdf, diffuse_free))
    has_diffuse = valid & lobes.diffuse
    # Not on the dark side of a one-sided surface (the outside of a room of thin
    # walls, lit by a sky): nothing there reflects, no lookup from the lit side
    # accepts it, and it would take a share of the map, and records, for nothing.
    # In a room lit through a window, 95 % of the photons were stored outside
    # (its indirect light then came from 11k photons, not 122k).
    store = has_diffuse & ~dark_side(bsdf, si, has_diffuse)
    if caustic:
        store = store & walk.specular_so_far & (not first)
    # Oriented towards the side the photon arrived from, so that lookups from the
    # other side of a thin wall reject it.
    n = mi.Vector3f(si.n)
    n = dr.select(dr.dot(n, -ray.d) < 0, -n, n)
    stored = PhotonBounce(store=store, position=si.p, normal=n,
                          power=to_rgb(flux * shading_normal_factors(si, n, -ray.d), ray.wavelengths),
                          specular=walk.specular_so_far, shared=walk.shared)
    u1, u2 = rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32())
    # A bounce off a BSDF that ignores lobe masks (principled) counts as diffuse:
    # the camera path cannot split its lobes either, so it must not be a caustic.
    separable = lobes_separable(bsdf, si, valid & has_diffuse & lobes.specular) \
        if inseparable else mi.Bool(True)
    # Rough plastic, for the caustic map: each lobe sampled apart, so that a photon
    # that took the glossy lobe carries that lobe's light only (sample_lobes_apart).
    # (Not for the global map, whose photons' lobe only marks the L S* D paths
    # that fallback estimates leave to the caustic map: there half of the bounces
    # took the weak glossy lobe and ended, and 200k photons took 1.2 s instead of
    # 0.7 s in the 97k-triangle room of benchmarks/stage_costs.py.)
    two_lobes = valid & lobes.rough_coat & separable
    shared = walk.shared & ~two_lobes  # the two passes sample this bounce differently
    apart = two_lobes & caustic
    mode = mi.TransportMode.Importance
    bs, bsdf_weight = bsdf.sample(mi.BSDFContext(mode), si, u1, u2, valid & ~apart)
    bs_apart, weight_apart = sample_lobes_apart(bsdf, si, u1, u2, apart, mode)
    bs[apart] = bs_apart
    bsdf_weight[apart] = weight_apart
    bsdf_weight = bsdf_weight * shading_normal_factors(si, n, -ray.d, bs.wo)[1]
    specular_so_far = walk.specular_so_far & lobes_of(bs.sampled_type).specular & separable
    alive = valid & (bs.pdf > 0) & (dr.max(bsdf_weight) > 0)
    if caustic:
        alive &= specular_so_far
    # Russian roulette on the bounce's albedo keeps photon powers roughly equal.
    survive = dr.minimum(dr.max(bsdf_weight), MAX_SURVIVAL)
    alive &= rng.next_float32() < survive
    return stored, alive, PhotonWalk(ray=si.spawn_ray(si.to_world(bs.wo)),
                              flux=flux * bsdf_weight / dr.maximum(survive, 1e-8), rng=rng,
                              path_id=walk.path_id, specular_so_far=specular_so_far, shared=shared,
                              from_delta=walk.from_delta)


#: What :func:`_trace_batch` returns for each photon, in order.
PHOTON_FIELDS = ("position", "normal", "power", "depth", "specular", "path", "delta", "shared")


def _photon_types() -> dict:
    """Each of :data:`PHOTON_FIELDS`' array type in the current variant."""
    return dict(position=mi.Point3f, normal=mi.Vector3f, power=mi.Color3f, depth=mi.UInt32,
                specular=mi.Bool, path=mi.UInt32, delta=mi.Bool, shared=mi.Bool, store=mi.Bool)


def _keep_photons(out: dict, photons: PhotonBounce, idx: mi.UInt32, paths: mi.UInt32, depth: mi.UInt32,
                  walk: PhotonWalk) -> None:
    """Append to ``out`` the photons at ``idx`` of ``photons``, stored by the paths
    ``paths`` of ``walk`` after ``depth`` interactions (both one per photon)."""
    types = _photon_types()
    for name in STORED_FIELDS:
        out[name].append(dr.gather(types[name], getattr(photons, name), idx))
    out["depth"].append(depth)
    out["path"].append(dr.gather(mi.UInt32, walk.path_id, paths))
    out["delta"].append(dr.gather(mi.Bool, walk.from_delta, paths))


def _trace_batch(scene: mi.Scene, kind: str, first_path: int, n_paths: int, seed: int,
                 max_store_depth: int, bounds: tuple, inseparable: bool = True,
                 guide: EmissionGuide | None = None, samples: list | None = None,
                 diffuse_free=None):
    """Trace ``n_paths`` light paths; return photon arrays and their path indices.
    ``bounds``: the scene's :func:`emission_bounds`; ``inseparable``: some BSDF may
    ignore lobe masks (tested at every bounce); ``guide``: emission samples drawn from
    it; ``samples``: a list that receives the paths' emission samples (origin,
    direction) as drawn; ``diffuse_free``: the scene's
    :func:`~pmic_integrator.bsdfs.diffuse_free_table` (None: there is none). A wavefront: each bounce one kernel (:func:`_photon_bounce`),
    then the paths that go on are compacted."""
    rng, path_id, ray, flux, emitter = _emit_batch(scene, first_path, n_paths, seed, bounds,
                                                   guide, samples)
    walk = PhotonWalk(ray=ray, flux=flux, rng=rng, path_id=path_id,
                      specular_so_far=dr.full(mi.Bool, True, n_paths),
                      shared=dr.full(mi.Bool, True, n_paths),
                      from_delta=mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta))
    out = {name: [] for name in PHOTON_FIELDS}
    bounces = min(max_store_depth, MAX_PHOTON_BOUNCES)
    bounce = 1
    while dr.width(walk.path_id):
        if bounce > 1 and dr.width(walk.path_id) <= TAIL_LOOP_PATHS:
            last = min(bounce + max(TAIL_LOOP_SLOTS // dr.width(walk.path_id), 1) - 1, bounces)
            walk, alive = _trace_tail(scene, walk, kind == CAUSTIC, (inseparable, diffuse_free), bounce, last,
                                      out)
        else:
            last = bounce
            stored, alive, walk = _photon_bounce(scene, walk, kind == CAUSTIC, bounce == 1, inseparable,
                                                 diffuse_free)
            dr.eval(stored, alive, walk)
            idx = dr.compress(stored.store)
            if dr.width(idx) > 0:
                _keep_photons(out, stored, idx, idx, dr.zeros(mi.UInt32, dr.width(idx)) + opaque_u32(bounce),
                              walk)
        if last == bounces:
            break
        walk = walk.survivors(alive)
        dr.eval(walk)
        bounce = last + 1
    types = _photon_types()
    return tuple(concat(out[name], types[name]) for name in PHOTON_FIELDS)


def _trace_tail(scene: mi.Scene, walk: PhotonWalk, caustic: bool, bsdfs: tuple,
                first_bounce: int, last_bounce: int, out: dict):
    """The bounces ``first_bounce``..``last_bounce`` of ``walk``'s few paths in one
    symbolic loop (:data:`TAIL_LOOP_PATHS`), their photons appended to ``out`` in the
    wavefront's order (by bounce, then by path): each bounce of the wavefront is
    recorded and code-generated anew, the same for 2 paths as for 60 000 (the white
    room's photon stage: 0.55 s of kernels in 2.92 s; 1.02 s with this loop,
    ``benchmarks/photon_stage.py``). Each path's photon of
    bounce ``b`` goes to slot ``(b - first_bounce) * paths + path``. Returns
    ``(walk, alive)``: the walk past ``last_bounce`` and the paths that go on.
    ``bsdfs``: :func:`_photon_bounce`'s ``(inseparable, diffuse_free)``."""
    paths = dr.width(walk.path_id)
    slots = paths * (last_bounce - first_bounce + 1)
    types = _photon_types()
    kept = ("store",) + STORED_FIELDS
    buffer = PhotonBounce(**{name: dr.zeros(types[name], slots) for name in kept})
    lane = dr.arange(mi.UInt32, paths)
    # (Opaque: one kernel for every batch and bounce count.)
    first, width, last = opaque_u32(first_bounce), opaque_u32(paths), opaque_u32(last_bounce)

    def body(walk, bounce, alive):
        stored, going, walk = _photon_bounce(scene, walk, caustic, False, *bsdfs)
        slot = (bounce - first) * width + lane
        for name in kept:
            dr.scatter(getattr(buffer, name), getattr(stored, name), slot, stored.store)
        return walk, bounce + 1, alive & going

    walk, _, alive = dr.while_loop(
        (walk, dr.zeros(mi.UInt32, paths) + first, dr.full(mi.Bool, True, paths)),
        lambda walk, bounce, alive: alive & (bounce <= last), body, label="photon_tail",
        max_iterations=last_bounce - first_bounce + 1)
    dr.eval(walk, alive)
    idx = dr.compress(buffer.store)
    if dr.width(idx):
        _keep_photons(out, buffer, idx, idx % width, idx // width + first, walk)
    return walk, alive


def trace_photons(scene: mi.Scene, kind: str, target: int, max_depth: int, seed: int,
                  max_paths: int, progress=None, warn: bool = True,
                  give_up_below: int = 0, inseparable: bool = True,
                  guide_emission: bool = False) -> PhotonMap:
    """Emit light paths in batches until ``target`` photons of ``kind`` are stored (whole
    paths: at most one path's photons more).

    ``max_depth`` has Mitsuba's meaning for the camera paths that will use the map: a
    photon after ``k`` surface interactions completes a path of at least ``k + 1``
    segments, so photons are stored up to ``max_depth - 1`` interactions (-1:
    unbounded). At most ``max_paths`` light paths are emitted, and none more once the
    yield so far, carried on to ``max_paths``, would store fewer than
    ``give_up_below`` photons (a map the caller drops below some count: its paths
    would be traced for nothing). With ``guide_emission``, a global pass lit by an
    environment through openings guides its emission (:class:`EmissionGuide`).
    """
    if target <= 0 or len(scene.emitters()) == 0:
        return PhotonMap.empty()
    max_store_depth = MAX_PHOTON_BOUNCES if max_depth < 0 else max_depth - 1
    if max_store_depth < (2 if kind == CAUSTIC else 1):
        return PhotonMap.empty()
    parts = []
    stored = 0
    emitted = 0
    batch = 0
    batch_paths = min(FIRST_BATCH_PATHS, max(1024, 2 * target), max_paths)
    start = time.perf_counter()
    bounds = emission_bounds(scene)  # once: every batch shoots from the same rectangles
    diffuse_free = scene_diffuse_free(scene)
    guide = None
    # (Not with a focus, emission.focus_box: both remap the origin's square, and the
    # guide's density is that of the square, not of the focus's mixture.)
    may_guide = guide_emission and kind == GLOBAL and bounds.focus is None and \
        any(mi.has_flag(e.flags(), mi.EmitterFlags.Infinite) for e in scene.emitters())
    while stored < target and emitted < max_paths:
        batch_paths = int(min(batch_paths, max_paths - emitted))
        samples = [] if may_guide and batch == 0 else None
        pos, nrm, pwr, dep, spec, path, delta, shared = _trace_batch(
            scene, kind, emitted, batch_paths, photon_batch_seed(seed, batch, kind == CAUSTIC),
            max_store_depth, bounds, inseparable, guide, samples, diffuse_free)
        got = dr.width(dep)
        if samples is not None and 0 < got < EMISSION_GUIDE_BELOW * batch_paths:
            # (All of the first batch: its paths' samples are uniform.)
            per_path = dr.zeros(mi.UInt32, batch_paths)
            scatter_count(per_path, path - opaque_u32(emitted))
            guide = EmissionGuide.learn(*samples, per_path)
        remaining = target - stored
        used_paths = batch_paths
        if got > remaining:
            # Keep whole paths only: the first P paths of the batch whose photons begin
            # before the target is reached (the last may run past it, by at most one
            # path's photons). Keeping only the paths that fit entirely could keep none
            # when a few photons were left to store: in a room lit indirectly (long
            # paths) ten more batches of 1024 paths were traced for 0.4 s before one
            # began with a path short enough.
            per_path = dr.zeros(mi.UInt32, batch_paths)
            scatter_count(per_path, path - opaque_u32(emitted))
            before = dr.prefix_sum(per_path)  # photons of the batch's earlier paths
            used_paths = int(dr.count(before < opaque_u32(remaining))[0]) if dr.width(before) else 0
            keep = dr.compress(path < opaque_u32(emitted + used_paths))
            pos, nrm, pwr, dep, spec, path, delta, shared = (
                dr.gather(type(a), a, keep) for a in (pos, nrm, pwr, dep, spec, path, delta, shared))
            got = dr.width(keep)
        if got:
            parts.append((pos, nrm, pwr, dep, spec, path, delta, shared))
        stored += got
        emitted += used_paths
        batch += 1
        if progress is not None:
            progress(kind, stored, target, emitted)
        # Size the next batch from the yield so far (+10 % so the last batch overshoots).
        yield_per_path = stored / max(emitted, 1)
        # Given up where even a generous estimate of the yield (GIVE_UP_SIGMAS Poisson
        # deviations above the count so far) would store fewer than give_up_below
        # photons by max_paths: the map would be dropped anyway.
        generous = (stored + GIVE_UP_SIGMAS * math.sqrt(stored) + 1) / max(emitted, 1)
        if generous * max_paths < give_up_below:
            break
        need = (target - stored) / max(yield_per_path, 1e-3) * 1.1
        batch_paths = int(min(max(need, 1024), MAX_BATCH_PATHS))
    if warn and stored < LOW_YIELD_FRACTION * target:
        message = (f"pmic: only {stored} of the {target} requested {kind} photons were stored "
                   f"after {emitted} emitted light paths (is a light enclosed in geometry, or "
                   f"do its photons reach no diffuse surface?)")
        log.warning(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)
    if stored == 0:
        out = PhotonMap.empty()
        out.paths_emitted = emitted
        return out
    position = concat([p[0] for p in parts], mi.Point3f)
    normal = concat([p[1] for p in parts], mi.Vector3f)
    # Opaque: the path count moves with the seed (a constant: a kernel per seed).
    power = concat([p[2] for p in parts], mi.Color3f) / opaque_float(emitted)
    depth = concat([p[3] for p in parts], mi.UInt32)
    specular = concat([p[4] for p in parts], mi.Bool)
    path = concat([p[5] for p in parts], mi.UInt32)
    delta = concat([p[6] for p in parts], mi.Bool)
    shared = concat([p[7] for p in parts], mi.Bool)
    dr.eval(position, normal, power, depth, specular, path, shared)
    log.info("pmic: %d %s photons from %d paths in %.2f s", stored, kind, emitted,
             time.perf_counter() - start)
    return PhotonMap(position, normal, power, depth, specular, path, emitted, delta_light=delta,
                     shared_path=shared)


def merge_caustic_photons(caustic: PhotonMap, global_map: PhotonMap) -> PhotonMap:
    """The caustic map with the caustic photons of the global map's odd paths added.

    The global pass samples light paths exactly as the caustic pass does until their
    first diffuse bounce (but where a caustic pass samples lobes apart: photons of such
    paths are left as they are, see ``shared_path``), so its L S+ D photons are caustic
    photons too, from other paths: the N_c caustic paths and the N_g / 2 odd global
    paths together are N_c + N_g / 2 samples of the same paths, and each photon's power
    is rescaled to that count. Where light reaches a room through glass only, nearly
    all the room's light is caustic and the caustic pass's yield is low (a window's
    pane, 1 % of the sky's paths): its 18k photons left the room's mean 1-2 % dark from
    one photon seed to the next; with the global pass's 200k paths' share, 2.6 times as
    many caustic photons fell on its floor.

    Odd paths only: irradiance is precomputed at photons of even paths
    (:func:`~pmic_integrator.irradiance.precompute_irradiance`), their caustic part from
    this map, which must not hold the very photon it is estimated at (its own power
    adds 3/k of the estimate: the bias the halves exist to avoid).
    """
    if caustic.count == 0 or global_map.count == 0 or caustic.shared_path is None \
            or global_map.shared_path is None:
        return caustic
    n_caustic = caustic.paths_emitted
    n_odd = global_map.paths_emitted // 2
    if n_caustic == 0 or n_odd == 0:
        return caustic
    extra = dr.compress(global_map.caustic & global_map.shared_path & ((global_map.path & 1) == 1))
    total = n_caustic + n_odd
    # Opaque: the path counts move with the photon seed (constants: a kernel per seed).
    merged = replace(caustic, power=dr.select(caustic.shared_path,
                                              caustic.power * opaque_float(n_caustic / total),
                                              caustic.power))
    if dr.width(extra):
        more = global_map.select(extra)
        more.power = more.power * opaque_float(global_map.paths_emitted / total)
        more.path = more.path + opaque_u32(n_caustic)  # unique path indices in the merged map
        merged = merged.joined(more)
    merged.shared_path = None
    dr.eval(merged.position, merged.normal, merged.power, merged.depth, merged.specular_path,
            merged.path, merged.delta_light)
    return merged
