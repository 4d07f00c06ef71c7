"""Rigid transforms, planes and angles (DESIGN.md section 2). Pure numpy, no I/O.

Conventions: ``T_a_b`` maps points in frame b to frame a (p_a = T_a_b p_b).
A plane is the homogeneous 4-vector (n, d) with n . p + d = 0 and |n| = 1, and
under p_a = T_a_b p_b it transforms as pi_b = T_a_b^T pi_a.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

# Columns are the optical frame's axes (x right, y down, z forward) written in the
# camera body frame (x forward, y left, z up).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def wrap_angle(a):
    """Wrap an angle (or array of angles) to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


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
    return make_transform(rot_z(phi), (x, y, 0.0))


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
