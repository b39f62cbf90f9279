"""The pmic plugin as a user meets it: loading, parameters, statistics, edge cases."""
import subprocess
import sys
import textwrap

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import pmic_integrator
from pmic_integrator.integrator import PMICIntegrator

from pmic_integrator.kinds import SMALL_PMIC as SMALL, envmap_exterior, pmic_cornell as small_cornell


def test_load_dict_and_render():
    scene = mi.load_dict(small_cornell())
    image = np.array(mi.render(scene, spp=2))
    assert image.shape == (32, 32, 3) and np.isfinite(image).all() and image.mean() > 0.05
    stats = scene.integrator().stats
    for key in ("photons_global", "photons_caustic", "paths_emitted", "time_photons",
                "time_precompute", "time_render", "records", "records_fallback",
                "cache_builds", "time_cache"):
        assert key in stats, key
    assert 20_000 <= stats["photons_global"] < 20_000 + 64  # whole paths
    assert stats["photons_caustic"] == 0  # no specular surface: caustic map skipped
    assert any("caustic map" in s for s in stats["skipped"])
    assert stats["records"] > 0 and stats["cache_builds"] == 1
    assert "PMICIntegrator" in str(scene.integrator())


def test_load_from_xml():
    scene = mi.load_string(textwrap.dedent("""
        <scene version="3.0.0">
            <integrator type="pmic">
                <string name="method" value="photon_map"/>
                <integer name="global_photons" value="5000"/>
                <float name="max_error" value="0.7"/>
            </integrator>
            <shape type="sphere"><emitter type="area"/></shape>
            <shape type="rectangle">
                <transform name="to_world"><translate z="-2"/><scale value="5"/></transform>
            </shape>
            <sensor type="perspective">
                <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
                <transform name="to_world"><lookat origin="0,0,5" target="0,0,0" up="0,1,0"/></transform>
            </sensor>
        </scene>"""))
    integrator = scene.integrator()
    assert isinstance(integrator, PMICIntegrator)
    assert integrator.settings.method == "photon_map" and integrator.settings.max_error == 0.7
    assert np.isfinite(np.array(mi.render(scene, spp=1))).all()


@pytest.mark.parametrize("order", ["package_first", "variant_first"])
def test_registration_in_either_import_order(order):
    lines = ["import pmic_integrator", "import mitsuba as mi", "mi.set_variant('llvm_ad_rgb')"]
    if order == "variant_first":
        lines = ["import pmic_integrator._llvm as l; l.configure()", "import mitsuba as mi",
                 "mi.set_variant('llvm_ad_rgb')", "import pmic_integrator"]
    lines.append("print(type(mi.load_dict({'type': 'pmic'})).__name__)")
    out = subprocess.run([sys.executable, "-c", "\n".join(lines)], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("PMICIntegrator")


def test_every_module_imports_before_a_variant_is_set():
    """Benchmarks and users import pmic's modules before ``mi.set_variant``: a module
    that touches a variant's types at import (a table of ``mi.Point3f`` ...) fails
    there, and would bind the first variant's types for every later one. Not these:
    ``integrator`` chooses the CPU variant when none is set (its class derives from
    the variant's), and the camera-path modules derive from Mitsuba's integrators
    (both are imported through it)."""
    chooses = ("pmic_integrator.integrator", "pmic_integrator.render.direct", "pmic_integrator.render.path")
    code = ("import importlib, pkgutil, pmic_integrator\n"
            "import mitsuba as mi\n"
            "for m in pkgutil.walk_packages(pmic_integrator.__path__, 'pmic_integrator.'):\n"
            f"    if m.name not in {chooses!r}:\n"
            "        importlib.import_module(m.name)\n"
            "        assert mi.variant() is None, m.name\n"
            "print('imported')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "imported"


def test_scalar_variant_gets_a_clear_error():
    code = ("import pmic_integrator, mitsuba as mi\nmi.set_variant('scalar_rgb')\n"
            "mi.load_dict({'type': 'pmic'})")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode != 0
    assert "llvm_ad_rgb" in out.stderr and "scalar_rgb" in out.stderr


@pytest.mark.parametrize("name,value,allowed", [
    ("global_photons", -1, "[1000, 50000000]"),
    ("global_photons", 0, "[1000, 50000000]"),
    ("global_photons", 10, "[1000, 50000000]"),
    ("global_photons", 10**9, "[1000, 50000000]"),
    ("caustic_photons", -5, "[0, 50000000]"),
    ("method", "path", "one of pmic, photon_map, irradiance_cache"),
    ("max_error", 0.0, "[0.01, 1.0]"),
    ("max_error", 1e-9, "[0.01, 1.0]"),
    ("max_error", 10.0, "[0.01, 1.0]"),
    ("max_error", float("nan"), "[0.01, 1.0]"),
    ("gather_rays", 2, "[16, 16384]"),
    ("lookup_size", 1, "[8, 10000]"),
    ("lookup_radius", -1.0, ">= 0"),
    ("lookup_radius", float("inf"), ">= 0"),
    ("max_depth", 0, "-1 (unbounded)"),
    ("max_depth", -2, "-1 (unbounded)"),
    ("rr_depth", 0, "[1, 1024]"),
    ("direct_samples", 0, "[1, 64]"),
    ("seed", -1, "[0, 4294967295]"),
    ("max_photon_paths", 1, "[1000, 2^40]"),
    ("seed", 2**40, "[0, 4294967295]"),
    # Types are checked as strictly as Mitsuba's own plugins: no silent truncation.
    ("global_photons", 1000.7, "of type integer"),
    ("max_depth", 2.9, "of type integer"),
    ("max_depth", 2.0, "of type integer"),
    ("global_photons", "abc", "of type integer"),
    ("max_error", "0.5", "of type float"),
    ("hide_emitters", 1, "of type boolean"),
    ("method", 3, "of type string"),
])
def test_bad_parameters_raise_value_error_naming_them(name, value, allowed):
    props = mi.Properties("pmic")
    props[name] = value
    with pytest.raises(ValueError) as info:
        PMICIntegrator(props)
    message = str(info.value)
    assert f"'{name}'" in message and allowed in message and repr(value)[:6] in message
    # Through Mitsuba's loader the same message arrives (Mitsuba re-raises plugin
    # errors as RuntimeError, with the ValueError's text).
    with pytest.raises(RuntimeError, match=f"ValueError: .*'{name}'"):
        mi.load_dict({"type": "pmic", name: value})


def test_same_seed_same_image_and_cache():
    images = []
    for _ in range(2):
        scene = mi.load_dict(small_cornell())
        images.append(np.array(mi.render(scene, spp=2, seed=3)))
    np.testing.assert_array_equal(images[0], images[1])
    # Another integrator seed traces other photons: the image changes.
    other = mi.load_dict(small_cornell(seed=1))
    assert not np.array_equal(np.array(mi.render(other, spp=2, seed=3)), images[0])


@pytest.mark.rgb_only("doubles an rgb emitter's 'value' through mi.traverse, which in spectral variants holds the sRGB model's coefficients")
def test_cache_is_view_independent_and_reused():
    d = small_cornell()
    second = dict(d["sensor"])
    second["to_world"] = mi.ScalarTransform4f().look_at(origin=[0.6, 0.3, 2.5], target=[-0.3, -0.4, 0],
                                                        up=[0, 1, 0])
    d["sensor_2"] = second
    scene = mi.load_dict(d)
    integrator = scene.integrator()
    first = np.array(mi.render(scene, sensor=0, spp=2))
    records = integrator.stats["records"]
    view2 = np.array(mi.render(scene, sensor=1, spp=2))
    assert integrator.stats["cache_builds"] == 1
    assert integrator.stats["records"] == records
    assert np.isfinite(view2).all() and view2.mean() > 0.05
    again = np.array(mi.render(scene, sensor=0, spp=2))
    assert integrator.stats["cache_builds"] == 1
    assert np.isfinite(again).all() and abs(again.mean() / first.mean() - 1) < 0.05
    # Editing the scene rebuilds the cache.
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith("radiance.value")][0]
    params[key] = params[key] * 2
    params.update()
    brighter = np.array(mi.render(scene, sensor=0, spp=2))
    assert integrator.stats["cache_builds"] == 2
    assert abs(brighter.mean() / first.mean() - 2) < 0.1


@pytest.mark.parametrize("estimator", ["final_gather", "first_hit"])
def test_renders_read_the_records_packed_with_the_image_of_field_reads(estimator, monkeypatch):
    """A render lays the records out record by record (RecordIndex.pack: packet loads,
    a tenth off a Cornell box's camera pass) and reads them so; the image is that of
    the field-by-field reads up to rounding (the rotational gradient's dot product is
    taken in another order)."""
    from pmic_integrator.cache import RecordIndex
    scene = mi.load_dict(small_cornell(estimator=estimator))
    packed = np.array(mi.render(scene, spp=2, seed=3))
    assert scene.integrator()._prepared.index.packed_body is not None
    monkeypatch.setattr(RecordIndex, "pack", lambda self: self)
    scene = mi.load_dict(small_cornell(estimator=estimator))
    fields = np.array(mi.render(scene, spp=2, seed=3))
    assert scene.integrator()._prepared.index.packed_body is None
    np.testing.assert_allclose(packed, fields, rtol=1e-5, atol=1e-7)


def test_direct_only_skips_photons():
    scene = mi.load_dict(small_cornell(max_depth=2))
    image = np.array(mi.render(scene, spp=4))
    stats = scene.integrator().stats
    assert stats["photons_global"] == 0 and stats["paths_emitted"] == 0
    assert any("max_depth" in s for s in stats["skipped"])
    ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 2}), spp=64))
    assert abs(image.mean() / ref.mean() - 1) < 0.03


def test_too_few_photons_and_no_emitters_give_finite_images():
    # One emitted path stores at most a few photons: no cache, but no failure either
    # (before: an uninitialised Dr.Jit loop variable).
    scene = mi.load_dict(small_cornell(max_photon_paths=1000, global_photons=1000, caustic_photons=0))
    image = np.array(mi.render(scene, spp=1))
    assert np.isfinite(image).all() and image.mean() > 0
    d = small_cornell()
    del d["light"]["emitter"]
    dark = mi.load_dict(d)
    image = np.array(mi.render(dark, spp=1))
    assert np.isfinite(image).all() and image.max() == 0
    assert any("no emitter" in s for s in dark.integrator().stats["skipped"])


def test_enclosed_light_warns_and_stays_finite():
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "pmic", "global_photons": 1000, "max_photon_paths": 20_000},
        "box": {"type": "cube", "flip_normals": False,
                "bsdf": {"type": "conductor"}},  # a mirror box: photons never land
        "light": {"type": "point", "position": [0, 0, 0], "intensity": {"type": "rgb", "value": 1.0}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -3]).scale(5)},
        "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, 0, 6], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 8, "height": 8}},
    })
    with pytest.warns(RuntimeWarning, match="global photons were stored"):
        image = np.array(mi.render(scene, spp=1))
    assert np.isfinite(image).all()
    stats = scene.integrator().stats
    assert stats["paths_emitted"] == 20_000  # the bound; the caustic pass is then skipped
    assert stats["photons_global"] == 0 and stats["photons_caustic"] == 0


def test_every_emitter_type_traces_photons():
    emitters = {
        "point": {"type": "point", "position": [0, 0.5, 0], "intensity": {"type": "rgb", "value": 2.0}},
        "spot": {"type": "spot", "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, 0.9, 0], target=[0, -1, 0], up=[0, 0, 1]), "intensity": {"type": "rgb", "value": 5.0}},
        "directional": {"type": "directional", "direction": [0.2, -1, 0.1],
                        "irradiance": {"type": "rgb", "value": 1.0}},
        "constant": {"type": "constant", "radiance": {"type": "rgb", "value": 0.5}},
        "envmap": {"type": "envmap", "bitmap": mi.Bitmap(np.full((8, 16, 3), 0.5, np.float32))},
    }
    for name, emitter in emitters.items():
        d = small_cornell(global_photons=5000)
        del d["light"]["emitter"]
        if name in ("directional", "constant", "envmap"):
            del d["ceiling"]  # let light from outside in
        d["extra_light"] = emitter
        scene = mi.load_dict(d)
        image = np.array(mi.render(scene, spp=1))
        stats = scene.integrator().stats
        assert np.isfinite(image).all(), name
        assert 5000 <= stats["photons_global"] < 5000 + 64, name  # whole paths


def test_unusable_llvm_loaded_first_gives_one_clear_sentence():
    code = textwrap.dedent("""
        import os
        os.environ.pop("DRJIT_LIBLLVM_PATH", None)
        import drjit, mitsuba as mi
        import warnings
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            import pmic_integrator
        print("LOADED", pmic_integrator._llvm._loaded_llvm())
        print("WARNED", [str(w.message) for w in caught])
        mi.set_variant("llvm_ad_rgb")
        try:
            mi.load_dict({"type": "pmic"})
            print("LOADED-PMIC")
        except Exception as e:
            print("REFUSED", e)
        """)
    env = {k: v for k, v in __import__("os").environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    loaded = [l for l in out.stdout.splitlines() if l.startswith("LOADED ")]
    major = pmic_integrator._llvm._llvm_major(loaded[0]) if loaded and "None" not in loaded[0] else None
    if major is None or major >= pmic_integrator._llvm.MIN_LLVM_MAJOR:
        pytest.skip(f"no old system LLVM is loaded by default here ({loaded})")
    warned = [l for l in out.stdout.splitlines() if l.startswith("WARNED")][0]
    assert "cannot compile Dr.Jit 1.5 kernels" in warned  # the warning at import
    assert "Restart the Python process (in Jupyter: restart the kernel)" in warned
    assert "REFUSED" in out.stdout and "import pmic_integrator before drjit" in out.stdout


def test_photon_map_final_gather_and_direct_samples_agree_with_path():
    """(At this 24-pixel size the box reads 1.018-1.020 of path's mean, against a
    reference of 8192 spp too; at 48 pixels 0.990-0.992.)"""
    scene = mi.load_dict(small_cornell(resolution=24))
    ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=1024))
    means = {}
    for name, params in {"final_gather": {"method": "photon_map", "final_gather": True},
                         "pmic": {}, "pmic_direct4": {"direct_samples": 4}}.items():
        integrator = mi.load_dict({"type": "pmic", "global_photons": 200_000, **params})
        image = np.array(mi.render(scene, integrator=integrator, spp=64))
        assert np.isfinite(image).all()
        means[name] = image.mean() / ref.mean()
    assert abs(means["final_gather"] - 1) < 0.025, means
    assert abs(means["pmic"] - 1) < 0.025, means
    assert abs(means["pmic_direct4"] / means["pmic"] - 1) < 0.005, means


@pytest.mark.parametrize("photons", [20_000, 60_000])
def test_every_global_photon_is_covered_after_the_whole_pipeline(photons):
    # Subset-first walk, neighbour clamping and view clamping all keep Fig. 2's promise.
    scene = mi.load_dict(small_cornell(resolution=64, global_photons=photons))
    integrator = scene.integrator()
    mi.render(scene, spp=1)
    prepared = integrator._prepared
    covered = prepared.index.covered(prepared.global_map.position, prepared.global_map.normal)
    assert bool(dr.all(covered))


def test_a_caustic_pass_that_cannot_pay_is_given_up_after_its_first_batch():
    """A plastic ball under a sky focuses a few light paths in a thousand: the caustic
    map would be dropped (records gather those paths), so the pass stops as soon as its
    yield shows it (the first batch, 65k paths) instead of tracing its whole bound
    (20 paths per requested photon: 2 M here)."""
    from pmic_integrator import photons, pipeline

    scene = mi.load_dict({**envmap_exterior(size=(8, 6)),
                          "integrator": {"type": "pmic", "global_photons": 5000,
                                         "caustic_photons": 100_000}})
    mi.render(scene, spp=1)
    stats = scene.integrator().stats
    assert stats["photons_caustic"] == 0
    assert any(s.startswith("caustic map:") and "gather rays count caustic light" in s
               for s in stats["skipped"])
    assert stats["paths_emitted_caustic"] == photons.FIRST_BATCH_PATHS
    assert stats["paths_emitted_caustic"] < pipeline.CAUSTIC_PATHS_PER_PHOTON * 100_000 / 10


def test_an_environment_map_with_nan_or_inf_texels_is_refused_naming_it():
    """Mitsuba samples such a map wrongly (path renders NaN pixels); pmic's image was
    finite but wrong (its photons all dropped, and with NaN its sky samples too, half
    as bright): an error instead, before any photon is traced."""
    for value in (np.nan, np.inf):
        bitmap = np.ones((8, 16, 3), np.float32)
        bitmap[2, 3] = value
        scene = {**envmap_exterior(size=(8, 6)), "integrator": {"type": "pmic", "global_photons": 5000}}
        scene["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(bitmap)}
        with pytest.raises(Exception) as info:
            mi.render(mi.load_dict(scene), spp=1)
        chain, error = [], info.value
        while error is not None:
            chain.append(error)
            error = error.__cause__
        refusal = [e for e in chain if isinstance(e, ValueError) and "NaN/Inf" in str(e)]
        assert refusal and "'sky'" in str(refusal[0]) and "1 NaN/Inf texel;" in str(refusal[0])


def _rough_floor_rooms(size=(32, 24)):
    from pmic_integrator import kinds as sb

    return mi.load_dict(sb.two_rooms(size=size, floor_bsdf={"type": "roughconductor", "alpha": 0.25,
                                                             "material": "Al"}))


def test_deferred_caustic_reads_give_the_image_of_reads_in_the_loop(monkeypatch):
    """In pmic's own render the caustic-map reads wait for the end of the camera loop
    and are made over the lanes that can find a photon (pmic_integrator.render.caustics);
    read in the loop instead (as for a caller of sample() alone), the image is the same
    up to the order of float sums. Two renders with deferral are bit-identical. (A
    pixel's samples sharing one estimate is turned off here: see the next test.)"""
    from pmic_integrator.render import caustics, config
    monkeypatch.setattr(caustics, "CAUSTIC_SHARE_RADII", 0.0)
    scene = _rough_floor_rooms()
    spec = {"type": "pmic", **SMALL}
    integrator = mi.load_dict(spec)
    deferred = np.array(mi.render(scene, integrator=integrator, spp=4, seed=3))
    assert config.defers_caustics(integrator.settings, integrator.prepared)
    again = np.array(mi.render(scene, integrator=integrator, spp=4, seed=3))
    assert np.array_equal(deferred, again)
    monkeypatch.setattr(config, "defers_caustics", lambda settings, prepared: False)
    inline = np.array(mi.render(scene, integrator=integrator, spp=4, seed=3))
    assert np.allclose(deferred, inline, rtol=1e-4, atol=1e-6)
    assert not np.array_equal(deferred, np.zeros_like(deferred))


def test_a_pixels_samples_share_their_first_caustic_estimate_without_changing_the_image(monkeypatch):
    """The first caustic-map reads of a pixel's samples share the estimate made at its
    first sample where they lie within CAUSTIC_SHARE_RADII of its kernel radius (in a
    room lit by a sky through a thin pane, all of whose light is caustic, the reads
    were 60 % of the render). The image stays that of one estimate per sample: mean
    within 0.2 %, 99 % of the pixels within 3 % and all within 6 %. It is not the same
    image: estimates were shared."""
    from pmic_integrator import kinds as sb
    from pmic_integrator.render import caustics, config

    d = sb.window_room(size=(32, 24))
    d["pane"] = {"type": "rectangle", "bsdf": {"type": "thindielectric"},
                 "to_world": mi.ScalarTransform4f().translate([0, 1.4, 1.99]).scale([0.6, 0.4, 1])}
    scene = mi.load_dict(d)
    integrator = mi.load_dict({"type": "pmic", **SMALL})
    shared = np.array(mi.render(scene, integrator=integrator, spp=8, seed=2))
    assert config.defers_caustics(integrator.settings, integrator.prepared)
    monkeypatch.setattr(caustics, "CAUSTIC_SHARE_RADII", 0.0)
    own = np.array(mi.render(scene, integrator=integrator, spp=8, seed=2))
    assert not np.array_equal(shared, own)
    assert shared.mean() == pytest.approx(own.mean(), rel=2e-3)
    # (Measured: median 0.14 %, 99 % of pixels within 2.3 %, the worst 4.0 %: with
    # 5000 caustic photons one photon's weight moves by a few per cent when the kernel
    # shifts by a tenth of its radius.)
    relative = np.abs(shared - own).max(-1) / np.maximum(own.max(-1), 1e-6)
    # (Spectral variants: each sample's wavelengths differ too; measured 3.1 % and
    # 10 % there.)
    assert np.quantile(relative, 0.99) < (0.04 if mi.is_spectral else 0.03)
    assert relative.max() < (0.15 if mi.is_spectral else 0.06)


def test_deferred_caustic_reads_run_in_passes_that_bound_their_memory(monkeypatch):
    """With reads deferred, a wavefront holds at most DEFERRED_WAVEFRONT samples: the
    render runs in several passes, each seeded on its own, with the same mean (within
    the noise of 16 samples of a dim room lit through a door)."""
    from pmic_integrator import camera
    from pmic_integrator.render import config

    scene = _rough_floor_rooms(size=(16, 12))
    spec = {"type": "pmic", **SMALL}
    passes = []
    original = camera.pass_counts

    def counted(film, spp, max_wavefront=camera.MAX_WAVEFRONT):
        counts = original(film, spp, max_wavefront)
        passes.append(counts)
        return counts

    monkeypatch.setattr(camera, "pass_counts", counted)
    whole = np.array(mi.render(scene, integrator=mi.load_dict(spec), spp=16, seed=0))
    assert passes[-1] == [16]
    monkeypatch.setattr(config, "DEFERRED_WAVEFRONT", 16 * 12 * 4)
    split = np.array(mi.render(scene, integrator=mi.load_dict(spec), spp=16, seed=0))
    assert passes[-1] == [4, 4, 4, 4]
    assert np.isfinite(split).all()
    assert abs(split.mean() / whole.mean() - 1) < 0.15
    assert not np.array_equal(split, whole)


def test_pass_counts_split_a_wavefront_at_the_bound():
    from pmic_integrator import camera

    film = mi.load_dict({"type": "hdrfilm", "width": 10, "height": 10, "rfilter": {"type": "box"}})
    assert camera.pass_counts(film, 7) == [7]
    assert camera.pass_counts(film, 7, max_wavefront=300) == [3, 3, 1]
    assert camera.pass_counts(film, 7, max_wavefront=50) == [1] * 7  # at least one per pixel


def test_participating_media_are_ignored_with_a_warning():
    """pmic renders surfaces only, as Mitsuba's path does: a shape holding a medium
    (behind a null BSDF) gives the image without it, and a warning that names the
    shape; a scene without media gives none."""
    import warnings

    d = small_cornell()
    d["fog"] = {"type": "sphere", "center": [0.3, -0.3, 0.2], "radius": 0.35, "bsdf": {"type": "null"},
                "interior": {"type": "homogeneous", "sigma_t": 2.0, "albedo": 0.5}}
    with pytest.warns(RuntimeWarning, match="participating media of shape 'fog'"):
        image = np.array(mi.render(mi.load_dict(d), spp=2))
    assert np.isfinite(image).all() and image.mean() > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        mi.render(mi.load_dict(small_cornell()), spp=1)
