"""What a new user meets first: comparing pmic with path on their own scene file, loading
any file with pmic, parameter help, and errors that say what is wrong."""
import os
import subprocess
import sys
import textwrap
import warnings

import mitsuba as mi
import numpy as np
import pytest

import pmic_integrator
from pmic_integrator import reference as refs
from pmic_integrator.cli import main as compare_main, reference_main

#: A user's scene, written outside the project: its own integrator (path, depth 8), a
#: $spp parameter, no integrator pmic knows of.
USER_SCENE = textwrap.dedent("""
    <scene version="3.0.0">
        <default name="spp" value="16"/>
        <default name="light" value="12"/>
        <integrator type="path"><integer name="max_depth" value="8"/></integrator>
        <sensor type="perspective">
            <float name="fov" value="60"/>
            <transform name="to_world"><lookat origin="0, 0.2, 2.5" target="0, -0.1, 0" up="0, 1, 0"/></transform>
            <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
            <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="16"/>
                <rfilter type="box"/></film>
        </sensor>
        <shape type="cube"><bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf>
            <transform name="to_world"><scale x="1.5" y="1" z="3"/></transform>
            <boolean name="flip_normals" value="true"/></shape>
        <shape type="sphere"><point name="center" x="-0.4" y="-0.6" z="0"/><float name="radius" value="0.4"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.3, 0.2"/></bsdf></shape>
        <shape type="rectangle"><emitter type="area"><rgb name="radiance" value="$light"/></emitter>
            <transform name="to_world"><scale value="0.35"/><rotate x="1" angle="90"/><translate y="0.99"/></transform></shape>
    </scene>""")
SMALL = ["--set", "global_photons=20000", "--set", "gather_rays=64", "--set", "caustic_photons=0"]


@pytest.fixture
def user_scene(tmp_path, monkeypatch):
    monkeypatch.setenv("PMIC_CACHE_DIR", str(tmp_path / "cache"))
    path = tmp_path / "elsewhere" / "my_room.xml"
    path.parent.mkdir()
    path.write_text(USER_SCENE)
    return path


def test_load_file_makes_pmic_the_integrator_whatever_the_file_says(user_scene):
    scene = pmic_integrator.load_file(user_scene, {"global_photons": 20_000}, spp=4, light="6")
    assert type(scene.integrator()).__name__ == "PMICIntegrator"
    assert scene.integrator().settings.global_photons == 20_000
    assert scene.sensors()[0].sampler().sample_count() == 4
    # Mitsuba's own way fails on such a file (it declares no $integrator):
    with pytest.raises(Exception, match="integrator"):
        mi.load_file(str(user_scene), integrator="pmic")


def test_compare_on_a_users_scene_file_prints_both_and_keeps_the_reference(user_scene, capsys):
    out = user_scene.parent / "out"
    args = [str(user_scene), "-D", "light=10", "--spp", "2", "--reference-spp", "64", "--output", str(out)]
    assert compare_main(args + SMALL) == 0
    printed = capsys.readouterr().out
    lines = {line.split()[0]: line.split() for line in printed.splitlines() if line.split()}
    assert "pmic" in lines and "path" in lines  # both integrators' rows
    assert float(lines["pmic"][3]) > 0 and float(lines["path"][3]) > 0  # their relMSE
    assert "path reference, 64 spp" in printed
    assert (out / "my_room_comparison.png").is_file() and (out / "results.json").is_file()
    kept = list((user_scene.parent.parent / "cache" / "references").glob("*.exr"))
    assert len(kept) == 1
    # The second run reads the kept reference (no second file, same image).
    before = kept[0].stat().st_mtime_ns
    assert compare_main(args + SMALL) == 0
    assert kept[0].stat().st_mtime_ns == before
    # Another light value is another scene: another reference.
    assert compare_main([str(user_scene), "-D", "light=5", "--spp", "1", "--reference-spp", "16",
                         "--output", str(out)] + SMALL) == 0
    assert len(list(kept[0].parent.glob("*.exr"))) == 2


def test_compare_with_a_given_reference_checks_its_size(user_scene, tmp_path):
    from pmic_integrator.scenes import write_exr

    wrong = tmp_path / "wrong.exr"
    write_exr(wrong, np.ones((8, 8, 3), np.float32))
    with pytest.raises(SystemExit):
        compare_main([str(user_scene), "--reference", str(wrong)])


def test_reference_command_writes_spp_and_noise(user_scene, tmp_path):
    from pmic_integrator.scenes import read_exr, read_exr_metadata

    out = tmp_path / "ref.exr"
    assert reference_main([str(user_scene), "--spp", "32", "-o", str(out)]) == 0
    meta = read_exr_metadata(out)
    assert meta["pmic_spp"] == "32" and 0 < float(meta["pmic_noise"]) < 1
    assert read_exr(out).shape == (16, 24, 3)


def test_noise_of_passes_matches_the_variance_of_their_mean():
    """Eight passes of a flat 0.5 image with Gaussian noise of sd 0.1: the mean's
    variance is 0.01 / 8, relative to 0.5^2 + 0.01."""
    rng = np.random.default_rng(3)
    passes = [0.5 + 0.1 * rng.standard_normal((64, 64, 3)) for _ in range(8)]
    assert refs.noise_of_passes(passes) == pytest.approx(0.01 / 8 / 0.26, rel=0.05)


def test_reference_needs_a_budget(user_scene):
    scene = pmic_integrator.load_file(user_scene)
    with pytest.raises(ValueError, match="'spp'.*or 'seconds'"):
        refs.render_reference(scene)
    with pytest.raises(ValueError, match="'spp' must be a positive integer, got 0"):
        refs.render_reference(scene, spp=0)


def test_documented_parameter_help_works_in_a_fresh_interpreter():
    code = "import pmic_integrator.integrator as m; help(m.PMICIntegrator)"
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**env, "PAGER": "cat"})
    assert out.returncode == 0, out.stderr
    assert "global_photons" in out.stdout and "max_error" in out.stdout


def test_a_misspelt_parameter_gets_a_suggestion():
    with pytest.raises(Exception, match=r"unknown parameter 'max_eror' \(did you mean 'max_error'\?"):
        mi.load_dict({"type": "pmic", "max_eror": 0.3})


def test_a_scene_without_emitters_gets_a_warning():
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "pmic", "global_photons": 5000},
                          "floor": {"type": "rectangle"},
                          "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8,
                                                                     "height": 8}}})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = np.array(mi.render(scene, spp=1))
    assert any("no emitter" in str(w.message) for w in caught)
    assert np.all(image == 0)


def test_an_error_while_rendering_reaches_the_user_as_itself():
    """A lookup_radius too large for the scene is found at render time (it needs the
    scene); mi.render raises the ValueError itself, not Dr.Jit's custom-operation
    wrapper whose message says only '(see above)'."""
    scene = mi.load_dict(mi.cornell_box())
    pmic = mi.load_dict({"type": "pmic", "lookup_radius": 5.0})
    with pytest.raises(ValueError, match="parameter 'lookup_radius' must be") as error:
        mi.render(scene, integrator=pmic, spp=1)
    assert "drjit.custom" not in str(error.value)
