"""Many views from one cache on Dask (``pmic_integrator.views``), on a LocalCluster."""
import textwrap

import mitsuba as mi
import numpy as np
import pytest

pytest.importorskip("dask.distributed")

from pmic_integrator.views import render_views  # noqa: E402

SETTINGS = {"global_photons": 20_000, "gather_rays": 64}

SCENE = textwrap.dedent("""
    <scene version="3.0.0">
        <shape type="rectangle"><emitter type="area"><rgb name="radiance" value="8"/></emitter>
            <transform name="to_world"><scale value="0.3"/><rotate x="1" angle="90"/><translate y="0.99"/></transform>
        </shape>
        <shape type="cube"><bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf>
            <boolean name="flip_normals" value="true"/></shape>
        <shape type="sphere"><point name="center" x="0" y="-0.6" z="0"/><float name="radius" value="0.4"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.3, 0.2"/></bsdf></shape>
        {sensors}
    </scene>""")
SENSOR = """<sensor type="perspective"><float name="fov" value="70"/>
            <transform name="to_world"><lookat origin="{x}, 0, 0.95" target="0, -0.3, 0" up="0, 1, 0"/></transform>
            <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
                <rfilter type="box"/></film></sensor>"""


def test_views_on_a_local_cluster_equal_local_renders(tmp_path):
    scene_file = tmp_path / "room.xml"
    scene_file.write_text(SCENE.format(sensors="".join(SENSOR.format(x=x) for x in (-0.5, 0.0, 0.5))))
    cache = tmp_path / "cache.npz"
    images = render_views(scene_file, sensors=[2, 0], spp=2, seed=1, integrator=SETTINGS,
                          cache_file=cache, n_workers=1, threads_per_worker=1, progress=False)
    assert list(images) == [2, 0] and cache.is_file()
    # The same views rendered here, from the same cache file, in another order.
    scene = mi.load_file(str(scene_file))
    pmic = mi.load_dict({"type": "pmic", **SETTINGS, "cache_file": str(cache)})
    for sensor in (0, 2):
        local = np.array(mi.render(scene, integrator=pmic, sensor=sensor, spp=2, seed=1))
        assert np.array_equal(images[sensor], local), sensor
    assert not np.array_equal(images[0], images[2])


def test_worker_threads_render_what_worker_processes_render(tmp_path):
    """``processes=False``: two worker threads of this process share one scene and one
    loaded cache; the images are those of the local renders (as above)."""
    scene_file = tmp_path / "room.xml"
    scene_file.write_text(SCENE.format(sensors="".join(SENSOR.format(x=x) for x in (-0.5, 0.5))))
    cache = tmp_path / "cache.npz"
    images = render_views(scene_file, spp=2, seed=1, integrator=SETTINGS, cache_file=cache,
                          n_workers=2, processes=False, progress=False)
    scene = mi.load_file(str(scene_file))
    pmic = mi.load_dict({"type": "pmic", **SETTINGS, "cache_file": str(cache)})
    assert pmic.build_cache(scene)["photons_global"] > 0
    for sensor in (0, 1):
        local = np.array(mi.render(scene, integrator=pmic, sensor=sensor, spp=2, seed=1))
        assert np.array_equal(images[sensor], local), sensor


def test_bad_spp_is_refused(tmp_path):
    with pytest.raises(ValueError, match="'spp'"):
        render_views(tmp_path / "none.xml", spp=0)


def test_camera_path_frames_equal_renders_of_the_moved_sensor(tmp_path):
    """A fly-through from one cache: frames along two key look-ats, on worker threads,
    are what rendering the scene with its sensor moved there gives (mi.traverse)."""
    from pmic_integrator.views import frames_along_path, place_camera, render_frames

    scene_file = tmp_path / "room.xml"
    scene_file.write_text(SCENE.format(sensors=SENSOR.format(x=0.0)))
    keys = [{"origin": [-0.5, 0, 0.95], "target": [0, -0.3, 0], "fov": 60},
            {"origin": [0.5, 0.2, 0.9], "target": [0, -0.3, 0], "fov": 80}]
    frames = frames_along_path(scene_file, keys, 3, seed=4)
    assert [f.seed for f in frames] == [4, 5, 6] and frames[1].fov == pytest.approx(70)
    cache = tmp_path / "cache.npz"
    images = render_frames(frames, 2, SETTINGS, cache, n_workers=1, processes=False, progress=False)
    scene = mi.load_file(str(scene_file))
    pmic = mi.load_dict({"type": "pmic", **SETTINGS, "cache_file": str(cache)})
    for frame, image in zip(frames, images):
        place_camera(scene, frame)
        local = np.array(mi.render(scene, integrator=pmic, spp=2, seed=frame.seed))
        assert np.array_equal(image, local), frame.name
        assert pmic.stats["cache_builds"] == 0  # loaded once, never rebuilt
    assert not np.array_equal(images[0], images[2])


def test_scene_files_sharing_geometry_render_from_the_first_files_cache(tmp_path):
    from pmic_integrator.views import frames_of_files, render_frames

    files = []
    for i, x in enumerate((-0.4, 0.4)):
        files.append(tmp_path / f"shot{i}.xml")
        files[-1].write_text(SCENE.format(sensors=SENSOR.format(x=x)))
    images = render_frames(frames_of_files(files), 2, SETTINGS, n_workers=1, processes=False,
                           progress=False)
    assert len(images) == 2 and all(np.isfinite(im).all() and im.mean() > 0 for im in images)
    # A file whose light moved is another scene: refused, naming what changed.
    moved = tmp_path / "moved.xml"
    moved.write_text(SCENE.format(sensors=SENSOR.format(x=0.0)).replace('<translate y="0.99"/>',
                                                                      '<translate y="0.9"/>'))
    with pytest.raises(Exception, match="frame 'moved'.*another scene.*changed: unnamed shape \\(Rectangle"):
        render_frames(frames_of_files([files[0], moved]), 1, SETTINGS, n_workers=1, processes=False,
                      progress=False)


@pytest.mark.parametrize("keys,match", [
    ([], "at least one key"),
    ([{"origin": [0, 0, 1]}], "'origin' and 'target'"),
    ([{"origin": [0, 0], "target": [0, 0, 0]}], "'origin' must be 3 finite numbers"),
    ([{"origin": [0, 0, 1], "target": [0, 0, 0], "fov": 200}], "'fov' must be in"),
])
def test_bad_camera_paths_are_refused(keys, match):
    from pmic_integrator.views import frames_along_path

    with pytest.raises(ValueError, match=match):
        frames_along_path("scene.xml", keys, 4)


def test_render_views_command_writes_exr_and_png(tmp_path):
    from pmic_integrator.cli import render_views_main

    scene_file = tmp_path / "room.xml"
    scene_file.write_text(SCENE.format(sensors=SENSOR.format(x=0.0)))
    keys = tmp_path / "keys.json"
    keys.write_text('[{"origin": [-0.5, 0, 0.95], "target": [0, -0.3, 0]},'
                    ' {"origin": [0.5, 0, 0.95], "target": [0, -0.3, 0]}]')
    out = tmp_path / "out"
    assert render_views_main([str(scene_file), "--camera-path", str(keys), "--frames", "2", "--spp", "1",
                              "--threads", "--set", "global_photons=20000", "--set", "gather_rays=64",
                              "--output", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["frame_0000.exr", "frame_0000.png",
                                                      "frame_0001.exr", "frame_0001.png"]
