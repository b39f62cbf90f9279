"""Stage 4's frame (camera.py): one render kernel for every sample count, passes past
2^32 samples, crops and pixel filters as Mitsuba's own render loop handles them."""
import gc
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import camera

from pmic_integrator.kinds import SMALL_PMIC as SMALL, cornell


def _largest_kernel(scene, integrator, spp, seed):
    """The code of the largest Dr.Jit kernel a render launches (the camera paths), but
    for the hashes in names and the alignment of its loads: Dr.Jit marks a buffer that happens to
    start on a 64-byte boundary, which depends on the allocator, not on our code."""
    # Objects of earlier tests that the collector frees between two renders leave
    # Mitsuba's registry, and the kernel's virtual calls span the registered instances.
    gc.collect()
    dr.kernel_history()  # clears it
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        dr.eval(image)
        dr.sync_thread()
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    jit = [k for k in history if k.get("type") == dr.KernelType.JIT]
    largest = max(jit, key=lambda k: k.get("operation_count", 0))
    code = re.sub(r"_[0-9a-f]{32}\b", "_HASH", largest["ir"].getvalue())  # its name
    return re.sub(r"align \d+", "align", code)


def test_one_render_kernel_serves_one_sample_per_pixel_and_many():
    """A 1-spp render (a preview, a warm-up) must compile the kernel that the 16-spp
    render then runs. Mitsuba's C++ loop divided the sample index by the sample count
    only above one sample, so the next render compiled a kernel of its own (0.5-0.7 s
    of a 2.5 s material-preview render where Dr.Jit's disk cache lacked it)."""
    scene = mi.load_dict(cornell(16))
    spec = {"type": "pmic", **SMALL}
    one = _largest_kernel(scene, mi.load_dict(spec), 1, 1)
    assert _largest_kernel(scene, mi.load_dict(spec), 16, 0) == one
    assert _largest_kernel(scene, mi.load_dict(spec), 7, 2) == one


def test_passes_split_a_wavefront_past_the_limit(monkeypatch):
    """Past MAX_WAVEFRONT samples the render is split into passes with seeds of their
    own: the image is the mean over all of them, not one pass repeated."""
    scene = mi.load_dict(cornell(16))
    spec = {"type": "pmic", **SMALL}
    whole = np.array(mi.render(scene, integrator=mi.load_dict(spec), spp=64, seed=3))
    monkeypatch.setattr(camera, "MAX_WAVEFRONT", 16 * 16 * 24)
    assert camera.pass_counts(scene.sensors()[0].film(), 64) == [24, 24, 16]
    split = np.array(mi.render(scene, integrator=mi.load_dict(spec), spp=64, seed=3))
    assert np.isfinite(split).all()
    # The same estimate, other random numbers: equal means, different pixels.
    assert abs(split.mean() / whole.mean() - 1) < 0.02
    assert not np.array_equal(split, whole)
    # A single pass of 24 spp repeated would be noisier than 64 spp: compare the
    # pixel noise against a 64-spp render with another seed.
    other = np.array(mi.render(scene, integrator=mi.load_dict(spec), spp=64, seed=4))
    assert np.mean((split - whole) ** 2) < 1.5 * np.mean((other - whole) ** 2)


@pytest.mark.rgb_only('per-row ratios at 10 % are below spectral colour noise at its sample count')
def test_crop_and_gaussian_filter_match_path():
    """A cropped film with a Gaussian filter (sampled border, positions not on pixel
    corners) gives path's image: same size, same mean within noise."""
    d = cornell(32)
    d["sensor"]["film"].update({"rfilter": {"type": "gaussian"}, "crop_offset_x": 4,
                                "crop_offset_y": 8, "crop_width": 20, "crop_height": 16})
    scene = mi.load_dict(d)
    ours = np.array(mi.render(scene, integrator=mi.load_dict({"type": "pmic", **SMALL}), spp=64))
    path = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=1024))
    assert ours.shape == path.shape == (16, 20, 3)
    assert abs(ours.mean() / path.mean() - 1) < 0.03
    # Row by row (the crop must sample the right part of the image, not its corner).
    rows = ours.mean((1, 2)) / path.mean((1, 2))
    assert np.all(np.abs(rows - 1) < 0.1)


def test_the_render_kernel_does_not_depend_on_the_scene_seed():
    """Radii measured from the photons (which move with the seed) must reach the render
    kernel as opaque values, not as constants: as constants, each new seed or scene
    compiled the camera-path kernel anew (0.5 s in the lamp room, in the timed render
    of a benchmark whose warm-up used another seed)."""
    scene = mi.load_dict(cornell(16))
    first = _largest_kernel(scene, mi.load_dict({"type": "pmic", **SMALL, "seed": 1}), 1, 0)
    assert _largest_kernel(scene, mi.load_dict({"type": "pmic", **SMALL, "seed": 2}), 1, 0) == first


@pytest.mark.rgb_only("Mitsuba's ldsampler in spectral variants moves path's own mean by 16 % against the independent sampler (0.139 / 0.165, Cornell box 16²)")
@pytest.mark.parametrize("sampler", ["stratified", "multijitter", "ldsampler", "orthogonal"])
def test_samplers_that_round_the_sample_count_render(sampler):
    """Samplers round a sample count to one they can stratify (a square, a power of
    two, a prime's square). The wavefront was sized by the count asked for, and the
    sampler refused it ("sample_count should be a multiple of samples_per_wavefront")
    for any count it rounded: 10 spp with each of these, 16 with ``orthogonal``. Now
    the render takes the sampler's count, as Mitsuba's own render does."""
    d = cornell(16)
    d["sensor"]["sampler"] = {"type": sampler, "sample_count": 4}
    scene = mi.load_dict(d)
    reference = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=1024))
    for spp in (10, 16):
        image = np.array(mi.render(scene, integrator=mi.load_dict({"type": "pmic", **SMALL}), spp=spp))
        assert image.shape == reference.shape and np.isfinite(image).all()
        assert abs(image.mean() / reference.mean() - 1) < 0.05


def _sensor_variant(d, kind):
    T = mi.ScalarTransform4f
    s = d["sensor"]
    if kind == "orthographic":
        s["type"] = "orthographic"
        s.pop("fov", None)
        s.pop("fov_axis", None)
        s["to_world"] = s["to_world"] @ T().scale([1.1, 1.1, 1.0])
    elif kind == "thinlens":
        s.update({"type": "thinlens", "aperture_radius": 0.05, "focus_distance": 3.9})
    elif kind == "batch":
        other = {k: v for k, v in s.items() if k not in ("film", "sampler")}
        moved = dict(other, to_world=T().look_at(origin=[0.5, 0.2, 3.9], target=[0, 0, 0], up=[0, 1, 0]))
        film = dict(s["film"], width=2 * s["film"]["width"])
        d["sensor"] = {"type": "batch", "film": film, "sampler": s["sampler"], "a": other, "b": moved}
    else:  # a film's pixel format
        s["film"]["pixel_format"] = kind
    return d


@pytest.mark.parametrize("kind", ["orthographic", "thinlens", "batch", "luminance", "xyz", "rgba"])
def test_sensors_and_films_render_as_path_does(kind):
    """Other sensors (orthographic, thin lens, a batch of two views) and film formats
    give path's image: same channels and size, same mean within noise."""
    scene = mi.load_dict(_sensor_variant(cornell(16), kind))
    ours = np.array(mi.render(scene, integrator=mi.load_dict({"type": "pmic", **SMALL}), spp=64))
    path = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=1024))
    assert ours.shape == path.shape and np.isfinite(ours).all()
    assert abs(ours.mean() / path.mean() - 1) < 0.04
