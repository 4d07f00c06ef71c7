"""Strict reading of YAML mappings: unknown keys are errors, missing optional keys take defaults.

Shared by the robot config, map and path loaders so every file gets the same kind of message:
``<file>: <where>: <problem>``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, Iterable, Optional

import yaml

from robot.base.errors import ConfigError

_MISSING = object()


def load_yaml_file(path) -> Any:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{p}: cannot read: {e}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"{p}: malformed YAML{where}: {problem}") from None


class Section:
    """A mapping being read; call ``done()`` to fail on keys nobody asked for."""

    def __init__(self, data: Any, where: str, source: str):
        self.source = source
        self.where = where
        if data is None:
            data = {}
        if not isinstance(data, dict):
            self.fail(f"expected a mapping, got {type(data).__name__}")
        self._data: Dict[str, Any] = dict(data)
        self._seen = set()

    def fail(self, msg: str):
        raise ConfigError(f"{self.source}: {self.where}: {msg}")

    def has(self, key: str) -> bool:
        return key in self._data

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        self._seen.add(key)
        if key not in self._data:
            if default is _MISSING:
                self.fail(f"missing required key '{key}'")
            return default
        return self._data[key]

    def sub(self, key: str, required: bool = False) -> Section:
        val = self.raw(key, _MISSING if required else None)
        return Section(val, f"{self.where}.{key}" if self.where else key, self.source)

    def number(self, key: str, default: Any = _MISSING, lo: Optional[float] = None,
               hi: Optional[float] = None, positive: bool = False) -> float:
        val = self.raw(key, default)
        return check_number(val, f"{key}", self, lo, hi, positive)

    def integer(self, key: str, default: Any = _MISSING, lo: Optional[int] = None) -> int:
        val = self.raw(key, default)
        if isinstance(val, bool) or not isinstance(val, int):
            self.fail(f"'{key}' must be an integer, got {val!r}")
        if lo is not None and val < lo:
            self.fail(f"'{key}' must be >= {lo}, got {val}")
        return val

    def string(self, key: str, default: Any = _MISSING, choices: Optional[Iterable[str]] = None) -> str:
        val = self.raw(key, default)
        if not isinstance(val, str) or not val:
            self.fail(f"'{key}' must be a non-empty string, got {val!r}")
        if choices is not None and val not in choices:
            self.fail(f"'{key}' must be one of {sorted(choices)}, got {val!r}")
        return val

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        val = self.raw(key, default)
        if not isinstance(val, bool):
            self.fail(f"'{key}' must be true or false, got {val!r}")
        return val

    def vector(self, key: str, length: int, default: Any = _MISSING) -> tuple:
        val = self.raw(key, default)
        if not isinstance(val, (list, tuple)) or len(val) != length:
            self.fail(f"'{key}' must be a list of {length} numbers, got {val!r}")
        return tuple(check_number(v, f"{key}[{i}]", self) for i, v in enumerate(val))

    def done(self):
        unknown = sorted(set(self._data) - self._seen)
        if unknown:
            self.fail(f"unknown key(s): {', '.join(map(str, unknown))}")


def check_number(val: Any, name: str, section: Section, lo=None, hi=None, positive=False) -> float:
    if isinstance(val, bool) or not isinstance(val, (int, float)):
        section.fail(f"'{name}' must be a number, got {val!r}")
    val = float(val)
    if not math.isfinite(val):
        section.fail(f"'{name}' must be finite, got {val}")
    if positive and val <= 0:
        section.fail(f"'{name}' must be > 0, got {val}")
    if lo is not None and val < lo:
        section.fail(f"'{name}' must be >= {lo}, got {val}")
    if hi is not None and val > hi:
        section.fail(f"'{name}' must be <= {hi}, got {val}")
    return val
