"""Image error metrics used to compare renders against the path-traced references.

All functions take anything ``np.asarray`` accepts (numpy arrays, ``mi.TensorXf``,
``mi.Bitmap``) holding linear RGB images of shape H x W x 3, and return Python floats.
Computation is done in float64 so that the results do not depend on the input dtype.

``rel_mse`` is the project's headline metric, defined as in ``/work/shared/PEERS.md``:
``mean((img - ref)^2 / (ref^2 + eps))`` with ``eps = 1e-2``. Dividing by the squared
reference makes errors in dark and bright regions count alike; ``eps`` keeps black
pixels from dominating. ``luminance_ratio`` catches a biased overall brightness (e.g.
truncated light paths), which relMSE reports only weakly. ``ciede2000`` measures the
visible colour difference after a fixed display transform.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
REC709_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _as_image(img) -> np.ndarray:
    return np.asarray(img, dtype=np.float64)


def _pair(img, ref) -> tuple[np.ndarray, np.ndarray]:
    a, b = _as_image(img), _as_image(ref)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: img has shape {a.shape}, ref has shape {b.shape}")
    if a.size == 0:
        raise ValueError("images are empty")
    return a, b


def _rgb(img: np.ndarray, what: str) -> np.ndarray:
    if img.ndim < 1 or img.shape[-1] != 3:
        raise ValueError(f"{what} must have 3 colour channels in its last axis; got shape {img.shape}")
    return img


def rel_mse(img, ref, eps: float = 1e-2) -> float:
    """Relative MSE ``mean((img - ref)^2 / (ref^2 + eps))`` over all pixels and channels."""
    a, b = _pair(img, ref)
    return float(np.mean((a - b) ** 2 / (b * b + eps)))


def rmse(img, ref) -> float:
    """Root mean squared error over all pixels and channels."""
    a, b = _pair(img, ref)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def mean_luminance(img) -> float:
    """Mean Rec. 709 luminance of a linear RGB image."""
    a = _rgb(_as_image(img), "img")
    return float(np.mean(a @ REC709_LUMINANCE))


def luminance_ratio(img, ref) -> float:
    """``mean_luminance(img) / mean_luminance(ref)``: 1 means no overall bias."""
    a, b = _pair(img, ref)
    return mean_luminance(a) / mean_luminance(b)


def tonemap_srgb(img, exposure: float = 1.0) -> np.ndarray:
    """The fixed display transform used by :func:`ciede2000`.

    Scale by ``exposure``, clip to [0, 1], apply the sRGB OETF (IEC 61966-2-1). No
    adaptive tone curve: the comparison must not depend on the image's own statistics.
    """
    linear = np.clip(_as_image(img) * exposure, 0.0, 1.0)
    return np.where(
        linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1.0 / 2.4) - 0.055
    )


def _srgb_to_lab(encoded: np.ndarray) -> np.ndarray:
    # colour-science warns at import time about optional SciPy features that this
    # conversion does not use; keep that noise out of benchmark output.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour

        whitepoint = colour.RGB_COLOURSPACES["sRGB"].whitepoint
        xyz = colour.RGB_to_XYZ(encoded, "sRGB", apply_cctf_decoding=True)
        return colour.XYZ_to_Lab(xyz, whitepoint)


def ciede2000(img, ref) -> float:
    """Mean CIEDE2000 colour difference after :func:`tonemap_srgb` (exposure 1).

    Both images go through the same clip + sRGB encoding, are converted to CIE L*a*b*
    (D65) with colour-science and compared per pixel with ``colour.delta_E(...,
    method='CIE 2000')``. Values below ~1 are hard to see; clipped highlights (the
    light source) compare equal whatever their HDR values.
    """
    a, b = _pair(img, ref)
    _rgb(a, "img")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour

        delta = colour.delta_E(
            _srgb_to_lab(tonemap_srgb(a)), _srgb_to_lab(tonemap_srgb(b)), method="CIE 2000"
        )
    return float(np.mean(delta))


def gaussian_blur(img, sigma: float) -> np.ndarray:
    """Separable Gaussian blur (truncated at 3σ, edges mirrored) of an H x W x C image."""
    a = _as_image(img)
    if sigma <= 0:
        return a
    radius = max(1, int(math.ceil(3 * sigma)))
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    taps /= taps.sum()
    for axis in (0, 1):
        pad = [(0, 0)] * a.ndim
        pad[axis] = (radius, radius)
        padded = np.pad(a, pad, mode="symmetric")
        n = a.shape[axis]
        a = sum(w * np.take(padded, np.arange(k, k + n), axis=axis) for k, w in enumerate(taps))
    return a


def low_frequency_rel_mse(img, ref, sigma: float = 4.0, eps: float = 1e-2) -> float:
    """relMSE of both images blurred by a Gaussian of ``sigma`` pixels: the structured
    (blotchy) error that the eye sees and a denoiser cannot remove; pixel noise
    averages away under the blur."""
    a, b = _pair(img, ref)
    return rel_mse(gaussian_blur(a, sigma), gaussian_blur(b, sigma), eps)


def flip(img, ref) -> float:
    """Mean FLIP error (NVIDIA's ꟻLIP, PyPI ``flip-evaluator``), LDR, after
    :func:`tonemap_srgb`: 0 identical, 1 most different."""
    a, b = _pair(img, ref)
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(tonemap_srgb(b), dtype=np.float32),
                                         np.ascontiguousarray(tonemap_srgb(a), dtype=np.float32),
                                         "LDR", inputsRGB=True, applyMagma=False)
    return float(mean)


def finite(img) -> bool:
    """True when no pixel is NaN or infinite."""
    return bool(np.all(np.isfinite(_as_image(img))))


__all__ = [
    "REC709_LUMINANCE",
    "rel_mse",
    "rmse",
    "mean_luminance",
    "luminance_ratio",
    "tonemap_srgb",
    "ciede2000",
    "gaussian_blur",
    "low_frequency_rel_mse",
    "flip",
    "finite",
]
