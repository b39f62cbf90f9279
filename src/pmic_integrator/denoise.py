"""Denoising as a post-process: Intel Open Image Denoise on the CPU, OptiX on CUDA.

The integrator keeps outputting radiance; ask it for the denoiser's guides with
``aovs="albedo,normal"`` (or render with Mitsuba's ``aov`` integrator) and pass them
here::

    integrator = mi.load_dict({"type": "pmic", "aovs": "albedo,normal"})
    image = mi.render(scene, integrator=integrator, spp=16)
    parts = pmic_integrator.split_channels(image, integrator)
    clean = pmic_integrator.denoise(parts["color"], parts["albedo"], parts["normal"])

On a ``cuda_*`` variant :func:`denoise` uses Mitsuba's ``mi.OptixDenoiser`` (guides:
the shading normal in the sensor's frame, which it converts from world space when given
the sensor); elsewhere OIDN through PyPI's ``pyoidn`` (a dependency of pmic), RT filter,
HDR, quality "high". Inputs may be NumPy arrays, ``mi.TensorXf`` or ``mi.Bitmap``; the
result is a float32 NumPy array of shape (H, W, 3).
"""
from __future__ import annotations

import numpy as np

#: OIDN's filter quality: "high" is its default for final frames (what users run).
OIDN_QUALITY = "high"


def _as_rgb(name: str, value, shape=None) -> np.ndarray:
    array = np.array(value, dtype=np.float32, copy=True)
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"denoise: '{name}' must be an (H, W, 3) image, got shape {array.shape}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"denoise: '{name}' must have the image's shape {shape}, got {array.shape}")
    # A denoiser given NaN/Inf spreads it over its whole receptive field.
    return np.nan_to_num(array, nan=0.0, posinf=0.0, neginf=0.0)


def split_channels(image, integrator=None, names=None) -> dict:
    """Split a rendered (H, W, 3 + AOVs) image into ``{"color": ..., <aov>: ...}``.

    Channels are grouped by the prefix of the integrator's ``aov_names()`` (``albedo.R``,
    ``albedo.G``, ``albedo.B`` → ``"albedo"``); pass ``names`` instead of an integrator
    for images from other integrators (Mitsuba's ``aov`` integrator names its channels
    after its ``aovs`` parameter in the same way).
    """
    array = np.array(image, dtype=np.float32)
    names = list(names if names is not None else integrator.aov_names())
    if array.ndim != 3 or array.shape[2] != 3 + len(names):
        raise ValueError(f"split_channels: expected an (H, W, {3 + len(names)}) image for "
                         f"channels {names}, got shape {array.shape}")
    parts = {"color": array[..., :3]}
    groups: dict = {}
    for k, name in enumerate(names):
        groups.setdefault(name.split(".")[0], []).append(3 + k)
    for group, channels in groups.items():
        parts[group] = array[..., channels] if len(channels) > 1 else array[..., channels[0]]
    return parts


def denoise(image, albedo=None, normal=None, *, sensor=None, backend: str = "auto") -> np.ndarray:
    """Denoised copy of an HDR ``image`` (H, W, 3), guided by ``albedo`` and ``normal``.

    ``backend``: ``"auto"`` (OptiX on a CUDA variant, else OIDN), ``"oidn"`` or
    ``"optix"``. A normal guide needs an albedo guide (both denoisers' rule).
    """
    if backend not in ("auto", "oidn", "optix"):
        raise ValueError(f"denoise: 'backend' must be one of auto, oidn, optix, got {backend!r}")
    color = _as_rgb("image", image)
    albedo = None if albedo is None else _as_rgb("albedo", albedo, color.shape)
    normal = None if normal is None else _as_rgb("normal", normal, color.shape)
    if normal is not None and albedo is None:
        raise ValueError("denoise: a 'normal' guide needs an 'albedo' guide too")
    if albedo is not None:
        albedo = np.clip(albedo, 0.0, 1.0)
    if backend == "auto":
        import mitsuba as mi
        backend = "optix" if mi.variant() and mi.variant().startswith("cuda") else "oidn"
    if backend == "optix":
        return _optix(color, albedo, normal, sensor)
    return _oidn(color, albedo, normal)


def _oidn(color, albedo, normal) -> np.ndarray:
    try:
        import pyoidn
    except ImportError as error:  # pragma: no cover - pyoidn is a dependency
        raise RuntimeError("denoise: OIDN needs the 'pyoidn' package (pip install pyoidn)") from error
    if normal is not None:
        normal = np.clip(normal, -1.0, 1.0)
    out = pyoidn.denoise(np.ascontiguousarray(color), albedo, normal, hdr=True, quality=OIDN_QUALITY)
    return np.asarray(out, dtype=np.float32)


def _optix(color, albedo, normal, sensor) -> np.ndarray:  # pragma: no cover - needs a GPU
    import mitsuba as mi
    h, w = color.shape[:2]
    denoiser = mi.OptixDenoiser(mi.ScalarVector2u(w, h), albedo is not None, normal is not None)
    kwargs = {}
    if albedo is not None:
        kwargs["albedo"] = mi.TensorXf(albedo)
    if normal is not None:
        kwargs["normals"] = mi.TensorXf(normal)
        if sensor is not None:
            kwargs["to_sensor"] = sensor.world_transform().inverse()
    return np.array(denoiser(mi.TensorXf(color), **kwargs), dtype=np.float32)
