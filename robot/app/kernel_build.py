"""``robotctl kernels build``: our numba kernels compiled ahead of time into one extension module.

The loader, and why, is :mod:`robot.base.aot_kernels`. Building needs numba (the perf extra) and a
C compiler; it compiles the kernels with the JIT first, whose warm-ups call each kernel with every
argument type the product passes, then exports each of those signatures with ``numba.pycc``, for
this machine's CPU as the JIT compiles (the robot builds its own).
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.machinery
import json
import logging
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

import numpy as np

from robot.base import aot_kernels
from robot.base.kernel_cache import cache_lock
from robot.localization import fit_kernels

_SEP = "__"


def _arg_spec(t: Any) -> aot_kernels.ArgSpec:
    from numba.core import types

    if isinstance(t, types.Array):
        if t.layout not in ("C", "A"):  # the checks know C order or any strides, nothing else
            raise TypeError(f"argument type {t}: layout {t.layout} is not supported ahead of time")
        return ("array", str(np.dtype(str(t.dtype))), t.ndim, t.layout == "C", not t.mutable)
    if isinstance(t, types.Boolean):
        return ("bool",)
    if isinstance(t, types.Float):
        return ("float32",) if t.bitwidth == 32 else ("float64",)
    if isinstance(t, types.Integer):
        return ("int64",)
    raise TypeError(f"argument type {t} is not supported ahead of time")


def _forwarder(dispatcher: Any, n_args: int) -> Callable:
    """A Python function of ``n_args`` that calls the JIT ``dispatcher``: exported ahead of time,
    it compiles the dispatcher's own function with the dispatcher's own flags (fastmath, error
    model) into the module."""
    names = ", ".join(f"a{i}" for i in range(n_args))
    scope: Dict[str, Any] = {"kernel": dispatcher}
    exec(f"def forward({names}):\n    return kernel({names})\n", scope)  # noqa: S102 (our own names only)
    return scope["forward"]


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """distutils logs every compiler command line at INFO through the root logger: not for a user."""
    root = logging.getLogger()
    level = root.level
    root.setLevel(max(level, logging.WARNING))
    try:
        yield
    finally:
        root.setLevel(level)


def build(folder: Optional[Path] = None) -> Tuple[Path, float]:
    """Compile every kernel ahead of time into ``folder`` (default ``aot_kernels.kernel_dir()``).
    Returns the module's path and the seconds it took. Compiles the kernels with the JIT first
    (their warm-ups call each with every argument type the product passes), then exports each
    signature. Raises RuntimeError when numba is missing or a kernel does not compile."""
    t0 = time.perf_counter()
    try:
        import numba

        with warnings.catch_warnings():
            # numba.pycc is "pending deprecation" since numba 0.57 with no replacement yet: the
            # robot's numba (0.58.1, the last with Python 3.8 wheels for the Nano) has it.
            warnings.simplefilter("ignore")
            from numba.pycc import CC
    except ImportError as e:
        raise RuntimeError(f"building the kernels needs numba (the perf extra): {e}") from None
    folder = Path(folder) if folder is not None else aot_kernels.kernel_dir()
    folder.mkdir(parents=True, exist_ok=True)
    if fit_kernels.set_backend("numba") != "numba":
        raise RuntimeError("the numba kernels do not compile")
    meta: Dict[str, Any] = {"numba": numba.__version__, "python": sys.version.split()[0], "numpy": np.__version__,
                            "kernels": {}}
    name = aot_kernels.module_name()
    with _quiet():  # its compiler probe logs too
        cc = CC(name)
    cc.verbose = False
    cc.target_cpu = "host"  # as the JIT compiles: this CPU's instructions (the robot builds its own)
    for tag, mod_name in aot_kernels.KERNEL_MODULES:
        mod = importlib.import_module(mod_name)
        mod.warm_up()
        dispatchers = mod._nb  # noqa: SLF001 (the kernel modules' own table of compiled kernels)
        if not dispatchers:
            raise RuntimeError(f"{mod_name}: the kernels did not compile ({mod.backend_note()})")
        kernels: Dict[str, List] = {}
        for kernel, disp in dispatchers.items():
            if kernel == "version":
                continue
            if not hasattr(disp, "nopython_signatures"):  # this process already runs a built module
                raise RuntimeError(f"{mod_name}: its kernels are not numba's here (build in a fresh process)")
            for k, sig in enumerate(disp.nopython_signatures):
                export = f"{tag}{_SEP}{kernel.strip('_')}{_SEP}{k}"
                cc.export(export, sig)(_forwarder(disp, len(sig.args)))
                kernels.setdefault(kernel, []).append([export, [list(_arg_spec(t)) for t in sig.args]])
        meta["kernels"][tag] = kernels
    with cache_lock(), tempfile.TemporaryDirectory(prefix=".kernels-build-", dir=str(folder)) as tmp, _quiet():
        cc.output_dir = tmp
        cc.compile()
        built = Path(tmp) / (name + importlib.machinery.EXTENSION_SUFFIXES[0])
        if not built.is_file():
            found = sorted(p.name for p in Path(tmp).iterdir())
            raise RuntimeError(f"numba.pycc wrote {found}, not {built.name}")
        target = aot_kernels.module_path(folder)
        # The description first, then the module: a process that sees the module sees its description.
        meta_tmp = Path(tmp) / "meta.json"
        meta_tmp.write_text(json.dumps(meta, indent=1))
        os.replace(str(meta_tmp), str(target.with_suffix(".json")))
        shutil.move(str(built), str(target))
    return target, time.perf_counter() - t0
