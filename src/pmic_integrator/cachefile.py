"""Saving and loading a prepared scene (photon maps, grids, precomputed irradiance and
the irradiance cache) as one ``.npz`` file.

The format is NumPy's ``.npz`` (a zip of ``.npy`` arrays), read with
``allow_pickle=False``: nothing in it can run code. One JSON entry, ``meta``, says what
the arrays are: the format name and version, pmic's version, the fingerprint of the
scene the cache was built for and the settings it was built with, and for every
dataclass the project writes (``PreparedScene`` and what it holds) the class and
field of each array, so that it is rebuilt exactly as it was saved, bit for bit, with
no recomputation (but for the sky tables of :mod:`pmic_integrator.skylight`, which
are rebuilt from the scene). The Mitsuba scene itself is not saved: a loaded cache is attached to
the scene it is loaded for, after checking that its fingerprint matches.

Errors (``ValueError``, naming the file): not a pmic cache, a newer or older format,
another scene, other settings, a truncated or corrupt file.
"""
from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .fingerprint import SceneFingerprint

FORMAT = "pmic-cache"
#: 2: first-hit caches completed by surface probes (no records added per view).
#: 3: gather sources hold the sparse photons' far grid (GatherSource.far_grid).
#: 4: records hold their shading normals; photon powers carry the shading-normal factor.
#: 5: final-gather records may hold the caustic map's irradiance (holds_caustics).
#: 6: records hold their directional distribution of gathered light (guiding).
#: 7: final-gather caches keep their brightest records as lights (RecordLights).
#: 8: photons know whether their path began at a delta light, precomputed photons
#:    keep their irradiance without delta lights' direct light apart, and final-gather
#:    records hold direct light from lights that are not delta only.
#: 9: gather sources search a spread subset of each wide cell (GatherSource.wide_grid);
#:    scene info says whether some BSDF is a smooth coat (SceneInfo.has_delta_coat).
#: 10: grid pyramids pick a query's level from the densest cell its scan visits
#:     (PointGridPyramid.level0_key): precomputed irradiance and estimates differ.
#: 11: records keep the sky their gather saw through openings (CacheRecords.sky_guide).
#: 12: photons sample a rough plastic's lobes apart (bsdfs.sample_lobes_apart); scene
#:     info says whether some BSDF has one (SceneInfo.has_glossy_coat).
#: 13: with a bounded max_depth, final-gather caches precompute irradiance for records
#:     read at depth 1 (Settings.records_read_depth), one photon bounce fewer.
#: 14: the sky sampler says whether the sky is even (SkySampler.even): records' guides
#:     then hold the sky they saw wherever they are.
#: 15: records keep their gather's nearest hit per azimuth sector (CacheRecords.obstacle_sectors).
#: 16: gather rays bounce on at diffuse hits closer than two lookup radii
#:     (GatherSource.near_hit_distance), reading there the caustic irradiance
#:     precomputed at the photons (PhotonMap.irradiance_caustic): records differ; wide
#:     and far search steps keep 4 photons per cell (GatherSource.WIDE_CELL_PHOTONS).
#: 17: a max_depth of 64 or more builds as unbounded (Settings.bounded), and scene info
#:     reads the materials of instanced shapes (SceneInfo.of).
#: 18: in open scenes, final-gather records gather a quarter of gather_rays, the rest
#:     only where bounced light matters (pipeline.FIRST_GATHER_SHARE).
#: 19: caustic maps hold the global pass's caustic photons of odd paths too
#:     (photons.merge_caustic_photons), all weighed by both passes' paths.
#: 20: caustic estimates use more photons where caustics carry most of the
#:     first-bounce light (pipeline.caustic_lookup_size): other radius and grid.
#: 21: there, the caustic map's radius is set over the surfaces' area, with six
#:     pyramid levels (pipeline.CAUSTIC_ROOM_PYRAMID_LEVELS).
#: 22: delta lights' caustic photons count with a narrower kernel there
#:     (PreparedScene.caustic_delta_scale).
#: 23: gather rays go on through principled BSDFs that transmit
#:     (SceneInfo.has_diffuse_transmission, GatherSource.crossing).
#: 24: gather rays through a coat stop by Russian roulette where a caustic map holds
#:     what they would meet (gather.GATHER_ROULETTE): records differ; scene info and
#:     gather sources say whether some BSDF ignores lobe masks (SceneInfo.has_inseparable).
#: 25: the global pass of a scene lit through openings guides its emission
#:     (photons.EmissionGuide): other photons.
#: 26: grid pyramids keep an entry's level in three bits of its key (bits 29-31;
#:     PointGridPyramid.LEVEL_SHIFT): keys stored by 25 would not be found; precomputed
#:     irradiance is estimated from every path not precomputed (irradiance.precompute_irradiance).
#: 27: the diffuse response is a 3-level quadrature, at three azimuths where some
#:     lobe leans (bsdfs.diffuse_response, SceneInfo.has_leaning_lobes,
#:     GatherSource.leaning): records differ.
#: 28: records keep their direct light's rotational gradient (RecordIndex.direct_rotation).
#: 29: the scene's fingerprint covers its shapes and emitters only, one digest per object
#:     (fingerprint.SceneFingerprint), and settings are stored by name: a file serves
#:     every camera of its scene.
#: 30: records keep their gather's mean squared ray luminance (CacheRecords.ray_moment,
#:     the adaptive estimator's test of a record's own noise).
#: 31: records keep whether they owe the rest of their gather (CacheRecords.partial,
#:     pipeline.GATHER_BUDGET_RAYS); gathers' near bounces weight emission by MIS.
#: 32: principled metals and glass are glossy only (bsdfs.diffuse_free): their
#:     reflections of the lights are caustic photons; maps, scene info and records differ.
VERSION = 32

#: Array types that may appear in a cache, by their name in ``mitsuba`` (the variant's).
_ARRAY_TYPES = ("Float", "UInt32", "Int32", "Bool", "Point3f", "Vector3f", "Color3f", "Vector3i",
                "Vector3u", "Point2f", "UInt64")


class CacheFileError(ValueError):
    """A cache file that cannot be used here (the message names the file and why)."""


def _classes():
    from .cache import CacheRecords, RecordIndex
    from .lights import RecordLights
    from .gather import GatherSource
    from .hashgrid import BallGrid, PointGrid, PointGridPyramid
    from .fingerprint import SceneFingerprint
    from .pipeline import PreparedScene, SceneInfo
    from .photons import PhotonMap

    return {c.__name__: c for c in (CacheRecords, RecordIndex, GatherSource, BallGrid, PointGrid,
                                    PointGridPyramid, PreparedScene, SceneInfo, PhotonMap,
                                    RecordLights, SceneFingerprint)}


def _flatten(obj, name: str, arrays: dict):
    """A JSON description of ``obj``; its Dr.Jit arrays go into ``arrays``."""
    if obj is None:
        return {"kind": "none"}
    if isinstance(obj, mi.Scene):
        return {"kind": "scene"}
    if dataclasses.is_dataclass(obj):
        return {"kind": "dataclass", "class": type(obj).__name__,
                "fields": {f.name: _flatten(getattr(obj, f.name), f"{name}.{f.name}", arrays)
                           for f in dataclasses.fields(obj) if not f.metadata.get("derived")}}
    if dr.is_array_v(obj):
        type_name = next((t for t in _ARRAY_TYPES if getattr(mi, t, None) is type(obj)), None)
        if type_name is None:
            raise TypeError(f"save_cache: cannot store a {type(obj).__name__} ({name})")
        arrays[name] = np.array(obj)
        return {"kind": "array", "type": type_name, "key": name}
    if isinstance(obj, (tuple, list)):
        return {"kind": type(obj).__name__,
                "items": [_flatten(v, f"{name}[{i}]", arrays) for i, v in enumerate(obj)]}
    if isinstance(obj, dict):
        return {"kind": "json", "value": json.loads(json.dumps(obj, default=str))}
    if isinstance(obj, (bool, int, float, str)):
        return {"kind": "scalar", "value": obj}
    raise TypeError(f"save_cache: cannot store {type(obj).__name__} ({name})")


def _build(desc, arrays, scene, classes):
    kind = desc["kind"]
    if kind == "none":
        return None
    if kind == "scene":
        return scene
    if kind == "scalar":
        return desc["value"]
    if kind == "json":
        return desc["value"]
    if kind in ("tuple", "list"):
        items = [_build(d, arrays, scene, classes) for d in desc["items"]]
        return tuple(items) if kind == "tuple" else items
    if kind == "array":
        array_type = getattr(mi, desc["type"])
        value = arrays[desc["key"]]
        out = array_type(value) if value.ndim == 1 else array_type(*[np.ascontiguousarray(c) for c in value])
        return out
    if kind == "dataclass":
        cls = classes[desc["class"]]
        return cls(**{k: _build(v, arrays, scene, classes) for k, v in desc["fields"].items()})
    raise ValueError(f"unknown entry kind {kind!r}")


def save(path, prepared, fingerprint, settings_key: tuple) -> Path:
    """Write ``prepared`` (a ``PreparedScene``) to ``path`` (``.npz``), with the
    :class:`~pmic_integrator.fingerprint.SceneFingerprint` of its scene and the
    :meth:`Settings.key` it was built with."""
    from . import __version__

    path = Path(path)
    arrays: dict = {}
    # The sky tables are the scene's, and cheap: rebuilt on loading (they hold the
    # emitter object, and its index in scene.emitters() changes from load to load).
    body = _flatten(dataclasses.replace(prepared, sky=None), "prepared", arrays)
    meta = {"format": FORMAT, "version": VERSION, "pmic_version": __version__,
            "fingerprint": fingerprint.digest, "scene_objects": fingerprint.to_json(),
            "settings": dict(settings_key), "body": body}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with open(path, "wb") as f:  # np.savez would append .npz to a name without it
        np.savez(f, **arrays)
    return path


def _settings_differences(saved: dict, settings_key: tuple) -> str:
    here = dict(settings_key)
    names = [n for n in {**saved, **here} if saved.get(n) != here.get(n)]
    return ", ".join(f"{n} {saved.get(n, '(absent)')!r} in the file, {here.get(n, '(absent)')!r} here"
                     for n in names)


def load(path, scene, fingerprint, settings_key: tuple):
    """Read a ``PreparedScene`` from ``path`` for ``scene`` (whose
    :class:`~pmic_integrator.fingerprint.SceneFingerprint` is ``fingerprint``; its
    cameras do not count); ValueError if the file is not a pmic cache of this format,
    of this scene and these settings, or is damaged."""
    path = Path(path)
    where = f"cache_file '{path}'"
    if not path.is_file():
        raise CacheFileError(f"{where}: no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            if meta.get("format") != FORMAT:
                raise CacheFileError(f"{where} is not a pmic cache (format {meta.get('format')!r})")
            if meta.get("version") != VERSION:
                raise CacheFileError(f"{where} has format version {meta.get('version')!r}; this pmic "
                                     f"reads version {VERSION} (rebuild the cache)")
            if meta["fingerprint"] != fingerprint.digest:
                saved = SceneFingerprint.from_json(meta["scene_objects"])
                raise CacheFileError(f"{where} was built for another scene (or an edited one): "
                                     f"{fingerprint.differences(saved)}")
            if meta["settings"] != dict(settings_key):
                raise CacheFileError(f"{where} was built with other settings: "
                                     f"{_settings_differences(meta['settings'], settings_key)}")
            arrays = {k: data[k] for k in data.files if k != "meta"}
    except CacheFileError:
        raise
    except (OSError, KeyError, EOFError, ValueError, zipfile.BadZipFile, UnicodeDecodeError) as error:
        # (json.JSONDecodeError is a ValueError; so is NumPy's refusal of pickled data.)
        raise CacheFileError(f"{where} is corrupt or truncated ({type(error).__name__}: {error})") from error
    try:
        prepared = _build(meta["body"], arrays, scene, _classes())
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CacheFileError(f"{where} is corrupt ({type(error).__name__}: {error})") from error
    from .skylight import SkySampler
    from .pipeline import pack_for_queries, with_scene_bsdfs
    prepared.sky = SkySampler.build(scene)
    if prepared.gather_source is not None:  # (its diffuse_free: registry indices are this process's)
        with_scene_bsdfs(prepared.gather_source, prepared.info, scene)
    # (The packed layouts are derived, not stored: laid out again as after a build.)
    return pack_for_queries(prepared)
