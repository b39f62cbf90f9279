"""What the view-independent stages depend on: a digest per shape and per emitter.

The photon maps, the precomputed irradiance and the cache are functions of the scene's
shapes (geometry, placement), their BSDFs and textures, its emitters and the settings
that change them (:meth:`Settings.key`) — not of its sensors, films, samplers or
reconstruction filters. So a camera moved through ``mi.traverse``, another field of
view, another film size or another number of sensors keep the cache (in memory and in a
cache file), and a fly-through renders every frame from one cache.

Each object's digest covers its plugin classes and every parameter ``mi.traverse``
lists for it (a shape's traversal holds its BSDF, its textures and its area emitter).
Large buffers (mesh vertices and faces, bitmaps) are hashed where they live, on the
device, and only two 32-bit sums per buffer come back to the host: a render call of a
scene of a million triangles does not copy its meshes to the host (docs/flythrough.md
gives the timings, from ``benchmarks/flythrough.py --fingerprint``).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

#: Buffers with at least this many entries are hashed on the device (smaller ones, such
#: as a transform or a colour, are read to the host: one read costs less than a kernel).
DEVICE_HASH_FROM = 4096
_MIX_1, _MIX_2, _MIX_3 = 0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D


def _mix(h):
    """A 32-bit integer finaliser (xor-shift-multiply): every input bit moves the output."""
    h = h ^ (h >> 16)
    h = h * 0x7FEB352D
    h = h ^ (h >> 15)
    h = h * 0x846CA68B
    return h ^ (h >> 16)


def _device_sums(value):
    """Two position-dependent 32-bit sums of a large flat buffer, left lazy (evaluated
    with every other buffer's in one batch), or None if ``value`` is not such a buffer."""
    flat = value.array if isinstance(value, mi.TensorXf) else value
    if not dr.is_array_v(flat) or dr.depth_v(flat) != 1 or dr.width(flat) < DEVICE_HASH_FROM:
        return None
    vt = dr.type_v(flat)
    if vt == dr.VarType.Float32 or vt == dr.VarType.Int32:
        bits = dr.reinterpret_array(mi.UInt32, flat)
    elif vt == dr.VarType.UInt32:
        bits = flat
    else:
        return None
    index = dr.arange(mi.UInt32, dr.width(flat))
    h = _mix(bits ^ _mix(index * _MIX_2 + _MIX_3))
    return dr.sum(h), dr.sum(_mix(h * _MIX_1 + index))


def _host_bytes(value) -> bytes:
    if dr.is_array_v(value):
        return np.ascontiguousarray(np.array(value)).tobytes()
    return repr(value).encode()


def _objects(scene: mi.Scene):
    """(name, classes, traversal) of every shape and of every emitter that is not a
    shape's area light (those are in their shape's traversal). Unnamed objects are
    named by their classes (and BSDF); :func:`scene_fingerprint` numbers namesakes."""
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        emitter = shape.emitter()
        classes = (shape.class_name(), bsdf.class_name() if bsdf is not None else "",
                   emitter.class_name() if emitter is not None else "")
        if shape.id():
            name = f"shape '{shape.id()}'"
        else:
            what = f", BSDF '{bsdf.id()}'" if bsdf is not None and bsdf.id() else ""
            name = f"unnamed shape ({shape.class_name()}{what})"
        yield name, classes, mi.traverse(shape)
    for emitter in scene.emitters():
        if mi.has_flag(emitter.flags(), mi.EmitterFlags.Surface):
            continue
        name = f"emitter '{emitter.id()}'" if emitter.id() else f"unnamed emitter ({emitter.class_name()})"
        yield name, (emitter.class_name(),), mi.traverse(emitter)


def _numbered(named_digests: list) -> tuple:
    """Sorted (name, digest) pairs, namesakes numbered in the order of their digests:
    Mitsuba's loader does not keep the order of a scene's shapes from load to load."""
    counts: dict = {}
    for name, _ in named_digests:
        counts[name] = counts.get(name, 0) + 1
    out, seen = [], {}
    for name, digest in sorted(named_digests):
        if counts[name] > 1:
            seen[name] = seen.get(name, 0) + 1
            name = f"{name} #{seen[name]}"
        out.append((name, digest))
    return tuple(out)


@dataclass(frozen=True)
class SceneFingerprint:
    """Digests of a scene's shapes and emitters (see the module)."""

    objects: tuple  #: ((object name, hex digest), ...), sorted by name

    @property
    def digest(self) -> str:
        """One digest of all the objects (what a cache is keyed by)."""
        h = hashlib.blake2b(digest_size=16)
        for name, digest in self.objects:
            h.update(name.encode() + b"\0" + digest.encode() + b"\0")
        return h.hexdigest()

    def differences(self, other: "SceneFingerprint", limit: int = 4) -> str:
        """What differs from ``other`` (the scene a cache was built for), in words:
        the objects changed, added or missing."""
        mine, theirs = dict(self.objects), dict(other.objects)
        changed = [n for n in mine if n in theirs and mine[n] != theirs[n]]
        added = [n for n in mine if n not in theirs]
        missing = [n for n in theirs if n not in mine]
        parts = []
        for label, names in (("changed", changed), ("not in the cache's scene", added),
                             ("missing here", missing)):
            if names:
                more = f" and {len(names) - limit} more" if len(names) > limit else ""
                parts.append(f"{label}: {', '.join(names[:limit])}{more}")
        if not parts and sorted(mine.values()) != sorted(theirs.values()):
            parts.append("unnamed objects changed")
        return "; ".join(parts) or "no object differs"

    def to_json(self) -> list:
        return [list(pair) for pair in self.objects]

    @staticmethod
    def from_json(items) -> "SceneFingerprint":
        return SceneFingerprint(tuple((str(name), str(digest)) for name, digest in items))


def scene_fingerprint(scene: mi.Scene) -> SceneFingerprint:
    """The :class:`SceneFingerprint` of ``scene``: its shapes and emitters, not its
    sensors. Stable across processes and loads."""
    pending = []  # (object index, parameter name, lazy device sums or host bytes)
    entries = []
    for index, (name, classes, params) in enumerate(_objects(scene)):
        entries.append((name, classes))
        for key in sorted(params.keys()):
            try:
                value = params[key]
            except Exception:  # pragma: no cover - unreadable parameters are skipped
                continue
            sums = _device_sums(value)
            pending.append((index, key, sums if sums is not None else _host_bytes(value),
                            dr.width(value) if dr.is_array_v(value) else 0))
    lazy = [item[2] for item in pending if isinstance(item[2], tuple)]
    if lazy:
        dr.eval(lazy)
    digests = [hashlib.blake2b(repr(classes).encode(), digest_size=16) for _, classes in entries]
    for index, key, data, width in pending:
        if isinstance(data, tuple):
            data = np.array([int(data[0][0]), int(data[1][0]), width], dtype=np.uint64).tobytes()
        digest = digests[index]
        digest.update(key.encode() + b"\0")
        digest.update(len(data).to_bytes(8, "little"))
        digest.update(data)
    return SceneFingerprint(_numbered([(name, d.hexdigest()) for (name, _), d in zip(entries, digests)]))
