"""Colour between the walks and the stored light: RGB in the maps and the cache, spectra
on the paths.

pmic stores photon power, irradiance and the cache's records as linear sRGB
(``mi.Color3f``) in every variant. In an RGB variant a path's quantities (``mi.Spectrum``)
are that same type and both functions here return their argument. In a spectral variant
a path carries four wavelengths:

* :func:`to_rgb` projects a path's spectral estimate (one that already holds its
  wavelengths' ``1/pdf``, as a camera weight or an emitter sample does) onto linear sRGB,
  as Mitsuba's film does (``mi.spectrum_to_srgb``). Photons are stored this way.
* :func:`from_rgb` turns stored RGB back into a spectrum at a path's wavelengths, so
  that a BSDF evaluated there can multiply it: the D65 illuminant (Mitsuba's white: an
  ``rgb`` emitter of (1, 1, 1)) times a sum of three smooth basis spectra, one per
  channel, that add up to one at every wavelength. The basis is solved once per variant
  (:func:`_basis_table`): the smoothest spectra (least first differences on 48 knots,
  360-830 nm) whose film projections are exactly the unit primaries. So the projection of
  ``from_rgb(c)`` is ``c`` (a round trip, tested), and grey light is D65 exactly.

The error this leaves: a BSDF's spectrum times the upsampled light is not its product
with the light's true spectrum (one that the RGB triple cannot tell apart). For
reflectances upsampled by Mitsuba's own model and light of smooth spectra it is small
(docs/method.md, "Spectral variants", gives the measured figures).
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi
import numpy as np

#: Wavelength range of Mitsuba's spectral variants (``mi.MI_CIE_MIN``/``MI_CIE_MAX``, nm).
LAMBDA_MIN, LAMBDA_MAX = 360.0, 830.0
#: Knots of the smooth basis (10 nm apart); its table is tabulated per nanometre.
BASIS_KNOTS = 48
#: Weight of "the three basis spectra add up to one" against their smoothness.
PARTITION_WEIGHT = 1e3


def channel_mean(value) -> mi.Float:
    """The mean of a spectrum's channels (three in RGB, four wavelengths in spectral)."""
    if not mi.is_spectral:
        return (value.x + value.y + value.z) * (1.0 / 3.0)
    return (value[0] + value[1] + value[2] + value[3]) * 0.25


def to_rgb(value, wavelengths) -> mi.Color3f:
    """Linear sRGB of a path's estimate ``value`` (``mi.Spectrum``) at ``wavelengths``."""
    if not mi.is_spectral:
        return value
    return mi.spectrum_to_srgb(mi.Spectrum(value), wavelengths)


def prepare_basis() -> None:
    """Build :func:`from_rgb`'s table now, before a symbolic loop that calls it: built
    inside one, its arrays cannot be evaluated (RGB variants: nothing to do)."""
    if mi.is_spectral:
        _basis_table(mi.variant())


def from_rgb(rgb, wavelengths) -> mi.Spectrum:
    """The spectrum at ``wavelengths`` of stored linear sRGB ``rgb`` (see the module)."""
    if not mi.is_spectral:
        return rgb
    channels = _basis_table(mi.variant())
    rgb = mi.Color3f(rgb)
    out = []
    for i in range(len(wavelengths)):
        # (The table holds one value per nanometre from LAMBDA_MIN.)
        x = dr.clip(wavelengths[i] - LAMBDA_MIN, 0.0, LAMBDA_MAX - LAMBDA_MIN - 0.001)
        k = mi.UInt32(x)
        t = x - mi.Float(k)
        value = mi.Float(0.0)
        for c in range(3):
            lo = dr.gather(mi.Float, channels[c], k)
            hi = dr.gather(mi.Float, channels[c], k + 1)
            value += rgb[c] * dr.lerp(lo, hi, t)
        out.append(value)
    return mi.Spectrum(*out)


def sample_wavelengths(sample: mi.Float):
    """Wavelengths for a walk that starts at a surface (a record's gather rays), and the
    weight that makes :func:`to_rgb` of its estimate unbiased: Mitsuba's sensor
    sampling (``mi.sample_rgb_spectrum``). RGB variants: ``(None, 1)``."""
    if not mi.is_spectral:
        return None, mi.Float(1.0)
    wavelengths, weight = mi.sample_rgb_spectrum(mi.sample_shifted(sample))
    return wavelengths, weight


def rgb_of(evaluate, lanes: int, rounds: int = 4) -> mi.Color3f:
    """Linear sRGB of ``evaluate(wavelengths)`` (a spectrum at the lanes' wavelengths,
    e.g. an environment's radiance) by a fixed quadrature: ``rounds`` times four
    stratified wavelengths, the same at every lane (tables built once per scene want
    the colour, not a sample of it). RGB variants: ``evaluate(None)``."""
    if not mi.is_spectral:
        return mi.Color3f(evaluate(None))
    total = dr.zeros(mi.Color3f, lanes)
    for r in range(rounds):
        wavelengths, weight = sample_wavelengths(dr.full(mi.Float, (r + 0.5) / (4 * rounds), lanes))
        total += to_rgb(evaluate(wavelengths) * weight, wavelengths)
    return total * (1.0 / rounds)


def reflectance_to_rgb(value, wavelengths) -> mi.Color3f:
    """Linear sRGB of a reflectance (an albedo) seen at a camera path's ``wavelengths``
    (drawn by ``mi.sample_rgb_spectrum``): under D65, white's spectrum, so that a white
    surface reads (1, 1, 1). RGB variants: ``value``."""
    if not mi.is_spectral:
        return value
    white = from_rgb(mi.Color3f(1.0), wavelengths)
    return to_rgb(value * white / mi.pdf_rgb_spectrum(wavelengths), wavelengths)


def camera_to_rgb(value, wavelengths) -> mi.Color3f:
    """Linear sRGB of a camera path's radiance ``value`` at ``wavelengths`` drawn by
    ``mi.sample_rgb_spectrum`` (as Mitsuba's sensors draw them): for AOVs, which the
    film takes as they are. RGB variants: ``value``."""
    if not mi.is_spectral:
        return value
    return to_rgb(value / mi.pdf_rgb_spectrum(wavelengths), wavelengths)


def spread(lanes: int) -> mi.Float:
    """One number in [0, 1) per lane, evenly spread (a golden-ratio sequence): a
    wavelength sample for probes that need no randomness of their own."""
    k = dr.arange(mi.Float, lanes) * 0.6180339887 + 0.5
    return k - dr.floor(k)


def reference_wavelengths(lanes: int):
    """Four fixed wavelengths spread over the visible range (450, 520, 580, 640 nm), for
    probes that ask whether a BSDF reflects at all (its largest value over them)."""
    if not mi.is_spectral:
        return None
    return mi.Spectrum(*[dr.full(mi.Float, w, lanes) for w in (450.0, 520.0, 580.0, 640.0)])


@functools.lru_cache(maxsize=None)
def _basis_table(variant: str) -> list:
    """D65 times each channel's basis spectrum, one value per nanometre from LAMBDA_MIN."""
    lam = np.arange(LAMBDA_MIN, LAMBDA_MAX + 0.5, 1.0)
    response, d65 = _film_response(lam)
    knots = np.linspace(LAMBDA_MIN, LAMBDA_MAX, BASIS_KNOTS)
    hats = np.array([np.interp(lam, knots, row) for row in np.eye(BASIS_KNOTS)])
    # Film projection of D65 times each knot's hat function.
    project = np.trapezoid(response[:, None, :] * (d65 * hats)[None], lam, axis=2)
    basis = _smoothest_basis(project)
    return [mi.Float((d65 * np.interp(lam, knots, basis[c])).astype(np.float32)) for c in range(3)]


def _film_response(lam: np.ndarray):
    """The film's linear sRGB per unit of spectrum at each wavelength of ``lam`` (per nm,
    so that a spectrum's projection is its integral against it), and D65 there."""
    grid = mi.Float(lam.astype(np.float32))
    wavelengths = mi.Spectrum(grid, grid, grid, grid)
    response = np.array(mi.spectrum_to_srgb(mi.Spectrum(1.0), wavelengths), dtype=np.float64)
    si = dr.zeros(mi.SurfaceInteraction3f, len(lam))
    si.wavelengths = wavelengths
    d65 = np.array(mi.load_dict({"type": "d65"}).eval(si), dtype=np.float64)[0]
    return response, d65


def _smoothest_basis(project: np.ndarray) -> np.ndarray:
    """Three knot vectors b_c: least squared first differences, plus PARTITION_WEIGHT
    times (sum_c b_c - 1)^2, subject to ``project @ b_c`` = the c-th unit vector."""
    k = project.shape[1]
    diff = np.diff(np.eye(k), 1, axis=0)
    n = 3 * k
    quad = np.zeros((n, n))
    for c in range(3):
        quad[c * k:(c + 1) * k, c * k:(c + 1) * k] = diff.T @ diff
    total = np.hstack([np.eye(k)] * 3)
    quad += PARTITION_WEIGHT * total.T @ total
    linear = PARTITION_WEIGHT * total.T @ np.ones(k)
    constraints = np.zeros((9, n))
    targets = np.zeros(9)
    for c in range(3):
        constraints[3 * c:3 * c + 3, c * k:(c + 1) * k] = project
        targets[3 * c + c] = 1.0
    system = np.block([[2 * quad, constraints.T], [constraints, np.zeros((9, 9))]])
    solution = np.linalg.solve(system, np.concatenate([2 * linear, targets]))
    return solution[:n].reshape(3, k)
