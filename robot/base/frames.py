"""Whether arrays or a live frame can be a depth frame: one check for snapshot files and the camera path. Pure.

A depth snapshot read from disk (``robot.recording.snapshot``) and a frame handed over by a
camera driver reach the localizer through the same door, so they are judged by the same rules:
a 2-D uint16 image no larger than a real camera's, a positive finite depth scale, a pinhole K.
A live frame must also be stamped sensibly on the host's clock: not ahead of the moment it is
judged (a camera-to-host clock mapping that went wrong) and not so old that the filter's
history no longer reaches back to it. Refusals are counted per camera by ``FrameCheck``; the
reason is kept for the status line.

Everything is numpy only, so the drivers, the core and the recorder can all use it.
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Sequence

import numpy as np

from robot.base.errors import InputError
from robot.base.samples import DepthFrame

MAX_WIDTH = 1920  # px: the largest image of the cameras the config accepts
MAX_HEIGHT = 1080  # px
MIN_SIDE = 16  # px
MAX_DEPTH_SCALE = 0.1  # m per depth unit (D400: 0.001 by default)
MAX_K_ENTRY = 1e6  # px: no real camera has a focal length or principal point beyond this


def validate_frame_arrays(where: str, depth, depth_scale, K, truth: Optional[Sequence[float]] = None) -> None:
    """Raise InputError naming ``where`` and the problem if the arrays cannot be a depth frame."""
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise InputError(f"{where}: 'depth' must be a 2-D array, got shape {getattr(depth, 'shape', None)}")
    if depth.dtype != np.uint16:
        holes = ""
        if depth.dtype.kind in "fc":
            bad = int(depth.size - np.count_nonzero(np.isfinite(depth)))
            holes = f" with {bad} non-finite values" if bad else ""
        raise InputError(f"{where}: 'depth' must be uint16 depth units, got {depth.dtype}{holes}")
    if depth.shape[0] < MIN_SIDE or depth.shape[1] < MIN_SIDE:
        raise InputError(f"{where}: 'depth' is too small ({depth.shape[1]}x{depth.shape[0]})")
    if depth.shape[0] > MAX_HEIGHT or depth.shape[1] > MAX_WIDTH:
        raise InputError(f"{where}: 'depth' is {depth.shape[1]}x{depth.shape[0]}, larger than a camera's "
                         f"{MAX_WIDTH}x{MAX_HEIGHT}")
    try:
        scale = float(depth_scale)
    except (TypeError, ValueError):
        raise InputError(f"{where}: 'depth_scale' must be a number, got {type(depth_scale).__name__}") from None
    if not math.isfinite(scale) or scale <= 0:
        raise InputError(f"{where}: 'depth_scale' must be a positive finite number, got {depth_scale}")
    if scale > MAX_DEPTH_SCALE:
        raise InputError(f"{where}: 'depth_scale' is {depth_scale} m per unit, more than {MAX_DEPTH_SCALE} "
                         f"(D400 cameras use 0.001)")
    K = np.asarray(K)
    # In floats: every live frame passes here on the event loop, and numpy's per-call cost on a
    # 3x3 matrix is several times the checks themselves.
    k = K.tolist() if K.shape == (3, 3) and K.dtype.kind in "fiu" else None
    if k is None or not all(math.isfinite(v) for row in k for v in row):
        raise InputError(f"{where}: 'K' must be a finite 3x3 matrix, got shape {K.shape}")
    if k[0][0] <= 0 or k[1][1] <= 0 or k[0][1] != 0 or k[2] != [0, 0, 1]:
        raise InputError(f"{where}: 'K' is not a pinhole intrinsic matrix: {np.round(K, 6).tolist()}")
    if any(abs(v) > MAX_K_ENTRY for row in k for v in row):
        raise InputError(f"{where}: 'K' has entries beyond {MAX_K_ENTRY:g} px: not a camera's intrinsics")
    if truth is not None:
        t = np.asarray(truth, dtype=float)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(f"{where}: 'truth' must be three finite numbers (x, y, phi)")


def frame_problem(frame: DepthFrame, t_now: float, max_ahead: float, max_age: float) -> Optional[str]:
    """Why a live frame judged at host time ``t_now`` must not be fused, or None if it may be."""
    where = f"camera '{frame.camera}' frame {frame.frame_number}"
    try:
        validate_frame_arrays(where, frame.depth, frame.depth_scale, frame.K)
    except InputError as e:
        return str(e)
    try:
        t = float(frame.t_capture)
    except (TypeError, ValueError):
        t = math.nan
    if not math.isfinite(t):
        return f"{where}: capture time {frame.t_capture!r} is not a finite number"
    ahead = t - t_now
    if ahead > max_ahead:
        return f"{where}: stamped {ahead:.3f} s in the future (more than {max_ahead:g} s): camera clock fault"
    if -ahead > max_age:
        return f"{where}: captured {-ahead:.2f} s ago (more than {max_age:g} s): too old to fuse"
    return None


class FrameCheck:
    """``frame_problem`` with the refusals counted per camera and the last reason kept."""

    def __init__(self, max_ahead: float, max_age: float):
        self.max_ahead = float(max_ahead)
        self.max_age = float(max_age)
        self.refused: Dict[str, int] = {}
        self.last_reason: Dict[str, str] = {}

    def admit(self, frame: DepthFrame, t_now: float) -> bool:
        """True when the frame may go on to the localizer; otherwise it is counted and its reason kept."""
        why = frame_problem(frame, t_now, self.max_ahead, self.max_age)
        if why is None:
            return True
        name = str(frame.camera)
        self.refused[name] = self.refused.get(name, 0) + 1
        self.last_reason[name] = why
        return False

    @property
    def total(self) -> int:
        return sum(self.refused.values())
