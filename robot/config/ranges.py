"""The physical range of every configurable number, declared once beside its field.

A config dataclass declares each field with one of the helpers here::

    rate: float = number(50.0, 10.0, 200.0, "Hz", "control loop rate")

The range then serves three readers: the YAML loader checks it (one ``ConfigError`` naming the
file, the key and the range), the dataclass's ``__post_init__`` checks it for configs built in
code (:func:`check_fields`), and ``docs/configuration.md`` is generated from it
(``robot.config.reference``). Limits are what the hardware and the safety design allow, not
what the code happens to survive: a link timeout of a minute is refused, because a robot that
takes a minute to notice a dead link is not safe.
"""

from __future__ import annotations

import dataclasses
import math
import reprlib
from dataclasses import dataclass
from typing import Any, Iterable, Optional, Tuple

from robot.base.errors import ConfigError

EXCERPT_CHARS = 60  # a rejected value is quoted up to this many characters

_repr = reprlib.Repr()
_repr.maxstring = EXCERPT_CHARS
_repr.maxother = EXCERPT_CHARS
_repr.maxlong = 40
_repr.maxlist = _repr.maxtuple = _repr.maxset = _repr.maxdict = 6
_repr.maxlevel = 3


def excerpt(value: Any, limit: int = EXCERPT_CHARS) -> str:
    """A short repr for error messages: a file may hold a megabyte where a number belongs."""
    try:
        text = _repr.repr(value)
    except Exception:  # e.g. an int too long to print (Python 3.11 limits int-to-str)
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _fmt(x: float) -> str:
    return repr(x)


@dataclass(frozen=True)
class Range:
    """Allowed values ``lo..hi`` (open ends when ``lo_open``/``hi_open``), in ``unit``."""

    lo: float
    hi: float
    unit: str = ""
    integer: bool = False
    lo_open: bool = False
    hi_open: bool = False
    text: str = ""  # how messages and docs say the range when the interval alone does not

    def describe(self) -> str:
        if self.text:
            return self.text
        interval = (f"{'(' if self.lo_open else '['}{_fmt(self.lo)}, {_fmt(self.hi)}"
                    f"{')' if self.hi_open else ']'}")
        return f"{interval} {self.unit}".rstrip()

    def problem(self, value: Any) -> Optional[str]:
        """Why ``value`` is not allowed ("must be ..., got ..."), or None."""
        kind = "an integer" if self.integer else "a number"
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"must be {kind}, got {excerpt(value)}"
        if isinstance(value, float) and not math.isfinite(value):
            return f"must be finite, got {value}"
        if self.integer and isinstance(value, float) and not value.is_integer():
            return f"must be an integer, got {excerpt(value)}"
        below = value <= self.lo if self.lo_open else value < self.lo
        above = value >= self.hi if self.hi_open else value > self.hi
        if not (below or above):
            return None
        if self.text:
            return f"must be {self.text}, got {excerpt(value)}"
        if below:
            bound = f"{'>' if self.lo_open else '>='} {_fmt(self.lo)}"
        else:
            bound = f"{'<' if self.hi_open else '<='} {_fmt(self.hi)}"
        return f"must be {bound} {self.unit}".rstrip() + f" (allowed: {self.describe()}), got {excerpt(value)}"

    def convert(self, value: Any) -> float:
        """The checked value as the field's type (an integral float for an integer field becomes int)."""
        return int(value) if self.integer else float(value)


def number(default: Any, lo: float, hi: float, unit: str = "", doc: str = "", *, lo_open: bool = False,
           hi_open: bool = False, text: str = ""):
    """A real-valued config field with its range, unit and meaning."""
    return dataclasses.field(default=default, metadata={
        "range": Range(float(lo), float(hi), unit, False, lo_open, hi_open, text), "doc": doc})


def integer(default: Any, lo: int, hi: int, unit: str = "", doc: str = "", *, text: str = ""):
    """An integer config field with its range, unit and meaning."""
    return dataclasses.field(default=default, metadata={"range": Range(lo, hi, unit, True, text=text), "doc": doc})


def choice(default: Any, choices: Iterable[str], doc: str = ""):
    """A string field that must be one of ``choices``."""
    return dataclasses.field(default=default, metadata={"choices": tuple(choices), "doc": doc})


def flag(default: bool, doc: str = ""):
    return dataclasses.field(default=default, metadata={"doc": doc})


def text(default: Any = dataclasses.MISSING, doc: str = "", **kwargs):
    """A free string field (names, ports); ``kwargs`` go to ``dataclasses.field``."""
    return dataclasses.field(default=default, metadata={"doc": doc}, **kwargs)


def field_range(f: dataclasses.Field) -> Optional[Range]:
    return f.metadata.get("range") if f.metadata else None


def field_choices(f: dataclasses.Field) -> Optional[Tuple[str, ...]]:
    return f.metadata.get("choices") if f.metadata else None


def field_doc(f: dataclasses.Field) -> str:
    return f.metadata.get("doc", "") if f.metadata else ""


def check_fields(obj: Any, where: str) -> None:
    """ConfigError naming ``where`` and the field when a value of a config built in code is out of range.

    Tuple-valued fields (a mount position) check each element against the field's range.
    """
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        rng = field_range(f)
        if rng is not None:
            items = enumerate(value) if isinstance(value, tuple) else [(None, value)]
            for i, v in items:
                why = rng.problem(v)
                if why is not None:
                    name = f.name if i is None else f"{f.name}[{i}]"
                    raise ConfigError(f"{where}: '{name}' {why}")
        choices = field_choices(f)
        if choices is not None and value not in choices:
            raise ConfigError(f"{where}: '{f.name}' must be one of {list(choices)}, got {excerpt(value)}")


__all__ = ["Range", "number", "integer", "choice", "flag", "text", "check_fields", "field_range", "field_choices",
           "field_doc", "excerpt", "EXCERPT_CHARS"]
