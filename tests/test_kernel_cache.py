"""The numba kernels compile (or load from numba's disk cache) only while holding the cache lock,
so two of our processes never write the same cache at once (numba can crash the reader of a
half-written cache: issues 4807 and 10128)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading

import pytest

from robot.base import kernel_cache
from robot.control import scan_kernels
from robot.localization import fit_kernels, integrity_kernels

fcntl = pytest.importorskip("fcntl", reason="the cache lock is an flock (Linux, the robot's OS)")

PROBE = textwrap.dedent("""
    import fcntl, os, sys
    fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        print("held")
    else:
        print("free")
""")


def held_by_another_process(path) -> bool:
    """Whether another process finds the lock taken (flock is per open file, so a process of its
    own is the honest probe)."""
    out = subprocess.run([sys.executable, "-c", PROBE, str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip() == "held"


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba-cache"))
    return tmp_path / "numba-cache"


def test_the_lock_lives_in_numba_cache_dir_and_excludes_other_processes(cache_dir):
    assert kernel_cache.lock_path() == cache_dir / kernel_cache.LOCK_NAME
    assert not held_by_another_process(cache_dir / kernel_cache.LOCK_NAME)
    with kernel_cache.cache_lock() as path:
        assert path == cache_dir / kernel_cache.LOCK_NAME
        assert held_by_another_process(path)
    assert not held_by_another_process(path)


def test_without_a_writable_place_there_is_no_lock_and_no_error(monkeypatch, tmp_path):
    monkeypatch.setattr(kernel_cache, "lock_path", lambda: tmp_path / "missing" / "dir" / "x.lock")
    with kernel_cache.cache_lock() as path:
        assert path is None


@pytest.mark.parametrize("module", ["fit", "integrity", "scan"])
def test_each_kernel_set_compiles_only_under_the_lock(module, cache_dir, monkeypatch):
    pytest.importorskip("numba", reason="the compiled kernels are the perf extra (numba)")
    seen = []
    if module == "fit":
        # A fresh process: the backend not chosen yet and nothing compiled; the first backend()
        # call compiles, before it answers numba (so no thread compiles outside the lock).
        monkeypatch.setattr(fit_kernels, "_backend", None)
        monkeypatch.setattr(fit_kernels, "_compiled", False)
        monkeypatch.setattr(fit_kernels, "_warmed", False)
        real = fit_kernels._run_each_kernel
        monkeypatch.setattr(fit_kernels, "_run_each_kernel",
                            lambda: (seen.append(held_by_another_process(kernel_cache.lock_path())), real())[1])
        assert fit_kernels.set_backend("numba") == "numba"
        assert seen == [True]
        # Once run under the lock in this process, a warm-up (each app start) neither runs them
        # again nor waits for the lock: another process may hold it for minutes (kernels build).
        with kernel_cache.cache_lock():  # (flock: a second open file of this process is another holder)
            done = threading.Event()
            threading.Thread(target=lambda: (fit_kernels.warm_up(), done.set()), daemon=True).start()
            assert done.wait(60), "warm_up waited for the cache lock with the kernels already run"
        assert seen == [True]
        return
    fit_kernels.set_backend("numba")
    mod = integrity_kernels if module == "integrity" else scan_kernels
    monkeypatch.setattr(mod, "_nb", {})
    real = mod._run_each_kernel

    def spy(*args):
        seen.append(held_by_another_process(kernel_cache.lock_path()))
        return real(*args)

    monkeypatch.setattr(mod, "_run_each_kernel", spy)
    mod.warm_up()
    assert seen == [True]
    assert mod._nb
