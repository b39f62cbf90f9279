"""The adaptive estimator: a camera path's first diffuse vertex reads the records'
bounced light where the records resolved the photons around them and gathered their
light evenly (:func:`pmic_integrator.render.reads.first_read_pays`), else it is traced
as the final gather traces it.
"""
import math

import mitsuba as mi
import numpy as np
import pytest

from pmic_integrator import kinds, metrics
from pmic_integrator.cache import CacheRecords, RecordIndex
from pmic_integrator.settings import Settings


def _render(scene, spp, **params):
    integrator = mi.load_dict({"type": "pmic", **params})
    image = np.array(mi.render(scene, integrator=integrator, spp=spp, seed=0))
    assert np.isfinite(image).all()
    return image


def test_the_adaptive_estimator_shares_the_final_gathers_cache():
    """Its records are the final gather's (they hold direct light and caustics; a first
    read takes their bounced part): one cache file and one key serve both."""
    assert Settings(estimator="adaptive").key() == Settings(estimator="final_gather").key()
    assert Settings(estimator="adaptive").key() != Settings(estimator="first_hit").key()
    props = mi.Properties("pmic")
    props["estimator"] = "guess"
    with pytest.raises(ValueError, match="'estimator'.*adaptive.*'guess'"):
        Settings.parse(props)


@pytest.mark.parametrize("photons, reads_first", [(4_000, False), (200_000, True)])
def test_first_reads_only_where_the_photons_resolve_the_records(photons, reads_first):
    """Where photons are sparse every record sits at its smallest radius (its reach one
    photon lookup radius: they could not resolve the geometry, nor the photons its
    light) and the adaptive estimator must trace every first vertex: its image is the
    final gather's bit for bit (the first reads' lookups draw no random numbers). With
    the default photons, records in the open of the room reach far enough and are
    read (the images differ): the control that this test can fail."""
    scene = mi.load_dict(kinds.two_rooms(size=(24, 16)))
    common = {"global_photons": photons, "gather_rays": 64}
    adaptive = _render(scene, 4, estimator="adaptive", **common)
    final_gather = _render(scene, 4, estimator="final_gather", **common)
    assert (not np.array_equal(adaptive, final_gather)) == reads_first


def test_a_room_lit_through_a_door_ajar_reads_the_records_at_the_first_hit():
    """Seen from the dim room, the light comes through the door: a traced first bounce
    finds the lit room now and then, and that was the final gather's noise (indirect
    AOV: 86 % of its variance). Reading the records there, at 16 spp: relMSE 2.1e-3
    against 6.7e-3 (door_ajar kind, 96×64; here 48×32 and a 4096-spp path reference),
    with the mean within 1.5 % of path's."""
    scene = mi.load_dict(kinds.two_rooms(size=(48, 32)))
    reference = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=4096, seed=1))
    adaptive = _render(scene, 16, estimator="adaptive")[..., :3]
    final_gather = _render(scene, 16, estimator="final_gather")[..., :3]
    assert metrics.luminance_ratio(adaptive, reference) == pytest.approx(1.0, abs=0.015)
    # (Spectral variants: both carry the colour noise of four wavelengths per sample;
    # measured 0.52 there.)
    assert metrics.rel_mse(adaptive, reference) < (0.6 if mi.is_spectral else 0.5) * \
        metrics.rel_mse(final_gather, reference)


def test_a_records_bounce_variance_is_its_rays_relative_variance():
    """Exact on tiny input: a record whose rays' mean luminance is L̄ (irradiance π L̄)
    and mean squared luminance m has relative variance m / L̄² - 1; a record that
    found no light has 0, and a lit one whose rays' moment is not known +inf (never
    taken for smooth)."""
    p = mi.Point3f([0, 1, 2], [0, 0, 0], [0, 0, 0])
    n = mi.Vector3f([0, 0, 0], [0, 0, 0], [1, 1, 1])
    records = CacheRecords.geometry_only(p, n, mi.Float([1, 1, 1]))
    records.irradiance = mi.Color3f([math.pi, 2 * math.pi, 0], [math.pi, 2 * math.pi, 0],
                                    [math.pi, 2 * math.pi, 0])
    records.ray_moment = mi.Float([1.0, 20.0, 3.0])
    index = RecordIndex.build(records, 0.5)
    np.testing.assert_allclose(np.array(index.bounce_variance()), [0.0, 4.0, 0.0], atol=1e-5)
    records.ray_moment = None
    np.testing.assert_array_equal(np.array(RecordIndex.build(records, 0.5).bounce_variance()),
                                  [np.inf, np.inf, 0.0])
