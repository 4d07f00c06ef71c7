"""Where the shipped default files live: found through the installed package, never the cwd.

The top-level ``config/`` folder of the source tree is installed as the package
``robot_defaults`` (see ``pyproject.toml``), so an editable checkout and a wheel installed by
the Nano installer resolve the same files.
"""

from __future__ import annotations

from pathlib import Path


def defaults_dir() -> Path:
    import robot_defaults

    return Path(robot_defaults.__file__).resolve().parent


DEFAULT_ROBOT = defaults_dir() / "robot.yaml"
DEFAULT_MAP = defaults_dir() / "maps" / "paper_arena.yaml"
