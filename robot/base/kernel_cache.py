"""One process at a time compiles our numba kernels into their on-disk cache, or loads them from it.

numba keeps a compiled kernel as an index file and a data file beside each other. Two processes
that compile the same kernels at the same moment can leave one of them loading the other's
half-written pair, and that one dies of a segmentation fault, not an exception (numba issues
4807 and 10128, open). On the robot that is the service starting after an upgrade while an
engineer runs ``robotctl localize``, or two ``robotctl`` commands at once: both compile into the
service's cache directory. An exclusive ``flock`` on a file in the cache directory makes the
second wait while the first compiles; it then loads what the first wrote.

The lock is advisory and only between our own processes; where no lock file can be made (a
read-only tree, no ``fcntl`` on the platform) the kernels compile without it, as numba would.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, Optional, Sequence

try:
    import fcntl
except ImportError:  # not on Linux: no lock (the robot runs Linux)
    fcntl = None  # type: ignore[assignment]

LOCK_NAME = "robot-kernels.lock"


def lock_path() -> Optional[Path]:
    """Where the lock file goes: in ``NUMBA_CACHE_DIR`` when it is set (the service sets it to its
    state directory), else beside the package's own ``__pycache__`` folders (numba's default
    cache), else in the temporary directory. None when none of them can be written."""
    env = os.environ.get("NUMBA_CACHE_DIR", "").strip()
    candidates = [Path(env)] if env else []
    candidates += [Path(__file__).resolve().parents[1] / "__pycache__", Path(tempfile.gettempdir())]
    for folder in candidates:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(folder, os.W_OK):
            return folder / LOCK_NAME
    return None


@contextlib.contextmanager
def cache_lock() -> Iterator[Optional[Path]]:
    """Hold the kernels' cache lock (blocking until no other of our processes holds it). Yields
    the lock file's path, or None when there is no lock to take."""
    path = lock_path() if fcntl is not None else None
    fd = -1
    if path is not None:
        try:
            fd = os.open(str(path), os.O_RDWR | os.O_CREAT, 0o666)
        except OSError:
            fd, path = -1, None
    try:
        if fd >= 0:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield path
    finally:
        if fd >= 0:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def jit_table(numba: Any, namespace: Dict[str, Any], names: Sequence[str], **flags: Any) -> Dict[str, Any]:
    """numba dispatchers of the functions ``names`` in ``namespace`` (a kernel module's globals),
    released from the GIL, fastmath off, cached on disk (beside the lock above), plus ``flags``;
    and "version". Without a writable cache location they compile at every start rather than fail."""
    out: Dict[str, Any] = {"version": numba.__version__}
    for name in names:
        try:
            out[name] = numba.njit(cache=True, nogil=True, fastmath=False, **flags)(namespace[name])
        except RuntimeError:
            out[name] = numba.njit(cache=False, nogil=True, fastmath=False, **flags)(namespace[name])
    return out


def compile_kernel_set(table: Dict[str, Any], load: Callable[[], Dict[str, Any]],
                       run_each: Callable[[Dict[str, Any]], None], what: str, strict: bool) -> str:
    """Fill ``table`` (a kernel module's own) with its compiled kernels: ``load()``'s dispatchers
    (or their ahead-of-time build), each run once by ``run_each`` under the cache lock, so that
    they compile or load from the cache there and nowhere else. Returns "", or why ``what`` did
    not compile (``table`` is then left empty: the module runs its numpy code); ``strict`` (the
    operator asked for numba): raises instead."""
    try:
        kernels = load()
        with cache_lock():  # no other process of ours writes numba's cache meanwhile
            run_each(kernels)
        table.update(kernels)
        return ""
    except Exception as e:
        table.clear()
        if strict:
            raise
        return f"{what} did not compile: {type(e).__name__}: {e}".split("\n")[0]
