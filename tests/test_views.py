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
