"""Rigid transforms, planes, angles and SE(2) motion. Pure numpy, no I/O.

Conventions: ``T_a_b`` maps points in frame b to frame a (p_a = T_a_b p_b).
A plane is the homogeneous 4-vector (n, d) with n . p + d = 0 and |n| = 1, and
under p_a = T_a_b p_b it transforms as pi_b = T_a_b^T pi_a.
"""

from __future__ import annotations

import math
from typing import Sequence, Tuple

import numpy as np

# Columns are the optical frame's axes (x right, y down, z forward) written in the
# camera body frame (x forward, y left, z up).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


_TWO_PI = 2.0 * math.pi


def wrap_angle(a):
    """Wrap an angle (or array of angles) to [-pi, pi): the one convention of the whole robot.

    A Python float stays a float on a fast path (no numpy dispatch): this runs at the control
    and odometry rates.
    """
    if isinstance(a, (float, int)):
        return (a + math.pi) % _TWO_PI - math.pi
    return (np.asarray(a) + math.pi) % _TWO_PI - math.pi


def arc_coefficients(a: float) -> Tuple[float, float, float, float]:
    """A = sin(a)/a, B = (1 - cos a)/a and their derivatives dA/da, dB/da; series near a = 0.

    A body moving with constant twist (vx, vy, wz) for dt turns by a = wz dt and moves
    (A vx - B vy, B vx + A vy) dt in its start frame: the exact arc on SE(2), not a chord.
    """
    if abs(a) < 1e-4:
        a2 = a * a
        return (1.0 - a2 / 6.0, a / 2.0 - a * a2 / 24.0, -a / 3.0 + a * a2 / 30.0, 0.5 - a2 / 8.0)
    s, c = math.sin(a), math.cos(a)
    return s / a, (1.0 - c) / a, (a * c - s) / (a * a), (a * s - (1.0 - c)) / (a * a)


def integrate_twist(x: float, y: float, phi: float, vx: float, vy: float, wz: float,
                    dt: float) -> Tuple[float, float, float]:
    """Pose after moving with a constant body twist for dt: exact on SE(2) (arcs, not chords)."""
    A, B, _, _ = arc_coefficients(wz * dt)
    dx_body = (A * vx - B * vy) * dt
    dy_body = (B * vx + A * vy) * dt
    c, s = math.cos(phi), math.sin(phi)
    return x + c * dx_body - s * dy_body, y + s * dx_body + c * dy_body, wrap_angle(phi + wz * dt)


def compose_se2(a: Tuple[float, float, float], b: Tuple[float, float, float]) -> Tuple[float, float, float]:
    """a o b on SE(2): pose b given in frame a, expressed where a is given."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], float(wrap_angle(a[2] + b[2])))


def invert_se2(a: Tuple[float, float, float]) -> Tuple[float, float, float]:
    """a^-1 on SE(2)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-(c * a[0] + s * a[1]), s * a[0] - c * a[1], float(wrap_angle(-a[2])))


def compose_se2_jacobians(a: Tuple[float, float, float], b: Tuple[float, float, float]) -> Tuple[np.ndarray, np.ndarray]:
    """d(a o b)/da and d(a o b)/db, each 3x3 over (x, y, phi): to carry covariances through."""
    c, s = math.cos(a[2]), math.sin(a[2])
    Ja = np.array([[1.0, 0.0, -s * b[0] - c * b[1]], [0.0, 1.0, c * b[0] - s * b[1]], [0.0, 0.0, 1.0]])
    Jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Ja, Jb


def invert_se2_jacobian(a: Tuple[float, float, float]) -> np.ndarray:
    """d(a^-1)/da, 3x3 over (x, y, phi)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([[-c, -s, s * a[0] - c * a[1]], [s, -c, c * a[0] + s * a[1]], [0.0, 0.0, -1.0]])


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(pitch: float) -> np.ndarray:
    c, s = math.cos(pitch), math.sin(pitch)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(roll: float) -> np.ndarray:
    c, s = math.cos(roll), math.sin(roll)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll); positive pitch tips the nose down."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def make_transform(R: np.ndarray, t: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def pose_to_T_ground_robot(x: float, y: float, phi: float) -> np.ndarray:
    """T_GR of the planar pose (x, y, phi): robot frame on the floor, z up."""
    # Written out (the same entries as make_transform(rot_z(phi), (x, y, 0))): it runs per frame.
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, -s, 0.0, float(x)], [s, c, 0.0, float(y)], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def invert_transform(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def mount_to_T_robot_camera(xyz: Sequence[float], rpy: Sequence[float]) -> np.ndarray:
    """T_RC of the optical frame, from the body-frame mount pose (radians)."""
    R_robot_body = rpy_to_matrix(*rpy)
    return make_transform(R_robot_body @ R_BODY_OPTICAL, xyz)


def transform_plane(T_a_b: np.ndarray, plane_a: np.ndarray) -> np.ndarray:
    """Plane(s) given in frame a, expressed in frame b: pi_b = T_a_b^T pi_a.

    ``plane_a`` is a 4-vector or an (N, 4) array. Rigid transforms keep |n| = 1.
    """
    return np.asarray(plane_a) @ T_a_b


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """(N, 3) points in frame b to frame a."""
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def plane_from_points(points: np.ndarray):
    """Least-squares plane through (N, 3) points: (n, d, rms). Sign of n is arbitrary."""
    c = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[-1]
    rms = float(s[-1] / math.sqrt(max(len(points), 1)))
    return n, float(-n @ c), rms


def newell_normal(vertices: np.ndarray) -> np.ndarray:
    """Area-weighted normal of a polygon (un-normalised); right-hand rule on vertex order."""
    v = np.asarray(vertices, dtype=float)
    w = np.roll(v, -1, axis=0)
    return np.array(
        [
            np.sum((v[:, 1] - w[:, 1]) * (v[:, 2] + w[:, 2])),
            np.sum((v[:, 2] - w[:, 2]) * (v[:, 0] + w[:, 0])),
            np.sum((v[:, 0] - w[:, 0]) * (v[:, 1] + w[:, 1])),
        ]
    )


_X_AXIS = np.array([1.0, 0.0, 0.0])
_Z_AXIS = np.array([0.0, 0.0, 1.0])


def plane_axes(n: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Unit in-plane axes (a, b) of the plane with unit normal n, with a x b = n, so that the 2-D
    coordinates (p . a, p . b) keep a polygon's winding as seen from n.

    For a wall, a = z x n is horizontal (to the right of a viewer facing the wall) and b points up;
    a plane within 26 degrees of horizontal takes a = x x n instead, as z x n vanishes for a floor.
    """
    a = np.cross(_Z_AXIS if abs(n[2]) < 0.9 else _X_AXIS, n)
    a /= np.linalg.norm(a)
    return a, np.cross(n, a)
