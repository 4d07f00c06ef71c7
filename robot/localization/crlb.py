"""Cramer-Rao lower bound of the pose from the points of the visible planes (docs/architecture.md, 'Depth noise and the accuracy bound').

Fisher information sum_k g_k g_k^T / sigma_r,k^2 over every pixel that sees a map plane, with
g_k the gradient of the point-to-plane residual with respect to (x, y, phi) and sigma_r,k the
stereo depth noise projected on the plane normal.
"""

from __future__ import annotations

import numpy as np

from robot.base.geometry import rot_z, transform_points
from robot.config import RobotConfig
from robot.localization.roi import camera_views
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import PlaneMap


def pose_fisher_information(robot: RobotConfig, plane_map: PlaneMap, pose, noise, dropout: float = 0.0,
                            max_range: float = 6.0) -> np.ndarray:
    info = np.zeros((3, 3))
    R2 = rot_z(pose[2])[:2, :2]
    J90 = np.array([[0.0, -1.0], [1.0, 0.0]])
    index = PlaneIndex(plane_map)
    for cam in robot.cameras:
        views, label, grid = camera_views(plane_map, index, cam, pose, max_range)
        K = grid.K
        for k, v in enumerate(views):
            rr, cc = np.nonzero(label == k)
            if len(rr) == 0:
                continue
            n_C, d_C = v.pi_camera[:3], v.pi_camera[3]
            rays = np.column_stack([(cc - K[0, 2]) / K[0, 0], (rr - K[1, 2]) / K[1, 1], np.ones(len(rr))])
            z = -d_C / (rays @ n_C)
            keep = (z > noise.min_range) & (z < max_range)
            rays, z = rays[keep], z[keep]
            p_R = transform_points(cam.T_robot_camera, rays * z[:, None])
            plane = plane_map.planes[v.plane_index]
            a = plane.normal[:2]
            b = R2.T @ J90.T @ a
            g = np.column_stack([np.full(len(z), a[0]), np.full(len(z), a[1]), p_R[:, :2] @ b])
            sigma = noise.sigma(z, K[0, 0]) * np.abs(rays @ n_C)
            w = (1.0 - dropout) / sigma**2
            info += (g * w[:, None]).T @ g
    return info


def pose_crlb(robot: RobotConfig, plane_map: PlaneMap, pose, noise) -> np.ndarray:
    """3x3 lower bound on the covariance of any unbiased (x, y, phi) estimator."""
    return np.linalg.inv(pose_fisher_information(robot, plane_map, pose, noise, noise.dropout))
