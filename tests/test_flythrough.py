"""One cache for every camera of a scene: the fingerprint covers shapes, BSDFs, textures
and emitters, never sensors, films or samplers (issue: the cache belongs to the scene)."""
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import cachefile
from pmic_integrator.fingerprint import scene_fingerprint

from pmic_integrator.kinds import SMALL_PMIC, _sensor, two_rooms

T = mi.ScalarTransform4f


def rooms(sensors=2, **params):
    """The two rooms (a door between them), pmic small, with 1 or 2 sensors."""
    d = two_rooms(size=(24, 16))
    d["integrator"] = {"type": "pmic", **SMALL_PMIC, **params}
    if sensors == 2:
        d["sensor_b"] = _sensor((1.5, 0.6, -0.8), (0.0, -0.5, 0.5), 60, (20, 20))
    return d


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A cache file saved from the scene with two sensors, and its view 0."""
    path = tmp_path_factory.mktemp("fly") / "rooms.npz"
    scene = mi.load_dict(rooms(2))
    image = np.array(mi.render(scene, spp=2, seed=3))
    scene.integrator().save_cache(path)
    return path, image


def test_one_sensor_fewer_loads_and_view_0_is_bit_identical(saved):
    path, image = saved
    scene = mi.load_dict(rooms(1, cache_file=str(path)))
    again = np.array(mi.render(scene, spp=2, seed=3))
    assert scene.integrator().stats["cache_loaded_from"] == str(path)
    assert np.array_equal(again, image)


def test_moved_camera_other_fov_and_film_load_and_render(saved):
    path, _ = saved
    d = rooms(1, cache_file=str(path))
    d["sensor"] = _sensor((1.2, 0.0, 0.5), (-1.0, -0.2, -0.5), 90, (30, 12))
    scene = mi.load_dict(d)
    image = np.array(mi.render(scene, spp=2))
    assert scene.integrator().stats["cache_loaded_from"] == str(path)
    assert image.shape[:2] == (12, 30) and np.isfinite(image).all() and image.mean() > 0


def test_edited_wall_colour_is_refused_naming_the_wall(saved):
    path, _ = saved
    d = rooms(2, cache_file=str(path))
    d["back"]["bsdf"]["reflectance"]["value"] = [0.2, 0.6, 0.4]
    scene = mi.load_dict(d)
    with pytest.raises(cachefile.CacheFileError, match=r"another scene.*changed: shape 'back'"):
        scene.integrator().build_cache(scene)


def test_moved_light_is_refused_naming_it(saved):
    path, _ = saved
    d = rooms(2, cache_file=str(path))
    d["light"]["to_world"] = T().translate([-1.0, 0.999, -0.2]).rotate([1, 0, 0], 90).scale([0.2, 0.2, 1])
    scene = mi.load_dict(d)
    with pytest.raises(cachefile.CacheFileError, match=r"changed: shape 'light'"):
        scene.integrator().build_cache(scene)


def test_settings_mismatch_names_each_parameter_with_both_values(saved):
    path, _ = saved
    scene = mi.load_dict(rooms(2, cache_file=str(path), max_error=0.3, gather_rays=128))
    with pytest.raises(cachefile.CacheFileError) as error:
        scene.integrator().build_cache(scene)
    message = str(error.value)
    assert "max_error 0.5 in the file, 0.3 here" in message
    assert "gather_rays 64 in the file, 128 here" in message


def test_camera_animated_through_traverse_keeps_the_cache():
    """Mitsuba's usual animation: move the sensor with mi.traverse between renders.
    Before, each frame rebuilt the cache (cache_builds 2, 3, 4)."""
    scene = mi.load_dict(rooms(1))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world") and "sensor" in k)
    for frame in range(3):
        params[key] = T().look_at(origin=[1.9 - 0.2 * frame, 0.3, 0.9], target=[0, -0.3, -0.2],
                                  up=[0, 1, 0])
        params.update()
        mi.render(scene, spp=1, seed=frame)
        assert scene.integrator().stats["cache_builds"] == 1


def test_an_edit_through_traverse_rebuilds():
    scene = mi.load_dict(rooms(1))
    mi.render(scene, spp=1)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("emitter.radiance.value"))
    params[key] = mi.Color3f(30, 30, 30)
    params.update()
    mi.render(scene, spp=1)
    assert scene.integrator().stats["cache_builds"] == 2


def test_fingerprint_sees_one_vertex_moved_in_a_large_mesh():
    """Large buffers are hashed on the device: one coordinate of one vertex of 10k
    still changes the digest, and only that shape is named."""
    mesh = mi.Mesh("big", 10_000, 9_998, has_vertex_normals=False)
    params = mi.traverse(mesh)
    rng = np.random.default_rng(1)
    params["vertex_positions"] = mi.Float(rng.random(30_000).astype(np.float32))
    params["faces"] = mi.UInt32(np.stack([np.arange(9_998), np.arange(1, 9_999), np.arange(2, 10_000)],
                                         1).ravel().astype(np.uint32))
    params.update()
    scene = mi.load_dict({"type": "scene", "big": mesh,
                          "small": {"type": "sphere", "radius": 0.1}})
    before = scene_fingerprint(scene)
    scene_params = mi.traverse(scene)
    positions = np.array(scene_params["big.vertex_positions"])
    positions[12_345] = np.nextafter(positions[12_345], np.float32(2))
    scene_params["big.vertex_positions"] = mi.Float(positions)
    scene_params.update()
    after = scene_fingerprint(scene)
    assert after.digest != before.digest
    assert after.differences(before) == "changed: shape 'big'"
    assert scene_fingerprint(scene) == after  # deterministic
