"""Small scenes built in code (for the tests, benchmarks and tools): each one isolates a way a photon-mapping
renderer can go wrong on real scenes (light through an opening, thin one-sided walls,
textured albedo, coated and glossy materials)."""
from __future__ import annotations

import mitsuba as mi
import numpy as np



def T(*args):
    """``mi.ScalarTransform4f`` of the variant set when called (this module is imported
    before one may be)."""
    return mi.ScalarTransform4f(*args)


def _diffuse(rgb):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}


def _area(radiance):
    """An area emitter of grey ``radiance``."""
    return {"type": "area", "radiance": {"type": "rgb", "value": [radiance] * 3}}


def _sensor(origin, target, fov=60.0, size=(48, 32), up=(0, 1, 0)):
    return {"type": "perspective", "fov": fov,
            "to_world": T().look_at(origin=list(origin), target=list(target), up=list(up)),
            "film": {"type": "hdrfilm", "width": size[0], "height": size[1],
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent"}}


def _box_part(center, half, bsdf):
    """An axis-aligned solid block (a cube scaled to ``half`` extents)."""
    return {"type": "cube", "to_world": T().translate(list(center)).scale(list(half)), "bsdf": bsdf}


def two_rooms(door_width=0.3, camera_in_lit_room=False, size=(48, 32), wall_bsdf=None,
              floor_bsdf=None):
    """Two 2×2×2 rooms side by side (x in [-2, 0] and [0, 2]) joined by a door in a
    4 cm partition; a small light on the ceiling of the left room only. Seen from the
    right room, everything is lit through the door: sparse photons, dim, mostly
    indirect light (the situation of Veach's "door ajar" scene)."""
    white = wall_bsdf or _diffuse((0.7, 0.7, 0.7))
    d = {"type": "scene"}
    # Outer shell: one block with the rooms carved out is awkward with primitives, so
    # the six sides are thick blocks (closed, two-sided).
    t = 0.05
    d["floor"] = _box_part((0, -1 - t, 0), (2 + 2 * t, t, 1 + 2 * t), floor_bsdf or white)
    d["ceiling"] = _box_part((0, 1 + t, 0), (2 + 2 * t, t, 1 + 2 * t), white)
    d["back"] = _box_part((0, 0, -1 - t), (2 + 2 * t, 1 + 2 * t, t), _diffuse((0.6, 0.6, 0.4)))
    d["front"] = _box_part((0, 0, 1 + t), (2 + 2 * t, 1 + 2 * t, t), white)
    d["left"] = _box_part((-2 - t, 0, 0), (t, 1 + 2 * t, 1 + 2 * t), _diffuse((0.7, 0.2, 0.2)))
    d["right"] = _box_part((2 + t, 0, 0), (t, 1 + 2 * t, 1 + 2 * t), _diffuse((0.2, 0.6, 0.2)))
    # Partition at x = 0 with a door of width door_width (z centred at 0.3), 1.4 high.
    w, z0, h = door_width, 0.3, 1.4
    pt = 0.02
    d["part_a"] = _box_part((0, 0, (-1 + (z0 - w / 2)) / 2), (pt, 1, ((z0 - w / 2) + 1) / 2), white)
    d["part_b"] = _box_part((0, 0, ((z0 + w / 2) + 1) / 2), (pt, 1, (1 - (z0 + w / 2)) / 2), white)
    d["part_c"] = _box_part((0, (-1 + h + 1) / 2, z0), (pt, (1 - (-1 + h)) / 2, w / 2), white)
    d["light"] = {"type": "rectangle",
                  "to_world": T().translate([-1.2, 0.999, -0.2]).rotate([1, 0, 0], 90).scale([0.2, 0.2, 1]),
                  "bsdf": _diffuse((0, 0, 0)), "emitter": _area(60)}
    view = ((-0.3, 0.2, 0.9), (-1.8, -0.3, -0.8)) if camera_in_lit_room else \
        ((1.9, 0.3, 0.9), (0.0, -0.3, -0.2))
    d["sensor"] = _sensor(*view, 70, size)
    return d


def thin_wall_room(camera_on_lit_side=False, thickness=0.002, size=(32, 24)):
    """A closed 2×1×1 box split by a wall ``thickness`` thick that closes it fully; the
    light is on the left only. Seen from the right, ``path`` is black."""
    d = {"type": "scene"}
    white = _diffuse((0.75, 0.75, 0.75))
    t = 0.05
    d["shell_floor"] = _box_part((0, -0.5 - t, 0), (1 + 2 * t, t, 0.5 + 2 * t), white)
    d["shell_ceiling"] = _box_part((0, 0.5 + t, 0), (1 + 2 * t, t, 0.5 + 2 * t), white)
    d["shell_back"] = _box_part((0, 0, -0.5 - t), (1 + 2 * t, 0.5 + 2 * t, t), white)
    d["shell_front"] = _box_part((0, 0, 0.5 + t), (1 + 2 * t, 0.5 + 2 * t, t), white)
    d["shell_left"] = _box_part((-1 - t, 0, 0), (t, 0.5 + 2 * t, 0.5 + 2 * t), white)
    d["shell_right"] = _box_part((1 + t, 0, 0), (t, 0.5 + 2 * t, 0.5 + 2 * t), white)
    # The wall reaches into the shell: coincident faces would leave float cracks.
    d["wall"] = _box_part((0, 0, 0), (thickness / 2, 0.5 + t, 0.5 + t), white)
    d["light"] = {"type": "sphere", "center": [-0.5, 0.1, 0.0], "radius": 0.08, "emitter": _area(20)}
    view = ((-0.1, 0.2, 0.45), (-0.9, -0.3, -0.4)) if camera_on_lit_side else \
        ((0.95, 0.2, 0.45), (0.1, -0.3, -0.4))
    d["sensor"] = _sensor(*view, 75, size)
    return d


def closed_box_on_floor(size=(32, 24)):
    """A closed two-sided box (turned 32.5°) standing on a floor under a white sky, the
    camera inside it: ``path`` is black. The box's walls meet the floor in creases
    where photons that land at a wall's foot lie on the wall's plane."""
    return {"type": "scene",
            "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale([4, 3, 1]),
                      "bsdf": {"type": "diffuse"}},
            "box": {"type": "cube", "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}},
                    "to_world": T().translate([1.237, 1.583, 0.393]).rotate([0, 1, 0], 32.5)
                    .scale([1.583, 1.583, 1.583])},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
            "sensor": _sensor((0.9, 1.5, 0.8), (0.0, 0.3, 1.1), 70.0, size)}


def glossy_metal_floor_box(size=(16, 16)):
    """A closed box of dark grey walls over a glossy metallic ``principled`` floor
    (metallic 0.85, roughness 0.13), lit by a small area light under the ceiling."""
    grey = {"type": "twosided", "bsdf": _diffuse((0.2, 0.2, 0.2))}
    d = {"type": "scene",
         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90),
                   "bsdf": {"type": "principled", "base_color": {"type": "rgb", "value": [0.85, 0.75, 0.3]},
                            "metallic": 0.85, "roughness": 0.13, "specular": 0.6}},
         "ceiling": {"type": "rectangle", "to_world": T().translate([0, 2, 0]).rotate([1, 0, 0], 90), "bsdf": grey},
         "back": {"type": "rectangle", "to_world": T().translate([0, 1, -1]), "bsdf": grey},
         "front": {"type": "rectangle", "to_world": T().translate([0, 1, 1]).rotate([0, 1, 0], 180), "bsdf": grey},
         "left": {"type": "rectangle", "to_world": T().translate([-1, 1, 0]).rotate([0, 1, 0], 90), "bsdf": grey},
         "right": {"type": "rectangle", "to_world": T().translate([1, 1, 0]).rotate([0, 1, 0], -90), "bsdf": grey},
         "light": {"type": "rectangle", "to_world": T().translate([0, 1.99, 0]).rotate([1, 0, 0], 90).scale(0.25),
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [15, 15, 15]}}},
         "sensor": _sensor((0, 1, 0.9), (0, 0.8, -1), 60.0, size)}
    return d


def checker_texture(n=8, dark=0.1, light=0.8, res=64):
    """A bitmap checkerboard (n×n squares) as a Mitsuba bitmap texture."""
    u = (np.arange(res) * n // res) % 2
    board = (u[:, None] ^ u[None, :]).astype(np.float32)
    rgb = np.repeat((dark + (light - dark) * board)[..., None], 3, axis=2)
    # (raw: no upsampling to spectra, which spectral variants refuse for a reflectance)
    return {"type": "bitmap", "bitmap": mi.Bitmap(rgb), "filter_type": "nearest", "raw": not mi.is_spectral}


def cornell(size=32, **replace):
    """Mitsuba's Cornell box at ``size``², with shapes' entries replaced or added."""
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = size
    d["sensor"]["film"]["rfilter"] = {"type": "box"}
    d.pop("integrator", None)
    for key, value in replace.items():
        if value is None:
            d.pop(key, None)
        elif isinstance(value, dict) and key in d and "type" not in value:
            d[key] = {**d[key], **value}
        else:
            d[key] = value
    return d


def glass_covered_panel(size=16, cover=0.2):
    """Mitsuba's Cornell box lit by a wide ceiling panel, a square of it ``cover`` half
    wide (a fifth of its area at 0.2) behind a thin glass pane: caustics of the white
    room's kind, light that glass spreads through a room among other light, which
    tracing finds readily (a fifth of the panel seen from the floor)."""
    d = cornell(size)
    d["light"] = {"type": "rectangle", "emitter": _area(3.0),
                  "to_world": T().translate([0.0, 0.99, 0.0]).rotate([1, 0, 0], 90).scale([0.6, 0.6, 1])}
    d["cover"] = {"type": "rectangle", "bsdf": {"type": "thindielectric"},
                  "to_world": T().translate([-0.3, 0.95, -0.3]).rotate([1, 0, 0], 90).scale([cover, cover, 1])}
    return d


#: A small, fast pmic configuration for tests of behaviour (not of accuracy).
SMALL_PMIC = {"global_photons": 20_000, "caustic_photons": 5_000, "gather_rays": 64}


def pmic_cornell(resolution=32, **params):
    """Mitsuba's Cornell box at ``resolution``² rendered by a small pmic (SMALL_PMIC,
    updated with ``params``)."""
    d = cornell(resolution)
    d["integrator"] = {"type": "pmic", **SMALL_PMIC, **params}
    return d


def envmap_exterior(rotate=True, size=(40, 30), bitmap=None):
    """A diffuse ground and a plastic sphere under an environment map with a bright
    patch (a 'sun'), optionally rotated as real scenes' envmaps are."""
    if bitmap is None:
        h, w = 32, 64
        theta = (np.arange(h) + 0.5) / h * np.pi
        sky = np.ones((h, w, 3), np.float32) * np.float32([0.5, 0.6, 0.8])
        sky *= (0.3 + np.sin(theta))[:, None, None].astype(np.float32)
        sky[6:9, 40:44] = 60.0  # the sun
        bitmap = mi.Bitmap(sky)
    to_world = T().rotate([0, 1, 0], 110).rotate([1, 0, 0], -90) if rotate else T()
    return {"type": "scene",
            "sky": {"type": "envmap", "bitmap": bitmap, "to_world": to_world},
            "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                       "bsdf": {"type": "diffuse", "reflectance": checker_texture()}},
            "ball": {"type": "sphere", "center": [0, 0.5, 0], "radius": 0.5,
                     "bsdf": {"type": "plastic",
                              "diffuse_reflectance": {"type": "rgb", "value": [0.7, 0.2, 0.2]}}},
            "sensor": _sensor((2.5, 1.6, 2.5), (0, 0.3, 0), 40, size)}


def lamp_room(size=(48, 32)):
    """A 4 × 3 × 2.5 room lit by a small bright sphere inside a lampshade: an open-top
    box of two-sided walls, with a 5 mm slit under two of them. Three quarters of the
    photons stay inside the shade, so the rest of the room (all of what the camera
    sees, lit off the ceiling) is 100 times sparser than the cluster that sets the
    lookup radius. The walls are rectangles of one material, which Mitsuba merges into
    one mesh whose bounding box it reports as invalid (``scene.bbox()`` then spans the
    lamp alone)."""
    half_w, half_d, half_h = 2.0, 1.5, 1.25
    wall = _diffuse((0.5, 0.5, 0.5))
    shade = {"type": "twosided", "bsdf": _diffuse((0.6, 0.6, 0.6))}
    scene = {"type": "scene",
             "sensor": _sensor((0, -half_d + 0.05, 0.2), (0, 0, 0.1), fov=70, size=size, up=(0, 0, 1)),
             "lamp": {"type": "sphere", "center": [1.2, 0.8, 0.0], "radius": 0.03,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [2000.0] * 3}}}}
    walls = {"floor": T().translate([0, 0, -half_h]).scale([half_w, half_d, 1]),
             "ceiling": T().translate([0, 0, half_h]).rotate([1, 0, 0], 180).scale([half_w, half_d, 1]),
             "back": T().translate([0, half_d, 0]).rotate([1, 0, 0], 90).scale([half_w, half_h, 1]),
             "front": T().translate([0, -half_d, 0]).rotate([1, 0, 0], -90).scale([half_w, half_h, 1]),
             "left": T().translate([-half_w, 0, 0]).rotate([0, 1, 0], 90).scale([half_h, half_d, 1]),
             "right": T().translate([half_w, 0, 0]).rotate([0, 1, 0], -90).scale([half_h, half_d, 1])}
    for name, to_world in walls.items():
        scene[name] = {"type": "rectangle", "to_world": to_world, "bsdf": wall}
    center, h = (1.2, 0.8, 0.025), 0.12
    for i, (axis, angle, offset) in enumerate((((0, 1, 0), 90, (h, 0, 0)), ((0, 1, 0), -90, (-h, 0, 0)),
                                               ((1, 0, 0), 90, (0, h, 0)), ((1, 0, 0), -90, (0, -h, 0)))):
        position = [c + o for c, o in zip(center, offset)]
        scene[f"shade_{i}"] = {"type": "rectangle", "bsdf": shade,
                               "to_world": T().translate(position).rotate(list(axis), angle).scale([h, 0.125, 1])}
    scene["shade_base"] = {"type": "rectangle", "bsdf": shade,
                           "to_world": T().translate([1.2, 0.8, -0.1]).scale(h)}
    return scene


def panel_in_shade(radiance=20.0, albedo=0.5, size=(32, 32)):
    """A 2 m cube of two-sided diffuse walls (``albedo``) lit by a 0.2 m square panel
    facing down, 0.4 m under the ceiling, inside a square shade whose walls start at
    the panel's edges: the shade's points beside the panel see it from millimetres
    away (the white room's wall lamps). Its indirect irradiance is at most
    π · radiance · albedo / (1 - albedo) anywhere."""
    wall = {"type": "twosided", "bsdf": _diffuse((albedo,) * 3)}
    scene = {"type": "scene", "sensor": _sensor((0, 0, 2.8), (0, 0, 0), size=size),
             "panel": {"type": "rectangle", "to_world": T().translate([0, 0.6, 0]).rotate([1, 0, 0], 90).scale(0.1),
                       "bsdf": _diffuse((0.0, 0.0, 0.0)), "emitter": _area(radiance)}}
    walls = {"floor": T().translate([0, -1, 0]).rotate([1, 0, 0], -90),
             "ceiling": T().translate([0, 1, 0]).rotate([1, 0, 0], 90),
             "back": T().translate([0, 0, -1]),
             "left": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
             "right": T().translate([1, 0, 0]).rotate([0, 1, 0], -90)}
    for name, to_world in walls.items():
        scene[name] = {"type": "rectangle", "to_world": to_world, "bsdf": wall}
    for i, (angle, offset) in enumerate(((0, (0, 0.5, 0.1)), (0, (0, 0.5, -0.1)),
                                         (90, (0.1, 0.5, 0)), (90, (-0.1, 0.5, 0)))):
        scene[f"shade_{i}"] = {"type": "rectangle", "bsdf": wall,
                               "to_world": T().translate(list(offset)).rotate([0, 1, 0], angle).scale([0.1, 0.1, 1])}
    return scene


def bent_normal_room(tilt=50.0, size=(32, 24)):
    """A closed 2 m room whose floor is a two-triangle mesh with vertex normals leaning
    ``tilt`` degrees towards a strip light low on the left wall: the light crosses the
    floor at grazing angles, where Mitsuba's BSDFs (which weigh light by the cosine to
    the *shading* normal) make the floor reflect several times what its geometric
    cosine, and so its photon flux, says. Coarse meshes with smoothed normals lit from
    the side (Veach's lamp shades) are the real case."""
    t = np.radians(tilt)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_diffuse((0.5, 0.5, 0.5)))
    floor = mi.Mesh("bent_floor", 4, 2, props, has_vertex_normals=True)
    params = mi.traverse(floor)
    params["vertex_positions"] = [-1, -1, -1, 1, -1, -1, 1, -1, 1, -1, -1, 1]
    params["faces"] = [0, 2, 1, 0, 3, 2]
    params["vertex_normals"] = [-float(np.sin(t)), float(np.cos(t)), 0.0] * 4
    params.update()
    wall = _diffuse((0.5, 0.5, 0.5))
    scene = {"type": "scene", "sensor": _sensor((0.9, -0.5, 0.9), (-0.5, 0.6, -0.6), 80, size),
             "floor": floor}
    walls = {"ceiling": T().translate([0, 1, 0]).rotate([1, 0, 0], 90),
             "back": T().translate([0, 0, -1]),
             "front": T().translate([0, 0, 1]).rotate([0, 1, 0], 180),
             "left": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
             "right": T().translate([1, 0, 0]).rotate([0, 1, 0], -90)}
    for name, to_world in walls.items():
        scene[name] = {"type": "rectangle", "to_world": to_world, "bsdf": wall}
    scene["light"] = {"type": "rectangle",
                      "to_world": T().translate([-0.99, -0.9, 0]).rotate([0, 1, 0], 90).scale([0.8, 0.08, 1]),
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [20.0] * 3}}}
    return scene


def sun_shelter(size=(40, 30), sky=False):
    """A roofed wall on an 8 m ground under a sun (``directional``), optionally with a
    constant sky. Ground and boxes share one material, and Mitsuba merges them into
    one mesh whose ``bbox()`` spans the boxes only (2.4 m): the sun's photons, shot
    from a disk round that box, lit the ground within 2 m of its centre."""
    scene = {"type": "scene",
             "sun": {"type": "directional", "direction": [-0.5, -1, -0.3],
                     "irradiance": {"type": "rgb", "value": [3.0] * 3}},
             "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                        "bsdf": {"type": "diffuse"}},
             "wall": {"type": "cube", "to_world": T().translate([0, 0.5, -0.6]).scale([1.2, 0.5, 0.1]),
                      "bsdf": {"type": "diffuse"}},
             "roof": {"type": "cube", "to_world": T().translate([0, 1.05, 0]).scale([1.2, 0.05, 0.7]),
                      "bsdf": {"type": "diffuse"}},
             "sensor": _sensor((2.0, 1.0, 2.5), (0, 0.4, 0), 45, size)}
    if sky:
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.4, 0.5, 0.7]}}
    return scene


def courtyard(size=(48, 36), sun=True, sky=(0.4, 0.5, 0.7)):
    """A ground walled on three sides, part of it roofed, with a block, under a constant
    sky and (``sun``) a directional sun: an open scene lit mostly directly, where
    direct light from the sky and the walls' occlusion of it are most of the noise."""
    grey = _diffuse((0.5, 0.5, 0.5))
    d = {"type": "scene", "sky": {"type": "constant", "radiance": {"type": "rgb", "value": list(sky)}},
         "ground": {"type": "rectangle", "to_world": T().scale(8), "bsdf": _diffuse((0.45, 0.4, 0.35))},
         "wall_n": _box_part((0, 3, 1.5), (3, 0.1, 1.5), grey),
         "wall_w": _box_part((-3, 0, 1.5), (0.1, 3, 1.5), grey),
         "wall_e": _box_part((3, -0.5, 1.0), (0.1, 2.5, 1.0), grey),
         "roof": _box_part((-1.5, 1.5, 2.5), (1.5, 1.5, 0.05), grey),
         "block": _box_part((0.8, 0.2, 0.5), (0.5, 0.5, 0.5), grey),
         "sensor": _sensor((4, -7, 5), (0, 0.5, 0.8), 55, size, up=(0, 0, 1))}
    if sun:
        d["sun"] = {"type": "directional", "direction": [-0.5, 0.6, -0.8],
                    "irradiance": {"type": "rgb", "value": 3.0}}
    return d


def sunlit_rough_floor(size=(32, 24)):
    """A rough plastic floor (broad glossy lobe over a grey diffuse one) before a white
    wall, under a sun whose glossy reflection off the floor lights the wall: light
    that reaches the wall through the floor's glossy lobe is a caustic (the caustic
    map's), through its diffuse lobe it is not."""
    return {"type": "scene",
            "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3),
                      "bsdf": {"type": "roughplastic", "alpha": 0.35,
                               "diffuse_reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}},
            "wall": {"type": "rectangle", "to_world": T().translate([0, 1.5, -1]).scale([3, 1.5, 1]),
                     "bsdf": _diffuse((0.8, 0.8, 0.8))},
            "sun": {"type": "directional", "direction": [0, -0.6, -0.8],
                    "irradiance": {"type": "rgb", "value": [3.0] * 3}},
            "sensor": _sensor((0, 1.0, 3.0), (0, 1.0, -1), 50, size)}


def window_room(size=(40, 30), sky=(0.5, 0.6, 0.8), shared_material=False):
    """A 4 × 2.5 × 4 m room of one-sided walls lit only by a constant sky through a
    1.2 × 0.8 m window in its front wall: seen from inside, the sky is a small part of
    each point's hemisphere, so emitter samples drawn over the whole sky mostly meet
    the walls. With ``shared_material`` the walls share one BSDF object, and Mitsuba
    3.9 merges them into one mesh whose bounding box is invalid (``scene.bbox()``,
    from which Mitsuba's environment emitters place their samples)."""
    shared = _diffuse((0.7, 0.7, 0.7))

    def panel(center, half, rot_axis, angle, k):
        # A material per wall unless shared (the tiny tint keeps them apart).
        bsdf = shared if shared_material else _diffuse((0.7, 0.7, 0.7 - 1e-4 * k))
        return {"type": "rectangle", "bsdf": bsdf,
                "to_world": T().translate(list(center)).rotate(rot_axis, angle).scale([half[0], half[1], 1])}

    d = {"type": "scene", "sky": {"type": "constant", "radiance": {"type": "rgb", "value": list(sky)}},
         "floor": panel((0, 0, 0), (2, 2), [1, 0, 0], -90, 0),
         "ceiling": panel((0, 2.5, 0), (2, 2), [1, 0, 0], 90, 1),
         "back": panel((0, 1.25, -2), (2, 1.25), [0, 1, 0], 0, 2),
         "left": panel((-2, 1.25, 0), (2, 1.25), [0, 1, 0], 90, 3),
         "right": panel((2, 1.25, 0), (2, 1.25), [0, 1, 0], -90, 4),
         # front wall (z = 2, facing -z) round a window x in [-0.6, 0.6], y in [1.0, 1.8]
         "front_below": panel((0, 0.5, 2), (2, 0.5), [0, 1, 0], 180, 5),
         "front_above": panel((0, 2.15, 2), (2, 0.35), [0, 1, 0], 180, 6),
         "front_left": panel((-1.3, 1.4, 2), (0.7, 0.4), [0, 1, 0], 180, 7),
         "front_right": panel((1.3, 1.4, 2), (0.7, 0.4), [0, 1, 0], 180, 8),
         "sensor": _sensor((1.2, 1.3, 1.5), (-0.8, 0.9, -2.0), 70, size)}
    return d


def slot(gap=0.1, albedo=0.9, size=(32, 32)):
    """Two white blocks a narrow ``gap`` apart on a grey ground under a constant sky:
    light enters the slot between them from above and bounces many times inside it,
    where a photon estimate, a disc wider than the slot, is far off."""
    white = _diffuse((albedo,) * 3)
    return {"type": "scene", "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0] * 3}},
            "ground": {"type": "rectangle", "to_world": T().scale(3), "bsdf": _diffuse((0.5,) * 3)},
            "left": _box_part((-(0.5 + gap / 2), 0, 0.5), (0.5, 0.5, 0.5), white),
            "right": _box_part(((0.5 + gap / 2), 0, 0.5), (0.5, 0.5, 0.5), white),
            "sensor": _sensor((0.35, -0.3, 1.9), (-gap / 2, 0, 0.75), 12, size)}


def rough_plastic_rooms(size=(40, 28)):
    """:func:`two_rooms` with rough plastic walls and a principled floor: the camera
    path's coat reads, lobe splits and inseparable (whole) reads."""
    return two_rooms(size=size, wall_bsdf={"type": "roughplastic", "alpha": 0.3,
                                           "diffuse_reflectance": {"type": "rgb", "value": [0.6] * 3}},
                     floor_bsdf={"type": "principled", "base_color": {"type": "rgb", "value": [0.5] * 3},
                                 "roughness": 0.5})


#: Scenes of the kinds that switch on the camera path's rarer cases, for
#: ``tools/image_digests.py`` (name: builder of a scene dict).
DIGEST_KINDS = {
    "lamp_room": lambda: lamp_room(size=(48, 32)),
    "bent_normal_room": lambda: bent_normal_room(size=(32, 24)),
    "sun_shelter_sky": lambda: sun_shelter(size=(40, 30), sky=True),
    "window_room": lambda: window_room(size=(40, 30)),
    "sunlit_rough_floor": lambda: sunlit_rough_floor(size=(32, 24)),
    "rough_plastic_rooms": lambda: rough_plastic_rooms(),
    "glossy_metal_floor_box": lambda: glossy_metal_floor_box(size=(32, 32)),
}


def sunlit_classroom(size=(48, 27), ground_half=110.0, sun=True):
    """An 8 × 3 × 6 m room of solid walls with three windows in its south wall, under a
    sun (``directional``) and a constant sky, standing on a ground square
    ``2·ground_half`` wide (the public classroom's is 221 m): the ground outside takes
    most of the photons and sets the scene's scale, the room is lit through its windows
    (sun patches on the floor, sky light, their bounces)."""
    grey, floor = _diffuse((0.6, 0.6, 0.6)), _diffuse((0.45, 0.35, 0.25))
    t = 0.1  # wall thickness
    d = {"type": "scene", "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.6, 0.8]}},
         "ground": {"type": "rectangle", "bsdf": _diffuse((0.3, 0.35, 0.25)),
                    "to_world": T().translate([0, -0.01, 0]).rotate([1, 0, 0], -90).scale(ground_half)},
         "floor": _box_part((0, -t / 2, 0), (4 + t, t / 2, 3 + t), floor),
         "ceiling": _box_part((0, 3 + t / 2, 0), (4 + t, t / 2, 3 + t), grey),
         "north": _box_part((0, 1.5, -3 - t / 2), (4, 1.5, t / 2), grey),
         "west": _box_part((-4 - t / 2, 1.5, 0), (t / 2, 1.5, 3), grey),
         "east": _box_part((4 + t / 2, 1.5, 0), (t / 2, 1.5, 3), grey),
         # South wall (z = 3): below the sills, above the lintels, and four piers.
         "south_low": _box_part((0, 0.45, 3 + t / 2), (4, 0.45, t / 2), grey),
         "south_high": _box_part((0, 2.6, 3 + t / 2), (4, 0.4, t / 2), grey),
         "desk": _box_part((0.5, 0.75, 0.5), (1.2, 0.04, 0.5), floor),
         "sensor": _sensor((3.5, 1.6, 2.6), (-2.0, 0.8, -2.0), 70, size)}
    for i, x in enumerate((-3.4, -1.1, 1.1, 3.4)):
        d[f"pier_{i}"] = _box_part((x, 1.55, 3 + t / 2), (0.6, 0.65, t / 2), grey)
    if sun:
        d["sun"] = {"type": "directional", "direction": [0.3, -0.6, -0.75],
                    "irradiance": {"type": "rgb", "value": [4.0] * 3}}
    return d


def inside_sunlit_classroom(x, y, z):
    """Which of the points (NumPy coordinates) lie inside :func:`sunlit_classroom`'s
    room, its inner faces included (1 cm of slack)."""
    return (np.abs(x) < 4.01) & (np.abs(z) < 3.01) & (y > -0.01) & (y < 3.01)


def tall_stairwell(size=(24, 40)):
    """A 3 × 8 × 3 m shaft of solid walls lit by one small, bright sphere 7 m up, with a
    flight of steps along one wall and a glass sphere under the light (a chandelier's
    drop): most of the shaft sees the light only by its bounces off the walls far
    above, and the glass makes caustics below it."""
    grey, wood = _diffuse((0.7, 0.7, 0.7)), _diffuse((0.5, 0.35, 0.2))
    t = 0.1
    d = {"type": "scene",
         "floor": _box_part((0, -t / 2, 0), (1.5 + t, t / 2, 1.5 + t), wood),
         "ceiling": _box_part((0, 8 + t / 2, 0), (1.5 + t, t / 2, 1.5 + t), grey),
         "north": _box_part((0, 4, -1.5 - t / 2), (1.5, 4, t / 2), grey),
         "south": _box_part((0, 4, 1.5 + t / 2), (1.5, 4, t / 2), grey),
         "west": _box_part((-1.5 - t / 2, 4, 0), (t / 2, 4, 1.5), grey),
         "east": _box_part((1.5 + t / 2, 4, 0), (t / 2, 4, 1.5), grey),
         "lamp": {"type": "sphere", "center": [0.0, 7.0, 0.0], "radius": 0.04, "emitter": _area(4000.0)},
         "drop": {"type": "sphere", "center": [0.0, 6.6, 0.0], "radius": 0.12,
                  "bsdf": {"type": "dielectric", "int_ior": 1.5}},
         "sensor": _sensor((1.2, 0.6, 1.2), (-0.6, 4.0, -0.6), 75, size)}
    for i in range(12):  # steps up the north wall
        d[f"step_{i}"] = _box_part((-1.2 + 0.22 * i, 0.18 * i + 0.09, -1.1), (0.11, 0.09, 0.4), wood)
    return d


#: Scenes of the public interiors' kinds (``benchmarks/public_scenes.py --kinds``).
INTERIOR_KINDS = {
    "door_ajar": lambda scale=1: two_rooms(door_width=0.3, size=(96 * scale, 64 * scale)),
    "sky_through_window": lambda scale=1: window_room(size=(80 * scale, 60 * scale)),
    "sunlit_classroom": lambda scale=1: sunlit_classroom(size=(96 * scale, 54 * scale)),
    "tall_stairwell": lambda scale=1: tall_stairwell(size=(48 * scale, 80 * scale)),
}
