"""Saving and loading the view-independent cache (``save_cache``, ``cache_file``)."""
import subprocess
import sys
import textwrap
import zipfile

import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import cachefile

from pmic_integrator.kinds import SMALL_PMIC as SMALL, pmic_cornell


def cornell(**params):
    return pmic_cornell(24, **params)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    path = tmp_path_factory.mktemp("cache") / "cornell.npz"
    scene = mi.load_dict(cornell())
    image = np.array(mi.render(scene, spp=2, seed=5))
    scene.integrator().save_cache(path)
    return path, image


@pytest.mark.rgb_only('the fresh process renders in llvm_ad_rgb')
def test_round_trip_in_a_fresh_process_is_bit_identical(saved, tmp_path):
    path, image = saved
    out = tmp_path / "image.npy"
    script = textwrap.dedent(f"""
        import pmic_integrator, numpy as np, mitsuba as mi
        mi.set_variant("llvm_ad_rgb")
        d = mi.cornell_box()
        d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 24
        d["sensor"]["film"]["rfilter"] = {{"type": "box"}}
        d["integrator"] = {{"type": "pmic", **{SMALL!r}, "cache_file": {str(path)!r}}}
        scene = mi.load_dict(d)
        np.save({str(out)!r}, np.array(mi.render(scene, spp=2, seed=5)))
        stats = scene.integrator().stats
        assert stats["cache_loaded_from"] == {str(path)!r}, stats
        assert "time_photons" in stats  # the saved stages' figures come back too
    """)
    subprocess.run([sys.executable, "-c", script], check=True, timeout=600)
    assert np.array_equal(np.load(out), image)


def test_cache_file_is_written_when_missing(tmp_path):
    path = tmp_path / "new.npz"
    scene = mi.load_dict(cornell(cache_file=str(path)))
    mi.render(scene, spp=1)
    assert path.is_file() and scene.integrator().stats["cache_saved_to"] == str(path)
    with np.load(path, allow_pickle=False) as data:  # no pickled object inside
        assert "meta" in data.files


def test_another_scene_is_refused(saved):
    path, _ = saved
    d = cornell(cache_file=str(path))
    d["light"]["emitter"]["radiance"]["value"] = [20.0, 20.0, 20.0]
    scene = mi.load_dict(d)
    with pytest.raises(ValueError, match="another scene"):
        scene.integrator().build_cache(scene)


def test_other_settings_are_refused(saved):
    path, _ = saved
    scene = mi.load_dict(cornell(cache_file=str(path), max_error=0.3))
    with pytest.raises(ValueError, match="other settings"):
        scene.integrator().build_cache(scene)


@pytest.mark.parametrize("damage", ["truncated", "garbage", "not_pmic"])
def test_damaged_files_get_a_clear_error(saved, tmp_path, damage):
    path, _ = saved
    bad = tmp_path / f"{damage}.npz"
    data = path.read_bytes()
    if damage == "truncated":
        bad.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        bad.write_bytes(b"\x00" * 1000)
    else:
        np.savez(bad, meta=np.frombuffer(b'{"format": "other"}', dtype=np.uint8))
    scene = mi.load_dict(cornell(cache_file=str(bad)))
    with pytest.raises(ValueError, match="corrupt or truncated|not a pmic cache"):
        scene.integrator().build_cache(scene)
    # Through mi.render the same error reaches the caller as itself (Mitsuba's custom
    # operation wrapped it in "drjit.custom(...): error while performing ...").
    with pytest.raises(cachefile.CacheFileError, match="corrupt or truncated|not a pmic cache"):
        mi.render(scene, spp=1)


def test_another_scene_through_mi_render_names_the_cache_file(saved):
    path, _ = saved
    d = cornell(cache_file=str(path))
    d["light"]["emitter"]["radiance"]["value"] = [20.0, 20.0, 20.0]
    with pytest.raises(cachefile.CacheFileError) as error:
        mi.render(mi.load_dict(d), spp=1)
    assert str(error.value).startswith(f"cache_file '{path}' was built for another scene")
    assert "changed: shape 'light'" in str(error.value)
    assert error.value.__cause__ is None and error.value.__suppress_context__


def test_save_before_any_render_is_refused(tmp_path):
    integrator = mi.load_dict({"type": "pmic"})
    with pytest.raises(ValueError, match="nothing to save"):
        integrator.save_cache(tmp_path / "x.npz")


@pytest.mark.rgb_only('the fresh process renders in llvm_ad_rgb')
@pytest.mark.parametrize("method", ["pmic", "photon_map"])
def test_a_principled_metal_round_trips_in_a_fresh_process(tmp_path, method):
    """Which BSDFs are principled metals (bsdfs.diffuse_free) is known by their registry
    indices, which are the process's: a loaded cache finds them again in its scene, and
    its image is the one rendered where it was built (``photon_map`` with
    ``final_gather``: camera paths trace gather rays, which meet the brass, from the
    loaded gather source; read as diffuse there, it came out different)."""
    brass = {"type": "principled", "metallic": 1.0, "roughness": 0.25}
    path, out = tmp_path / "brass.npz", tmp_path / "image.npy"
    d = cornell(method=method, final_gather=method == "photon_map")
    d["large-box"]["bsdf"] = brass
    scene = mi.load_dict(d)
    image = np.array(mi.render(scene, spp=2, seed=5))
    assert scene.integrator().stats["photons_caustic"] > 0
    scene.integrator().save_cache(path)
    script = textwrap.dedent(f"""
        import pmic_integrator, numpy as np, mitsuba as mi
        mi.set_variant("llvm_ad_rgb")
        from pmic_integrator.kinds import pmic_cornell
        d = pmic_cornell(24, **{SMALL!r}, method={method!r}, final_gather={method == "photon_map"!r},
                         cache_file={str(path)!r})
        d["large-box"]["bsdf"] = {brass!r}
        scene = mi.load_dict(d)
        np.save({str(out)!r}, np.array(mi.render(scene, spp=2, seed=5)))
        assert scene.integrator().stats["cache_loaded_from"] == {str(path)!r}
    """)
    subprocess.run([sys.executable, "-c", script], check=True, timeout=600)
    assert np.array_equal(np.load(out), image)
