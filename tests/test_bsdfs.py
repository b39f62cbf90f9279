"""The diffuse response (``bsdfs.diffuse_response``): what a vertex that reads the
cache reflects per unit irradiance, (1/π) ∫ f(wo) cos θ dω, checked against a dense
quadrature of the same integral (one million directions) for the BSDFs whose lobes
are not symmetric about the shading normal (a normal map, a bump map) or fall
towards grazing angles (coated plastics)."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator.bsdfs import diffuse_context, diffuse_response, lobes_lean
from pmic_integrator.spectra import reference_wavelengths

DIFFUSE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8] * 3}}


def _normal_map(tilt_deg, azimuth_deg, inner=DIFFUSE):
    """A ``normalmap`` of one tangent-space normal, tilted by ``tilt_deg`` towards the
    azimuth ``azimuth_deg`` (0: the tangent, 90: the bitangent)."""
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    normal = np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])
    texel = (0.5 * normal + 0.5).astype(np.float32)
    return {"type": "normalmap", "bsdf": inner,
            "normalmap": {"type": "bitmap", "raw": True, "bitmap": mi.Bitmap(np.tile(texel, (4, 4, 1)))}}


def _interaction(width, wi):
    si = dr.zeros(mi.SurfaceInteraction3f, width)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    si.uv = mi.Point2f(0.5, 0.5)
    si.wi = dr.normalize(mi.Vector3f(*wi))
    if mi.is_spectral:  # (four fixed wavelengths; the first is compared below)
        si.wavelengths = reference_wavelengths(width)
    return si


def _dense_response(bsdf, wi, side=1000):
    """(1/π) ∫ f cos dω by the midpoint rule on a side × side grid in (cos θ, φ)
    (uniform in solid angle, so the mean is ∫ / 2π)."""
    n = side * side
    i = dr.arange(mi.Float, n)
    row = dr.floor(i / side)
    cos_t = (row + 0.5) / side
    phi = (i - row * side + 0.5) / side * (2 * math.pi)
    sin_t = dr.sqrt(1 - cos_t * cos_t)
    wo = mi.Vector3f(sin_t * dr.cos(phi), sin_t * dr.sin(phi), cos_t)
    value = mi.Spectrum(bsdf.eval(diffuse_context(), _interaction(n, wi), wo))
    return 2.0 * float(dr.mean(value[0])[0])


def _response(bsdf, wi):
    return float(diffuse_response(bsdf, _interaction(1, wi), True)[0][0])


@pytest.mark.parametrize("name, bsdf, tolerance", [
    ("diffuse", DIFFUSE, 1e-4),
    # before: +1.6 % (four cosine-weighted directions)
    ("plastic", {"type": "plastic"}, 0.005),
    ("plastic index 2", {"type": "plastic", "int_ior": 2.0}, 0.005),
    ("rough plastic", {"type": "roughplastic", "alpha": 0.3}, 0.005),
    ("flat normal map", _normal_map(0, 0), 1e-4),
    # before: 1.05, 0.72, 0.90, 0.93 of the dense value (one azimuth per level)
    ("normal map tilted 30° along the tangent", _normal_map(30, 0), 0.02),
    ("normal map tilted 30° along the bitangent", _normal_map(30, 90), 0.02),
    ("normal map tilted 30° against the tangent", _normal_map(30, 180), 0.02),
    ("normal map tilted 30° diagonally", _normal_map(30, 45), 0.02),
    ("normal map tilted 20° under plastic", _normal_map(20, 135, {"type": "plastic"}), 0.02),
])
@pytest.mark.parametrize("wi", [(0.3, 0.2, 0.93), (0.8, 0.0, 0.6)])
def test_diffuse_response_matches_a_dense_quadrature(name, bsdf, tolerance, wi):
    bsdf = mi.load_dict(bsdf)
    assert _response(bsdf, wi) == pytest.approx(_dense_response(bsdf, wi), rel=tolerance), name


def test_diffuse_response_of_the_back_of_a_twosided_surface():
    bsdf = mi.load_dict({"type": "twosided", "bsdf": _normal_map(30, 90)})
    front, back = (0.3, 0.2, 0.93), (0.3, 0.2, -0.93)
    assert _response(bsdf, back) == pytest.approx(_response(bsdf, front), rel=1e-5)


@pytest.mark.parametrize("bsdf, leans", [
    (DIFFUSE, False),
    ({"type": "plastic"}, False),
    ({"type": "roughplastic", "alpha": 0.3}, False),
    ({"type": "twosided", "bsdf": {"type": "roughplastic"}}, False),
    ({"type": "blendbsdf", "weight": 0.5, "bsdf_0": DIFFUSE, "bsdf_1": {"type": "roughconductor"}}, False),
    ({"type": "dielectric"}, False),  # (no diffuse lobe: never read)
    (_normal_map(30, 90), True),
    ({"type": "twosided", "bsdf": _normal_map(30, 90)}, True),
    ({"type": "principled", "roughness": 0.5}, True),
])
def test_which_lobes_lean(bsdf, leans):
    """Scenes whose lobes all stand symmetric about the shading normal evaluate the
    response at one azimuth per level (``bsdfs.lobes_lean``)."""
    assert lobes_lean(mi.load_dict(bsdf)) is leans


@pytest.mark.parametrize("bsdf", [DIFFUSE, {"type": "plastic"}, {"type": "roughplastic", "alpha": 0.3}])
def test_one_azimuth_serves_lobes_that_do_not_lean(bsdf):
    bsdf = mi.load_dict(bsdf)
    si = _interaction(1, (0.3, 0.2, 0.93))
    one = float(diffuse_response(bsdf, si, True, azimuths=1)[0][0])
    assert one == pytest.approx(float(diffuse_response(bsdf, si, True)[0][0]), rel=1e-5)


def test_a_tilt_needs_three_azimuths():
    with pytest.raises(ValueError, match="azimuths"):
        diffuse_response(mi.load_dict(DIFFUSE), _interaction(1, (0, 0, 1)), True, with_tilt=True,
                         azimuths=1)
