"""Strict reading of YAML mappings: unknown keys are errors, missing optional keys take defaults.

Shared by the robot config, map and path loaders so every file gets the same kind of message:
``<file>: <where>: <problem>``, quoting at most a short excerpt of a bad value.

YAML is parsed with bounds, because a config is input like any other: at most
``MAX_YAML_DEPTH`` levels of nesting (a 20,000-deep list would exhaust Python's stack), and
aliases may add at most ``MAX_ALIAS_NODES`` nodes to what the file spells out (a 1.4 kB "billion
laughs" file otherwise expands to gigabytes). The file itself is opened through
``robot.base.files`` (regular files only, size-limited per kind).

Numbers: YAML 1.1, which PyYAML implements, reads ``1e-4`` and ``1E5`` as strings (its floats
need a dot and a signed exponent). People write them as numbers, so they are read as numbers.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Dict, Iterable, Optional

import yaml

from robot.base.errors import ConfigError
from robot.base.files import CONFIG, FileKind, read_text
from robot.config.ranges import Range, excerpt

_MISSING = object()

MAX_YAML_DEPTH = 32  # nesting levels; a plane map needs 7 (planes, plane, polygons, polygon, vertex, ...)
MAX_ALIAS_NODES = 100_000  # nodes that aliases may add beyond the ones written out
_PROBLEM_CHARS = 120  # PyYAML's problem texts quote the document: keep them short too


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader with a nesting limit, an alias-expansion budget and YAML 1.2-style floats.

    Aliases are counted while composing (before any Python object exists): each alias costs
    the size of the node it repeats, so a bomb is refused after reading a few hundred bytes.
    """

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0
        self._alias_nodes = 0
        self._sizes: Dict[int, int] = {}  # id(collection node) -> nodes in it, aliases expanded

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            node = self.anchors.get(event.anchor)
            if node is not None:
                if isinstance(node, yaml.ScalarNode):
                    size = 1
                else:
                    size = self._sizes.get(id(node))
                    if size is None:
                        raise yaml.composer.ComposerError(
                            None, None, f"alias *{excerpt(event.anchor, 30)} refers to a node that contains it "
                            "(recursive aliases are not allowed)", event.start_mark)
                self._alias_nodes += size
                if self._alias_nodes > MAX_ALIAS_NODES:
                    raise yaml.composer.ComposerError(
                        None, None, f"aliases expand the document by more than {MAX_ALIAS_NODES} nodes "
                        "(an alias bomb?)", event.start_mark)
            return super().compose_node(parent, index)
        self._depth += 1
        if self._depth > MAX_YAML_DEPTH:
            raise yaml.composer.ComposerError(None, None, f"nested deeper than {MAX_YAML_DEPTH} levels",
                                              self.peek_event().start_mark)
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        if isinstance(node, yaml.SequenceNode):
            self._sizes[id(node)] = 1 + sum(self._size(c) for c in node.value)
        elif isinstance(node, yaml.MappingNode):
            self._sizes[id(node)] = 1 + sum(self._size(k) + self._size(v) for k, v in node.value)
        return node

    def _size(self, node) -> int:
        return 1 if isinstance(node, yaml.ScalarNode) else self._sizes.get(id(node), 1)


# Floats without a dot or with an unsigned exponent (1e-4, 1E5, 2.5e3, -.5): YAML 1.2 reads
# them as numbers, YAML 1.1 as strings.
_BoundedLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+|[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?)$"),
    list("-+0123456789."))


def parse_yaml(text: str, source: str = "<yaml>") -> Any:
    """The document in ``text``; ConfigError naming ``source`` and the place of a syntax error."""
    try:
        return yaml.load(text, Loader=_BoundedLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        if len(problem) > _PROBLEM_CHARS:
            problem = problem[:_PROBLEM_CHARS - 3] + "..."
        raise ConfigError(f"{source}: malformed YAML{where}: {problem}") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as e:
        # PyYAML's constructors let these through: a date like 2024-13-45, an integer with more
        # digits than Python converts (3.11+), ...
        problem = str(e)
        if len(problem) > _PROBLEM_CHARS:
            problem = problem[:_PROBLEM_CHARS - 3] + "..."
        raise ConfigError(f"{source}: malformed YAML: {problem}") from None


def load_yaml_file(path, kind: FileKind = CONFIG) -> Any:
    """Parse a YAML file of ``kind`` (its size limit; regular files only), see :func:`parse_yaml`."""
    p = Path(path)
    return parse_yaml(read_text(p, kind), str(p))


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
        raise ConfigError(f"{self.source}: {self.where}: {msg}" if self.where else f"{self.source}: {msg}")

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

    def ranged(self, key: str, rng: Range, default: Any = _MISSING) -> float:
        """A number checked against its declared range (int for an integer range)."""
        val = self.raw(key, default)
        why = rng.problem(val)
        if why is not None:
            self.fail(f"'{key}' {why}")
        return rng.convert(val)

    def integer(self, key: str, default: Any = _MISSING, lo: Optional[int] = None) -> int:
        val = self.raw(key, default)
        if isinstance(val, bool) or not isinstance(val, int):
            self.fail(f"'{key}' must be an integer, got {excerpt(val)}")
        if lo is not None and val < lo:
            self.fail(f"'{key}' must be >= {lo}, got {excerpt(val)}")
        return val

    def string(self, key: str, default: Any = _MISSING, choices: Optional[Iterable[str]] = None) -> str:
        val = self.raw(key, default)
        if not isinstance(val, str) or not val:
            self.fail(f"'{key}' must be a non-empty string, got {excerpt(val)}")
        if choices is not None and val not in choices:
            self.fail(f"'{key}' must be one of {sorted(choices)}, got {excerpt(val)}")
        return val

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        val = self.raw(key, default)
        if not isinstance(val, bool):
            self.fail(f"'{key}' must be true or false, got {excerpt(val)}")
        return val

    def vector(self, key: str, length: int, default: Any = _MISSING, rng: Optional[Range] = None) -> tuple:
        val = self.raw(key, default)
        if not isinstance(val, (list, tuple)) or len(val) != length:
            self.fail(f"'{key}' must be a list of {length} numbers, got {excerpt(val)}")
        if rng is None:
            return tuple(check_number(v, f"{key}[{i}]", self) for i, v in enumerate(val))
        out = []
        for i, v in enumerate(val):
            why = rng.problem(v)
            if why is not None:
                self.fail(f"'{key}[{i}]' {why}")
            out.append(rng.convert(v))
        return tuple(out)

    def done(self):
        unknown = sorted(set(map(str, self._data)) - set(map(str, self._seen)))
        if unknown:
            # A key is quoted when it is long or holds a line break or other control character.
            shown = ", ".join(k if len(k) <= 40 and k.isprintable() else excerpt(k, 40) for k in unknown[:10])
            more = f" and {len(unknown) - 10} more" if len(unknown) > 10 else ""
            self.fail(f"unknown key(s): {shown}{more}")


def check_number(val: Any, name: str, section: Section, lo=None, hi=None, positive=False) -> float:
    if isinstance(val, bool) or not isinstance(val, (int, float)):
        section.fail(f"'{name}' must be a number, got {excerpt(val)}")
    try:
        val = float(val)
    except OverflowError:  # an integer beyond the float range
        section.fail(f"'{name}' must be finite, got an integer of {val.bit_length()} bits")
    if val != val or val in (float("inf"), float("-inf")):
        section.fail(f"'{name}' must be finite, got {val}")
    if positive and val <= 0:
        section.fail(f"'{name}' must be > 0, got {val}")
    if lo is not None and val < lo:
        section.fail(f"'{name}' must be >= {lo}, got {val}")
    if hi is not None and val > hi:
        section.fail(f"'{name}' must be <= {hi}, got {val}")
    return val
