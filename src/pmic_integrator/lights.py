"""Bright records as disk lights: where the continuation of a traced diffuse vertex is
drawn towards small, very bright sources of bounced light (final gather).

A lamp inside a shade lights the shade's inside a thousand times brighter than the
room; the room is lit by that inside, a source of a few thousandths of a steradian.
Cosine or BSDF sampling meets it once in hundreds of rays, each carrying hundreds of
times the pixel's value: fireflies, which no denoiser removes. The guide histograms
(0.1 sr bins) are too coarse for it. The records on such a surface know their
irradiance, position, normal and extent: :class:`RecordLights` keeps the brightest as
disks and draws directions towards them, one strategy of the continuation's one-sample
MIS (:meth:`~pmic_integrator.integrator.PMICIntegrator.sample`), whose density
:meth:`RecordLights.pdf` gives exactly for any direction (a sum over the disks the ray
crosses). Whatever the ray meets is then read as for any other continuation: the
estimate stays unbiased, only its variance changes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

# --- Tuning constants --------------------------------------------------------------------
#: A record is bright where its irradiance (bounced + direct) is at least this many
#: times the median record's: a lamp's shade lit from inside, a sunlit patch seen from
#: a dim room; not the bright side of an evenly lit box (Cornell box: the brightest
#: record is ~10× the median, the lamp room's shades ~2500×), where guiding serves.
LIGHT_CONTRAST = 50.0
#: Bright records closer than this many of their reaches (a·R) join one light: a
#: shade's inside is one light, the two lamps of a room two. (Tighter groups, cells
#: of 2 reaches, measured worse in the lamp room: relMSE 0.5-0.7 against 0.3-0.45,
#: as 16 cells left a third of the bright records' power uncovered.)
JOIN_REACHES = 4.0
#: Lights are kept only where together they hold at least this share of the power
#: (irradiance × reach²) of all records, i.e. where most bounced light starts from
#: them (the lamp room: 81 %); a sunlit patch or a ceiling above a lamp holding 3 %
#: (a room lit through a window) is left to guiding, which draws such wide sources
#: well, while the lights' share of the rays would be taken from it.
LIGHTS_MIN_SHARE = 0.25
#: ...and each light at least this share (smaller ones are not worth their cost).
LIGHT_MIN_SHARE = 0.01
#: A group whose radius is over this fraction of the records' extent (the diagonal of
#: their bounding box) is no small source (a sunlit floor joined into one 4.4 m
#: sphere round a whole 7.6 m room, from inside which it has no weight): dropped,
#: guiding serves it. The lamp room's shades measure 0.06 and 0.09.
MAX_LIGHT_EXTENT = 0.2
#: At most this many lights (the most powerful): each costs a few flops per density
#: evaluation, and a traced vertex evaluates the density once per emitter sample and
#: once for its continuation.
MAX_LIGHTS = 16


@dataclass
class RecordLights:
    """Groups of bright records as spherical lights (centre, radius, power). A query
    point x with normal n draws light k with probability w_k / W,

        w_k = P_k · clip(n·ω_k + sin θ_k, 0, 1) / d_k²,

    (ω_k, d_k: direction and distance from x to the centre, θ_k: the half-angle the
    sphere subtends; 0 where x is inside it), then a direction uniformly in the cone of
    the sphere. The density is a sum of constants over the cones holding the direction:
    a direction that meets the bright surface through the cone is drawn with density at
    least α·w_k/(W·Ω_k), so it can never carry more than its share of the cone."""

    center: mi.Point3f
    radius: mi.Float  #: bounding sphere of the group's record disks (reach a·R)
    power: mi.Float  #: Σ irradiance luminance × reach² of the group
    count: int

    @staticmethod
    def select(position: mi.Point3f, reach: mi.Float, irradiance: mi.Color3f) -> RecordLights | None:
        """The lights among records (``irradiance``: all of each record's light, ``reach``
        their a·R), or None where no record stands out (:data:`LIGHT_CONTRAST`).
        Deterministic: a function of the records only (NumPy, stable orders). Normals
        play no part: a group's records face many ways (the inside of a shade)."""
        if dr.width(irradiance) == 0:
            return None
        lum = np.array(mi.luminance(irradiance), dtype=np.float64)
        r = np.array(reach, dtype=np.float64)
        # Component by component: converting a 3-vector array makes a kernel that holds
        # its size, compiled anew for each record count.
        p = np.stack([np.array(c, dtype=np.float64) for c in (position.x, position.y, position.z)], 1)
        median = float(np.median(lum))
        bright = np.flatnonzero((lum > LIGHT_CONTRAST * median) & np.isfinite(lum) & (r > 0))
        if bright.size == 0 or not median > 0:
            return None
        # Single-linkage groups over the pairs closer than JOIN_REACHES × the larger
        # reach, found through a grid of cells that wide (27 neighbours each); each
        # group is labelled by its smallest member (labels spread along the pairs).
        bp, br = p[bright], r[bright]
        extent = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
        cell = JOIN_REACHES * float(br.max())
        keys = np.floor((bp - bp.min(axis=0)) / cell).astype(np.int64)
        buckets: dict = {}
        for i, key in enumerate(map(tuple, keys)):
            buckets.setdefault(key, []).append(i)
        pairs_i, pairs_j = [], []
        for key, members in buckets.items():
            mine = np.array(members)
            for a in (-1, 0, 1):
                for b in (-1, 0, 1):
                    for c in (-1, 0, 1):
                        other = buckets.get((key[0] + a, key[1] + b, key[2] + c))
                        if other is None:
                            continue
                        other = np.array(other)
                        dist = np.linalg.norm(bp[mine][:, None, :] - bp[other][None, :, :], axis=-1)
                        ii, jj = np.nonzero(dist <= JOIN_REACHES * np.maximum(br[mine][:, None],
                                                                              br[other][None, :]))
                        pairs_i.append(mine[ii])
                        pairs_j.append(other[jj])
        pairs_i, pairs_j = np.concatenate(pairs_i), np.concatenate(pairs_j)
        group = np.arange(bright.size)
        while True:
            smaller = np.minimum(group[pairs_i], group[pairs_j])
            before = group.copy()
            np.minimum.at(group, pairs_i, smaller)
            np.minimum.at(group, pairs_j, smaller)
            group = group[group]  # follow labels to their own labels (pointer jumping)
            if np.array_equal(group, before):
                break
        power = lum[bright] * br ** 2
        lights = []
        for g in np.unique(group):
            m = group == g
            w = power[m]
            c = (bp[m] * w[:, None]).sum(0) / w.sum()
            radius = float(np.max(np.linalg.norm(bp[m] - c, axis=1) + br[m]))
            if radius <= MAX_LIGHT_EXTENT * extent:
                lights.append((float(w.sum()), c, radius))
        total = float(np.sum(np.where(np.isfinite(lum), lum, 0.0) * r ** 2))
        lights.sort(key=lambda t: -t[0])
        lights = [t for t in lights[:MAX_LIGHTS] if t[0] >= LIGHT_MIN_SHARE * total]
        if not lights or sum(t[0] for t in lights) < LIGHTS_MIN_SHARE * total:
            return None
        center = np.array([t[1] for t in lights], dtype=np.float32)
        return RecordLights(center=mi.Point3f(*[mi.Float(center[:, i]) for i in range(3)]),
                            radius=mi.Float(np.array([t[2] for t in lights], dtype=np.float32)),
                            power=mi.Float(np.array([t[0] for t in lights], dtype=np.float32)),
                            count=len(lights))

    def _light(self, k: mi.UInt32, x: mi.Point3f, n: mi.Vector3f, active):
        """Light k seen from (x, n): (axis, cos θ_k, 1 − cos θ_k, w_k); w_k = 0 inside
        the sphere. (1 − cos θ computed as sin²θ / (1 + cos θ): far lights subtend
        angles whose 1 − cos θ would round to 0 in single precision.)"""
        c = dr.gather(mi.Point3f, self.center, k, active)
        r = dr.gather(mi.Float, self.radius, k, active)
        power = dr.gather(mi.Float, self.power, k, active)
        v = c - x
        d2 = dr.squared_norm(v)
        outside = d2 > r * r
        axis = v * dr.rsqrt(dr.maximum(d2, 1e-30))
        sin2 = dr.minimum(r * r / dr.maximum(d2, 1e-30), 1.0)
        cos_max = dr.safe_sqrt(1.0 - sin2)
        one_minus_cos = sin2 / (1.0 + cos_max)
        w = power * dr.clip(dr.dot(n, axis) + dr.sqrt(sin2), 0.0, 1.0) / dr.maximum(d2, 1e-30)
        return axis, cos_max, one_minus_cos, dr.select(outside & active, w, 0.0)

    def _loop(self, state, body, active, label):
        lanes = dr.width(active)

        def cond(k, active, state):
            return active & (k < self.count)

        def step(k, active, state):
            return k + 1, active, body(k, active, state)

        _, _, state = dr.while_loop((dr.zeros(mi.UInt32, lanes), mi.Bool(active), state),
                                    cond, step, label=label)
        return state

    def total_weight(self, x: mi.Point3f, n: mi.Vector3f, active=True) -> mi.Float:
        """W(x, n) = Σ w_k: 0 where no light faces (x, n)."""
        x, n = mi.Point3f(x), mi.Vector3f(n)

        def body(k, active, total):
            return total + self._light(k, x, n, active)[3]

        return self._loop(dr.zeros(mi.Float, dr.width(x)), body, mi.Bool(active), "record_lights_weight")

    def sample(self, x: mi.Point3f, n: mi.Vector3f, total: mi.Float, u_pick: mi.Float,
               u_cone: mi.Point2f, active=True) -> mi.Vector3f:
        """A world-space direction from (x, n) towards a light (light k with probability
        w_k / ``total``, ``u_pick`` ∈ [0, 1); uniform in its cone with ``u_cone``).
        Where ``total`` is 0 the result is meaningless (not used)."""
        x, n = mi.Point3f(x), mi.Vector3f(n)
        lanes = dr.width(x)
        target = mi.Float(u_pick) * total

        def body(k, active, state):
            running, axis, cos_max = state
            ax, cm, _, w = self._light(k, x, n, active)
            # The last light with a weight whose running sum starts at or below the
            # target: the one whose interval holds it (or, should rounding leave the
            # target above every sum, the last with a weight).
            take = (running <= target) & (w > 0)
            return running + w, dr.select(take, ax, axis), dr.select(take, cm, cos_max)

        _, axis, cos_max = self._loop(
            (dr.zeros(mi.Float, lanes), dr.zeros(mi.Vector3f, lanes), dr.zeros(mi.Float, lanes)),
            body, mi.Bool(active), "record_lights_pick")
        local = mi.warp.square_to_uniform_cone(u_cone, cos_max)
        return mi.Frame3f(axis).to_world(local)

    def pdf(self, x: mi.Point3f, n: mi.Vector3f, total: mi.Float, d: mi.Vector3f,
            active=True) -> mi.Float:
        """Solid-angle density with which :meth:`sample` draws the world direction
        ``d`` at (x, n): Σ over the cones holding d of (w_k / W) / (2π (1 − cos θ_k))."""
        x, n, d = mi.Point3f(x), mi.Vector3f(n), mi.Vector3f(d)
        active = mi.Bool(active) & (total > 0)

        def body(k, active, density):
            axis, cos_max, one_minus_cos, w = self._light(k, x, n, active)
            inside = (dr.dot(d, axis) >= cos_max) & (w > 0)
            return density + dr.select(inside, w / dr.maximum(2.0 * math.pi * one_minus_cos, 1e-30), 0.0)

        density = self._loop(dr.zeros(mi.Float, dr.width(x)), body, active, "record_lights_pdf")
        return dr.select(active, density / dr.maximum(total, 1e-30), 0.0)
