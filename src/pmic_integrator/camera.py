"""Stage 4's frame: the wavefront of camera rays (pixels × samples per pixel) and the
splatting of their radiance into the film, written in Python as Mitsuba's own ``ad``
integrators write it, around :meth:`PMICIntegrator.sample`.

Why not Mitsuba's C++ ``SamplingIntegrator.render``: it builds a different render
kernel for one sample per pixel than for several (it divides the sample index by the
sample count only when that is above one, and coalesces the film's writes only from
four). A first render at 1 spp (a preview, a warm-up) then compiled a kernel that the
next render at 16 spp could not reuse: that one compiled its own, 0.5-0.7 s of a
2.5-3 s render of the material preview, whenever Dr.Jit's kernel cache on disk did not
hold it yet (a new scene, a new machine). Here the sample count enters the kernel as
an opaque value: one kernel serves every count.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Largest wavefront (camera samples in one kernel launch): Mitsuba's sample indices
#: are 32-bit. More samples are rendered in passes of at most this many.
MAX_WAVEFRONT = (1 << 32) - 1


def film_extent(film: mi.Film) -> mi.ScalarVector2u:
    """Pixels the wavefront covers: the crop, plus the filter's border if sampled."""
    size = mi.ScalarVector2u(film.crop_size())
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    return size


def pass_counts(film: mi.Film, spp: int, max_wavefront: int = MAX_WAVEFRONT) -> list[int]:
    """Samples per pixel of each pass: all in one unless the wavefront would exceed
    ``max_wavefront`` (at most ``MAX_WAVEFRONT``) samples."""
    extent = film_extent(film)
    pixels = int(extent[0]) * int(extent[1])
    per_pass = max(1, min(spp, min(max_wavefront, MAX_WAVEFRONT) // max(pixels, 1)))
    counts = [per_pass] * (spp // per_pass)
    if spp % per_pass:
        counts.append(spp % per_pass)
    return counts


def seeded_sampler(sensor: mi.Sensor, seed: int, spp: int) -> mi.Sampler:
    """A copy of the sensor's sampler, set to ``spp`` per pixel for one wavefront and
    seeded with ``seed``.

    Samplers round the count to one they can stratify (``stratified`` and
    ``multijitter`` a square, ``ldsampler`` a power of two, ``orthogonal`` a prime's
    square), as in Mitsuba's own render: the wavefront takes their count (asked for
    10, the film gets 9 or 16 samples per pixel, each weighed as one)."""
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    spp = sampler.sample_count()
    sampler.set_samples_per_wavefront(spp)
    extent = film_extent(sensor.film())
    sampler.seed(seed, int(extent[0]) * int(extent[1]) * spp)
    return sampler


def camera_rays(sensor: mi.Sensor, sampler: mi.Sampler):
    """One ray per camera sample of the wavefront, sample ``i`` in pixel ``i // spp``.

    Returns ``(ray, weight, position)``: the ray differential (its differentials
    scaled for the sample count), the sensor's weight, and the film position to
    splat to (the pixel's corner with a box filter, else the sampled point)."""
    film = sensor.film()
    extent = film_extent(film)
    spp = sampler.sample_count()
    index = dr.arange(mi.UInt32, int(extent[0]) * int(extent[1]) * spp)
    # Opaque: the same kernel for every sample count (see the module's docstring).
    index //= dr.opaque(mi.UInt32, spp)
    pixel = mi.Vector2i()
    pixel.y = mi.Int32(index // int(extent[0]))
    pixel.x = mi.Int32(index) - pixel.y * int(extent[0])
    if film.sample_border():
        pixel -= mi.Vector2i(film.rfilter().border_size())
    pixel += mi.Vector2i(film.crop_offset())
    position = mi.Vector2f(pixel) + sampler.next_2d()

    scale = dr.rcp(mi.ScalarVector2f(film.crop_size()))
    offset = -mi.ScalarVector2f(film.crop_offset()) * scale
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    time = mi.Float(sensor.shutter_open())
    if sensor.shutter_open_time() > 0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    wavelength_sample = sampler.next_1d() if mi.is_spectral else mi.Float(0.5)
    ray, weight = sensor.sample_ray_differential(time, wavelength_sample,
                                                 dr.fma(position, scale, offset), aperture)
    ray.scale_differential(dr.rsqrt(dr.opaque(mi.Float, spp)))
    splat_at = mi.Vector2f(pixel) if film.rfilter().is_box_filter() else position
    return ray, weight, splat_at


def splat(film: mi.Film, block: mi.ImageBlock, position: mi.Vector2f, radiance: mi.Spectrum,
          valid: mi.Bool, aovs: list, wavelengths):
    """Add one camera sample per lane to ``block``: its colour, alpha (``valid``), a
    weight of one and the integrator's AOVs, in the film's channel layout."""
    alpha = dr.select(valid, mi.Float(1.0), mi.Float(0.0))
    if mi.has_flag(film.flags(), mi.FilmFlags.Special):  # a film with its own layout
        block.put(position, film.prepare_sample(radiance, wavelengths, block.channel_count(),
                                                weight=mi.Float(1.0), alpha=alpha))
        return
    if mi.is_polarized:
        radiance = mi.unpolarized_spectrum(radiance)
    if mi.is_spectral:
        rgb = mi.spectrum_to_srgb(radiance, wavelengths)
    elif mi.is_monochromatic:
        rgb = mi.Color3f(radiance.x)
    else:
        rgb = radiance
    front = [rgb.x, rgb.y, rgb.z] + ([alpha] if mi.has_flag(film.flags(), mi.FilmFlags.Alpha) else [])
    block.put(position, front + [mi.Float(1.0)] + list(aovs))
