"""The small Dr.Jit helpers of ``pmic_integrator._jit``, on tiny inputs."""
import drjit as dr
import mitsuba as mi
import numpy as np

from pmic_integrator._jit import only_where, segment_blocked


def test_only_where_computes_on_the_masked_lanes_and_zeros_elsewhere():
    x = dr.arange(mi.Float, 8)
    mask = (dr.arange(mi.UInt32, 8) % 3) == 0
    value, flag = only_where(mask, lambda: (x * 2.0 + 1.0, x > 2.0),
                             lambda: (dr.zeros(mi.Float, 8), dr.zeros(mi.Bool, 8)))
    assert np.array(value).tolist() == [1.0, 0.0, 0.0, 7.0, 0.0, 0.0, 13.0, 0.0]
    assert np.array(flag).tolist() == [False, False, False, True, False, False, True, False]


def test_only_where_advances_the_sampler_on_the_masked_lanes_only():
    """The random streams of the other lanes are left as they were: their next draw
    is the one a sampler that never entered the conditional gives."""
    def fresh():
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(7, 8)
        return sampler
    mask = dr.arange(mi.UInt32, 8) < 3
    sampler, untouched = fresh(), fresh()
    drawn = only_where(mask, lambda s: s.next_1d(), lambda s: dr.zeros(mi.Float, 8), sampler)
    first = np.array(untouched.next_1d())
    second = np.array(untouched.next_1d())
    assert np.array(drawn).tolist() == [*first[:3].tolist(), 0.0, 0.0, 0.0, 0.0, 0.0]
    after = np.array(sampler.next_1d())
    assert after[:3].tolist() == second[:3].tolist()
    assert after[3:].tolist() == first[3:].tolist()


def test_segment_blocked_past_its_target_counts_a_target_on_a_wall_as_behind_it():
    """A target on a wall's plane (a photon at the wall's foot, lifted along the floor's
    normal) is behind the wall with ``past``; stopped just short of it, the ray passed
    (the light of the closed box on a floor, tests/test_bias.py). Targets clear of the
    wall are unchanged."""
    wall = mi.load_dict({"type": "scene", "wall": {"type": "rectangle",
                         "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], 90)}})  # the x = 0 plane
    origin = mi.Point3f([-0.1] * 4, [0.01] * 4, [0.0] * 4)
    target = mi.Point3f([0.0, 1e-7, -1e-7, -0.05], [0.01] * 4, [0.0] * 4)
    short = np.array(segment_blocked(wall, origin, target, True))
    past = np.array(segment_blocked(wall, origin, target, True, past=0.005))
    assert past.tolist() == [True, True, True, False]
    assert not short[0] and not short[2] and not short[3]  # (the leak)
