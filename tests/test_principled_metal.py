"""A ``principled`` metal (``metallic`` 1) or glass (``spec_trans`` 1, no sheen) has
glossy lobes only, though its flags list a diffuse one: photons, gathers and camera
paths read it as a rough conductor or dielectric
(:func:`pmic_integrator.bsdfs.diffuse_free`), so the light it reflects or transmits onto
diffuse surfaces is a caustic the caustic map holds.
"""
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator.bsdfs import diffuse_free, lobe_flags, scene_diffuse_free
from pmic_integrator.metrics import REC709_LUMINANCE as LUMINANCE

BRASS = {"type": "principled", "base_color": {"type": "rgb", "value": [0.8, 0.6, 0.3]},
         "metallic": 1.0, "roughness": 0.25}
GLASS = {"type": "principled", "spec_trans": 1.0, "roughness": 0.1, "eta": 1.5}
DIFFUSE = int(mi.BSDFFlags.Diffuse)


def _brass_box(res=32, normal_map=False):
    """Mitsuba's Cornell box with a brass tall box and a smoother two-sided brass short
    one (as the public glossy Cornell box's tall box): their tops reflect the light
    onto the ceiling. With ``normal_map``, the short one under a flat normal map."""
    from stress_cases import cornell

    d, _ = cornell(res=res)
    d["large-box"]["bsdf"] = BRASS
    d["small-box"]["bsdf"] = {"type": "twosided", "bsdf": {**BRASS, "roughness": 0.1}}
    if normal_map:
        d["small-box"]["bsdf"] = _normal_mapped(d["small-box"]["bsdf"])
    return mi.load_dict(d)


def _normal_mapped(bsdf):
    """``bsdf`` under a flat normal map (a dict; its tensor is taken by the load)."""
    flat = {"type": "bitmap", "raw": True, "data": mi.TensorXf(np.full((2, 2, 3), 0.5, np.float32))}
    return {"type": "normalmap", "normalmap": flat, "bsdf": bsdf}


def _glass_sphere(res=32):
    """Mitsuba's Cornell box with a sphere of principled glass (rough 0.1) standing in
    place of the tall box: its caustic on the floor."""
    from stress_cases import cornell

    d, _ = cornell(res=res, bsdf_object=GLASS)
    return mi.load_dict(d)


SCENES = {"brass": _brass_box, "glass": _glass_sphere,
          "brass_normal_mapped": lambda res=32: _brass_box(res, normal_map=True)}


def test_principled_metals_are_told_apart_from_other_bsdfs():
    assert diffuse_free(mi.load_dict(BRASS))
    assert diffuse_free(mi.load_dict({"type": "twosided", "bsdf": BRASS}))
    assert diffuse_free(mi.load_dict(_normal_mapped({"type": "twosided", "bsdf": BRASS})))
    assert not diffuse_free(mi.load_dict(_normal_mapped({"type": "principled"})))
    assert not diffuse_free(mi.load_dict({**BRASS, "metallic": 0.9}))
    assert diffuse_free(mi.load_dict(GLASS))
    assert not diffuse_free(mi.load_dict({**GLASS, "spec_trans": 0.9}))
    # Mitsuba's sheen is weighed by 1 - metallic only: principled glass with sheen has it.
    assert not diffuse_free(mi.load_dict({**GLASS, "sheen": 0.5}))
    # A textured metallic may be under 1 somewhere: not read.
    assert not diffuse_free(mi.load_dict({**BRASS, "metallic": {
        "type": "checkerboard", "color0": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
        "color1": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}))
    assert not diffuse_free(mi.load_dict({"type": "principled"}))
    assert not diffuse_free(mi.load_dict({"type": "roughconductor"}))
    assert not diffuse_free(mi.load_dict({"type": "diffuse"}))


def test_only_a_metal_lane_loses_its_diffuse_flag():
    """Per lane (a BSDF pointer's registry index), the flags the walks read: the
    metal's without its diffuse lobe, every other BSDF's as Mitsuba gives them."""
    scene = mi.load_dict({"type": "scene",
                          "metal": {"type": "sphere", "bsdf": BRASS},
                          "plastic": {"type": "sphere", "center": [3, 0, 0], "bsdf": {"type": "principled"}},
                          "wall": {"type": "sphere", "center": [6, 0, 0], "bsdf": {"type": "diffuse"}}})
    table = scene_diffuse_free(scene)
    assert table is not None
    pointers = scene.shapes_dr().bsdf()
    raw, read = np.array(pointers.flags()), np.array(lobe_flags(pointers, table))
    metal = np.array([diffuse_free(shape.bsdf()) for shape in scene.shapes()])
    assert metal.sum() == 1
    assert (raw & DIFFUSE).all()
    assert not (read[metal] & DIFFUSE).any()
    assert (read[metal] == (raw[metal] & np.uint32(~DIFFUSE & 0xFFFFFFFF))).all()
    assert (read[~metal] == raw[~metal]).all()
    plain = mi.load_dict({"type": "scene", "wall": {"type": "sphere", "bsdf": {"type": "principled"}}})
    assert scene_diffuse_free(plain) is None


@pytest.mark.parametrize("kind", SCENES)
def test_principled_metal_and_glass_cast_caustics(kind):
    """Before, a photon's bounce off a principled metal or glass counted as diffuse (its
    lobes cannot be taken apart by a context's mask): no caustic photon was stored in
    either scene (the map was dropped) and camera paths found the light they send onto
    the ceiling or the floor only by tracing (the public glossy Cornell box: 0 ->
    ~23 000 of the caustic pass's photons, relMSE 2.0e-2 -> 1.5e-2 at 16 spp)."""
    integrator = mi.load_dict({"type": "pmic", "global_photons": 50_000, "caustic_photons": 10_000,
                               "gather_rays": 64})
    stats = integrator.build_cache(SCENES[kind](res=16))
    assert stats["photons_caustic"] >= 5_000  # (before: 0)


@pytest.mark.parametrize("kind", SCENES)
@pytest.mark.parametrize("estimator", ["adaptive", "final_gather", "first_hit"])
def test_principled_metal_and_glass_match_path(kind, estimator):
    """The light the brass reflects, or the glass transmits, onto diffuse surfaces is
    counted once: by the caustic map where a traced vertex reads it, never again by the
    paths that continue through the brass or the glass to the light. Against ``path``
    at 4096 spp (pixels that see the light left out), two seeds at 64 spp: brass
    0.996-0.999 (before the map held it: 0.989-1.012), glass 0.997-1.004 (before:
    0.991-1.002), the glass's relMSE 0.8-2.4e-3 (before 2.3e-3-2.1e-2 with the
    adaptive estimator and the final gather). For the brass, also its top six rows (the
    ceiling it lights): 1.007-1.012 (before 0.957-1.091)."""
    scene = SCENES[kind]()
    reference = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=4096, seed=1))
    reference = reference[..., :3] @ LUMINANCE
    seen = reference < 1.0
    image_ratio, ceiling_ratio = [], []
    for seed in (0, 1):
        integrator = mi.load_dict({"type": "pmic", "estimator": estimator, "seed": seed,
                                   "global_photons": 100_000, "caustic_photons": 20_000, "gather_rays": 64})
        image = np.array(mi.render(scene, integrator=integrator, spp=64, seed=seed))
        assert np.isfinite(image).all()
        image = image[..., :3] @ LUMINANCE
        image_ratio.append(image[seen].mean() / reference[seen].mean())
        ceiling_ratio.append(image[:6][seen[:6]].mean() / reference[:6][seen[:6]].mean())
    assert np.mean(image_ratio) == pytest.approx(1.0, abs=0.015)
    if kind != "glass":
        assert np.mean(ceiling_ratio) == pytest.approx(1.0, abs=0.03)
