"""Frame conventions and the plane transform identities (docs/architecture.md, 'Frames and units')."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.base.geometry import (
    R_BODY_OPTICAL,
    invert_transform,
    mount_to_T_robot_camera,
    plane_axes,
    pose_to_T_ground_robot,
    rpy_to_matrix,
    transform_plane,
    transform_points,
    wrap_angle,
)
from robot.config import load_robot_config
from robot.maps.plane_map import load_plane_map


def random_transform(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
    return T


def test_plane_transform_keeps_points_on_the_plane():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T_a_b = random_transform(rng)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        pi_a = np.array([*n, rng.normal()])
        # Points on the plane in frame a, expressed in frame b, lie on pi_b = T_a_b^T pi_a.
        basis = np.linalg.svd(n[None])[2][1:]
        p_a = -pi_a[3] * n + rng.normal(size=(10, 2)) @ basis
        p_b = transform_points(invert_transform(T_a_b), p_a)
        pi_b = transform_plane(T_a_b, pi_a)
        assert np.allclose(p_b @ pi_b[:3] + pi_b[3], 0, atol=1e-12)
        assert np.linalg.norm(pi_b[:3]) == pytest.approx(1.0)
        # Composition: going a -> b -> a returns the plane.
        assert np.allclose(transform_plane(invert_transform(T_a_b), pi_b), pi_a)


def test_plane_seen_by_camera_matches_design_formula():
    robot = load_robot_config("config/robot.yaml")
    cam = robot.camera("front")
    T_GR = pose_to_T_ground_robot(0.5, 0.5, math.pi)
    pi_G = np.array([1.0, 0.0, 0.0, 0.25])  # wall x = -0.25 facing +x
    pi_C = transform_plane(T_GR @ cam.T_robot_camera, pi_G)
    # Front camera looks along -x of G from x = 0.4: the wall is 0.65 m straight ahead on the optical axis.
    assert np.allclose(pi_C[:3], [0, 0, -1], atol=1e-12)
    assert pi_C[3] == pytest.approx(0.65)


def test_optical_frame_and_urdf_pitch():
    # Optical z is body x (forward), optical x is body -y (right), optical y is body -z (down).
    assert np.allclose(R_BODY_OPTICAL @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(R_BODY_OPTICAL @ [1, 0, 0], [0, -1, 0])
    assert np.allclose(R_BODY_OPTICAL @ [0, 1, 0], [0, 0, -1])
    # Positive pitch tips the nose down (URDF).
    assert (rpy_to_matrix(0, math.radians(10), 0) @ [1, 0, 0])[2] < 0
    # The left camera (yaw 90 deg) looks along robot +y.
    T = mount_to_T_robot_camera((0, 0.1, 0.12), (0, 0, math.pi / 2))
    assert np.allclose(T[:3, :3] @ [0, 0, 1], [0, 1, 0], atol=1e-12)


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 401)
    w = wrap_angle(a)
    assert np.all(w >= -math.pi) and np.all(w < math.pi)
    assert np.allclose(np.cos(w), np.cos(a)) and np.allclose(np.sin(w), np.sin(a))


def test_plane_axes_of_a_wall_are_horizontal_and_up():
    a, b = plane_axes(np.array([-1.0, 0.0, 0.0]))  # a wall seen from -x
    assert a == pytest.approx([0.0, -1.0, 0.0]) and b == pytest.approx([0.0, 0.0, 1.0])
    rng = np.random.default_rng(5)
    for n in [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])] + [v / np.linalg.norm(v) for v in rng.normal(size=(50, 3))]:
        a, b = plane_axes(n)
        assert np.allclose([a @ a, b @ b, a @ b, a @ n, b @ n], [1, 1, 0, 0, 0], atol=1e-12)
        assert np.allclose(np.cross(a, b), n, atol=1e-12)


def test_plane_axes_keep_the_maps_winding():
    # Map polygons are counter-clockwise seen from their normal: positive area in (a, b).
    for name in ("paper_arena.yaml", "fzk_haus_ground.yaml"):
        for plane in load_plane_map(f"config/maps/{name}").planes:
            a, b = plane_axes(plane.normal)
            areas = []
            for poly in plane.polygons:
                x, y = poly @ a, poly @ b
                areas.append(0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
            assert min(areas) > 0 and sum(areas) == pytest.approx(plane.area, rel=1e-9)


def test_se2_jacobians_match_finite_differences():
    from robot.base.geometry import compose_se2, compose_se2_jacobians, invert_se2, invert_se2_jacobian

    rng = np.random.default_rng(3)
    h = 1e-6
    for _ in range(20):
        a = tuple(rng.uniform(-3.0, 3.0, 3))
        b = tuple(rng.uniform(-3.0, 3.0, 3))
        Ja, Jb = compose_se2_jacobians(a, b)
        Ji = invert_se2_jacobian(a)
        for k in range(3):
            d = np.zeros(3)
            d[k] = h
            num_a = (np.subtract(compose_se2(tuple(a + d), b), compose_se2(tuple(a - d), b))) / (2 * h)
            num_b = (np.subtract(compose_se2(a, tuple(b + d)), compose_se2(a, tuple(b - d)))) / (2 * h)
            num_i = (np.subtract(invert_se2(tuple(a + d)), invert_se2(tuple(a - d)))) / (2 * h)
            for num in (num_a, num_b, num_i):
                num[2] = (num[2] + np.pi / h) % (2 * np.pi / h) - np.pi / h  # a wrap inside the step
            np.testing.assert_allclose(Ja[:, k], num_a, atol=1e-6)
            np.testing.assert_allclose(Jb[:, k], num_b, atol=1e-6)
            np.testing.assert_allclose(Ji[:, k], num_i, atol=1e-6)


def test_a_relocalization_confirmed_from_a_later_view_carries_the_turns_odometry_error():
    """Monte Carlo: the first view's pose is view k's fix composed with the inverse of the turn's
    odometry; both are uncertain, and the reported covariance must cover both."""
    from robot.base.geometry import compose_se2, invert_se2
    from robot.localization.relocalize import VIEW_PHI_STD, VIEW_POS_STD, view_covariance

    rng = np.random.default_rng(5)
    pose_k, rel = (4.0, 2.0, 1.2), (0.01, -0.02, np.pi / 2)
    cov_k = np.diag([0.003**2, 0.002**2, np.radians(0.2) ** 2])
    cov = view_covariance(pose_k, cov_k, rel)
    truth = compose_se2(pose_k, invert_se2(rel))
    errs = []
    for _ in range(20000):
        pk = tuple(np.add(pose_k, rng.multivariate_normal(np.zeros(3), cov_k)))
        r = tuple(np.add(rel, rng.normal(0.0, [VIEW_POS_STD, VIEW_POS_STD, VIEW_PHI_STD])))
        e = np.subtract(compose_se2(pk, invert_se2(r)), truth)
        e[2] = (e[2] + np.pi) % (2 * np.pi) - np.pi
        errs.append(e)
    errs = np.array(errs)
    nees = np.einsum("ni,ij,nj->n", errs, np.linalg.inv(cov), errs)
    assert 2.8 < nees.mean() < 3.2  # honest (the fix's own covariance alone gives hundreds)
    assert np.sqrt(cov[0, 0]) > 0.015  # the turn's odometry dominates a 3 mm fix
    np.testing.assert_allclose(view_covariance(pose_k, cov_k, (0.0, 0.0, 0.0)), cov_k)  # view 0: as it was
