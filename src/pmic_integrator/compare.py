"""Render a scene with ``pmic`` and with Mitsuba's ``path`` at equal time, and score both.

Timing rules (the same everywhere in the project): every measured render runs after a
warm-up render of the same configuration in the same process, so kernel compilation is
reported separately (``compile_s``) and not hidden in, or added to, the timings; time is
wall-clock from the call to ``mi.render`` until the image is evaluated, and for ``pmic``
it includes every stage (photons, precomputation, cache, camera pass).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import metrics

PATH_INTEGRATOR = {"type": "path", "max_depth": -1}
#: Blur of the low-frequency error (pixels): what remains is structure, not noise.
LOW_FREQUENCY_SIGMA = 4.0


def with_guides(spec: dict) -> dict:
    """``spec`` made to output the denoiser's guides after the colour: albedo (3
    channels), then the shading normal (3). pmic outputs them itself; any other
    integrator is wrapped in Mitsuba's ``aov`` integrator, which computes the same."""
    if spec["type"] == "pmic":
        return {**spec, "aovs": "albedo,normal"}
    return {"type": "aov", "aovs": "albedo:albedo,normal:sh_normal", "integrator": dict(spec)}


def denoise_guided(image: np.ndarray) -> np.ndarray:
    """Denoise an image rendered with :func:`with_guides` (colour, albedo, normal)."""
    from .denoise import denoise

    return denoise(image[..., 0:3], image[..., 3:6], image[..., 6:9])


@dataclass
class RenderResult:
    """One timed render and its error against the reference."""

    label: str  #: e.g. "pmic" or "path"
    integrator: dict  #: the mi.load_dict dictionary used
    spp: int  #: samples per pixel
    seconds: float  #: wall time of the timed render (after warm-up)
    compile_s: float  #: extra time of the first, cold render (kernel compilation)
    rel_mse: float = math.nan  #: mean((img - ref)² / (ref² + 1e-2))
    denoised: bool = False  #: denoised with OIDN (OptiX on CUDA), time included
    flip: float = math.nan  #: mean LDR FLIP error
    low_frequency: float = math.nan  #: relMSE of both images blurred by σ = 4 px
    rmse: float = math.nan  #: root mean squared error
    luminance_ratio: float = math.nan  #: mean luminance / the reference's
    ciede2000: float = math.nan  #: mean CIEDE2000 after a fixed sRGB tone map
    stats: dict = field(default_factory=dict)  #: scene.integrator().stats, if any
    image: np.ndarray | None = field(default=None, repr=False)

    def row(self) -> dict:
        d = asdict(self)
        d.pop("image")
        d["stats"] = {k: v for k, v in self.stats.items() if isinstance(v, (int, float, str, list))}
        return d


def timed_render(scene, integrator, spp: int, seed: int = 0, denoised: bool = False):
    """Render and evaluate (and denoise an image from :func:`with_guides`); return
    (RGB image as numpy, seconds including the denoiser)."""
    start = time.perf_counter()
    image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(image)
    dr.sync_thread()
    image = np.array(image)
    image = denoise_guided(image) if denoised else image[..., :3]
    seconds = time.perf_counter() - start
    return image, seconds


def score(result: RenderResult, reference: np.ndarray | None) -> RenderResult:
    if reference is not None:
        img = result.image
        result.rel_mse = metrics.rel_mse(img, reference)
        result.rmse = metrics.rmse(img, reference)
        result.luminance_ratio = metrics.luminance_ratio(img, reference)
        result.ciede2000 = metrics.ciede2000(img, reference)
        result.flip = metrics.flip(img, reference)
        result.low_frequency = metrics.low_frequency_rel_mse(img, reference, LOW_FREQUENCY_SIGMA)
    return result


def render_measured(scene, spec: dict, spp: int, reference=None, label=None, seed=0,
                    denoised: bool = False, progress: bool | None = False) -> RenderResult:
    """A 1-spp warm-up render, then the timed render, scored against ``reference``.

    The warm-up uses a separate integrator object, so the timed run rebuilds its
    photon maps and cache (a reused cache would hide their cost).
    ``compile_s`` is the warm-up's time minus what the timed run's stages would take
    at 1 spp: the cost of compiling kernels on a first run. ``progress``: progress
    bars of the timed run's photon and cache stages (None: where a person watches).
    """
    run_spec = with_guides(spec) if denoised else dict(spec)
    # The warm-up is another integrator object, so the timed run still builds its own
    # photon maps and cache; with the same settings it finds every kernel compiled
    # (photon and record counts, which depend on the seed, are baked into some).
    warm_up = mi.load_dict(run_spec)
    if hasattr(warm_up, "build_cache"):
        warm_up.progress = False  # (its bars would only repeat the timed run's)
    _, cold_seconds = timed_render(scene, warm_up, 1, seed + 1, denoised)
    integrator = mi.load_dict(run_spec)
    if hasattr(integrator, "build_cache"):  # pmic's stages
        integrator.progress = progress
    image, seconds = timed_render(scene, integrator, spp, seed, denoised)
    stats = dict(getattr(integrator, "stats", {}) or {})
    render_s = stats.get("time_render", seconds)
    one_spp = seconds - render_s + render_s / spp
    result = RenderResult(label or spec["type"], dict(spec), spp, seconds,
                          max(0.0, cold_seconds - one_spp), denoised=denoised, stats=stats, image=image)
    return score(result, reference)


def path_at_equal_time(scene, seconds: float, reference=None, seed=0, max_spp=1 << 16,
                       denoised: bool = False, max_depth: int = -1) -> RenderResult:
    """Mitsuba's ``path`` (+ the denoiser) with the spp that fits in ``seconds``
    (measured, not guessed), paths as long as pmic's (``max_depth``)."""
    base = {**PATH_INTEGRATOR, "max_depth": max_depth}
    spec = with_guides(base) if denoised else dict(base)
    integrator = mi.load_dict(spec)
    _, cold = timed_render(scene, integrator, 1, seed + 1, denoised)  # compiles the kernel
    _, probe = timed_render(scene, integrator, 4, seed + 2, denoised)
    per_spp = max(probe / 4, 1e-6)
    spp = int(max(1, min(max_spp, seconds / per_spp)))
    image, took = timed_render(scene, integrator, spp, seed, denoised)
    if abs(took / seconds - 1) > 0.1 and spp < max_spp:
        # The probe's fixed overhead skews the rate: correct once from the real run.
        spp = int(max(1, min(max_spp, spp * seconds / took)))
        image, took = timed_render(scene, integrator, spp, seed, denoised)
    result = RenderResult("path", base, spp, took, max(0.0, cold - probe / 4),
                          denoised=denoised, image=image)
    return score(result, reference)


def compare(scene, spec: dict | None = None, spp: int = 32, reference=None, denoised: bool = False,
            progress: bool | None = None, log=None) -> list:
    """pmic (``spec``: its parameters) at ``spp`` against ``path`` at equal wall time,
    and with ``denoised`` both again through OIDN (same guides, denoiser time
    included); each scored against ``reference`` (an H x W x 3 array, or None).
    Returns the :class:`RenderResult` s: pmic, path[, pmic+OIDN, path+OIDN].
    ``log``: a function given a line before each render (e.g. ``print``)."""
    log = log or (lambda line: None)
    spec = {"type": "pmic", **{k: v for k, v in (spec or {}).items() if k != "type"}}
    mi.load_dict(dict(spec))  # checks the parameters before any heavy work
    log("rendering with pmic (a warm-up render compiles the kernels first) ...")
    pmic = render_measured(scene, spec, spp, reference, label="pmic", progress=progress)
    log(f"rendering with path for the same time ({pmic.seconds:.2f} s) ...")
    path = path_at_equal_time(scene, pmic.seconds, reference, max_depth=spec.get("max_depth", -1))
    results = [pmic, path]
    if denoised:
        log("rendering pmic + OIDN, then path + OIDN for the same time ...")
        pmic_dn = render_measured(scene, spec, spp, reference, label="pmic+OIDN", denoised=True)
        path_dn = path_at_equal_time(scene, pmic_dn.seconds, reference, denoised=True,
                                     max_depth=spec.get("max_depth", -1))
        path_dn.label = "path+OIDN"
        results += [pmic_dn, path_dn]
    return results


def write_strip(path, results, reference=None, exposure: float = 1.0) -> None:
    """A PNG of the results' images side by side (and the reference), each titled with
    its label, spp, time and relMSE (matplotlib, sRGB at ``exposure``)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    panels = [(f"{r.label}\n{r.spp} spp, {r.seconds:.2f} s"
               + (f"\nrelMSE {r.rel_mse:.2e}" if math.isfinite(r.rel_mse) else ""), r.image)
              for r in results]
    if reference is not None:
        panels.append(("reference (path)\n\n", reference))
    height, width = panels[0][1].shape[:2]
    scale = 3.0 / max(height, width) * max(1.0, min(height, width) / 160)
    figure, axes = plt.subplots(1, len(panels), figsize=(len(panels) * width * scale + 0.2,
                                                         height * scale + 0.9), squeeze=False)
    for axis, (title, image) in zip(axes[0], panels):
        axis.imshow(metrics.tonemap_srgb(image, exposure), interpolation="nearest")
        axis.set_title(title, fontsize=9)
        axis.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
