"""The bundled test scenes, their path-traced references, and EXR input/output.

The scenes live as Mitsuba 3 XML files in the repository's top-level ``scenes/`` folder
(next to ``src/``), so they can be opened by any Mitsuba tool, not only through this
module. Each XML file takes the parameters ``res``, ``spp`` and ``integrator`` (a plugin
name); the ``<integrator>`` element carries no properties, so any integrator type loads
it and the default ``path`` integrator is unbounded (``max_depth = -1``, Russian roulette
from its default ``rr_depth``).

Integrators that need properties (``{'type': 'pmic', 'photon_count': ...}``) cannot be
passed through an XML parameter, which substitutes plain strings only. For those,
:func:`load_scene` rebuilds the loaded scene around an integrator instance created by
:func:`make_integrator`, so that ``scene.integrator()`` is always the configured one and
``mi.render(scene)`` needs no extra argument.

References are stored as ``scenes/references/{name}_{resolution}.exr`` (RGB, float32,
linear) and are made by ``tools/make_references.py``.

This module never calls ``mi.set_variant``: the caller chooses the variant (the
references were rendered with ``llvm_ad_rgb``, but any RGB variant loads the scenes).
Set ``PMIC_SCENES_DIR`` to use a scene folder other than the bundled one.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

#: Names of the bundled scenes, in the order benchmarks report them.
SCENES: tuple[str, ...] = ("cornell_box", "cornell_caustics", "indirect_room", "exterior_envmap",
                          "interior_window")

#: Integrator used when none is given: Mitsuba's path tracer without a depth limit
#: (every bounce is kept, so its images converge to the references).
DEFAULT_INTEGRATOR: Mapping[str, Any] = {"type": "path", "max_depth": -1}

#: Environment variable that overrides the folder holding the scene XML files.
SCENES_DIR_ENV = "PMIC_SCENES_DIR"

#: Resolution of the committed references.
DEFAULT_RESOLUTION = 128


def scenes_dir() -> Path:
    """Folder with the scene XML files: ``$PMIC_SCENES_DIR``, else the repository's
    ``scenes/`` (a checkout or an editable install: ``src/pmic_integrator/scenes.py`` ->
    ``scenes/``), else the package's own copy (``pmic_integrator/data``, what
    ``pip install .`` installs)."""
    override = os.environ.get(SCENES_DIR_ENV)
    if override:
        return Path(override).expanduser().resolve()
    checkout = Path(__file__).resolve().parents[2] / "scenes"
    if (checkout / "cornell_box.xml").is_file():
        return checkout
    return Path(__file__).resolve().parent / "data"


def _check_name(name: str) -> str:
    if name not in SCENES:
        raise ValueError(
            f"scene must be one of {', '.join(repr(s) for s in SCENES)}; got {name!r}"
        )
    return name


def _check_resolution(resolution: int) -> int:
    if isinstance(resolution, bool) or int(resolution) != resolution or resolution < 1:
        raise ValueError(f"resolution must be a positive integer; got {resolution!r}")
    return int(resolution)


def scene_path(name: str) -> Path:
    """Path of the XML file of the bundled scene ``name`` (one of :data:`SCENES`).

    Raises ``ValueError`` for an unknown name, and ``FileNotFoundError`` when the scene
    folder does not contain the file (e.g. a wrong ``PMIC_SCENES_DIR``).
    """
    _check_name(name)
    path = scenes_dir() / f"{name}.xml"
    if not path.is_file():
        raise FileNotFoundError(
            f"scene file {path} not found (scene folder: {scenes_dir()}; "
            f"set {SCENES_DIR_ENV} to the folder holding the scene XML files)"
        )
    return path


def _mitsuba():
    """Import Mitsuba and check that the caller has chosen a variant.

    Loading a scene without a variant fails deep inside Mitsuba with an obscure error;
    this module must not pick one itself (the caller may want ``cuda_ad_rgb``, or may
    already hold objects of another variant), so it asks for one instead.
    """
    import mitsuba as mi

    if mi.variant() is None:
        raise RuntimeError(
            "no Mitsuba variant is set: call mitsuba.set_variant('llvm_ad_rgb') (or "
            "another RGB variant) before loading scenes or integrators"
        )
    return mi


def make_integrator(integrator: Mapping[str, Any] | None = None):
    """Instantiate an integrator from a ``mi.load_dict`` dictionary.

    ``None`` gives :data:`DEFAULT_INTEGRATOR` (unbounded ``path``). The dictionary is
    copied, so the caller's dictionary is never modified by Mitsuba.
    """
    mi = _mitsuba()
    spec = dict(DEFAULT_INTEGRATOR if integrator is None else integrator)
    if "type" not in spec:
        raise ValueError(f"integrator must have a 'type' key; got {spec!r}")
    return mi.load_dict(spec)


def load_file(path: str | os.PathLike, integrator: Mapping[str, Any] | Any | None = None, **params):
    """Load any Mitsuba scene file with ``pmic`` as its integrator, whatever the file
    says (or has no integrator at all).

    ``integrator``: pmic's parameters as a dict (``{"global_photons": 400_000}``; a dict
    with a ``type`` is any integrator's ``mi.load_dict`` dictionary), or an integrator
    object. ``params``: values for the file's ``$name`` parameters, as
    ``mi.load_file`` takes them (``spp=64``, ``res=256``).
    """
    mi = _mitsuba()
    if not Path(path).is_file():
        raise FileNotFoundError(f"load_file: no scene file {str(path)!r}")
    if not isinstance(integrator, mi.Integrator):
        spec = dict(integrator or {})
        integrator = mi.load_dict({"type": "pmic", **spec} if "type" not in spec else spec)
    return _with_integrator(mi.load_file(str(path), **params), integrator)


def _with_integrator(scene, integrator):
    """A new scene holding the objects of ``scene`` and the given integrator instance.

    ``mi.Scene`` has no setter for its integrator, but ``mi.load_dict`` accepts objects
    that already exist: the shapes (with their area emitters and BSDFs), the sensors and
    any emitter not attached to a shape are reused as they are, so nothing is loaded or
    allocated twice and an image rendered with the same seed is bit-identical to
    ``mi.render(scene, integrator=integrator)``.
    """
    mi = _mitsuba()
    spec: dict[str, Any] = {"type": "scene", "integrator": integrator}
    for i, sensor in enumerate(scene.sensors()):
        spec[f"sensor_{i}"] = sensor
    for i, shape in enumerate(scene.shapes()):
        spec[f"shape_{i}"] = shape
    for i, emitter in enumerate(scene.emitters()):
        # Area emitters come back with their shapes; add only the others (envmaps...).
        if not mi.has_flag(emitter.flags(), mi.EmitterFlags.Surface):
            spec[f"emitter_{i}"] = emitter
    return mi.load_dict(spec)


def load_scene(
    name: str,
    resolution: int = DEFAULT_RESOLUTION,
    spp: int = 64,
    integrator: Mapping[str, Any] | None = None,
):
    """Load a bundled scene at ``resolution`` x ``resolution`` pixels and ``spp`` samples.

    ``integrator`` is a ``mi.load_dict`` dictionary (``None``: unbounded ``path``) or an
    existing ``mi.Integrator``. A dictionary with only a ``type`` key is handed to the XML
    file's ``$integrator`` parameter; any other is instantiated with
    :func:`make_integrator` and the scene is rebuilt around it. Either way
    ``scene.integrator()`` is the requested integrator.
    """
    mi = _mitsuba()
    path = scene_path(name)
    resolution = _check_resolution(resolution)
    if isinstance(spp, bool) or int(spp) != spp or spp < 1:
        raise ValueError(f"spp must be a positive integer; got {spp!r}")
    if isinstance(integrator, mi.Integrator):
        scene = mi.load_file(str(path), res=resolution, spp=int(spp), integrator="path")
        return _with_integrator(scene, integrator)
    spec = dict(DEFAULT_INTEGRATOR if integrator is None else integrator)
    if "type" not in spec:
        raise ValueError(f"integrator must have a 'type' key; got {spec!r}")

    if set(spec) == {"type"} or spec == dict(DEFAULT_INTEGRATOR):
        # The XML's property-less <integrator> already is the unbounded path tracer.
        return mi.load_file(str(path), res=resolution, spp=int(spp), integrator=spec["type"])
    scene = mi.load_file(str(path), res=resolution, spp=int(spp), integrator="path")
    return _with_integrator(scene, mi.load_dict(spec))


def reference_path(name: str, resolution: int = DEFAULT_RESOLUTION) -> Path:
    """Path of the path-traced reference EXR of scene ``name`` at ``resolution``."""
    _check_name(name)
    resolution = _check_resolution(resolution)
    return scenes_dir() / "references" / f"{name}_{resolution}.exr"


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an RGB EXR file into a float32 H x W x 3 array (extra channels are dropped)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = exr.channels()
        missing = [c for c in "RGB" if c not in channels]
        if missing:
            raise ValueError(
                f"{path} has no {', '.join(missing)} channel(s); channels: {sorted(channels)}"
            )
        return np.stack([channels[c].pixels for c in "RGB"], axis=-1).astype(np.float32)


def check_positive_int(value, what: str) -> int:
    """``value`` as an int; ValueError "``what`` must be a positive integer" otherwise
    (a bool, a fraction, zero or less)."""
    if isinstance(value, bool) or int(value) != value or value < 1:
        raise ValueError(f"{what} must be a positive integer, got {value!r}")
    return int(value)


def _image_to_write(image, path) -> tuple[np.ndarray, Path]:
    """(``image`` as float32, checked to be H x W x 3; ``path``, its folder made)."""
    data = np.asarray(image, dtype=np.float32)
    if data.ndim != 3 or data.shape[2] != 3:
        raise ValueError(f"image must have shape (H, W, 3); got {data.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return data, path


def write_exr(
    path: str | os.PathLike, image, metadata: Mapping[str, Any] | None = None, half: bool = False
) -> None:
    """Write an H x W x 3 image as a float32 RGB EXR (ZIP compression, lossless), or
    with ``half`` as half floats (relative rounding under 5e-4, far under a reference's
    own noise; half the size).

    Accepts anything ``np.asarray`` accepts (a numpy array, ``mi.TensorXf``,
    ``mi.Bitmap``). ``metadata`` is stored as string attributes of the EXR header (the
    references record how they were made this way; see :func:`read_exr_metadata`).
    Parent folders are created as needed.
    """
    import OpenEXR

    data, path = _image_to_write(image, path)
    if half:
        data = data.astype(np.float16)
    channels = {c: np.ascontiguousarray(data[:, :, i]) for i, c in enumerate("RGB")}
    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
    }
    for key, value in (metadata or {}).items():
        header[str(key)] = str(value)
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def write_png(path: str | os.PathLike, image, exposure: float = 1.0) -> None:
    """Write an H x W x 3 linear image as an 8-bit sRGB PNG preview (scaled by
    ``exposure``, clipped at 1: :func:`pmic_integrator.metrics.tonemap_srgb`)."""
    from .metrics import tonemap_srgb

    data, path = _image_to_write(image, path)
    encoded = (tonemap_srgb(data, exposure) * 255 + 0.5).clip(0, 255).astype(np.uint8)
    _mitsuba().Bitmap(np.ascontiguousarray(encoded)).write(str(path))


def read_exr_metadata(path: str | os.PathLike) -> dict[str, str]:
    """The string attributes of an EXR header (those written through ``metadata``)."""
    import OpenEXR

    with OpenEXR.File(str(path), header_only=True) as exr:
        return {k: v for k, v in exr.header().items() if isinstance(v, str)}


def reference_command(name: str | None = None, resolution: int = DEFAULT_RESOLUTION) -> str:
    """Shell command that (re)creates the reference(s), for error messages and READMEs."""
    cmd = "python tools/make_references.py"
    if resolution != DEFAULT_RESOLUTION:
        cmd += f" --resolution {resolution}"
    if name is not None:
        cmd += f" --scenes {name}"
    return cmd


def load_reference(name: str, resolution: int = DEFAULT_RESOLUTION) -> np.ndarray:
    """The path-traced reference of scene ``name`` as a float32 H x W x 3 array.

    Raises ``FileNotFoundError`` with the command that renders it when it is missing
    (only the 128 x 128 references are committed).
    """
    path = reference_path(name, resolution)
    if not path.is_file():
        raise FileNotFoundError(
            f"no reference for scene {name!r} at {resolution}x{resolution}: {path} is "
            f"missing; render it with `{reference_command(name, resolution)}` "
            f"(run from the repository root)"
        )
    return read_exr(path)


__all__ = [
    "SCENES",
    "DEFAULT_INTEGRATOR",
    "SCENES_DIR_ENV",
    "scenes_dir",
    "scene_path",
    "make_integrator",
    "load_scene",
    "reference_path",
    "reference_command",
    "read_exr",
    "write_exr",
    "read_exr_metadata",
    "load_reference",
]
