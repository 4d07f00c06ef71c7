"""The last known pose on disk, so a restart resumes where the robot stopped (like Nav2 AMCL).

A small JSON file in the state directory (e.g. ``/var/lib/robot/last_pose.json``)::

    {"version": 1, "frame": "G", "map": "paper_arena", "x": 0.5, "y": 0.25, "phi": 1.57,
     "cov": [[...3...], [...], [...]], "saved_at": "2026-05-09T07:35:25+00:00"}

Writes are atomic (temp file in the same directory, fsync, ``os.replace``, fsync of the
directory) so a power cut leaves either the old or the new file, never half of one.
Saving is rate limited to one write per ``min_interval`` seconds (AMCL's ``save_pose_rate``
0.5 Hz) to spare the Jetson's SD card; ``force=True`` writes anyway (on shutdown).
Loading never raises: a missing, corrupt or foreign file gives ``None`` and a reason.
"""

from __future__ import annotations

import datetime
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from robot.base.files import atomic_write_text

log = logging.getLogger(__name__)

FORMAT_VERSION = 1


@dataclass(frozen=True)
class StoredPose:
    x: float
    y: float
    phi: float
    cov: np.ndarray  # (3, 3) covariance of (x, y, phi)
    map_name: str = ""
    saved_at: str = ""  # ISO 8601 wall-clock time, for people reading the file


class PoseStore:
    def __init__(self, state_dir, filename: str = "last_pose.json", min_interval: float = 2.0):
        self.path = Path(state_dir) / filename
        self.min_interval = float(min_interval)
        self._last_save: Optional[float] = None

    def save(self, t: float, x: float, y: float, phi: float, cov: np.ndarray, map_name: str = "",
             force: bool = False) -> bool:
        """Write the pose if ``min_interval`` has passed since the last write (t: monotonic s).

        Returns True when written. I/O errors are logged, not raised: losing a saved pose
        must never stop the robot.
        """
        if not force and self._last_save is not None and t - self._last_save < self.min_interval:
            return False
        cov = np.asarray(cov, dtype=float)
        if not (np.isfinite([x, y, phi]).all() and cov.shape == (3, 3) and np.isfinite(cov).all()):
            log.warning("not saving a non-finite pose to %s", self.path)
            return False
        data = {
            "version": FORMAT_VERSION,
            "frame": "G",
            "map": map_name,
            "x": float(x),
            "y": float(y),
            "phi": float(phi),
            "cov": [[float(v) for v in row] for row in cov],
            "saved_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
        try:
            atomic_write_text(self.path, json.dumps(data, indent=1) + "\n")
        except OSError as e:
            log.warning("cannot save the pose to %s: %s", self.path, e)
            return False
        self._last_save = t
        return True

    def load(self, map_name: str = "") -> Tuple[Optional[StoredPose], str]:
        """(pose, "") or (None, why not). A pose saved on another map is refused."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None, f"{self.path}: no saved pose"
        except (OSError, UnicodeDecodeError) as e:
            return None, f"{self.path}: cannot read: {e}"
        try:
            data = json.loads(text)
        except ValueError as e:
            return None, f"{self.path}: corrupt (not JSON: {e})"
        pose, problem = _parse(data)
        if pose is None:
            return None, f"{self.path}: corrupt ({problem})"
        if map_name and pose.map_name and pose.map_name != map_name:
            return None, f"{self.path}: saved on map '{pose.map_name}', not '{map_name}'"
        return pose, ""


def _parse(data) -> Tuple[Optional[StoredPose], str]:
    if not isinstance(data, dict):
        return None, "expected a JSON object"
    if data.get("version") != FORMAT_VERSION:
        return None, f"unknown version {data.get('version')!r}"
    if data.get("frame", "G") != "G":
        return None, f"pose in frame {data.get('frame')!r}, expected 'G'"
    vals = []
    for key in ("x", "y", "phi"):
        v = data.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return None, f"'{key}' must be a finite number, got {v!r}"
        vals.append(float(v))
    try:
        cov = np.array(data.get("cov"), dtype=float)
    except (TypeError, ValueError):
        return None, "'cov' must be a 3x3 list of numbers"
    if cov.shape != (3, 3) or not np.isfinite(cov).all():
        return None, "'cov' must be a 3x3 list of finite numbers"
    if not np.allclose(cov, cov.T, atol=1e-12) or np.linalg.eigvalsh(cov)[0] < -1e-12:
        return None, "'cov' is not a symmetric positive semi-definite matrix"
    map_name = data.get("map", "")
    saved_at = data.get("saved_at", "")
    if not isinstance(map_name, str) or not isinstance(saved_at, str):
        return None, "'map' and 'saved_at' must be strings"
    return StoredPose(vals[0], vals[1], vals[2], cov, map_name, saved_at), ""


