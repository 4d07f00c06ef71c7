"""PoseFilter: consistency (NEES), lagged-measurement replay, gating and observability."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.base.geometry import wrap_angle
from robot.base.stats import chi2_quantile as chi2_threshold
from robot.config import FilterConfig
from robot.fusion.ekf import PoseFilter, body_increment
from robot.localization.measurements import PlaneMeasurement

# The paper arena's walls as (id, n_G, d_G), normals facing inward (config/maps/paper_arena.yaml).
WALLS = {
    "wall_south": (np.array([0.0, 1.0, 0.0]), 0.25),
    "wall_east": (np.array([-1.0, 0.0, 0.0]), 1.25),
    "wall_north": (np.array([0.0, -1.0, 0.0]), 1.25),
    "wall_west": (np.array([1.0, 0.0, 0.0]), 0.25),
}
R_PLANE = np.diag([0.003 ** 2, math.radians(0.5) ** 2])
Q_TWIST = np.diag([0.01 ** 2, 0.01 ** 2, 0.02 ** 2])  # std of the interval's mean twist
ODOM_DT = 0.02  # 50 Hz chassis reports
FRAME_DT = 1.0 / 15.0  # camera frames carrying plane fits
LATENCY = 0.09  # s from exposure to the fitted plane reaching the filter


def measure(wall: str, pose, t: float, rng: np.random.Generator, camera: str = "front",
            geometry_of: str = "") -> PlaneMeasurement:
    """What the localizer reports for ``wall`` seen from the true pose (noisy, at capture time t).

    ``geometry_of`` simulates a misidentification: the camera really saw that other wall.
    """
    n, d = WALLS[wall]
    seen_n, seen_d = WALLS[geometry_of or wall]
    x, y, phi = pose
    z_true = np.array([seen_n[0] * x + seen_n[1] * y + seen_d, float(wrap_angle(math.atan2(seen_n[1], seen_n[0]) - phi))])
    z = z_true + rng.multivariate_normal(np.zeros(2), R_PLANE)
    return PlaneMeasurement(plane_id=wall, camera=camera, t_capture=t, n_ground=n, d_ground=d, z=z, R=R_PLANE.copy())


def true_twist(t: float) -> np.ndarray:
    return np.array([0.15 * math.cos(0.3 * t), 0.10 * math.sin(0.2 * t), 0.4 * math.sin(0.25 * t)])


def simulate(seed: int, duration: float, walls=("wall_south", "wall_east"), cfg: FilterConfig = None):
    """A robot driving with noisy odometry; yields a time-ordered event list and the truth.

    The true motion gets exactly the noise the filter's model describes: the odometry's
    mean-twist error per interval plus the floor (white noise and slip per metre / radian).
    """
    cfg = cfg or FilterConfig()
    rng = np.random.default_rng(seed)
    truth = np.array([0.2, 0.9, -0.3])
    truths = [(0.0, truth.copy())]
    odom = []  # (t, twist_measured)
    t = 0.0
    n = int(round(duration / ODOM_DT))
    for k in range(1, n + 1):
        t = k * ODOM_DT
        tw = true_twist(t - 0.5 * ODOM_DT)
        inc, _ = body_increment(tw, ODOM_DT)
        dist, turn = math.hypot(inc[0], inc[1]), abs(inc[2])
        var_pos = cfg.pos_noise_density * ODOM_DT + cfg.slip_per_metre * dist
        var_phi = (cfg.heading_noise_density * ODOM_DT + cfg.heading_slip_per_rad * turn
                   + cfg.heading_slip_per_metre * dist)
        c, s = math.cos(truth[2]), math.sin(truth[2])
        truth = truth + np.array([c * inc[0] - s * inc[1], s * inc[0] + c * inc[1], inc[2]])
        truth += rng.normal(0.0, [math.sqrt(var_pos), math.sqrt(var_pos), math.sqrt(var_phi)])
        truth[2] = float(wrap_angle(truth[2]))
        truths.append((t, truth.copy()))
        odom.append((t, tw + rng.multivariate_normal(np.zeros(3), Q_TWIST)))
    meas = []
    for k in range(1, int(duration / FRAME_DT)):
        tc = k * FRAME_DT + 0.003  # exposures are not aligned with odometry
        # Truth at the capture time: interpolate inside the odometry interval (tiny motion).
        i = int(tc // ODOM_DT)
        a, b = truths[i][1], truths[i + 1][1]
        f = (tc - truths[i][0]) / ODOM_DT
        pose = a + f * np.array([b[0] - a[0], b[1] - a[1], float(wrap_angle(b[2] - a[2]))])
        for w in walls:
            meas.append(measure(w, pose, tc, rng, camera="front" if w == walls[0] else "left"))
    return truths, odom, meas


def start_filter(truth0, seed: int, cfg: FilterConfig = None) -> PoseFilter:
    rng = np.random.default_rng(seed + 10_000)
    P0 = np.diag([0.01 ** 2, 0.01 ** 2, math.radians(1.0) ** 2])
    est = truth0 + rng.multivariate_normal(np.zeros(3), P0)
    f = PoseFilter(cfg)
    f.set_pose(0.0, est[0], est[1], est[2], P0)
    return f


def run_in_order(f: PoseFilter, odom, meas, latency: float = 0.0, checks=(), on_check=None):
    """Feed odometry as it happens and each measurement ``latency`` seconds after its capture."""
    pending = sorted(meas, key=lambda m: m.t_capture)
    results = []
    j = 0
    check_i = 0
    for t, tw in odom:
        while j < len(pending) and pending[j].t_capture + latency <= t:
            results.append(f.update_plane(pending[j]))
            j += 1
        assert f.predict_twist(t, tw[0], tw[1], tw[2], Q_TWIST).accepted
        while check_i < len(checks) and checks[check_i] <= t + 1e-12:
            on_check(checks[check_i])
            check_i += 1
    while j < len(pending):
        results.append(f.update_plane(pending[j]))
        j += 1
    return results


def nees(f: PoseFilter, truth_at_t) -> float:
    _, x, P = f.state()
    e = x - truth_at_t
    e[2] = float(wrap_angle(e[2]))
    return float(e @ np.linalg.solve(P, e))


def test_chi2_threshold_matches_tables():
    assert chi2_threshold(0.997, 2) == pytest.approx(-2.0 * math.log(0.003), rel=1e-9)
    assert chi2_threshold(0.95, 3) == pytest.approx(7.8147, abs=1e-4)
    assert chi2_threshold(0.95, 1) == pytest.approx(3.8415, abs=1e-4)


def test_body_increment_is_exact_arc_and_jacobian_matches_finite_differences():
    # A full circle at constant twist comes back to the start.
    v, w = 0.2, 0.8
    inc, _ = body_increment(np.array([v, 0.0, w]), 2 * math.pi / w)
    assert np.allclose(inc[:2], 0.0, atol=1e-12)
    # Half circle: displaced 2r to the left.
    inc, _ = body_increment(np.array([v, 0.0, w]), math.pi / w)
    assert np.allclose(inc, [0.0, 2 * v / w, math.pi], atol=1e-12)
    for tw in (np.array([0.1, -0.05, 0.7]), np.array([0.1, 0.05, 1e-7]), np.array([0.0, 0.2, 0.0])):
        _, D = body_increment(tw, 0.3)
        num = np.zeros((3, 3))
        for k in range(3):
            h = np.zeros(3)
            h[k] = 1e-6
            num[:, k] = (body_increment(tw + h, 0.3)[0] - body_increment(tw - h, 0.3)[0]) / 2e-6
        assert np.allclose(D, num, atol=1e-7)


def test_nees_is_consistent_over_monte_carlo_runs():
    """Bar-Shalom's consistency check: the average NEES over M runs lies in the chi-square band."""
    runs, duration = 50, 8.0
    checks = [0.5 * k for k in range(1, int(duration / 0.5) + 1)]
    values = np.zeros((runs, len(checks)))
    for r in range(runs):
        truths, odom, meas = simulate(seed=r, duration=duration)
        f = start_filter(truths[0][1], seed=r)
        col = {}

        def on_check(tc, f=f, truths=truths, col=col):
            col[tc] = nees(f, truths[int(round(tc / ODOM_DT))][1])

        run_in_order(f, odom, meas, latency=LATENCY, checks=checks, on_check=on_check)
        values[r] = [col[c] for c in checks]
    lo = chi2_threshold(0.025, 3 * runs) / runs
    hi = chi2_threshold(0.975, 3 * runs) / runs
    per_time = values.mean(axis=0)
    inside = np.mean((per_time >= lo) & (per_time <= hi))
    # Each check time is its own 95 % test; neighbouring times are correlated, so demand most.
    assert inside >= 0.85, f"ANEES per time {np.round(per_time, 2)} vs band [{lo:.2f}, {hi:.2f}]"
    assert lo <= per_time.mean() <= hi


def test_default_floor_never_makes_the_filter_overconfident_with_odometry_only():
    # Odometry only, truth noisier than the twist covariance alone: the floor keeps NEES sane.
    runs = 30
    vals = []
    for r in range(runs):
        truths, odom, _ = simulate(seed=100 + r, duration=5.0, walls=())
        f = start_filter(truths[0][1], seed=100 + r)
        run_in_order(f, odom, [])
        vals.append(nees(f, truths[-1][1]))
    assert np.mean(vals) <= chi2_threshold(0.975, 3 * runs) / runs


def _states_along(f: PoseFilter, times):
    return np.array([np.concatenate([f.predicted(t)[:3], f.predicted(t)[3].ravel()]) for t in times])


def test_delayed_and_shuffled_measurements_give_the_in_order_result():
    truths, odom, meas = simulate(seed=7, duration=1.8, walls=("wall_south", "wall_east", "wall_north"))
    f_in = start_filter(truths[0][1], seed=7)
    run_in_order(f_in, odom, meas, latency=0.0)

    # Each plane arrives 50 to 500 ms after its capture: late, and in a scrambled order.
    f_late = start_filter(truths[0][1], seed=7)
    delays = np.random.default_rng(3).uniform(0.05, 0.5, len(meas))
    arrivals = sorted(zip(np.array([m.t_capture for m in meas]) + delays, range(len(meas))))
    assert any(a[1] > b[1] for a, b in zip(arrivals, arrivals[1:]))  # really out of order
    j = 0
    for t, tw in odom:
        while j < len(arrivals) and arrivals[j][0] <= t:
            res = f_late.update_plane(meas[arrivals[j][1]])
            assert "older than the history" not in res.reason
            j += 1
        f_late.predict_twist(t, tw[0], tw[1], tw[2], Q_TWIST)
    for _, i in arrivals[j:]:
        f_late.update_plane(meas[i])

    t_in, x_in, P_in = f_in.state()
    t_late, x_late, P_late = f_late.state()
    assert t_in == t_late
    assert np.max(np.abs(x_in - x_late)) < 1e-9
    assert np.max(np.abs(P_in - P_late)) < 1e-12
    times = np.linspace(0.5, 1.8, 7)
    assert np.max(np.abs(_states_along(f_in, times) - _states_along(f_late, times))) < 1e-9

    # The planes of each frame handed over together (one replay per frame) give the same.
    f_batch = start_filter(truths[0][1], seed=7)
    frames = {}
    for m in meas:
        frames.setdefault(m.t_capture, []).append(m)
    queue = sorted(frames.items())
    for t, tw in odom:
        while queue and queue[0][0] + 0.1 <= t:
            assert all(r.accepted for r in f_batch.update_planes(queue.pop(0)[1][::-1]))
        f_batch.predict_twist(t, tw[0], tw[1], tw[2], Q_TWIST)
    for _, ms in queue:
        f_batch.update_planes(ms)
    assert np.max(np.abs(f_batch.state()[1] - x_in)) < 1e-9
    assert np.max(np.abs(f_batch.state()[2] - P_in)) < 1e-12
    # And the measurements mattered: without them the estimate is elsewhere.
    f_none = start_filter(truths[0][1], seed=7)
    run_in_order(f_none, odom, [])
    assert np.max(np.abs(f_none.state()[2] - P_in)) > 1e-6


def test_measurement_applied_at_capture_time_not_arrival_time():
    # Robot drives at 0.2 m/s along x; a plane of the east wall captured at t=1.0 s reaches the
    # filter at t=1.5 s. The correction must be the one for the pose at 1.0 s.
    rng = np.random.default_rng(0)
    f = PoseFilter()
    f.set_pose(0.0, 0.0, 0.5, 0.0, np.diag([0.02 ** 2, 0.02 ** 2, 1e-6]))
    for k in range(1, 76):
        f.predict_twist(k * ODOM_DT, 0.2, 0.0, 0.0, np.diag([1e-8, 1e-8, 1e-10]))
    m = measure("wall_east", (0.2 + 0.01, 0.5, 0.0), 1.0, rng)  # truth is 1 cm ahead of odometry
    m.z = m.predict(0.21, 0.5, 0.0)  # noiseless for a sharp check
    assert f.update_plane(m).accepted
    x = f.state()[1]
    # Odometry is near-perfect, so after the fix the estimate at 1.5 s is 0.3 + ~0.01.
    assert x[0] == pytest.approx(0.31, abs=1e-3)


def test_gating_rejects_a_misidentified_wall_and_keeps_the_state():
    rng = np.random.default_rng(1)
    f = PoseFilter()
    pose = (0.2, 0.5, 0.0)
    f.set_pose(0.0, *pose, np.diag([0.01 ** 2, 0.01 ** 2, math.radians(2) ** 2]))
    f.predict_twist(0.02, 0.0, 0.0, 0.0, Q_TWIST)
    before = f.state()
    # The front camera really saw the west wall's geometry but it was labelled east.
    wrong = measure("wall_east", pose, 0.01, rng, geometry_of="wall_west")
    res = f.update_plane(wrong)
    assert not res.accepted
    assert res.mahalanobis2 > f.gate_threshold
    assert "gated out" in res.reason
    after = f.state()
    # (equal up to rounding: the rejected plane still splits the odometry interval at 0.01 s)
    assert np.allclose(before[1], after[1], rtol=0, atol=1e-15)
    assert np.allclose(before[2], after[2], rtol=1e-12, atol=0)
    # A parallel surface 10 cm in front of the right wall (clutter) is also refused ...
    clutter = measure("wall_south", pose, 0.015, rng)
    clutter.z[0] -= 0.10
    assert not f.update_plane(clutter).accepted
    # ... while the right wall passes.
    assert f.update_plane(measure("wall_south", pose, 0.018, rng)).accepted


def test_single_wall_constrains_only_its_normal_direction():
    truths, odom, meas = simulate(seed=3, duration=6.0, walls=("wall_south",))
    f = start_filter(truths[0][1], seed=3)
    sig = []

    def on_check(tc):
        P = f.state()[2]
        sig.append((math.sqrt(P[0, 0]), math.sqrt(P[1, 1]), math.sqrt(P[2, 2])))

    run_in_order(f, odom, meas, latency=LATENCY, checks=[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], on_check=on_check)
    sx = [s[0] for s in sig]
    sy = [s[1] for s in sig]
    sphi = [s[2] for s in sig]
    # Along the wall (x) the uncertainty keeps growing; across it (y) and in heading it stays small.
    assert all(b > a for a, b in zip(sx, sx[1:]))
    assert sx[-1] > 3 * sy[-1]
    assert max(sy) < 0.005
    assert max(sphi) < math.radians(1.0)


def test_measurement_older_than_history_is_rejected():
    rng = np.random.default_rng(2)
    f = PoseFilter(FilterConfig(history=1.0))
    f.set_pose(0.0, 0.5, 0.5, 0.0, np.eye(3) * 1e-4)
    for k in range(1, 151):
        f.predict_twist(k * ODOM_DT, 0.0, 0.0, 0.0, Q_TWIST)
    assert f.history_start > 1.5
    res = f.update_plane(measure("wall_south", (0.5, 0.5, 0.0), 1.2, rng))
    assert not res.accepted and "older than the history" in res.reason
    assert f.update_plane(measure("wall_south", (0.5, 0.5, 0.0), 2.5, rng)).accepted


def test_bad_inputs_are_refused_with_a_reason():
    rng = np.random.default_rng(4)
    f = PoseFilter()
    assert "not set" in f.predict_twist(0.1, 0, 0, 0, Q_TWIST).reason
    with pytest.raises(ValueError):
        f.set_pose(0.0, math.nan, 0.0, 0.0, np.eye(3))
    f.set_pose(0.0, 0.5, 0.5, 0.0, np.eye(3) * 1e-4)
    assert not f.predict_twist(0.1, math.nan, 0, 0, Q_TWIST).accepted
    assert f.predict_twist(0.1, 0, 0, 0, Q_TWIST).accepted
    assert "not after" in f.predict_twist(0.1, 0, 0, 0, Q_TWIST).reason
    m = measure("wall_south", (0.5, 0.5, 0.0), 0.05, rng)
    m.z[1] = math.inf
    assert not f.update_plane(m).accepted
    floor = PlaneMeasurement("floor", "front", 0.05, np.array([0.0, 0.0, 1.0]), 0.0, np.array([0.0, 0.0]), R_PLANE)
    assert "not a wall" in f.update_plane(floor).reason
    assert "ahead" in f.update_plane(measure("wall_south", (0.5, 0.5, 0.0), 50.0, rng)).reason
    assert np.all(np.isfinite(f.state()[1]))


def test_predicted_extrapolates_without_changing_the_filter():
    f = PoseFilter()
    f.set_pose(0.0, 0.0, 0.0, 0.0, np.eye(3) * 1e-6)
    f.predict_twist(0.1, 0.2, 0.0, 0.0, Q_TWIST)
    before = f.state()
    x, y, phi, P = f.predicted(0.2)  # held twist for hold = 0.25 s
    assert x == pytest.approx(0.04, abs=1e-12)
    assert P[0, 0] > before[2][0, 0]
    x, _, _, _ = f.predicted(1.0)  # beyond the hold the robot is assumed still
    assert x == pytest.approx(0.02 + 0.2 * 0.25, abs=1e-12)
    after = f.state()
    assert np.array_equal(before[1], after[1]) and np.array_equal(before[2], after[2])


def test_pose_fix_wraps_heading_and_set_pose_resets():
    f = PoseFilter()
    f.set_pose(0.0, 0.5, 0.5, math.pi - 0.01, np.diag([1e-4, 1e-4, 1e-3]))
    res = f.update_pose(0.0, 0.5, 0.5, -math.pi + 0.01, np.diag([1e-4, 1e-4, 1e-3]))
    assert res.accepted
    phi = f.state()[1][2]
    assert abs(float(wrap_angle(phi - math.pi))) < 1e-9  # halfway the short way, not through 0
    f.set_pose(5.0, 0.1, 0.2, 0.3, np.eye(3) * 1e-2)
    t, x, P = f.state()
    assert t == 5.0 and np.allclose(x, [0.1, 0.2, 0.3]) and np.allclose(P, np.eye(3) * 1e-2)


def test_gyro_replaces_slipping_wheel_yaw_rate():
    # The wheels report 20 % too much rotation (slip); the gyro is right.
    def run(use_gyro: bool):
        f = PoseFilter(FilterConfig(gyro_mode="replace"))
        f.set_pose(0.0, 0.5, 0.5, 0.0, np.eye(3) * 1e-6)
        for k in range(1, 101):
            t = k * ODOM_DT
            if use_gyro:
                for g in range(4):  # 200 Hz gyro, delivered before the odometry sample
                    f.predict_gyro(t - ODOM_DT + (g + 1) * ODOM_DT / 4, 0.5, 1e-4)
            f.predict_twist(t, 0.0, 0.0, 0.6, Q_TWIST)
        return f.state()

    _, x_wheel, P_wheel = run(False)
    _, x_gyro, P_gyro = run(True)
    assert x_wheel[2] == pytest.approx(1.2, abs=1e-9)
    assert x_gyro[2] == pytest.approx(1.0, abs=1e-9)
    assert P_gyro[2, 2] < P_wheel[2, 2]


def test_late_gyro_sample_is_replayed():
    f_a, f_b = PoseFilter(), PoseFilter()
    for f in (f_a, f_b):
        f.set_pose(0.0, 0.0, 0.0, 0.0, np.eye(3) * 1e-6)
    f_a.predict_gyro(0.01, 0.3, 1e-4)
    f_a.predict_twist(0.02, 0.1, 0.0, 0.2, Q_TWIST)
    f_b.predict_twist(0.02, 0.1, 0.0, 0.2, Q_TWIST)
    f_b.predict_gyro(0.01, 0.3, 1e-4)
    assert np.array_equal(f_a.state()[1], f_b.state()[1])
    assert np.array_equal(f_a.state()[2], f_b.state()[2])


def _braking_x(t: float) -> float:
    """True x of a robot at 0.15 m/s until 1.2 s (its commands stopped at 1.0 s, the board's watchdog
    at 1.2 s), then braking to rest by 1.45 s: 48.75 mm after 1.0 s, all of it early in [1, 2]."""
    if t <= 1.2:
        return 0.3 + 0.15 * t
    if t <= 1.45:
        u = t - 1.2
        return 0.48 + 0.15 * u - 0.3 * u * u
    return 0.48 + 0.01875


def _run_through_a_gap(cfg: FilterConfig, seed: int):
    """Odometry every 10 ms, except one 1 s interval [1, 2] bridged by cumulative ticks (its exact
    mean twist arrives at 2 s); two walls at 15 Hz throughout, fused 50 ms after capture, so the
    fixes taken in the gap are in the filter before the sample that spans it. Returns the NEES
    after each odometry input."""
    rng = np.random.default_rng(seed)
    f = PoseFilter(cfg)
    f.set_pose(0.0, 0.3, 0.6, 0.0, np.diag([0.002 ** 2, 0.002 ** 2, math.radians(0.2) ** 2]))
    pending = []
    for k in range(1, 46):
        tc = k / 15.0 + 0.003
        pose = (_braking_x(tc), 0.6, 0.0)
        pending += [(tc + 0.05, measure("wall_south", pose, tc, rng)),
                    (tc + 0.05, measure("wall_east", pose, tc, rng, camera="left"))]
    odom = ([(k * 0.01, 0.15) for k in range(1, 101)] + [(2.0, _braking_x(2.0) - _braking_x(1.0))]
            + [(2.0 + k * 0.01, 0.0) for k in range(1, 101)])
    out, j, prev = [], 0, 0.0
    for t, v in odom:
        while j < len(pending) and pending[j][0] <= t:
            f.update_plane(pending[j][1])
            j += 1
        Q = Q_TWIST * min(1.0, 0.01 / (t - prev))  # ripple averages down over a long interval
        prev = t
        assert f.predict_twist(t, v, 0.0, 0.0, Q).accepted
        out.append(nees(f, np.array([_braking_x(t), 0.6, 0.0])))
    return out


def test_a_long_odometry_interval_is_not_a_constant_velocity_path_through_the_fixes_inside_it():
    """The robot braked early in a 1 s dropout. Placed on a constant-velocity path, the fixes taken
    meanwhile contradict the odometry and the filter ends up overconfident; with the gap's unknown
    timing in the covariance they are accepted where the robot really was, and NEES stays honest."""
    honest = [max(_run_through_a_gap(FilterConfig(), seed)) for seed in range(20)]
    constant = [max(_run_through_a_gap(FilterConfig(max_odom_interval=5.0), seed)) for seed in range(20)]
    limit = chi2_threshold(0.999, 3)
    assert max(honest) < limit, sorted(honest)
    assert sum(n > limit for n in constant) >= 5, sorted(constant)  # the scenario does test something


def test_an_unsplit_long_interval_keeps_its_exact_displacement():
    """No fix inside the gap: the bridged displacement is known exactly and costs nothing extra."""
    a, b = PoseFilter(), PoseFilter(FilterConfig(max_odom_interval=5.0))
    for f in (a, b):
        f.set_pose(0.0, 0.0, 0.0, 0.0, np.eye(3) * 1e-6)
        f.predict_twist(2.0, 0.05, 0.0, 0.1, Q_TWIST * 0.005)
    np.testing.assert_array_equal(a.state()[1], b.state()[1])
    np.testing.assert_array_equal(a.state()[2], b.state()[2])


def test_past_the_newest_odometry_the_held_motion_is_uncertain():
    """A robot whose odometry stopped may have stopped too, or kept going for the hold time: the
    provisional covariance covers half the held displacement along its direction."""
    f = PoseFilter()
    f.set_pose(0.0, 0.0, 0.0, 0.0, np.eye(3) * 1e-8)
    f.predict_twist(0.01, 0.2, 0.0, 0.0, Q_TWIST * 1e-4)
    _, _, _, P = f.predicted(0.01 + FilterConfig().hold)
    held = 0.2 * FilterConfig().hold
    assert math.sqrt(P[0, 0]) >= 0.5 * held and math.sqrt(P[1, 1]) < 0.5 * math.sqrt(P[0, 0])


def test_the_float_motion_the_filter_replays_equals_the_numpy_reference():
    """``_motion`` (plain floats, on the replay path) against ``body_increment`` and D Q D^T."""
    from robot.fusion.ekf import _motion

    cfg = FilterConfig()
    rng = np.random.default_rng(3)
    for _ in range(50):
        tw = rng.normal(0.0, [0.3, 0.3, 1.0])
        dt = float(rng.uniform(1e-3, 0.2))
        A = rng.normal(size=(3, 3))
        Q = A @ A.T * 1e-4
        m = _motion(*tw, Q.tolist(), dt, 1.7, cfg)
        inc, D = body_increment(tw, dt)
        np.testing.assert_allclose(m[:3], inc, rtol=1e-12, atol=1e-15)
        C = 1.7 * D @ Q @ D.T
        np.testing.assert_allclose(m[3:9], [C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2]], rtol=1e-9, atol=1e-18)


def _random_cov(rng, scale):
    A = rng.normal(size=(3, 3)) * scale
    return A @ A.T + np.diag(scale**2 * np.array([0.1, 0.1, 0.1]))


def test_the_filter_steps_are_filterpys_ekf_equations():
    """The predict and update written out in floats are filterpy's ExtendedKalmanFilter (the
    reference: x' = x + u, P' = F P F^T + Q; K = P H^T S^-1, Joseph-form P) on random states,
    motions, walls and pose fixes, to rounding."""
    kalman = pytest.importorskip("filterpy.kalman", reason="filterpy (the reference) is not installed")
    from robot.fusion.ekf import _cov6, _cov33, _Fix, _motion

    rng = np.random.default_rng(7)
    f = PoseFilter()
    for _ in range(200):
        x = np.array([[rng.uniform(-5, 5)], [rng.uniform(-5, 5)], [rng.uniform(-math.pi, math.pi)]])
        P = _random_cov(rng, rng.choice([1e-3, 1e-2, 0.1]))
        # predict: a motion as the history builds it
        vx, vy, wz, dt = rng.normal(0, 0.3), rng.normal(0, 0.3), rng.normal(0, 0.5), rng.uniform(0.005, 0.2)
        mo = _motion(vx, vy, wz, _random_cov(rng, 0.01).tolist(), dt, 1.0, f.config)
        # The history keeps a state as (x, y, phi) and a covariance as its upper triangle.
        xs, Ps = tuple(x.ravel().tolist()), _cov6(P)
        xn, Pn = f._predict(xs, Ps, mo)
        xn, Pn = np.reshape(xn, (3, 1)), _cov33(Pn)
        i0, i1, i2, a, b, e, d, g_, h, var_pos, var_phi = mo
        phi = x.item(2)
        c, s = math.cos(phi), math.sin(phi)
        Rg = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        Qb = np.array([[a, b, e], [b, d, g_], [e, g_, h]])
        Q = Rg @ Qb @ Rg.T + np.diag([var_pos, var_pos, var_phi])
        gx, gy = c * i0 - s * i1, s * i0 + c * i1
        ref = kalman.ExtendedKalmanFilter(dim_x=3, dim_z=2)
        ref.x, ref.P = x.copy(), P.copy()
        ref.F = np.array([[1.0, 0.0, -gy], [0.0, 1.0, gx], [0.0, 0.0, 1.0]])
        ref.Q = Q
        ref.predict(u=0)
        ref.x = x + np.array([[gx], [gy], [i2]])
        ref.x[2, 0] = wrap_angle(ref.x.item(2))
        assert np.allclose(xn, ref.x, rtol=0, atol=1e-12)
        assert np.allclose(Pn, 0.5 * (ref.P + ref.P.T), rtol=1e-9, atol=1e-15)
        # update with a wall: z = (d_R, angle of the normal in R)
        ang = rng.uniform(-math.pi, math.pi)
        n0, n1, dg = math.cos(ang), math.sin(ang), rng.uniform(-5, 5)
        R = _random_cov(rng, 0.01)[:2, :2] + np.eye(2) * 1e-6
        z0 = n0 * x.item(0) + n1 * x.item(1) + dg + rng.normal(0, 0.01)
        z1 = wrap_angle(ang - x.item(2) + rng.normal(0, 0.01))
        model = (n0, n1, dg, ang, z0, z1, R[0, 0], R[0, 1], R[1, 0], R[1, 1], "wall")
        f._gate2 = math.inf
        xu, Pu, res = f._apply_plane(xs, Ps, model)
        xu, Pu = np.reshape(xu, (3, 1)), _cov33(Pu)
        assert res.accepted
        H = np.array([[n0, n1, 0.0], [0.0, 0.0, -1.0]])

        def residual(za, zb):
            r = za - zb
            r[1, 0] = wrap_angle(r.item(1))
            return r

        ref = kalman.ExtendedKalmanFilter(dim_x=3, dim_z=2)
        ref.x, ref.P = x.copy(), P.copy()
        def hx(st, n0=n0, n1=n1, dg=dg, ang=ang):
            return np.array([[n0 * st.item(0) + n1 * st.item(1) + dg], [wrap_angle(ang - st.item(2))]])

        ref.update(np.array([[z0], [z1]]), HJacobian=lambda st, H=H: H, R=R, residual=residual, Hx=hx)
        ref.x[2, 0] = wrap_angle(ref.x.item(2))
        assert np.allclose(xu, ref.x, rtol=0, atol=1e-10)
        assert np.allclose(Pu, 0.5 * (ref.P + ref.P.T), rtol=1e-7, atol=1e-14)
        # an absolute pose fix (H = I)
        target = x.reshape(3) + rng.normal(0, 0.02, 3)
        Rf = _random_cov(rng, 0.02)
        fix = _Fix((0.0, 2, "", "", 0), 0.0, pose=target, pose_cov=Rf, gate=False)
        xf, Pf, res = f._apply_fix(xs, Ps, fix)
        xf, Pf = np.reshape(xf, (3, 1)), _cov33(Pf)
        ref = kalman.ExtendedKalmanFilter(dim_x=3, dim_z=3)
        ref.x, ref.P = x.copy(), P.copy()
        zt = target.reshape(3, 1).copy()
        zt[2, 0] = x.item(2) + wrap_angle(target[2] - x.item(2))
        ref.update(zt, HJacobian=lambda st: np.eye(3), Hx=lambda st: st, R=Rf)
        ref.x[2, 0] = wrap_angle(ref.x.item(2))
        assert res.accepted and np.allclose(xf, ref.x, rtol=0, atol=1e-10)
        assert np.allclose(Pf, 0.5 * (ref.P + ref.P.T), rtol=1e-7, atol=1e-14)


def test_odometry_covariance_as_rows_of_floats_fuses_as_the_array_does():
    """The odometry feed passes Q as a tuple of float rows (no numpy round trip per sample): the
    filter must come out bit for bit where the same Q as an array takes it, refuse the same bad
    ones, and send anything that is not exactly float rows through numpy as before."""
    rng = np.random.default_rng(11)
    a, b = PoseFilter(), PoseFilter()
    for f in (a, b):
        f.set_pose(0.0, 0.5, 0.5, 0.1, np.eye(3) * 1e-4)
    for k in range(1, 120):
        L = rng.normal(0.0, 0.01, (3, 3))
        Q = L @ L.T + np.eye(3) * 1e-6
        twist = rng.normal(0.0, 0.3, 3).tolist()
        rows = tuple(tuple(r) for r in Q.tolist())
        ra = a.predict_twist(k * ODOM_DT, *twist, rows)
        rb = b.predict_twist(k * ODOM_DT, *twist, Q)
        assert ra == rb and ra.accepted
        if k % 10 == 0:
            m = measure("wall_south", (0.5, 0.5, 0.1), k * ODOM_DT - 0.02, rng)
            assert a.update_plane(m) == b.update_plane(m)
    (ta, xa, Pa), (tb, xb, Pb) = a.state(), b.state()
    assert ta == tb and xa.tolist() == xb.tolist() and Pa.tolist() == Pb.tolist()
    assert a.predicted(3.0)[3].tolist() == b.predicted(3.0)[3].tolist()
    t = 200 * ODOM_DT
    bad = ((1e-4, 0.0, 0.0), (0.0, math.nan, 0.0), (0.0, 0.0, 1e-4))
    assert not a.predict_twist(t, 0.0, 0.0, 0.0, bad).accepted
    assert not a.predict_twist(t, 0.0, 0.0, 0.0, ((1e-4, 1.0, 0.0), (0.0, 1e-4, 0.0), (0.0, 0.0, 1e-4))).accepted
    assert not a.predict_twist(t, 0.0, 0.0, 0.0, ((1e-4, 0.0), (0.0, 1e-4))).accepted  # not 3x3
    # ints (or numpy scalars) are not float rows: numpy's path, which accepts them as before
    assert a.predict_twist(t, 0.0, 0.0, 0.0, ((1, 0, 0), (0, 1, 0), (0, 0, 1))).accepted
