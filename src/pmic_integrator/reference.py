"""Path-traced references of any scene, made on demand and kept.

A comparison needs the noise-free image; :func:`render_reference` approximates it with
Mitsuba's ``path`` at many samples per pixel, rendered in passes with different seeds:
memory stays that of one pass, progress shows per pass, and the spread between passes
estimates the noise left in the reference itself (its expected relMSE against the
truth), the floor under every error measured against it.

:func:`cached_reference` keeps references in a folder (default
``~/.cache/pmic/references``, or ``$PMIC_CACHE_DIR/references``) under a key of what the
image depends on: the scene's shapes, materials and lights
(:mod:`pmic_integrator.fingerprint`), the sensor and its film, and the path tracer's
settings; a reference with at least the asked spp is reused.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Seed of the first pass: far from 0, mi.render's default, so that a test render with
#: the same seed and spp does not reuse a pass's random numbers.
FIRST_SEED = 1_000_000
#: Passes a reference is split into (its noise is estimated from their spread).
PASSES = 8
#: eps of the project's relMSE (metrics.rel_mse).
REL_MSE_EPS = 1e-2


@dataclass
class Reference:
    """A path-traced reference image and how it was made."""

    image: np.ndarray  #: H x W x 3, linear RGB
    spp: int  #: samples per pixel in all
    seconds: float  #: wall time of its passes
    noise: float  #: its own expected relMSE against the noise-free image
    path: str = ""  #: where it is kept ("" if not)

    def describe(self) -> str:
        return (f"path reference, {self.spp} spp in {self.seconds:.1f} s, its own noise relMSE "
                f"{self.noise:.1e}" + (f" ({self.path})" if self.path else ""))


def noise_of_passes(passes) -> float:
    """Expected relMSE of the mean of ``passes`` (equal-spp images) against the truth:
    the variance of a pass over their count, relative as in ``metrics.rel_mse``."""
    stack = np.stack([np.asarray(p, np.float64) for p in passes])
    if len(stack) < 2:
        return math.nan
    mean = stack.mean(0)
    variance_of_mean = stack.var(0, ddof=1) / len(stack)
    return float(np.mean(variance_of_mean / (mean ** 2 + REL_MSE_EPS)))


def _check_budget(spp, seconds) -> None:
    if spp is None and seconds is None:
        raise ValueError("reference: give 'spp' (samples per pixel) or 'seconds' (a time budget)")
    if spp is not None:
        from .scenes import check_positive_int

        check_positive_int(spp, "reference: 'spp'")
    if seconds is not None and not (isinstance(seconds, (int, float)) and seconds > 0):
        raise ValueError(f"reference: 'seconds' must be a positive number, got {seconds!r}")


def render_reference(scene, spp: int | None = None, seconds: float | None = None, sensor: int = 0,
                     integrator: dict | None = None, passes: int = PASSES,
                     progress: bool | None = None) -> Reference:
    """Render ``scene`` with ``path`` (``integrator``: its parameters, default
    unbounded) to ``spp`` samples per pixel, or for about ``seconds`` (the spp then
    chosen from a timed first pass), in ``passes`` passes."""
    import drjit as dr
    import mitsuba as mi
    from tqdm.auto import tqdm

    from .compare import PATH_INTEGRATOR
    from .pipeline import interactive

    _check_budget(spp, seconds)
    path = mi.load_dict({**PATH_INTEGRATOR, **(integrator or {}), "type": "path"})
    images, start = [], time.perf_counter()
    if spp is None:  # a timed probe pass, kept as the first pass
        probe_spp = 16
        _render(mi, dr, scene, path, sensor, 1, FIRST_SEED - 1)  # compiles: not in the rate
        probe_start = time.perf_counter()
        images.append(_render(mi, dr, scene, path, sensor, probe_spp, FIRST_SEED))
        per_spp = (time.perf_counter() - probe_start) / probe_spp
        spp = max(passes, int(seconds / per_spp) // passes * passes)
        pass_spp = max(1, (spp - probe_spp) // max(passes - 1, 1))
        counts = [probe_spp] + [pass_spp] * (passes - 1)
    else:
        pass_spp = max(1, int(spp) // passes)
        counts = [pass_spp] * min(passes, int(spp))
    show = interactive() if progress is None else progress
    with tqdm(total=sum(counts), initial=sum(counts[:len(images)]), unit="spp", desc="path reference",
              disable=not show) as bar:
        for i in range(len(images), len(counts)):
            images.append(_render(mi, dr, scene, path, sensor, counts[i], FIRST_SEED + i))
            bar.update(counts[i])
    weights = np.array(counts, np.float64) / sum(counts)
    image = sum(w * im for w, im in zip(weights, images)).astype(np.float32)
    equal = [im for im, c in zip(images, counts) if c == counts[-1]]
    noise = noise_of_passes(equal) * len(equal) * counts[-1] / sum(counts)
    return Reference(image, int(sum(counts)), time.perf_counter() - start, noise)


def _render(mi, dr, scene, integrator, sensor, spp, seed) -> np.ndarray:
    image = mi.render(scene, integrator=integrator, sensor=sensor, spp=int(spp), seed=int(seed))
    dr.eval(image)
    return np.array(image, dtype=np.float32)[..., :3]


def cache_folder() -> Path:
    base = os.environ.get("PMIC_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "pmic")
    return Path(base) / "references"


def reference_key(scene, sensor: int = 0, integrator: dict | None = None) -> str:
    """A digest of what a reference image depends on: the scene's shapes, materials
    and lights, the sensor (placement, optics, film, filter) and the path tracer's
    parameters."""
    import mitsuba as mi

    from .fingerprint import scene_fingerprint

    digest = hashlib.blake2b(digest_size=16)
    digest.update(scene_fingerprint(scene).digest.encode())
    params = mi.traverse(scene.sensors()[sensor])
    for key in sorted(params.keys()):
        digest.update(key.encode() + repr(np.array(params[key]).tolist()).encode())
    film = scene.sensors()[sensor].film()
    digest.update(repr((film.class_name(), list(film.size()), film.rfilter().class_name(),
                        film.rfilter().radius())).encode())
    digest.update(json.dumps(integrator or {}, sort_keys=True).encode())
    if mi.is_spectral:  # (another image than the RGB variants' of the same scene)
        digest.update(b"spectral")
    return digest.hexdigest()


def cached_reference(scene, spp: int | None = None, seconds: float | None = None, sensor: int = 0,
                     integrator: dict | None = None, folder=None,
                     progress: bool | None = None) -> Reference:
    """A kept reference of at least ``spp`` (or of any spp, with ``seconds``) if there
    is one, else :func:`render_reference` and keep it (EXR, how it was made in its
    header)."""
    from .scenes import read_exr, read_exr_metadata, write_exr

    _check_budget(spp, seconds)
    folder = Path(folder) if folder is not None else cache_folder()
    path = folder / f"{reference_key(scene, sensor, integrator)}.exr"
    if path.is_file():
        meta = read_exr_metadata(path)
        kept_spp = int(meta.get("pmic_spp", 0))
        if spp is None or kept_spp >= spp:
            return Reference(read_exr(path), kept_spp, float(meta.get("pmic_seconds", "nan")),
                             float(meta.get("pmic_noise", "nan")), str(path))
    reference = render_reference(scene, spp, seconds, sensor, integrator, progress=progress)
    write_exr(path, reference.image, {"pmic_spp": reference.spp, "pmic_seconds": reference.seconds,
                                      "pmic_noise": reference.noise, "pmic_integrator": "path"})
    reference.path = str(path)
    return reference
