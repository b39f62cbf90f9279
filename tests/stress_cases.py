"""Scenes and a case runner for the robustness / stress tests (``test_stress.py``).

Run as a script, this module executes the job described by a JSON object (its first
command-line argument) in this fresh process and prints one line
``STRESS-RESULT {...json...}``. ``test_stress.py`` launches it in a subprocess with a
timeout, so a hang, an abort or a segfault in one case cannot take the test session (or
the other cases) down with it.

A job is a dict with a ``kind``:

* ``render``: build ``scene``, render it with pmic (``params`` on top of ``SMALL``,
  ``spp``); report the mean luminance, non-finite values, errors, warnings, stats.
* ``error``: build pmic through ``mi.load_dict`` (as a user does) and, if that works,
  render ``scene`` with it; report the exception text, or that none came.
* ``load``: a list of parameter sets (``param_sets``), each only *constructed* (no
  rendering: nothing risky); report each exception text or that it was accepted.
* ``references``: a list of reference jobs (``refs``), each rendering a scene with
  Mitsuba's ``path`` in ``PATH_PASSES`` passes; report each mean and its standard error.
* ``compare``: a reference (``ref``, as in ``references``) and then ``render``, in one
  process (the hypothesis scene fuzzing uses it).
* ``repeat``: pmic twice with one integrator object, once with a fresh object; report
  whether the three images are bit-identical.
* ``edit``: pmic, then double the light's radiance through ``mi.traverse``, pmic again
  with the same integrator object; report both means.
* ``threads``: pmic once on this thread, then the same integrator object from two Python
  threads at once; report whether each thread's image equals the single-thread image.

``python stress_cases.py --serve`` instead reads one JSON job per line on stdin and
answers each with a result line (a persistent worker, for the hypothesis tests).

Scenes are small (48x48 unless told otherwise), with a box pixel filter and the
``stratified`` sampler: several scenes show their light directly, and with independent
pixel samples the few pixels on a bright light's edge make the image mean noisy by
several per cent at 16 spp (measured: 3.8 % at 32x32, 16 spp, independent; 0.5 % at
48x48, 16 spp, stratified).
"""
from __future__ import annotations

import json
import logging
import math
import sys
import time
import traceback

RESULT_TAG = "STRESS-RESULT "

#: Small pmic settings used by every case unless it overrides them.
SMALL = {"global_photons": 30_000, "caustic_photons": 10_000, "gather_rays": 64}
#: pmic samples per pixel (a square: the stratified sampler wants one).
PMIC_SPP = 16
#: path's reference is rendered in this many passes with different seeds: the spread of
#: the pass means gives the reference's own standard error.
PATH_PASSES = 4
PATH_SPP = 256  # 48x48: path's mean good to ~0.2 % (measured; the test wants <= 1 %)
RES = 48


# -------------------------------------------------------------------------------------
# Scenes. Every builder returns (scene dict, light_scale): light_scale is the largest
# radiance / intensity / irradiance of the scene's (finite) lights; "black" bounds are
# relative to it.
# -------------------------------------------------------------------------------------
def _mi():
    import mitsuba as mi
    return mi


def _T():
    return _mi().ScalarTransform4f()


def _rgb(v):
    if isinstance(v, (int, float)):
        v = [v, v, v]
    return {"type": "rgb", "value": [float(x) for x in v]}


def _diffuse(v):
    return {"type": "diffuse", "reflectance": _rgb(v)}


def _sensor(origin, target, res, fov=40.0, up=(0, 1, 0), scale=1.0):
    return {
        "type": "perspective", "fov": fov, "fov_axis": "smaller",
        "near_clip": 1e-3 * scale, "far_clip": 1e4 * scale,
        "to_world": _T().look_at(origin=list(origin), target=list(target), up=list(up)),
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                 "pixel_format": "rgb"},
        "sampler": {"type": "stratified", "sample_count": PMIC_SPP},
    }


EMITTER_TYPES = ("area", "point", "spot", "directional", "constant", "envmap")


def _emitter_scale(em):
    for key in ("radiance", "intensity", "irradiance"):
        v = em.get(key)
        if isinstance(v, dict) and "value" in v:
            vals = v["value"] if isinstance(v["value"], (list, tuple)) else [v["value"]]
            finite = [abs(x) for x in vals if math.isfinite(x)]
            return max(finite) if finite else 0.0
    return 1.0


def cornell(res=RES, scale=1.0, light=True, radiance_factor=1.0, back=None, extra=None,
            bsdf_object=None, twosided_panel=False, thin_slab=False, zero_area=False,
            hidden_light=False, light_texture=None):
    """Mitsuba's Cornell box (open at the front), optionally scaled and edited."""
    mi = _mi()
    d = mi.cornell_box()
    d.pop("integrator", None)
    light_scale = 0.0
    if light:
        rad = [c * radiance_factor for c in d["light"]["emitter"]["radiance"]["value"]]
        d["light"]["emitter"]["radiance"]["value"] = rad
        light_scale = max(rad)
        if light_texture is not None:
            d["light"]["emitter"]["radiance"] = light_texture
            light_scale = max(light_texture.get("color0", 1.0), light_texture.get("color1", 1.0))
    else:
        d.pop("light")
    if back is not None:
        d["back"]["bsdf"] = back
    if bsdf_object is not None:
        # The tested BSDF on a sphere standing where the large box was.
        d.pop("large-box", None)
        d["object"] = {"type": "sphere", "center": [-0.35, -0.6, -0.25], "radius": 0.4,
                       "bsdf": bsdf_object}
    if twosided_panel:
        # A panel whose front faces the back wall: the camera sees its back side.
        d["panel"] = {"type": "rectangle",
                      "to_world": _T().translate([0.0, -0.1, 0.45]) @ _T().rotate([0, 1, 0], 180)
                      @ _T().scale([0.35, 0.35, 1.0]),
                      "bsdf": {"type": "twosided", "bsdf": _diffuse([0.8, 0.8, 0.2])}}
    if thin_slab:
        # A floating slab 2e-4 thick under the light (its underside is lit indirectly).
        d["slab"] = {"type": "cube", "to_world": _T().translate([0.0, 0.35, 0.1])
                     @ _T().scale([0.45, 1e-4, 0.45]), "bsdf": {"type": "ref", "id": "white"}}
    if zero_area:
        # A rectangle squashed to zero area (scale 0 on one axis) in mid-air.
        d["flat"] = {"type": "rectangle", "to_world": _T().translate([0.2, 0.1, 0.3])
                     @ _T().scale([0.4, 0.0, 1.0]), "bsdf": {"type": "ref", "id": "white"}}
    if hidden_light:
        # An area light facing the camera in front of a red back wall.
        d["back"]["bsdf"] = {"type": "ref", "id": "red"}
        d["front-light"] = {"type": "rectangle",
                            "to_world": _T().translate([0.1, 0.1, -0.6]) @ _T().scale(0.25),
                            "emitter": {"type": "area", "radiance": _rgb(4.0)}}
        light_scale = max(light_scale, 4.0)
    for key, value in (extra or {}).items():
        d[key] = value
        em = value if value.get("type") in EMITTER_TYPES else value.get("emitter")
        if isinstance(em, dict):
            light_scale = max(light_scale, _emitter_scale(em))
    d["sensor"] = _sensor([0, 0, 3.9 * scale], [0, 0, 0], res, fov=39.3077, scale=scale)
    if scale != 1.0:
        S = _T().scale(scale)
        for key, value in d.items():
            if key == "sensor" or not isinstance(value, dict):
                continue
            if "to_world" in value:
                value["to_world"] = S @ value["to_world"]
            if value.get("type") == "sphere" and "center" in value:
                value["center"] = [c * scale for c in value["center"]]
                value["radius"] = value["radius"] * scale
            if value.get("type") == "point":
                value["position"] = [c * scale for c in value["position"]]
    return d, light_scale


def cornell_lights(res=RES, kind="point"):
    """The Cornell box with its area light replaced by a point or a spot light, or
    lit by a light whose texture is procedural (Mitsuba cannot sample a checkerboard:
    ``spot_textured``, ``projector``, ``area_textured``)."""
    down = _T().look_at(origin=[0.0, 0.95, 0.0], target=[0.0, -1.0, 0.0], up=[0, 0, 1])
    if kind == "point":
        em = {"type": "point", "position": [0.0, 0.85, 0.0], "intensity": _rgb(4.0)}
    elif kind in ("spot", "spot_textured"):
        em = {"type": "spot", "intensity": _rgb(8.0), "cutoff_angle": 40.0, "beam_width": 30.0,
              "to_world": down}
        if kind == "spot_textured":
            em["texture"] = _checker([1.0] * 3, [0.2] * 3)
    elif kind == "projector":
        em = {"type": "projector", "fov": 60.0, "scale": 4.0, "to_world": down,
              "irradiance": _checker([1.0] * 3, [0.2] * 3)}
    elif kind == "area_textured":
        # (Scalar colours: an RGB texture above 1 is refused as a reflectance.)
        return cornell(res=res, light_texture={"type": "checkerboard", "color0": 20.0,
                                               "color1": 2.0})
    else:
        raise ValueError(f"cornell_lights: unknown kind {kind!r}")
    return cornell(res=res, light=False, extra={"lamp": em})


def _checker(c0, c1, n=4):
    return {"type": "checkerboard", "color0": _rgb(c0), "color1": _rgb(c1),
            "to_uv": _mi().ScalarTransform4f().scale([n, n, 1])}


BSDFS = {
    "diffuse": lambda: _diffuse([0.3, 0.6, 0.8]),
    "roughplastic": lambda: {"type": "roughplastic", "diffuse_reflectance": _rgb([0.2, 0.5, 0.8]),
                             "alpha": 0.2},
    "plastic": lambda: {"type": "plastic", "diffuse_reflectance": _rgb([0.8, 0.3, 0.2])},
    "principled": lambda: {"type": "principled", "base_color": _rgb([0.7, 0.5, 0.3]),
                           "roughness": 0.4, "metallic": 0.2, "specular": 0.5},
    # Principled metal and glass: flags that list a diffuse lobe they do not have
    # (bsdfs.diffuse_free).
    "principled_metal": lambda: {"type": "principled", "base_color": _rgb([0.8, 0.6, 0.3]),
                                 "roughness": 0.25, "metallic": 1.0},
    "principled_glass": lambda: {"type": "principled", "roughness": 0.3, "spec_trans": 1.0},
    "roughconductor": lambda: {"type": "roughconductor", "material": "Au", "alpha": 0.15},
    "conductor": lambda: {"type": "conductor", "material": "Ag"},
    "dielectric": lambda: {"type": "dielectric", "int_ior": 1.5},
    "thindielectric": lambda: {"type": "thindielectric", "int_ior": 1.5},
    "mask": lambda: {"type": "mask", "opacity": _checker(0.1, 0.9),
                     "bsdf": _diffuse([0.2, 0.7, 0.3])},
}


def cornell_object(res=RES, bsdf="diffuse"):
    """The Cornell box with a sphere of the given BSDF instead of the large box."""
    return cornell(res=res, bsdf_object=BSDFS[bsdf]())


def all_bsdfs(res=RES, skip=()):
    """The Cornell box without its boxes, holding one small sphere of each BSDF in
    ``BSDFS`` but ``skip`` (rows of three): every BSDF in one scene, one set of kernels to
    compile (instead of one set per BSDF)."""
    d, scale = cornell(res=res)
    d.pop("large-box")
    d.pop("small-box")
    for i, name in enumerate(n for n in sorted(BSDFS) if n not in skip):
        x, y = (i % 3 - 1) * 0.55, -0.8 + (i // 3) * 0.5
        d[f"sphere-{name}"] = {"type": "sphere", "center": [x, y, -0.1], "radius": 0.19,
                               "bsdf": BSDFS[name]()}
    return d, scale


def twosided_back(res=RES):
    return cornell(res=res, twosided_panel=True)


def thin_box(res=RES):
    return cornell(res=res, thin_slab=True)


def zero_area_rect(res=RES):
    return cornell(res=res, zero_area=True)


def hidden_light(res=RES):
    return cornell(res=res, hidden_light=True)


def huge_ground(res=RES):
    """A 2e6-unit ground plane under a 1-unit box, lit by a small area light."""
    d = {
        "type": "scene",
        "ground": {"type": "rectangle", "bsdf": _diffuse(0.5),
                   "to_world": _T().rotate([1, 0, 0], -90) @ _T().scale(1e6)},
        "box": {"type": "cube", "bsdf": _diffuse([0.7, 0.4, 0.3]),
                "to_world": _T().translate([0, 0.5, 0]) @ _T().scale(0.5)},
        "light": {"type": "rectangle", "emitter": {"type": "area", "radiance": _rgb(10.0)},
                  "to_world": _T().translate([0.5, 3.0, 0.5]) @ _T().rotate([1, 0, 0], 90)
                  @ _T().scale(0.5)},
        "sensor": _sensor([0, 2.5, 5.0], [0, 0.4, 0], res, fov=40),
    }
    return d, 10.0


def split_room(res=RES, camera="dark"):
    """A closed 4x2x2 room split in two by a 2 mm wall; the light is in the +x half.

    ``camera="dark"``: the camera is in the -x half (no light can reach it: path is
    black); ``"lit"``: in the +x half, looking at the wall."""
    d = {
        "type": "scene",
        "room": {"type": "cube", "flip_normals": True, "bsdf": _diffuse(0.7),
                 "to_world": _T().scale([2.0, 1.0, 1.0])},
        # 2 mm thick, reaching slightly into the room's walls: no gap anywhere.
        "divider": {"type": "cube", "bsdf": _diffuse(0.6),
                    "to_world": _T().scale([0.001, 1.001, 1.001])},
        "light": {"type": "rectangle", "emitter": {"type": "area", "radiance": _rgb(10.0)},
                  "to_world": _T().translate([1.0, 0.99, 0.0]) @ _T().rotate([1, 0, 0], 90)
                  @ _T().scale(0.3)},
    }
    x = -1.95 if camera == "dark" else 1.95
    d["sensor"] = _sensor([x, 0.0, 0.0], [0.0, -0.2, 0.0], res, fov=70)
    return d, 10.0


def _ones_env():
    import numpy as np
    return _mi().Bitmap(np.ones((8, 16, 3), np.float32))


def _sun_env():
    """A sky brighter towards the zenith with a bright patch (a "sun") at one azimuth,
    so that rotating it changes the image."""
    import numpy as np
    h, w = 16, 32
    rows = np.linspace(1.0, 0.1, h, dtype=np.float32)
    img = rows[:, None, None] * np.array([0.5, 0.7, 1.0], np.float32)[None, None, :]
    img = np.ascontiguousarray(np.broadcast_to(img, (h, w, 3)), dtype=np.float32)
    img[3:5, 5:7] = [40.0, 35.0, 25.0]
    return _mi().Bitmap(img)


def outdoor(res=RES, emitter="directional"):
    """Ground, a box and a sphere under an environment or a directional light."""
    if emitter == "directional":
        em, scale = {"type": "directional", "direction": [-0.3, -1.0, -0.4],
                     "irradiance": _rgb(3.0)}, 3.0
    elif emitter == "constant":
        em, scale = {"type": "constant", "radiance": _rgb(1.0)}, 1.0
    elif emitter == "envmap":
        em, scale = {"type": "envmap", "bitmap": _ones_env()}, 1.0
    elif emitter == "envmap_rotated":
        em, scale = {"type": "envmap", "bitmap": _sun_env(),
                     "to_world": _T().rotate([0, 1, 0], 70) @ _T().rotate([1, 0, 0], 20)}, 40.0
    else:
        raise ValueError(emitter)
    d = {
        "type": "scene",
        "ground": {"type": "rectangle", "bsdf": _diffuse(0.5),
                   "to_world": _T().rotate([1, 0, 0], -90) @ _T().scale(3.0)},
        "box": {"type": "cube", "bsdf": _diffuse([0.7, 0.7, 0.7]),
                "to_world": _T().translate([-0.4, 0.5, 0]) @ _T().scale(0.5)},
        "ball": {"type": "sphere", "center": [0.9, 0.4, 0.6], "radius": 0.4,
                 "bsdf": _diffuse([0.8, 0.2, 0.2])},
        "sky": em,
        "sensor": _sensor([0, 3.0, 5.0], [0, 0.3, 0], res, fov=45),
    }
    return d, scale


def enclosed_light(res=RES):
    """An emitting sphere inside a closed box standing on a ground plane: no light
    leaves the box, so the image is black."""
    d = {
        "type": "scene",
        "ground": {"type": "rectangle", "bsdf": _diffuse(0.5),
                   "to_world": _T().rotate([1, 0, 0], -90) @ _T().scale(3.0)},
        "box": {"type": "cube", "bsdf": {"type": "twosided", "bsdf": _diffuse(0.8)},
                "to_world": _T().translate([0, 0.5, 0]) @ _T().scale(0.5)},
        "bulb": {"type": "sphere", "center": [0, 0.5, 0], "radius": 0.2,
                 "emitter": {"type": "area", "radiance": _rgb(10.0)}},
        "sensor": _sensor([0, 2.5, 4.0], [0, 0.4, 0], res, fov=45),
    }
    return d, 10.0


def nan_emitter(res=RES, which="point", value="nan", reference=False):
    """The Cornell box plus a second light whose radiance is NaN (or Inf).

    ``reference=True``: the same geometry without that light (what path renders)."""
    bad = float(value)
    if which == "point":
        extra = {} if reference else {
            "bad-light": {"type": "point", "position": [0.4, 0.3, 0.3], "intensity": _rgb(bad)}}
    else:
        sphere = {"type": "sphere", "center": [0.5, 0.5, 0.0], "radius": 0.1,
                  "bsdf": _diffuse(0.0)}
        if not reference:
            sphere["emitter"] = {"type": "area", "radiance": _rgb(bad)}
        extra = {"bad-light": sphere}
    return cornell(res=res, extra=extra)


NAN_TEXELS = [(2, 3, "nan"), (8, 8, "inf"), (12, 5, "nan"), (5, 13, "inf"), (10, 11, "-inf")]


def nan_texture(res=RES, replace=False):
    """The Cornell box whose back wall has a 16x16 bitmap texture with NaN/Inf texels.

    ``replace=True`` puts 0 in those texels instead (path's reference)."""
    import numpy as np
    tex = np.full((16, 16, 3), 0.6, np.float32)
    for r, c, v in NAN_TEXELS:
        tex[r, c] = 0.0 if replace else float(v)
    back = {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": _mi().Bitmap(tex),
                                               "filter_type": "nearest", "raw": True}}
    return cornell(res=res, back=back)


def random_scene(res=32, objects=()):
    """A closed 2x2x2 room (a flipped cube) holding ``objects`` (boxes, spheres and
    two-sided rectangles with a diffuse albedo) and one area light under the ceiling."""
    d = {
        "type": "scene",
        "room": {"type": "cube", "flip_normals": True, "bsdf": _diffuse(0.6)},
        "light": {"type": "rectangle", "emitter": {"type": "area", "radiance": _rgb(8.0)},
                  "to_world": _T().translate([0, 0.98, 0]) @ _T().rotate([1, 0, 0], 90)
                  @ _T().scale(0.25)},
        "sensor": _sensor([0, 0, 0.97], [0, -0.1, -1], res, fov=75),
    }
    for i, b in enumerate(objects):
        pos, size = list(b["pos"]), float(b["size"])
        bsdf = _diffuse(b["albedo"])
        if b["kind"] == "sphere":
            d[f"obj{i}"] = {"type": "sphere", "center": pos, "radius": size, "bsdf": bsdf}
            continue
        tw = _T().translate(pos) @ _T().rotate([0.3, 1, 0.2], float(b["angle"])) @ _T().scale(size)
        if b["kind"] == "rectangle":
            bsdf = {"type": "twosided", "bsdf": bsdf}
        d[f"obj{i}"] = {"type": b["kind"], "to_world": tw, "bsdf": bsdf}
    return d, 8.0


SCENES = {
    "cornell": cornell,
    "cornell_lights": cornell_lights,
    "cornell_object": cornell_object,
    "all_bsdfs": all_bsdfs,
    "twosided_back": twosided_back,
    "thin_box": thin_box,
    "zero_area_rect": zero_area_rect,
    "hidden_light": hidden_light,
    "huge_ground": huge_ground,
    "split_room": split_room,
    "outdoor": outdoor,
    "enclosed_light": enclosed_light,
    "nan_emitter": nan_emitter,
    "nan_texture": nan_texture,
    "random_scene": random_scene,
}


def build_scene_dict(spec):
    spec = dict(spec)
    name = spec.pop("name")
    return SCENES[name](**spec)


# -------------------------------------------------------------------------------------
# Measurements
# -------------------------------------------------------------------------------------
def luminance_mean(img):
    """Mean Rec. 709 luminance of an image's first three channels."""
    import numpy as np
    from pmic_integrator.metrics import mean_luminance
    return mean_luminance(np.asarray(img)[..., :3])


def _finite_info(img):
    import numpy as np
    a = np.asarray(img)
    bad = ~np.isfinite(a)
    finite = a[~bad]
    return {"nonfinite": int(bad.sum()), "negative": int((finite < 0).sum()),
            "max": float(finite.max()) if finite.size else None,
            "mean_finite": luminance_mean(np.where(bad, 0.0, a))}


def pmic_dict(params, bare=False):
    base = {} if bare else dict(SMALL)
    base.update(params or {})
    return {"type": "pmic", **base}


def _render(mi, scene, integ, spp, seed=0):
    import numpy as np
    import drjit as dr
    img = mi.render(scene, integrator=integ, spp=spp, seed=seed)
    dr.eval(img)
    return np.array(img)


def _reference(mi, ref):
    """path's mean luminance over PATH_PASSES passes, and its standard error."""
    d, light_scale = build_scene_dict(ref["scene"])
    scene = mi.load_dict(d)
    integ = mi.load_dict({"type": "path", **ref.get("path", {})})
    spp = int(ref.get("spp", PATH_SPP))
    per = max(1, spp // PATH_PASSES)
    means = []
    t0 = time.perf_counter()
    for k in range(PATH_PASSES):
        means.append(luminance_mean(_render(mi, scene, integ, per, seed=1000 + k)))
    m = sum(means) / len(means)
    var = sum((x - m) ** 2 for x in means) / max(1, len(means) - 1)
    return {"path_mean": m, "path_se": math.sqrt(var / len(means)), "path_spp": per * PATH_PASSES,
            "path_time": time.perf_counter() - t0, "light_scale": light_scale}


def _error_text(e):
    """The exception's type and message, and the messages of the exceptions it chains
    (``mi.render`` wraps an integrator's exception in a generic Dr.Jit RuntimeError
    "error while performing a custom differentiable operation"; the integrator's own
    message is its cause, printed above it in the traceback)."""
    chain, seen, cur = [], set(), e
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        chain.append(f"{type(cur).__name__}: {cur}")
        cur = cur.__cause__ or cur.__context__
    return {"type": type(e).__name__, "message": str(e), "chain": chain}


_CAUGHT: list = []
_HOOKED = False


def _hook_warnings():
    """Record pmic's warnings (``warnings.warn`` and its ``pmic`` logger), once."""
    global _HOOKED
    if _HOOKED:
        return
    import warnings

    class Catch(logging.Handler):
        def emit(self, record):
            if record.levelno >= logging.WARNING:
                _CAUGHT.append(f"log {record.levelname}: {record.getMessage()}")

    logging.getLogger("pmic").addHandler(Catch())
    warnings.simplefilter("always")
    old_show = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        _CAUGHT.append(f"{category.__name__}: {message}")
        old_show(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    _HOOKED = True


def run(job):
    """Run one job in this process; return a JSON-able dict."""
    import pmic_integrator  # noqa: F401  (sets up LLVM before mitsuba/drjit load)
    import mitsuba as mi
    import numpy as np
    mi.set_variant("llvm_ad_rgb")
    _hook_warnings()
    del _CAUGHT[:]

    out = {"kind": job["kind"]}
    kind = job["kind"]
    spp = int(job.get("spp", PMIC_SPP))
    try:
        if kind == "references":
            out["refs"] = []
            for ref in job["refs"]:
                try:
                    out["refs"].append(_reference(mi, ref))
                except Exception as e:
                    out["refs"].append({"exception": _error_text(e)})
            return out
        if kind == "load":
            out["loads"] = []
            for params in job["param_sets"]:
                try:
                    mi.load_dict(pmic_dict(params, job.get("bare", False)))
                    out["loads"].append({"error": None})
                except Exception as e:
                    out["loads"].append({"error": _error_text(e)})
            return out
        if kind == "error":
            try:
                integ = mi.load_dict(pmic_dict(job.get("params"), job.get("bare", False)))
            except Exception as e:  # what the user sees
                out["error"] = dict(_error_text(e), stage="load")
                return out
            d, _ = build_scene_dict(job["scene"])
            scene = mi.load_dict(d)
            try:
                img = _render(mi, scene, integ, spp)
            except Exception as e:
                out["error"] = dict(_error_text(e), stage="render")
                return out
            out["error"] = None
            out["pmic_mean"] = luminance_mean(img)
            out.update(_finite_info(img))
            return out
        if kind == "compare":
            out.update(_reference(mi, job["ref"]))

        d, light_scale = build_scene_dict(job["scene"])
        out["light_scale"] = light_scale
        scene = mi.load_dict(d)
        t0 = time.perf_counter()
        integ = mi.load_dict(pmic_dict(job.get("params"), job.get("bare", False)))
        if kind in ("render", "compare"):
            img = _render(mi, scene, integ, spp)
            out["pmic_time"] = time.perf_counter() - t0
            out["pmic_mean"] = luminance_mean(img)
            out.update(_finite_info(img))
            stats = getattr(integ, "stats", {}) or {}
            out["stats"] = {k: v for k, v in stats.items()
                            if isinstance(v, (int, float, str, list)) and not k.startswith("memory")}
        elif kind == "repeat":
            a = _render(mi, scene, integ, spp)
            b = _render(mi, scene, integ, spp)
            c = _render(mi, scene, mi.load_dict(pmic_dict(job.get("params"))), spp)
            out.update(pmic_mean=luminance_mean(a), nonfinite=int((~np.isfinite(a)).sum()),
                       same_object_identical=bool(np.array_equal(a, b)),
                       fresh_object_identical=bool(np.array_equal(a, c)),
                       max_diff_same=float(np.abs(a - b).max()),
                       max_diff_fresh=float(np.abs(a - c).max()))
        elif kind == "edit":
            a = _render(mi, scene, integ, spp)
            params = mi.traverse(scene)
            key = job.get("edit_key", "light.emitter.radiance.value")
            params[key] = params[key] * 2.0
            params.update()
            b = _render(mi, scene, integ, spp)
            out.update(mean_before=luminance_mean(a), mean_after=luminance_mean(b),
                       nonfinite=int((~np.isfinite(a)).sum() + (~np.isfinite(b)).sum()),
                       cache_builds=int(integ.stats.get("cache_builds", -1)))
        elif kind == "threads":
            import threading
            single = _render(mi, scene, integ, spp)
            results, errors = [None, None], [None, None]

            def work(i):
                try:
                    results[i] = _render(mi, scene, integ, spp)
                except Exception as e:  # reported, not raised: the other thread goes on
                    errors[i] = f"{type(e).__name__}: {e}"

            threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            out["pmic_mean"] = luminance_mean(single)
            out["nonfinite"] = int((~np.isfinite(single)).sum())
            out["thread_errors"] = errors
            out["thread_equal"] = [bool(r is not None and np.array_equal(r, single)) for r in results]
            out["thread_max_diff"] = [None if r is None else float(np.nanmax(np.abs(r - single)))
                                      for r in results]
            out["thread_means"] = [None if r is None else luminance_mean(r) for r in results]
        else:
            raise ValueError(f"unknown job kind {kind!r}")
    except Exception as e:
        out["exception"] = dict(_error_text(e), traceback=traceback.format_exc()[-3000:])
    finally:
        out["warnings"] = _CAUGHT[-20:]
    return out


def _emit(out):
    sys.stdout.flush()
    print(RESULT_TAG + json.dumps(out, default=str), flush=True)


def main(argv):
    if len(argv) > 1 and argv[1] == "--serve":
        # Persistent worker (used by the hypothesis tests): one JSON job per stdin line,
        # one result line per job. The parent restarts it after a timeout or a crash.
        for line in sys.stdin:
            if line.strip():
                _emit(run(json.loads(line)))
        return 0
    _emit(run(json.loads(argv[1])))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
