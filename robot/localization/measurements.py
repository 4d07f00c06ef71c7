"""What the localizer hands to the fusion filter: one constraint per fitted map plane.

For map plane (n_G, d_G) observed in the robot frame as (n_R, d_R), pi_R = T_GR^T pi_G gives
(docs/architecture.md, 'Plane constraints'):

    d_R           = n_Gx x + n_Gy y + d_G
    atan2(n_R,xy) = atan2(n_G,xy) - phi

so the measurement z = [d_R, psi_R] with psi_R = atan2(n_Ry, n_Rx) has the model
h(x, y, phi) = [n_Gx x + n_Gy y + d_G, wrap(atan2(n_Gy, n_Gx) - phi)].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robot.base.geometry import wrap_angle


@dataclass
class PlaneMeasurement:
    plane_id: str
    camera: str
    t_capture: float  # host monotonic seconds of the frame's exposure
    n_ground: np.ndarray  # (3,) map plane normal in G
    d_ground: float
    z: np.ndarray  # (2,) [d_R (m), psi_R (rad)]
    # (2, 2) covariance of z: pixel noise and the systematic errors (depth scale, mount, the wall as
    # built; robot/localization/integrity.py). Those are the same in every frame of this camera and
    # wall, so a filter that averages them over frames gets too confident: the quality monitor adds
    # the localization's systematic covariance back to its protection levels.
    R: np.ndarray
    inliers: int = 0

    def predict(self, x: float, y: float, phi: float) -> np.ndarray:
        """h(x): the measurement this plane would give at pose (x, y, phi)."""
        n = self.n_ground
        return np.array([n[0] * x + n[1] * y + self.d_ground, float(wrap_angle(math.atan2(n[1], n[0]) - phi))])

    def jacobian(self) -> np.ndarray:
        """dh/d(x, y, phi); constant because h is linear in position and in phi."""
        n = self.n_ground
        return np.array([[n[0], n[1], 0.0], [0.0, 0.0, -1.0]])

    def residual(self, x: float, y: float, phi: float) -> np.ndarray:
        r = self.z - self.predict(x, y, phi)
        r[1] = float(wrap_angle(r[1]))
        return r
