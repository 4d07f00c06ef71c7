"""Mecanum kinematics: the documented sign conventions, exact inverses, covariance, SE(2) integration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.base.geometry import integrate_twist
from robot.config import ChassisConfig
from robot.control.kinematics import MecanumKinematics, limit_floats, make_kinematics

CFG = ChassisConfig()  # r = 0.03, lx = 0.075, ly = 0.085
K = make_kinematics(CFG)


def test_pure_forward_turns_all_wheels_forward_equally():
    w = K.inverse(0.3, 0.0, 0.0)
    np.testing.assert_allclose(w, [10.0, 10.0, 10.0, 10.0])  # 0.3 m/s / 0.03 m


def test_pure_left_turns_fl_rr_backwards_fr_rl_forwards():
    """The bench check in the module docstring: what an X-roller robot does to move left."""
    w = K.inverse(0.0, 0.3, 0.0)
    np.testing.assert_allclose(w, [-10.0, 10.0, 10.0, -10.0])


def test_counter_clockwise_turn_spins_left_wheels_back_right_wheels_forward():
    w = K.inverse(0.0, 0.0, 1.0)
    L = CFG.half_wheelbase + CFG.half_track
    np.testing.assert_allclose(w, np.array([-L, L, -L, L]) / CFG.wheel_radius)


def test_wheel_rim_speed_matches_rigid_body_velocity_along_the_roller_axis():
    """Derivation check, independent of the formula: the contact roller's axis is the direction in
    which the wheel cannot slip, so rim speed along it equals the wheel-centre velocity along it."""
    rng = np.random.default_rng(0)
    lx, ly, r = CFG.half_wheelbase, CFG.half_track, CFG.wheel_radius
    positions = [(lx, ly), (lx, -ly), (-lx, ly), (-lx, -ly)]
    axes = [(1, -1), (1, 1), (1, 1), (1, -1)]  # FL, FR, RL, RR floor-roller axes, as documented
    for _ in range(20):
        vx, vy, wz = rng.normal(size=3)
        w = K.inverse(vx, vy, wz)
        for (px, py), (ax, ay), wi in zip(positions, axes, w):
            a = np.array([ax, ay]) / math.sqrt(2)
            v_centre = np.array([vx - wz * py, vy + wz * px])
            rim = np.array([wi * r, 0.0])  # the wheel drives along x
            assert v_centre @ a == pytest.approx(rim @ a, abs=1e-12)


def test_forward_inverts_inverse_exactly():
    rng = np.random.default_rng(1)
    twists = rng.normal(size=(100, 3))
    for t in twists:
        np.testing.assert_allclose(K.forward(K.inverse(*t)), t, atol=1e-12)
    # vectorised over a batch of wheel-speed rows
    wheels = np.array([K.inverse(*t) for t in twists])
    np.testing.assert_allclose(K.forward(wheels), twists, atol=1e-12)


def test_forward_is_least_squares_and_slip_residual_measures_the_rest():
    w_rigid = K.inverse(0.2, -0.1, 0.5)
    disturbance = 0.7 * K.n_slip  # the one wheel pattern no rigid motion produces
    np.testing.assert_allclose(K.forward(w_rigid + disturbance), K.forward(w_rigid), atol=1e-12)
    assert K.slip_residual(w_rigid) == pytest.approx(0.0, abs=1e-12)
    assert K.slip_residual(w_rigid + disturbance) == pytest.approx(0.7)
    lsq, *_ = np.linalg.lstsq(K.J, w_rigid + np.array([0.3, 0.0, -0.1, 0.2]), rcond=None)
    np.testing.assert_allclose(K.forward(w_rigid + np.array([0.3, 0.0, -0.1, 0.2])), lsq, atol=1e-12)


def test_forward_covariance_equal_noise_closed_form():
    s2 = 0.04
    r, L = CFG.wheel_radius, CFG.half_wheelbase + CFG.half_track
    cov = K.forward_covariance(s2)
    np.testing.assert_allclose(cov, np.diag([r * r * s2 / 4, r * r * s2 / 4, r * r * s2 / (4 * L * L)]), atol=1e-15)


def test_forward_covariance_matches_monte_carlo_for_unequal_noise():
    var = np.array([0.01, 0.09, 0.04, 0.25])
    rng = np.random.default_rng(2)
    samples = rng.normal(size=(200_000, 4)) * np.sqrt(var)
    emp = np.cov(K.forward(samples).T)
    np.testing.assert_allclose(K.forward_covariance(var), emp, rtol=0.03, atol=1e-9)
    np.testing.assert_allclose(K.forward_covariance(np.diag(var)), K.forward_covariance(var))


def test_forward_covariance_rejects_bad_shapes():
    with pytest.raises(ValueError, match="shape"):
        K.forward_covariance([1.0, 2.0])


def test_limit_scales_all_wheels_and_keeps_the_direction():
    w = K.inverse(0.9, 0.4, 1.0)  # beyond 20 rad/s on some wheel
    limited, scale = K.limit(w, 20.0)
    assert scale < 1.0 and np.max(np.abs(limited)) == pytest.approx(20.0)
    t0, t1 = K.forward(w), K.forward(limited)
    np.testing.assert_allclose(t1 / np.linalg.norm(t1), t0 / np.linalg.norm(t0), atol=1e-12)
    same, s = K.limit([1.0, -2.0, 3.0, 0.0], 20.0)
    assert s == 1.0 and list(same) == [1.0, -2.0, 3.0, 0.0]


def _limit_numpy(wheels, max_speed):
    """The array formula ``limit`` had before it went through ``limit_floats``: the reference."""
    w = np.asarray(wheels, dtype=float)
    peak = float(np.max(np.abs(w))) if w.size else 0.0
    if peak <= max_speed or peak == 0.0:
        return w.copy(), 1.0
    scale = max_speed / peak
    return w * scale, scale


def test_limit_floats_and_limit_give_the_array_formula_bit_for_bit():
    """One rule for the array API and the control tick: the same scale and speeds to the bit,
    scaled or not, zero, and non-finite speeds (NaN wins the peak wherever it is, as in numpy)."""
    rng = np.random.default_rng(7)
    cases = [K.inverse(*rng.uniform(-1.5, 1.5, 3)) for _ in range(300)]
    cases += [np.zeros(4), np.array([-0.0, 0.0, 0.0, -0.0]), np.array([20.0, -20.0, 0.0, 1.0]),
              np.array([math.nan, 1.0, 50.0, 2.0]), np.array([1.0, 50.0, 2.0, math.nan]),
              np.array([math.inf, 1.0, -3.0, 0.0]), np.array([1.0, -math.inf, 30.0, 0.0])]
    for w in cases:
        ref, ref_scale = _limit_numpy(w, 20.0)
        floats, scale = limit_floats(w.tolist(), 20.0)
        arr, arr_scale = K.limit(w, 20.0)
        assert np.array_equal(np.array(floats), ref, equal_nan=True) and np.array_equal(arr, ref, equal_nan=True)
        assert np.array_equal(np.signbit(np.array(floats)), np.signbit(ref))
        assert (scale == ref_scale and arr_scale == ref_scale) or (math.isnan(ref_scale) and math.isnan(scale)
                                                                   and math.isnan(arr_scale))
    assert any(_limit_numpy(w, 20.0)[1] < 1.0 for w in cases[:300])  # the random cases did scale some
    assert limit_floats([], 1.0) == ((), 1.0) and K.limit(np.zeros(0), 1.0)[0].shape == (0,)


def test_bad_geometry_is_rejected():
    with pytest.raises(ValueError, match="geometry"):
        MecanumKinematics(0.0, 0.1, 0.1)


def test_integrate_straight_and_sideways_in_a_rotated_frame():
    x, y, phi = integrate_twist(1.0, 2.0, math.pi / 2, 0.5, 0.0, 0.0, 2.0)
    assert (x, y, phi) == pytest.approx((1.0, 3.0, math.pi / 2))
    x, y, phi = integrate_twist(0.0, 0.0, math.pi / 2, 0.0, 0.5, 0.0, 2.0)  # robot's left is -x
    assert (x, y) == pytest.approx((-1.0, 0.0))


def test_integrate_arc_is_exact_in_one_step():
    """Quarter circle of radius 1 in a single step lands exactly on the circle (no chord error)."""
    x, y, phi = integrate_twist(0.0, 0.0, 0.0, math.pi / 2, 0.0, math.pi / 2, 1.0)
    assert (x, y, phi) == pytest.approx((1.0, 1.0, math.pi / 2), abs=1e-12)


def test_integrate_many_small_steps_equals_one_big_step():
    big = integrate_twist(0.3, -0.2, 0.4, 0.2, 0.1, 0.7, 3.0)
    p = (0.3, -0.2, 0.4)
    for _ in range(3000):
        p = integrate_twist(*p, 0.2, 0.1, 0.7, 0.001)
    assert p == pytest.approx(big, abs=1e-9)


def test_integrate_tiny_rotation_uses_the_series_without_loss():
    a = integrate_twist(0.0, 0.0, 0.0, 1.0, 0.5, 1e-12, 1.0)
    assert a == pytest.approx((1.0, 0.5, 1e-12), abs=1e-12)
