"""The online calibration's estimates on disk, beside the saved pose, so a restart starts from them.

One JSON file in the state directory (``online_calibration.json``), written atomically like the
pose (``robot.app.pose_store``) and rate limited to spare the SD card. What it holds is the
``CalibrationFilter.to_json`` state: per camera keyed by its serial number where the config has
one (a camera moved to another robot takes nothing with it), with the configured values each
estimate was made against, so an estimate for another camera or another config is not used.
Loading never raises: a missing, corrupt or foreign file gives ``None`` and a reason.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Optional, Tuple

from robot.base.files import atomic_write_text

log = logging.getLogger(__name__)


class CalibrationStore:
    def __init__(self, state_dir, filename: str = "online_calibration.json", min_interval: float = 30.0):
        self.path = Path(state_dir) / filename
        self.min_interval = float(min_interval)
        self._last_save: Optional[float] = None

    def save(self, t: float, state: dict, force: bool = False) -> bool:
        """Write ``state`` if ``min_interval`` has passed since the last write; I/O errors are logged."""
        if not force and self._last_save is not None and t - self._last_save < self.min_interval:
            return False
        try:
            text = json.dumps(state, indent=None, allow_nan=False) + "\n"
        except ValueError:
            log.warning("not saving a non-finite calibration state to %s", self.path)
            return False
        try:
            atomic_write_text(self.path, text)
        except OSError as e:
            log.warning("cannot save the calibration state to %s: %s", self.path, e)
            return False
        self._last_save = t
        return True

    def load(self) -> Tuple[Optional[dict], str]:
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None, f"{self.path}: no saved calibration state"
        except (OSError, UnicodeDecodeError) as e:
            return None, f"{self.path}: cannot read: {e}"
        try:
            data = json.loads(text)
        except ValueError as e:
            return None, f"{self.path}: corrupt (not JSON: {e})"
        if not isinstance(data, dict):
            return None, f"{self.path}: corrupt (expected a JSON object)"
        return data, ""
