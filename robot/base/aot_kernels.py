"""Our numba kernels compiled ahead of time into one extension module: no numba, no LLVM at run time.

The JIT keeps numba and LLVM in the process for as long as it runs: on the robot's Python 3.8 with
numba 0.58, importing numba takes about 60 MiB and loading the first kernel from its cache about
50 MiB more, for kernels whose machine code is under 1 MiB. ``robotctl kernels build`` compiles the
same kernels (the plane fit's, the integrity checks' and the obstacle scan's), with the same
compiler flags and for every argument type the product passes, into one module with
``numba.pycc``; a process that finds it imports it as any extension module and never imports
numba. The results are bit for bit those of the JIT (tests/test_aot_kernels.py).

The module's name carries a hash of the kernels' source files, this loader's, the builder's
(:mod:`robot.app.kernel_build`) and numpy's version: after an upgrade that changes any of them,
the old module is not found and the JIT (or numpy) takes over until it is built again. It is
looked for in ``ROBOT_KERNEL_DIR``, else ``NUMBA_CACHE_DIR`` (the service's state directory),
else the package's own ``__pycache__``.

A compiled function does not check its arguments: given an array of another type it reads
memory as that type, and can crash the process (measured: a segmentation fault). Every call
therefore goes through :class:`_Typed`, which compares each argument with the signatures built;
an argument type not built goes to numba's JIT where numba is installed (as the JIT itself would
compile a new variant, with a warning in the log), and is refused with a TypeError where not.

What it costs: each call boxes its result arrays in C code slower than the JIT's dispatcher, and
the type checks run in Python: about 5 % more CPU per localization (interleaved runs in fresh
processes on Python 3.8; docs/cpu-budget.md).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.machinery
import importlib.util
import json
import logging
import os
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

ENV_DIR = "ROBOT_KERNEL_DIR"
# (tag, module): the modules whose kernels go into the one ahead-of-time module.
KERNEL_MODULES = (("fit", "robot.localization.fit_kernels"), ("integrity", "robot.localization.integrity_kernels"),
                  ("scan", "robot.control.scan_kernels"))
# The source files that decide what the module holds: the kernels, this loader and the builder.
SOURCES = ("localization/fit_kernels.py", "localization/integrity_kernels.py", "control/scan_kernels.py",
           "base/aot_kernels.py", "app/kernel_build.py")
log = logging.getLogger(__name__)

# module path -> (tag -> {kernel name: callable, "version": ...}, or None; why not)
_loaded: Dict[str, Tuple[Optional[Dict[str, Dict[str, Any]]], str]] = {}
_last_path = ""


def source_hash() -> str:
    """16 hex digits over :data:`SOURCES` and numpy's major.minor version (the module is built
    against numpy's C API)."""
    package = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for rel in SOURCES:
        h.update((package / rel).read_bytes())
    h.update(".".join(np.__version__.split(".")[:2]).encode())
    return h.hexdigest()[:16]


def module_name() -> str:
    return f"robot_kernels_{source_hash()}"


def kernel_dir() -> Path:
    """Where the module is built and looked for (see the module's docstring)."""
    for env in (ENV_DIR, "NUMBA_CACHE_DIR"):
        value = os.environ.get(env, "").strip()
        if value:
            return Path(value)
    return Path(__file__).resolve().parents[1] / "__pycache__"


def module_path(folder: Optional[Path] = None) -> Path:
    return (folder or kernel_dir()) / (module_name() + importlib.machinery.EXTENSION_SUFFIXES[0])


# -- run time -----------------------------------------------------------------------------------------

# ("array", dtype name, ndim, C-contiguous required, read-only accepted) or (scalar kind,)
ArgSpec = Tuple[Any, ...]


_FLOAT_TYPES = frozenset([float, int] + [t for t in np.sctypeDict.values() if issubclass(t, (np.floating, np.integer))])
_INT_TYPES = frozenset([int] + [t for t in np.sctypeDict.values() if issubclass(t, np.integer)])
_BOOL_TYPES = frozenset([bool, np.bool_])


class _Typed:
    """One kernel's compiled variants, each called only with arguments of exactly its types. Other
    types go to ``fallback()``'s function (numba compiling one, as the JIT does for a type it has
    not seen), or are refused with a TypeError where it gives none.

    The checks are generated as one Python function per kernel (a chain of comparisons per
    variant): a kernel call costs a few microseconds more than the JIT's, not tens."""

    def __init__(self, name: str, variants: Sequence[Tuple[Callable, List[ArgSpec]]],
                 fallback: Optional[Callable[[], Optional[Callable]]] = None):
        self.name = name
        self._fallback = fallback
        self._other: Optional[Callable] = None
        scope: Dict[str, Any] = {"ndarray": np.ndarray, "FLOATS": _FLOAT_TYPES, "INTS": _INT_TYPES,
                                 "BOOLS": _BOOL_TYPES, "float32": np.float32, "other": self._other_types}
        lines = ["def call(*args):", "    n = len(args)"]
        for k, (fn, spec) in enumerate(variants):
            scope[f"f{k}"] = fn
            conds = [f"n == {len(spec)}"]
            for i, arg in enumerate(spec):
                conds.append(self._condition(f"args[{i}]", arg, scope, f"{k}_{i}"))
            lines += [f"    if {' and '.join(conds)}:", f"        return f{k}(*args)"]
        lines.append("    return other(args)")
        exec("\n".join(lines) + "\n", scope)  # noqa: S102 (built from our own specs only)
        self.call: Callable[..., Any] = scope["call"]
        self.call.typed = self  # type: ignore[attr-defined]  (set_fallbacks finds it there)

    @staticmethod
    def _condition(a: str, spec: ArgSpec, scope: Dict[str, Any], key: str) -> str:
        kind = spec[0]
        if kind == "array":
            # dtype equality: byte order included (an equal dtype need not be the same object).
            scope[f"d{key}"] = np.dtype(spec[1])
            # numpy makes a new flags object at every ``.flags``: one per argument.
            cond = (f"(type({a}) is ndarray and {a}.dtype == d{key} and {a}.ndim == {int(spec[2])} "
                    f"and (fl := {a}.flags).aligned")
            if spec[3]:
                cond += " and fl.c_contiguous"
            if not spec[4]:
                # A read-only array only where the kernel was compiled for one: a variant for
                # writable arrays may write into it.
                cond += " and fl.writeable"
            return cond + ")"
        if kind == "float64":
            return f"type({a}) in FLOATS"
        if kind == "float32":
            return f"type({a}) is float32"
        if kind == "int64":
            return f"type({a}) in INTS"
        if kind == "bool":
            return f"type({a}) in BOOLS"
        raise ValueError(f"argument kind {kind!r} has no check")

    def __call__(self, *args: Any) -> Any:
        return self.call(*args)

    def _other_types(self, args: Tuple[Any, ...]) -> Any:
        types = ", ".join(_describe(a) for a in args)
        if self._other is None and self._fallback is not None:
            self._other = self._fallback()
            if self._other is not None:
                log.warning("kernel %s: no variant compiled ahead of time for (%s); numba compiles it", self.name, types)
        if self._other is None:
            raise TypeError(f"{self.name}: no ahead-of-time variant for arguments ({types})"
                            + ("" if self._fallback is None else ", and no numba to compile one"))
        return self._other(*args)


def set_fallbacks(table: Dict[str, Any], jit_kernels: Callable[[], Dict[str, Any]]) -> None:
    """Where a kernel of ``table`` (a module's, from :func:`load`) meets an argument type it was
    not built for, numba compiles it: ``jit_kernels()``, that module's fresh dispatchers, made at
    the first such call (None without numba: the call is refused)."""
    made: Dict[str, Any] = {}

    def kernel(name: str) -> Optional[Callable]:
        try:
            import numba  # noqa: F401
        except ImportError:
            return None
        if not made:
            made.update(jit_kernels())
        return made[name]

    for name, fn in table.items():
        typed = getattr(fn, "typed", None)
        if isinstance(typed, _Typed) and typed._fallback is None:  # noqa: SLF001 (this module's own class)
            typed._fallback = functools.partial(kernel, name)


def _describe(a: Any) -> str:
    if isinstance(a, np.ndarray):
        return f"{a.dtype}[{a.ndim}d{'' if a.flags.c_contiguous else ', strided'}]"
    return type(a).__name__


def load() -> Optional[Dict[str, Dict[str, Any]]]:
    """The kernels of the module built for this source, per tag, or None (:func:`why_not` says
    why). Each module is loaded once per process."""
    global _last_path
    try:
        path = module_path()
    except OSError as e:  # a source file unreadable: no module can be matched to it
        _last_path = f"(sources: {e})"
        _loaded[_last_path] = (None, f"the kernels' sources cannot be read: {e}")
        return None
    _last_path = str(path)
    if _last_path not in _loaded:
        _loaded[_last_path] = _load(path)
    return _loaded[_last_path][0]


def why_not() -> str:
    """Why the last :func:`load` found no kernels ("" if it did)."""
    return _loaded.get(_last_path, (None, "not looked for"))[1]


def _load(path: Path) -> Tuple[Optional[Dict[str, Dict[str, Any]]], str]:
    try:
        meta_path = path.with_suffix(".json")
        if not path.is_file() or not meta_path.is_file():
            return None, f"no ahead-of-time kernels for this source in {path.parent} (robotctl kernels build makes them)"
        meta = json.loads(meta_path.read_text())
        spec = importlib.util.spec_from_file_location(module_name(), str(path))
        if spec is None or spec.loader is None:
            return None, f"{path} cannot be imported"
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)  # type: ignore[union-attr]
        out: Dict[str, Dict[str, Any]] = {}
        for tag, kernels in meta["kernels"].items():
            out[tag] = {"version": f"{meta['numba']} ahead of time ({path.name})"}
            for kernel, variants in kernels.items():
                typed = _Typed(kernel, [(getattr(mod, export), [tuple(s) for s in spec_]) for export, spec_ in variants])
                out[tag][kernel] = typed.call  # the generated function itself: one Python call less
    except (OSError, ImportError, ValueError, KeyError, AttributeError, TypeError) as e:
        return None, f"the ahead-of-time kernels in {path} do not load: {type(e).__name__}: {e}".split("\n")[0]
    return out, ""
