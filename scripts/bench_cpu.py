"""CPU budget for the Jetson Nano: where the controller's CPU goes, against what it could cost.

    python scripts/bench_cpu.py [--quick]                  # the Markdown section (also via scripts/benchmark.py)
    python scripts/bench_cpu.py --worker NAME [--quick]    # one part as JSON (run under another Python)

Every figure is CPU time of a thread (``time.thread_time`` inside the threads this script owns,
/proc/self/task/<tid> for the app's threads), never wall clock, and a median over repetitions
that alternate between the variants compared (A B A B ...): the machine is shared, and a burst
of someone else's load then hits both variants alike instead of one. The machine-factor line
times a fixed numpy and a fixed pure-Python workload in the same run, so figures taken on
different machines (and the Nano) can be compared.

Parts:

- the localizer per step (ROI prediction, hypothesis search, refit, covariance, pose solve),
  timed by wrapping its functions from outside; on this Python and, where a ``.venv38`` exists,
  on Python 3.8 (the Nano's);
- the floor: a minimal numpy routine and a compiled kernel (numba, the ``perf`` extra) doing
  the per-wall work on the same walls, and the localizer's ratio to each;
- the anchors (the ``bench`` extra, never on the robot): small_gicp GICP and Open3D
  point-to-plane ICP against a cloud sampled from the map, on the same frames;
- the whole controller in real time on the simulator (the app on the pty board emulator and
  fake cameras whose threads are left out by name), CPU per thread, peak RSS, allocations;
- what importing the controller loads.
"""

from __future__ import annotations

import os

# Small matrices on one core: multi-threaded BLAS and OpenMP only add contention (on the Nano, stalls).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import asyncio  # noqa: E402
import cProfile  # noqa: E402
import functools  # noqa: E402
import glob  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robot.base.geometry import pose_to_T_ground_robot, wrap_angle  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.localization.localizer import FIX_STATUSES, Localizer, coarse_covariance  # noqa: E402
from robot.maps.plane_map import PlaneMap, load_plane_map  # noqa: E402

JSON_TAG = "BENCH_CPU_JSON "
# The factor line divides by these, so a run on another machine (or a busy one) says how much
# slower or faster it is (the Nano: expect 5 to 8).
# Best of 40 on the project's development machine (Intel Xeon, 2 cores, Python 3.11.7, numpy
# 1.26.4): the figure of an unloaded core, so a busy run shows up as a factor above 1.
REFERENCE = {"numpy_ms": 6.4, "python_ms": 19.9, "machine": "Intel Xeon, 2 cores, Python 3.11.7, numpy 1.26.4"}
NANO_FACTORS = (5.0, 8.0)
# Poses in the paper arena from which both cameras see at least two walls.
POSES = [(0.5, 0.5, 0.3), (0.35, 0.7, 2.6), (0.2, 0.9, -0.8), (0.9, 0.3, 2.4), (0.7, 0.6, -2.0), (0.3, 0.2, 1.2)]
TRACKING = ("tracking: 1 cm / 0.5 deg off", (0.007, -0.007, 0.008), (0.02, math.radians(1.0)))
COLD = ("cold: 0.1 m / 10 deg off", (0.07, -0.07, math.radians(10.0)), None)
PY38_GLOB = "/root/.pyenv/versions/3.8*/bin/python3.8"


# -- CPU clocks ------------------------------------------------------------------------------------

def thread_cpu() -> Dict[int, float]:
    """CPU seconds per native thread id of this process: schedstat's nanoseconds where the kernel
    has them, else stat's user + system clock ticks (10 ms)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: Dict[int, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/schedstat") as f:
                out[int(tid)] = int(f.read().split()[0]) * 1e-9
            continue
        except (OSError, IndexError, ValueError):
            pass
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            out[int(tid)] = (int(fields[11]) + int(fields[12])) / tick
        except (OSError, IndexError, ValueError):
            continue
    return out


def thread_names() -> Dict[int, str]:
    """Python's names of this process's threads, and the kernel's for the others."""
    names = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                names[int(tid)] = f.read().strip()
        except OSError:
            continue
    for t in threading.enumerate():
        if t.native_id is not None:
            names[t.native_id] = t.name
    return names


def cpu_of(fn: Callable[..., Any], *args: Any) -> Tuple[float, Any]:
    """(CPU seconds of this thread, result) of one call."""
    c0 = time.thread_time()
    r = fn(*args)
    return time.thread_time() - c0, r


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def median(xs: Sequence[float]) -> float:
    return float(np.median(xs)) if len(xs) else float("nan")


def p95(xs: Sequence[float]) -> float:
    return float(np.percentile(xs, 95)) if len(xs) else float("nan")


def vm_status(field: str) -> float:
    """A /proc/self/status field in MiB (VmRSS, VmHWM)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    if field == "VmHWM":
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return float("nan")


# -- machine factor --------------------------------------------------------------------------------

def _numpy_workload() -> float:
    """Fixed: what a localization does in numpy, bulk arrays and many small calls."""
    rng = np.random.default_rng(0)
    a = rng.random(20000)
    idx = rng.integers(0, 20000, 5000)
    acc = 0.0
    for _ in range(20):
        b = a * 1.0001 + 0.5
        m = b > 0.9
        acc += float(np.sqrt(b[m]).sum()) + float(b[idx] @ a[idx])
    H = np.eye(3) * 2.0 + 0.1
    g = np.ones(3)
    for _ in range(400):
        acc += float(np.linalg.solve(H, g)[0]) + float(np.abs(g).max())
    return acc


def _python_workload() -> float:
    """Fixed pure Python: attribute access, calls, floats, dicts and lists."""
    acc = 0.0
    d: Dict[int, float] = {}
    for i in range(60000):
        x = math.sqrt(i + 1.0) * 0.5
        d[i & 255] = d.get(i & 255, 0.0) + x
        if x > 10.0:
            acc += min(x, 50.0)
    return acc + sum(d.values()) + len([k for k in d if k % 3 == 0])


def machine_factor(reps: int) -> Dict[str, float]:
    nps, pys = [], []
    for _ in range(reps):
        nps.append(cpu_of(_numpy_workload)[0] * 1e3)
        pys.append(cpu_of(_python_workload)[0] * 1e3)
    npm, pym = median(nps), median(pys)
    return {"numpy_ms": npm, "python_ms": pym, "numpy_factor": npm / REFERENCE["numpy_ms"],
            "python_factor": pym / REFERENCE["python_ms"],
            "factor": math.sqrt(npm / REFERENCE["numpy_ms"] * pym / REFERENCE["python_ms"])}


def machine_line(m: Dict[str, float]) -> str:
    return (f"MACHINE-FACTOR: numpy workload {m['numpy_ms']:.2f} ms, pure-Python workload {m['python_ms']:.2f} ms "
            f"CPU (reference machine, {REFERENCE['machine']}: {REFERENCE['numpy_ms']:.1f} and "
            f"{REFERENCE['python_ms']:.1f} ms); this machine is x{m['numpy_factor']:.2f} (numpy) and "
            f"x{m['python_factor']:.2f} (Python) the reference's time.")


def speed_line(m: Dict[str, float]) -> str:
    """A Python 3.8 table's note: its Nano row scales by ``m``, this process's machine factor timed
    just before the 3.8 subprocess. The reference's workloads ran under Python 3.11, and the
    subprocess's own pure-Python workload also holds 3.8's slower interpreter (about 1.6 times
    3.11's on the same machine), which the Nano, running 3.8, does pay."""
    return (f"Nano estimates below scale by this machine's speed as Python {platform.python_version()} "
            f"measured it just before (x{m['numpy_factor']:.2f} numpy, x{m['python_factor']:.2f} Python), not by "
            "this interpreter's own factor, which holds its slower interpreter too.")


def nano(ms: float, m: Dict[str, float]) -> str:
    """A figure measured here as the Nano's, at factors 5 and 8 over the reference machine."""
    base = ms / max(m["factor"], 1e-9)
    return " / ".join(f"{base * k:.1f}" for k in NANO_FACTORS)


# -- scenes ----------------------------------------------------------------------------------------

_CACHE: Dict[str, Any] = {}


def robot_and_map():
    if "robot" not in _CACHE:
        _CACHE["robot"] = load_robot_config(ROOT / "config/robot.yaml")
        _CACHE["map"] = load_plane_map(ROOT / "config/maps/paper_arena.yaml")
    return _CACHE["robot"], _CACHE["map"]


def frame_sets(n: int) -> List[Tuple[Tuple[float, float, float], list]]:
    """(true pose, [front, rear] 848x480 frames with realistic D435i noise) for the first n poses."""
    from drivers.sim.render import SimScene, render_depth_frame

    robot, arena = robot_and_map()
    key = f"frames{n}"
    if key not in _CACHE:
        scene = SimScene(arena)
        rng = np.random.default_rng(41)
        _CACHE[key] = [(p, [render_depth_frame(robot, scene, c.name, p, rng=rng) for c in robot.cameras])
                       for p in POSES[:n]]
    return _CACHE[key]


def coarse_for(truth, case) -> Tuple[Tuple[float, float, float], Optional[np.ndarray]]:
    _, off, std = case
    coarse = (truth[0] + off[0], truth[1] + off[1], truth[2] + off[2])
    return coarse, (None if std is None else coarse_covariance(std[0], std[1]))


# -- localizer per step ----------------------------------------------------------------------------

# (module, attribute, step): each wrapped callable's CPU minus that of wrapped callables inside
# it is booked to its step. A hook whose attribute is gone (the localizer was changed) is
# reported and its time stays with the step that calls it.
HOOKS = [
    ("robot.localization.localizer", "Localizer.localize", "request checks and pass loop"),
    ("robot.localization.localizer", "Localizer._fit_frame", "gather ROI depth and rays, per-wall bookkeeping"),
    ("robot.localization.localizer", "Localizer.plane_rois", "ROI prediction (visibility, raster, erosion)"),
    ("robot.localization.localizer", "Localizer._fit_params", "gather ROI depth and rays, per-wall bookkeeping"),
    ("robot.localization.localizer", "fit_plane", "fit: subsample, gates, verdicts"),
    ("robot.localization.plane_fit", "identify", "hypothesis search (surfaces, scores, refinement)"),
    ("robot.localization.fit_kernels", "one_surface", "hypothesis search (surfaces, scores, refinement)"),
    ("robot.localization.plane_fit", "_solve_step", "refit, covariance, inlier summary"),
    ("robot.localization.fit_kernels", "fit_tail", "refit, covariance, inlier summary"),
    ("robot.localization.plane_fit", "_tail", "refit, covariance, inlier summary"),
    ("robot.localization.localizer", "Localizer._rival_plane", "rival-wall check"),
    ("robot.localization.localizer", "Localizer._observation", "measurement error model"),
    ("robot.localization.localizer", "Localizer._solve", "pose solve and integrity checks"),
    ("robot.localization.localizer", "Localizer._weigh_evidence", "pose solve and integrity checks"),
    ("robot.localization.localizer", "Localizer._result", "result, protection levels, report"),
]
# Calls made from inside these steps stay with them: the hypothesis search refines its surfaces
# with the same least-squares step as the refit.
INHERIT = {"refit, covariance, inlier summary": {"hypothesis search (surfaces, scores, refinement)"}}
STEP_ORDER = []
for _h in HOOKS:
    if _h[2] not in STEP_ORDER:
        STEP_ORDER.append(_h[2])


class StepProfiler:
    """Exclusive CPU time per step of wrapped callables, on the calling thread."""

    def __init__(self) -> None:
        self.totals: Dict[str, float] = {}
        self._stack: List[List[Any]] = []
        self.missing: List[str] = []
        self._saved: List[Tuple[Any, str, Any]] = []

    def reset(self) -> None:
        self.totals = {}

    def _wrap(self, fn: Callable, step: str) -> Callable:
        prof = self
        inherit = INHERIT.get(step, set())

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            stack = prof._stack
            if inherit and stack and stack[-1][0] in inherit:
                return fn(*args, **kwargs)
            t0 = time.thread_time()
            stack.append([step, 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.thread_time() - t0
                _, inner = stack.pop()
                prof.totals[step] = prof.totals.get(step, 0.0) + dt - inner
                if stack:
                    stack[-1][1] += dt

        return wrapper

    @contextmanager
    def installed(self) -> Iterator[StepProfiler]:
        import importlib

        self.missing = []
        try:
            for mod_name, attr, step in HOOKS:
                owner: Any = importlib.import_module(mod_name)
                parts = attr.split(".")
                for p in parts[:-1]:
                    owner = getattr(owner, p, None)
                fn = getattr(owner, parts[-1], None) if owner is not None else None
                if fn is None or not callable(fn):
                    self.missing.append(f"{mod_name}.{attr}")
                    continue
                own = owner.__dict__.get(parts[-1]) if isinstance(owner, type) else fn
                wrapped = self._wrap(fn, step)
                setattr(owner, parts[-1], staticmethod(wrapped) if isinstance(own, staticmethod) else wrapped)
                self._saved.append((owner, parts[-1], own))
            yield self
        finally:
            while self._saved:
                owner, name, orig = self._saved.pop()
                if orig is None:  # inherited: drop the wrapper and the base's shows through again
                    delattr(owner, name)
                else:
                    setattr(owner, name, orig)


def localizer_steps(quick: bool) -> Dict[str, Any]:
    """Per-step CPU of the localizer, plain and hooked runs interleaved, plus a cProfile top list
    and the per-call cost that no point count reduces."""
    from robot.localization import fit_kernels

    kernels = kernel_load_times(fresh=not quick)  # first: compiling must not find numba's cache warm
    robot, arena = robot_and_map()
    sets = frame_sets(2 if quick else 6)
    reps = 4 if quick else 25
    loc = Localizer(robot, arena)
    compiled = fit_kernels.backend() == "numba"
    prof = StepProfiler()
    cases = [(n, case) for n in (1, 2) for case in (TRACKING, COLD)]
    plain: Dict[int, List[float]] = {i: [] for i in range(len(cases))}
    fallback: Dict[int, List[float]] = {i: [] for i in range(len(cases))}  # the numpy code, when numba runs
    hooked: Dict[int, List[float]] = {i: [] for i in range(len(cases))}
    steps: Dict[int, Dict[str, List[float]]] = {i: {} for i in range(len(cases))}
    passes: Dict[int, List[int]] = {i: [] for i in range(len(cases))}
    ok: Dict[int, List[bool]] = {i: [] for i in range(len(cases))}
    first: List[float] = []
    for truth, frames in sets:  # warm-up: caches of the localizer and numpy's first calls
        for n, case in cases:
            loc.localize(frames[:n], *coarse_for(truth, case))
    for _ in range(reps):
        for i, (n, case) in enumerate(cases):
            for truth, frames in sets:
                coarse, cov = coarse_for(truth, case)
                dt, res = cpu_of(loc.localize, frames[:n], coarse, cov)
                plain[i].append(dt * 1e3)
                if compiled:
                    fit_kernels.set_backend("numpy")
                    fallback[i].append(cpu_of(loc.localize, frames[:n], coarse, cov)[0] * 1e3)
                    fit_kernels.set_backend("numba")
                passes[i].append(res.passes)
                ok[i].append(res.status in FIX_STATUSES)
                with prof.installed():
                    prof.reset()
                    dt, _ = cpu_of(loc.localize, frames[:n], coarse, cov)
                hooked[i].append(dt * 1e3)
                for s in STEP_ORDER:
                    steps[i].setdefault(s, []).append(prof.totals.get(s, 0.0) * 1e3)
        truth, frames = sets[0]
        fresh = Localizer(robot, arena)
        first.append(cpu_of(fresh.localize, frames, *coarse_for(truth, TRACKING))[0] * 1e3)
    out_cases = []
    for i, (n, case) in enumerate(cases):
        out_cases.append({"frames": n, "case": case[0], "ms": median(plain[i]), "p95": p95(plain[i]),
                          "numpy_ms": median(fallback[i]) if fallback[i] else None,
                          "hooked_ms": median(hooked[i]), "passes": float(np.mean(passes[i])),
                          "ok": f"{sum(ok[i])}/{len(ok[i])}",
                          "steps": {s: median(v) for s, v in steps[i].items()}})
    return {"cases": out_cases, "missing_hooks": prof.missing, "first_call_ms": median(first), "kernels": kernels,
            "profile": profile_top(loc, sets, 3 if quick else 10), "scaling": point_scaling(sets, reps),
            "paced": paced(loc, sets, 2 if quick else 8)}


PACED_GAPS_S = (0.0, 1.0 / 30.0, 0.1)  # back to back; one frame period at 30 Hz; at 10 Hz


def paced(loc: Localizer, sets, reps: int) -> Dict[str, Any]:
    """The same call back to back and after the thread slept a camera period (2 frames, tracking).

    The step table times calls back to back, with the localizer's code and data still in the
    caches; on the robot a call comes once per frame, after the thread has waited for it. On a
    shared machine what ran meanwhile (other threads, other guests of the host) leaves the caches
    and predictors cold, and the same call costs more CPU: the real-time windows below pay that.
    Gaps alternate within each repetition; 'back to back' is the second of two identical calls."""
    ts: Dict[float, List[float]] = {g: [] for g in PACED_GAPS_S}
    for _ in range(reps):
        for gap in PACED_GAPS_S:
            for truth, frames in sets:
                coarse, cov = coarse_for(truth, TRACKING)
                if gap > 0.0:
                    time.sleep(gap)
                else:
                    loc.localize(frames, coarse, cov)
                ts[gap].append(cpu_of(loc.localize, frames, coarse, cov)[0] * 1e3)
    return {"gaps_s": list(PACED_GAPS_S), "ms": [median(ts[g]) for g in PACED_GAPS_S],
            "p95": [p95(ts[g]) for g in PACED_GAPS_S], "n": reps * len(sets)}


def kernel_load_times(fresh: bool = True) -> Dict[str, Any]:
    """The plane fit's backend, and what loading its kernels costs: compiling them into an empty
    cache (a first start) and loading them from it (every later start, in a fresh process).

    ``fresh=False`` (quick mode) leaves numba's own cache as it is and reports no compile time:
    under Python 3.8 and numba 0.58 a compile into an empty cache is about two minutes of CPU,
    most of the quick run, and the smoke test of this script does not need it."""
    import atexit
    import shutil
    import tempfile

    from robot.localization import fit_kernels

    if fresh:
        cache = tempfile.mkdtemp(prefix="bench-numba-")
        # The process keeps loading its kernels from this cache until it ends; then it goes.
        atexit.register(shutil.rmtree, cache, True)
        os.environ["NUMBA_CACHE_DIR"] = cache  # before numba is imported (by backend())
    t0 = time.perf_counter()
    out: Dict[str, Any] = {"backend": fit_kernels.backend(), "note": fit_kernels.backend_note()}
    first = time.perf_counter() - t0  # with numba, the first backend() call compiles the kernels
    if out["backend"] != "numba":
        return out
    import numba

    from robot.control import scan_kernels
    from robot.localization import integrity_kernels

    out["numba"] = numba.__version__
    loads = (first + fit_kernels.warm_up(), integrity_kernels.warm_up(), scan_kernels.warm_up())
    if fresh:
        out["compile_s"], out["integrity_compile_s"], out["scan_compile_s"] = loads
    probe = ("import time; t0 = time.perf_counter(); from robot.localization import fit_kernels, integrity_kernels; "
             "from robot.control import scan_kernels; "
             "s = fit_kernels.warm_up() + integrity_kernels.warm_up() + scan_kernels.warm_up(); "
             "print(time.perf_counter() - t0, s)")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=300)
    if p.returncode == 0 and p.stdout.split():
        out["cached_total_s"], out["cached_s"] = (float(v) for v in p.stdout.split()[-2:])
    return out


def profile_top(loc: Localizer, sets, reps: int, top: int = 12) -> Dict[str, Any]:
    """cProfile on this thread's CPU clock: two frames, tracking. Per localization."""
    pr = cProfile.Profile(time.thread_time)
    calls = 0
    pr.enable()
    for _ in range(reps):
        for truth, frames in sets:
            loc.localize(frames, *coarse_for(truth, TRACKING))
            calls += 1
    pr.disable()
    st = pstats.Stats(pr)
    rows = []
    for (fname, line, func), (_cc, nc, tt, ct, _) in st.stats.items():  # type: ignore[attr-defined]
        rows.append((tt, ct, nc, f"{Path(fname).name}:{line} {func}" if line else func))
    rows.sort(reverse=True)
    total = sum(r[0] for r in rows)
    return {"total_ms": total / calls * 1e3,
            "rows": [{"where": w, "calls": nc / calls, "tottime_ms": tt / calls * 1e3, "cumtime_ms": ct / calls * 1e3}
                     for tt, ct, nc, w in rows[:top]]}


def point_scaling(sets, reps: int) -> Dict[str, Any]:
    """CPU against the number of ROI points, by pixel stride (two frames, tracking): the intercept
    is the per-call cost that sampling fewer points does not reduce."""
    robot, arena = robot_and_map()
    strides = (4, 8, 16)
    locs = {s: Localizer(robot, arena, replace(robot.localizer, pixel_stride=s)) for s in strides}
    ts: Dict[int, List[float]] = {s: [] for s in strides}
    pts: Dict[int, List[int]] = {s: [] for s in strides}
    for truth, frames in sets:
        for s in strides:
            locs[s].localize(frames, *coarse_for(truth, TRACKING))
    for _ in range(reps):
        for s in strides:  # interleaved: s1 s2 s3 s1 s2 s3 ...
            for truth, frames in sets:
                dt, res = cpu_of(locs[s].localize, frames, *coarse_for(truth, TRACKING))
                ts[s].append(dt * 1e3)
                pts[s].append(sum(p.roi_points for p in res.planes))
    x = np.array([median(pts[s]) for s in strides], float)
    y = np.array([median(ts[s]) for s in strides], float)
    b, a = np.polyfit(x, y, 1)
    return {"strides": list(strides), "points": x.tolist(), "ms": y.tolist(), "fixed_ms": float(a),
            "per_1000_points_ms": float(b * 1e3), "fixed_share_default": float(a / y[0]) if y[0] > 0 else float("nan")}


# -- the floor -------------------------------------------------------------------------------------

def _walls(loc: Localizer, frames, pose, cov) -> List[Dict[str, Any]]:
    """The walls the localizer would fit from ``pose``: its own ROIs, gates and geometry."""
    robot = loc.robot
    p = loc.params
    out = []
    for frame in frames:
        cam = robot.camera(frame.camera)
        h, w = frame.depth.shape
        geo = loc.frame_geometry(cam, frame.K, w, h)
        T_ground_camera = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
        full_px = (geo.grid.stride / geo.scale) ** 2
        std_n = math.sqrt(max(cov[0, 0], cov[1, 1]))
        gate = p.offset_gate + 3.0 * std_n + 0.6 * math.sqrt(cov[2, 2])
        for view in loc.plane_rois(geo, T_ground_camera, cov):
            if view.roi_rows is None or len(view.roi_rows) * full_px < p.min_roi_pixels:
                continue
            plane = loc.map.planes[view.plane_index]
            out.append({"depth": frame.depth, "scale": float(frame.depth_scale), "rr": view.roi_rows.astype(np.int64),
                        "cc": view.roi_cols.astype(np.int64), "stride": int(geo.grid.stride),
                        "ray_cols": np.asarray(geo.ray_cols, float), "ray_rows": np.asarray(geo.ray_rows, float),
                        "pi": np.asarray(view.pi_camera, float), "gate": gate, "T_rc": cam.T_robot_camera,
                        "n_G": plane.normal, "d_G": plane.d, "zmin": p.min_range, "zmax": p.max_range})
    return out


def _inverse_depth_noise(loc: Localizer) -> float:
    # The stereo matcher's 0.08 px on f_x b: inverse depth has the same noise at every pixel.
    K = loc.robot.cameras[0].intrinsics_from_fov()
    return 0.08 / (float(K[0, 0]) * 0.050)


def floor_wall_numpy(w: Dict[str, Any], c: float) -> Tuple[np.ndarray, np.ndarray]:
    """Gather the ROI's depth, keep points within the prior's offset gate of the predicted plane,
    fit 1/z = q . (x/z, y/z, 1) by least squares, refit inside a 3-sigma band, covariance."""
    s = w["stride"]
    z = w["depth"][w["rr"] * s, w["cc"] * s] * w["scale"]
    ok = (z > w["zmin"]) & (z < w["zmax"])
    z = z[ok]
    rx = w["ray_cols"][w["cc"][ok]]
    ry = w["ray_rows"][w["rr"][ok]]
    n, d = w["pi"][:3], w["pi"][3]
    m = np.abs((n[0] * rx + n[1] * ry + n[2]) * z + d) < w["gate"]
    y = 1.0 / z
    q = np.zeros(3)
    H = np.eye(3)
    for _ in range(2):
        ax, ay, ay1 = rx[m], ry[m], y[m]
        H = np.array([[ax @ ax, ax @ ay, ax.sum()], [ax @ ay, ay @ ay, ay.sum()], [ax.sum(), ay.sum(), float(m.sum())]])
        g = np.array([ax @ ay1, ay @ ay1, ay1.sum()])
        q = np.linalg.solve(H, g)
        m = np.abs(y - (q[0] * rx + q[1] * ry + q[2])) < 3.0 * c
    return q, np.linalg.inv(H) * (c * c)


def floor_pose(walls: List[Dict[str, Any]], qs: List[np.ndarray], pose) -> np.ndarray:
    """(x, y, phi) from the fitted walls: heading from the normals, position from the offsets
    (n_R = R^T n_G and d_R = n_G . t + d_G for a plane n . p + d = 0)."""
    dphi, A, b = [], [], []
    for w, q in zip(walls, qs):
        qn = math.sqrt(float(q @ q))
        n_c, d_c = -q / qn, 1.0 / qn
        R, t = w["T_rc"][:3, :3], w["T_rc"][:3, 3]
        n_r = R @ n_c
        d_r = d_c - float(n_r @ t)
        ng = w["n_G"]
        if abs(ng[2]) > 0.5:
            continue
        dphi.append(math.atan2(ng[1], ng[0]) - math.atan2(n_r[1], n_r[0]))
        A.append(ng[:2])
        b.append(d_r - w["d_G"])
    phi = pose[2] + float(np.mean([wrap_angle(v - pose[2]) for v in dphi]))
    xy = np.linalg.lstsq(np.array(A), np.array(b), rcond=None)[0]
    return np.array([xy[0], xy[1], phi])


def floor_numpy(walls, pose, c: float) -> np.ndarray:
    return floor_pose(walls, [floor_wall_numpy(w, c)[0] for w in walls], pose)


def numba_floor() -> Optional[Callable]:
    """The per-wall work as one compiled loop over the ROI pixels (None without numba)."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=False)
    def wall(depth, scale, rr, cc, stride, ray_cols, ray_rows, pi, gate, zmin, zmax, c, out):
        q0 = 0.0
        q1 = 0.0
        q2 = 0.0
        H = np.zeros((3, 3))
        for it in range(2):
            H[:, :] = 0.0
            g0 = 0.0
            g1 = 0.0
            g2 = 0.0
            for i in range(rr.shape[0]):
                z = depth[rr[i] * stride, cc[i] * stride] * scale
                if z <= zmin or z >= zmax:
                    continue
                rx = ray_cols[cc[i]]
                ry = ray_rows[rr[i]]
                y = 1.0 / z
                if it == 0:
                    if abs((pi[0] * rx + pi[1] * ry + pi[2]) * z + pi[3]) >= gate:
                        continue
                elif abs(y - (q0 * rx + q1 * ry + q2)) >= 3.0 * c:
                    continue
                H[0, 0] += rx * rx
                H[0, 1] += rx * ry
                H[0, 2] += rx
                H[1, 1] += ry * ry
                H[1, 2] += ry
                H[2, 2] += 1.0
                g0 += rx * y
                g1 += ry * y
                g2 += y
            H[1, 0] = H[0, 1]
            H[2, 0] = H[0, 2]
            H[2, 1] = H[1, 2]
            # 3x3 inverse by cofactors: no LAPACK call for a matrix this small
            a, b, e = H[0, 0], H[0, 1], H[0, 2]
            f, k, m = H[1, 1], H[1, 2], H[2, 2]
            c00 = f * m - k * k
            c01 = e * k - b * m
            c02 = b * k - e * f
            c11 = a * m - e * e
            c12 = b * e - a * k
            c22 = a * f - b * b
            det = a * c00 + b * c01 + e * c02
            if det == 0.0:
                return False
            q0 = (c00 * g0 + c01 * g1 + c02 * g2) / det
            q1 = (c01 * g0 + c11 * g1 + c12 * g2) / det
            q2 = (c02 * g0 + c12 * g1 + c22 * g2) / det
            s = c * c / det
            out[0], out[1], out[2] = q0, q1, q2
            out[3], out[4], out[5] = c00 * s, c01 * s, c02 * s
            out[6], out[7], out[8] = c11 * s, c12 * s, c22 * s
        return True

    def run(walls, pose, c: float) -> np.ndarray:
        buf = np.empty(9)
        qs = []
        for w in walls:
            wall(w["depth"], w["scale"], w["rr"], w["cc"], w["stride"], w["ray_cols"], w["ray_rows"], w["pi"],
                 w["gate"], w["zmin"], w["zmax"], c, buf)
            qs.append(buf[:3].copy())
        return floor_pose(walls, qs, pose)

    return run


def floor(quick: bool) -> Dict[str, Any]:
    """The localizer against a minimal numpy routine and a compiled kernel on the same walls
    (two frames, tracking), interleaved."""
    robot, arena = robot_and_map()
    sets = frame_sets(2 if quick else 6)
    reps = 5 if quick else 30
    loc = Localizer(robot, arena)
    c = _inverse_depth_noise(loc)
    prepared = []
    for truth, frames in sets:
        coarse, cov = coarse_for(truth, TRACKING)
        prepared.append((truth, frames, coarse, cov, _walls(loc, frames, coarse, cov)))
    t_compile = 0.0
    nb = numba_floor()
    if nb is not None:
        t_compile, _ = cpu_of(nb, prepared[0][4], prepared[0][2], c)
    variants: Dict[str, Callable] = {"localizer": lambda p: loc.localize(p[1], p[2], p[3]),
                                     "numpy floor": lambda p: floor_numpy(p[4], p[2], c)}
    if nb is not None:
        variants["numba floor"] = lambda p: nb(p[4], p[2], c)
    ts: Dict[str, List[float]] = {k: [] for k in variants}
    errs: Dict[str, List[float]] = {k: [] for k in variants}
    for p in prepared:
        for fn in variants.values():
            fn(p)
    for _ in range(reps):
        for name, fn in variants.items():
            for p in prepared:
                dt, r = cpu_of(fn, p)
                ts[name].append(dt * 1e3)
                x = np.array(r.pose) if name == "localizer" else r
                errs[name].append(1e3 * math.hypot(x[0] - p[0][0], x[1] - p[0][1]))
    roi_ms = []
    for _ in range(reps):
        for p in prepared:
            roi_ms.append(cpu_of(_walls, loc, p[1], p[2], p[3])[0] * 1e3)
    return {"ms": {k: median(v) for k, v in ts.items()}, "err_mm": {k: median(v) for k, v in errs.items()},
            "walls": float(np.mean([len(p[4]) for p in prepared])),
            "points": float(np.mean([sum(len(w["rr"]) for w in p[4]) for p in prepared])),
            "roi_ms": median(roi_ms), "numba_compile_s": t_compile, "numba": nb is not None}


# -- the anchors -----------------------------------------------------------------------------------

def map_cloud(arena: PlaneMap, spacing: float = 0.01) -> Tuple[np.ndarray, np.ndarray]:
    """Points on every polygon of the map on a ``spacing`` grid, and their normals."""
    pts, nrm = [], []
    for plane in arena.planes:
        n = plane.normal
        u = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
        u = u / np.linalg.norm(u)
        v = np.cross(n, u)
        for poly in plane.polygons:
            o = poly[0]
            uv = np.column_stack([(poly - o) @ u, (poly - o) @ v])
            gu = np.arange(uv[:, 0].min(), uv[:, 0].max() + 1e-9, spacing)
            gv = np.arange(uv[:, 1].min(), uv[:, 1].max() + 1e-9, spacing)
            U, V = np.meshgrid(gu, gv)
            U, V = U.ravel(), V.ravel()
            inside = np.zeros(len(U), bool)
            for (u0, v0), (u1, v1) in zip(uv, np.roll(uv, -1, axis=0)):  # crossing test
                cross = (v0 > V) != (v1 > V)
                with np.errstate(divide="ignore", invalid="ignore"):
                    at = u0 + (V - v0) * (u1 - u0) / (v1 - v0)
                inside ^= cross & (U < at)
            P = o + np.outer(U[inside], u) + np.outer(V[inside], v)
            pts.append(P)
            nrm.append(np.tile(n, (len(P), 1)))
    return np.vstack(pts), np.vstack(nrm)


def frame_cloud_robot(robot, frames, stride: int, z_band=(0.03, 0.27), max_range: float = 6.0) -> np.ndarray:
    """Every ``stride``-th pixel of the frames (the localizer's grid) in the robot frame, cropped
    to the height band of the walls (the floor and what shows above the walls are not in the map)."""
    out = []
    for f in frames:
        cam = robot.camera(f.camera)
        h, w = f.depth.shape
        z = f.depth[::stride, ::stride] * float(f.depth_scale)
        K = np.asarray(f.K, float)
        cols = (np.arange(0, w, stride) - K[0, 2]) / K[0, 0]
        rows = (np.arange(0, h, stride) - K[1, 2]) / K[1, 1]
        ok = (z > 0.2) & (z < max_range)
        rr, cc = np.nonzero(ok)
        zz = z[rr, cc]
        P = np.column_stack([cols[cc] * zz, rows[rr] * zz, zz])
        T = cam.T_robot_camera
        P = P @ T[:3, :3].T + T[:3, 3]
        out.append(P[(P[:, 2] > z_band[0]) & (P[:, 2] < z_band[1])])
    return np.vstack(out)


def _pose_of(T: np.ndarray) -> np.ndarray:
    return np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])


EVERY_PIXEL = "small_gicp GICP, every pixel (no voxel grid)"


def anchors(quick: bool) -> Dict[str, Any]:
    """small_gicp GICP and Open3D point-to-plane ICP against the map's cloud, and the localizer,
    from the same perturbed starts on the same frames. CPU of the whole process (the libraries
    may start helper threads; their thread count is pinned to 1)."""
    robot, arena = robot_and_map()
    sets = frame_sets(1 if quick else 3)
    starts = 4 if quick else 20
    res = 0.02  # m: voxel size of both clouds, and the spacing of the map's
    corr = 0.25  # m: largest correspondence distance (0.1 m and 10 deg at 1 m reach 0.2 m)
    stride = robot.localizer.pixel_stride
    tgt_pts, tgt_nrm = map_cloud(arena, 0.01)
    methods: Dict[str, Callable] = {}
    notes: Dict[str, str] = {}
    loc = Localizer(robot, arena)

    def ours(frames, init):
        return np.array(loc.localize(frames, tuple(_pose_of(init)), None).pose)

    methods["plane localizer (ours)"] = ours
    try:
        import small_gicp

        target, target_tree = small_gicp.preprocess_points(tgt_pts, downsampling_resolution=res, num_threads=1)

        def gicp(frames, init):
            src = frame_cloud_robot(robot, frames, stride)
            source, _ = small_gicp.preprocess_points(src, downsampling_resolution=res, num_threads=1)
            r = small_gicp.align(target, source, target_tree, init, registration_type="GICP",
                                 max_correspondence_distance=corr, num_threads=1, max_iterations=50)
            return _pose_of(np.asarray(r.T_target_source))

        def gicp_every_pixel(frames, init):
            # What a user who does not thin the cloud gets: every pixel, its own covariance from
            # its 20 neighbours. As accurate as the plane localizer here, at the cost the table shows.
            source = small_gicp.PointCloud(frame_cloud_robot(robot, frames, 1))
            small_gicp.estimate_covariances(source, num_neighbors=20, num_threads=1)
            r = small_gicp.align(target, source, target_tree, init, registration_type="GICP",
                                 max_correspondence_distance=corr, num_threads=1, max_iterations=50)
            return _pose_of(np.asarray(r.T_target_source))

        methods["small_gicp GICP"] = gicp
        methods[EVERY_PIXEL] = gicp_every_pixel
        notes["small_gicp GICP"] = f"small_gicp {getattr(small_gicp, '__version__', '')}".strip()
    except ImportError as e:
        notes["small_gicp GICP"] = f"not installed ({e}): pip install -e '.[bench]'"
    try:
        import open3d as o3d

        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        reg = o3d.pipelines.registration
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt_pts))
        tgt.normals = o3d.utility.Vector3dVector(tgt_nrm)
        tgt = tgt.voxel_down_sample(res)
        crit = reg.ICPConvergenceCriteria(max_iteration=50)
        est = reg.TransformationEstimationPointToPlane()

        def icp(frames, init):
            src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(frame_cloud_robot(robot, frames, stride)))
            src = src.voxel_down_sample(res)
            r = reg.registration_icp(src, tgt, corr, init, est, crit)
            return _pose_of(np.asarray(r.transformation))

        methods["Open3D point-to-plane ICP"] = icp
        notes["Open3D point-to-plane ICP"] = f"Open3D {o3d.__version__}"
    except ImportError as e:
        notes["Open3D point-to-plane ICP"] = f"not installed ({e}): pip install -e '.[bench]'"
    rng = np.random.default_rng(17)
    trials = []
    for truth, frames in sets:
        for _ in range(starts):
            a = rng.uniform(0, 2 * math.pi)
            dphi = math.radians(10.0) * (1 if rng.random() < 0.5 else -1)
            trials.append((truth, frames, pose_to_T_ground_robot(truth[0] + 0.1 * math.cos(a),
                                                                 truth[1] + 0.1 * math.sin(a), truth[2] + dphi)))
    for fn in methods.values():  # warm-up
        fn(trials[0][1], trials[0][2])
    out: Dict[str, Dict[str, Any]] = {k: {"ms": [], "pos": [], "head": []} for k in methods}
    for truth, frames, init in trials:  # interleaved: each start through every method in turn
        for name, fn in methods.items():
            c0 = time.process_time()
            x = fn(frames, init)
            out[name]["ms"].append((time.process_time() - c0) * 1e3)
            out[name]["pos"].append(1e3 * math.hypot(x[0] - truth[0], x[1] - truth[1]))
            out[name]["head"].append(abs(math.degrees(float(wrap_angle(x[2] - truth[2])))))
    summary = {}
    for name, r in out.items():
        pos, head = np.array(r["pos"]), np.array(r["head"])
        good = (pos < 10.0) & (head < 0.5)
        summary[name] = {"ms": median(r["ms"]), "pos_mm": median(pos), "pos_p95": p95(pos), "head_deg": median(head),
                         "success": f"{int(good.sum())}/{len(good)}", "n": len(good)}
    return {"methods": summary, "notes": notes, "trials": len(trials), "frames": len(sets),
            "source_points": int(len(frame_cloud_robot(robot, sets[0][1], stride))), "voxel": res, "corr": corr}


# -- the whole controller --------------------------------------------------------------------------

GROUPS = ("event loop (control, fusion, serial writes)", "localization worker", "serial reader",
          "other controller threads")


def group_of(tid: int, name: str, main_tid: int) -> Optional[str]:
    """The controller's thread group, or None for the simulator's own threads (left out)."""
    if tid == main_tid:
        return GROUPS[0]
    if name.startswith("camera-") or name.startswith("firmware-emulator"):
        return None
    if name.startswith("localize"):
        return GROUPS[1]
    if name.startswith("chassis-reader"):
        return GROUPS[2]
    return GROUPS[3]


def _malloc_trim() -> None:
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass  # not glibc: RSS keeps the freed heap, and the figure says a little more than the controller uses


@contextmanager
def _in_thread_cpu(targets: Sequence[Tuple[Any, str, str]]) -> Iterator[Dict[str, List[float]]]:
    """CPU seconds and calls of methods, timed with ``time.thread_time`` inside the thread that
    runs them (the app's localization worker): {label: [seconds, calls]}."""
    acc: Dict[str, List[float]] = {}
    saved = []
    for cls, name, label in targets:
        fn = cls.__dict__.get(name)
        if fn is None:
            continue
        acc[label] = [0.0, 0.0]

        def wrapper(*args, _fn=fn, _a=acc[label], **kwargs):
            c0 = time.thread_time()
            try:
                return _fn(*args, **kwargs)
            finally:
                _a[0] += time.thread_time() - c0
                _a[1] += 1

        saved.append((cls, name, fn))
        setattr(cls, name, functools.wraps(fn)(wrapper))
    try:
        yield acc
    finally:
        for cls, name, fn in saved:
            setattr(cls, name, fn)


START_GUARD_S = 420.0  # below the smoke test's own hang guard


def controller_window(fps: float, seconds: float, alloc_seconds: float = 0.0) -> Dict[str, Any]:
    """One run of the real app on the simulator: warm up until localizations flow, then a
    window of ``seconds`` measuring CPU per thread, then (optionally) a tracemalloc window."""
    with _in_thread_cpu(_worker_targets()) as inside:
        return _controller_window(fps, seconds, alloc_seconds, inside)


def _worker_targets() -> List[Tuple[Any, str, str]]:
    from robot.app.controller import RobotApp

    return [(Localizer, "localize", "localizer"), (RobotApp, "_scan_obstacles", "obstacle scan (protective stop)")]


def _controller_window(fps: float, seconds: float, alloc_seconds: float,
                       inside: Dict[str, List[float]]) -> Dict[str, Any]:
    from robot.app.controller import AppOptions
    from robot.sim.realtime import RealtimeSimSettings, sim_rig

    robot, arena = robot_and_map()
    pose = (0.5, 0.5, 0.3)
    settings = RealtimeSimSettings(fps=fps, decimation=1, frame_cache=8, radius_error_std=0.0, slip_noise=0.0)
    opts = AppOptions(install_signal_handlers=False, stop_when_done=False)
    r: Dict[str, Any] = {"fps": fps}
    with sim_rig(robot, arena, pose, settings, opts, initial_pose=pose) as rig:
        app = rig.app

        async def measure(task: asyncio.Future[int]) -> None:
            loop = asyncio.get_running_loop()
            # Waits for the event, not for a time: a first start compiles the kernels (tens of
            # seconds, minutes on a loaded machine). The guard is against a hang only.
            guard = loop.time() + START_GUARD_S
            while app.stats.localizations < 10 and loop.time() < guard and not task.done():
                await asyncio.sleep(0.05)
            if task.done():
                r["error"] = f"the controller stopped before localizing ({app.exit_reason or 'no reason given'})"
                return
            if app.stats.localizations < 10:
                r["error"] = f"no localizations within {START_GUARD_S:.0f} s of start"
                return
            # The peak RSS of the controller at work, not of start-up (the fake cameras render their
            # frames then): Linux resets VmHWM to the current RSS on "5" in clear_refs.
            _malloc_trim()  # what the renderer freed goes back to the OS first, or RSS keeps it
            try:
                with open("/proc/self/clear_refs", "w") as f:
                    f.write("5")
                r["hwm_reset"] = True
            except OSError:
                r["hwm_reset"] = False
            r["window_rss0"] = vm_status("VmRSS")
            cpu0, loc0, odo0, ticks0 = thread_cpu(), app.stats.localizations, app.stats.odometry, len(app.stats.tick_times)
            frames0 = sum(app.stats.frames.values())
            inside0 = {k: list(v) for k, v in inside.items()}
            t0 = loop.time()
            await asyncio.sleep(seconds)
            r["inside"] = {k: [v[0] - inside0[k][0], v[1] - inside0[k][1]] for k, v in inside.items()}
            cpu1, wall = thread_cpu(), loop.time() - t0
            r["window_hwm"] = vm_status("VmHWM")
            names = thread_names()
            main_tid = threading.main_thread().native_id
            groups = {g: 0.0 for g in GROUPS}
            left_out: Dict[str, float] = {}
            other: Dict[str, float] = {}
            for tid, c in cpu1.items():
                dc = c - cpu0.get(tid, 0.0)
                g = group_of(tid, names.get(tid, ""), main_tid)
                if g is None:
                    left_out[names.get(tid, str(tid))] = dc / wall
                else:
                    groups[g] += dc / wall
                    if g == GROUPS[3] and dc > 0:
                        other[names.get(tid, str(tid))] = dc / wall
            loc_n = app.stats.localizations - loc0
            r["frames_per_s"] = (sum(app.stats.frames.values()) - frames0) / wall
            r.update({"seconds": wall, "share": groups, "left_out": left_out, "other": other,
                      "localizations_per_s": loc_n / wall, "odometry_per_s": (app.stats.odometry - odo0) / wall,
                      "ticks_per_s": (len(app.stats.tick_times) - ticks0) / wall,
                      "localize_ms": median(app.stats.localize_ms[-loc_n:]) if loc_n else float("nan")})
            if alloc_seconds > 0:
                tracemalloc.start(1)
                await asyncio.sleep(0.5)
                snap0 = tracemalloc.take_snapshot()
                cur0 = tracemalloc.get_traced_memory()[0]
                if hasattr(tracemalloc, "reset_peak"):
                    tracemalloc.reset_peak()  # novermin (3.9+; on 3.8 the peak counts from start)
                la = app.stats.localizations
                await asyncio.sleep(alloc_seconds)
                snap1 = tracemalloc.take_snapshot()
                peak = tracemalloc.get_traced_memory()[1]
                la = max(app.stats.localizations - la, 1)
                # Still tracing: stopped only once the app and the rig have stopped their threads
                # (below). tracemalloc.stop() while another thread is inside PyTraceMalloc_Track
                # without the GIL (numpy's allocator calls it) frees the tables under it: a
                # segfault now and then (CPython issue 128679, fixed in 3.12.9 and 3.13.2, not in
                # 3.8 or 3.11).
                # The simulator's own allocations (board emulator, fake cameras) are not the controller's.
                flt = [tracemalloc.Filter(False, tracemalloc.__file__), tracemalloc.Filter(False, "*/drivers/sim/*"),
                       tracemalloc.Filter(False, "*/drivers/chassis/emulator.py"),
                       tracemalloc.Filter(False, "*/drivers/camera/sim.py")]
                diff = snap1.filter_traces(flt).compare_to(snap0.filter_traces(flt), "filename")
                grow = sorted(diff, key=lambda s: -s.count_diff)[:3]
                r["alloc"] = {"frames": la, "blocks_per_frame": sum(s.count_diff for s in diff) / la,
                              "bytes_per_frame": sum(s.size_diff for s in diff) / la,
                              "peak_above_mib": (peak - cur0) / 2**20,
                              "top": [(f"{Path(s.traceback[0].filename).name}", s.count_diff / la) for s in grow]}

        async def main() -> int:
            task = asyncio.ensure_future(app.run())
            try:
                await measure(task)
            finally:
                app.request_stop("benchmark done")
            return await task

        asyncio.run(main())
    if tracemalloc.is_tracing():
        tracemalloc.stop()  # (see the allocation window: only now is this the one thread at work)
    return r


def controller(quick: bool) -> Dict[str, Any]:
    """Windows at 2 x 30 Hz (A) and 2 x 10 Hz (B), alternating A B A B, each its own run; the
    two rates separate the per-frame from the fixed part of the cost (``cost_model``)."""
    import robot.app.controller  # noqa: F401  (imported before the RSS baseline)
    import robot.sim.realtime  # noqa: F401

    _malloc_trim()
    rss_start = vm_status("VmRSS")
    plan = [(30.0, 2.5), (10.0, 2.0)] if quick else [(30.0, 5.0), (10.0, 4.0)] * 4
    # The allocation window follows the first run's CPU window: tracemalloc slows what it traces.
    # Never beside numba's kernels: they allocate through Python's raw allocator (so that
    # tracemalloc sees it) from threads without the GIL, and tracemalloc's hook races the main
    # thread there (CPython issues 128679 and 143143): the Python 3.11 worker died of it, in the
    # obstacle scan's kernel while the main thread filtered a snapshot. The numpy run measures it.
    from robot.localization import fit_kernels

    alloc = (2.0 if quick else 8.0) if fit_kernels.backend() == "numpy" else 0.0
    runs = [controller_window(fps, secs, alloc if i == 0 else 0.0) for i, (fps, secs) in enumerate(plan)]
    errors = [r["error"] for r in runs if "error" in r]
    out: Dict[str, Any] = {"rss_start_mib": rss_start, "errors": errors, "alloc": runs[0].get("alloc"),
                           # The first run's: later runs in this process inherit what earlier rigs left.
                           "window_peak_rss_mib": runs[0].get("window_hwm", float("nan")),
                           "window_start_rss_mib": [r.get("window_rss0", float("nan")) for r in runs],
                           "window_hwm_mib": [r.get("window_hwm", float("nan")) for r in runs],
                           "hwm_reset": all(r.get("hwm_reset", False) for r in runs)}
    for fps in (30.0, 10.0):
        rs = [r for r in runs if r["fps"] == fps and "share" in r]
        if not rs:
            continue
        out[str(int(fps))] = {
            "seconds": sum(r["seconds"] for r in rs), "windows": len(rs),
            "share": {g: median([r["share"][g] for r in rs]) for g in GROUPS},
            "total": median([sum(r["share"].values()) for r in rs]),
            "left_out": {k: median([r["left_out"].get(k, 0.0) for r in rs]) for k in rs[0]["left_out"]},
            "other": {k: median([r["other"].get(k, 0.0) for r in rs]) for k in rs[0]["other"]},
            "localizations_per_s": median([r["localizations_per_s"] for r in rs]),
            "frames_per_s": median([r["frames_per_s"] for r in rs]),
            "odometry_per_s": median([r["odometry_per_s"] for r in rs]),
            "ticks_per_s": median([r["ticks_per_s"] for r in rs]),
            "localize_ms": median([r["localize_ms"] for r in rs])}
    out["model"] = cost_model([r for r in runs if "share" in r])
    out["peak_rss_mib"] = vm_status("VmHWM")
    return out


ODOMETRY_HZ = 100.0  # the board's encoder reports (firmware_protocol)


def cost_model(runs: List[Dict[str, Any]]) -> Optional[Dict[str, float]]:
    """The controller's CPU as costs per event, from all windows together: the worker's per
    localized frame, the serial reader's per odometry report, and the event loop's per frame and
    per control tick (least squares over windows of different frame rates). Per event rather than
    per window, so a window in which a busy machine starved some threads still counts right."""
    if len(runs) < 2:
        return None
    sec = np.array([r["seconds"] for r in runs])
    loc = np.array([r["localizations_per_s"] for r in runs])
    ticks = np.array([r["ticks_per_s"] for r in runs])
    odo = np.array([r["odometry_per_s"] for r in runs])
    share = {g: np.array([r["share"][g] for r in runs]) for g in GROUPS}
    if float((loc * sec).sum()) <= 0 or float((odo * sec).sum()) <= 0:
        return None
    worker = float((share[GROUPS[1]] * sec).sum() / (loc * sec).sum())
    reader = float((share[GROUPS[2]] * sec).sum() / (odo * sec).sum())
    ev = share[GROUPS[0]]
    A = np.column_stack([loc, ticks])
    (e_f, e_t), _, rank, _ = np.linalg.lstsq(A, ev, rcond=None)
    if rank < 2:
        return None
    if e_f < 0:  # noise can push one of the two below zero: then the other alone explains the loop
        e_f, e_t = 0.0, float((ev * ticks).sum() / (ticks * ticks).sum())
    elif e_t < 0:
        e_f, e_t = float((ev * loc).sum() / (loc * loc).sum()), 0.0
    robot, _ = robot_and_map()
    other = float(np.median(share[GROUPS[3]]))
    fixed = e_t * robot.control.rate + reader * ODOMETRY_HZ + other
    inside: Dict[str, float] = {}
    for label in runs[0].get("inside", {}):
        cpu = sum(r["inside"][label][0] for r in runs if label in r.get("inside", {}))
        calls = sum(r["inside"][label][1] for r in runs if label in r.get("inside", {}))
        if calls:
            inside[label] = cpu / calls
    return {"inside": inside, "worker_per_frame": worker, "loop_per_frame": float(e_f), "loop_per_tick": float(e_t),
            "reader_per_report": reader, "other": other, "per_frame": worker + float(e_f), "fixed": fixed,
            "control_hz": float(robot.control.rate), "windows": len(runs)}


# -- imports ---------------------------------------------------------------------------------------

# filterpy.kalman is measured for what it would cost: the controller no longer imports it (its EKF
# equations are written out in robot/fusion/ekf.py and tested against it).
IMPORTS = ["numpy", "scipy.linalg", "filterpy.kalman", "robot.localization.localizer", "robot.fusion.ekf",
           "drivers.chassis.serial_chassis", "robot.app.controller"]
_IMPORT_PROBE = """
import json, resource, sys
r0 = resource.getrusage(resource.RUSAGE_SELF)
import {mod}
r1 = resource.getrusage(resource.RUSAGE_SELF)
rss = 0.0
for line in open('/proc/self/status'):
    if line.startswith('VmRSS:'):
        rss = int(line.split()[1]) / 1024.0
tops = sorted({{m.split('.')[0] for m in sys.modules}})
print(json.dumps({{'rss': rss, 'cpu_ms': 1e3 * (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime),
                  'modules': len(sys.modules), 'scipy': 'scipy' in sys.modules, 'cv2': 'cv2' in sys.modules,
                  'tops': [t for t in tops if t in ('numpy', 'scipy', 'cv2', 'filterpy', 'yaml', 'serial', 'asyncio')]}}))
"""


def _parse_importtime(text: str) -> List[Tuple[int, str, int, int]]:
    """(depth, module, self us, cumulative us) per line of ``-X importtime``, in its order."""
    rows = []
    for line in text.splitlines():
        if not line.startswith("import time:") or "imported package" in line:
            continue
        parts = line[len("import time:"):].split("|")
        if len(parts) != 3:
            continue
        try:
            self_us, cum = int(parts[0]), int(parts[1])
        except ValueError:
            continue
        name = parts[2]
        rows.append(((len(name) - len(name.lstrip(" ")) - 1) // 2, name.strip(), self_us, cum))
    return rows


def _chain(rows, target: str) -> List[str]:
    """Who imported ``target`` first: -X importtime prints a module after everything it imports,
    so the parent of a line is the next line one level up."""
    for i, (depth, name, _, _) in enumerate(rows):
        if name == target:
            chain = [name]
            for j in range(i + 1, len(rows)):
                if rows[j][0] == depth - 1:
                    chain.append(rows[j][1])
                    depth -= 1
            return list(reversed(chain))
    return []


def imports(python: str, modules: Sequence[str]) -> Dict[str, Any]:
    """What importing each module loads, each in a fresh interpreter."""
    out: Dict[str, Any] = {"modules": list(modules)}
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    base = subprocess.run([python, "-c", _IMPORT_PROBE.format(mod="os")], capture_output=True, text=True,
                          env=env, timeout=120)
    out["baseline_rss"] = json.loads(base.stdout.strip().splitlines()[-1])["rss"] if base.returncode == 0 else float("nan")
    for mod in modules:
        name = mod
        code = _IMPORT_PROBE.format(mod=name)
        p = subprocess.run([python, "-X", "importtime", "-c", code], capture_output=True, text=True, env=env,
                           timeout=120)
        if p.returncode != 0:
            out[mod] = {"error": (p.stderr.strip().splitlines() or ["?"])[-1]}
            continue
        info = json.loads(p.stdout.strip().splitlines()[-1])
        rows = _parse_importtime(p.stderr)
        info["chains"] = {t: _chain(rows, t) for t in ("scipy", "numpy", "cv2") if _chain(rows, t)[:1] == [name]}
        info["scipy_modules"] = sum(1 for r in rows if r[1].split(".")[0] == "scipy")
        out[mod] = info
    return out


# -- workers and the report ------------------------------------------------------------------------

def controller_memory(quick: bool) -> Dict[str, Any]:
    """The controller's memory without the compiled kernels (run with ROBOT_KERNELS=numpy, the
    light install): RSS after importing it and the peak of one working window at 2 x 30 Hz."""
    import robot.app.controller  # noqa: F401  (imported before the RSS baseline)
    import robot.sim.realtime  # noqa: F401
    from robot.localization import fit_kernels

    _malloc_trim()
    rss_start = vm_status("VmRSS")
    alloc = (2.0 if quick else 8.0) if fit_kernels.backend() == "numpy" else 0.0  # see controller()
    r = controller_window(30.0, 2.0 if quick else 5.0, alloc)
    return {"backend": fit_kernels.backend(), "rss_start_mib": rss_start, "error": r.get("error"), "alloc": r.get("alloc"),
            "window_start_rss_mib": r.get("window_rss0", float("nan")),
            "window_peak_rss_mib": r.get("window_hwm", float("nan")), "hwm_reset": r.get("hwm_reset", False),
            "note": fit_kernels.backend_note(), "numba_loaded": "numba" in sys.modules,
            "localizations_per_s": r.get("localizations_per_s", float("nan")),
            "localize_ms": r.get("localize_ms", float("nan"))}


WORKERS = {"localizer": localizer_steps, "controller": controller, "memory_numpy": controller_memory,
           "memory_aot": controller_memory}


def build_aot(python: str, folder: str) -> Dict[str, Any]:
    """``robotctl kernels build`` under ``python`` into ``folder``: the module's path and seconds."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("ROBOT_KERNEL_DIR", None)
    cmd = [python, "-m", "robot.cli.main", "kernels", "build", "--dir", folder, "--json"]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1500, cwd=str(ROOT))
    except subprocess.TimeoutExpired:
        return {"error": "robotctl kernels build timed out"}
    if p.returncode != 0:
        return {"error": f"robotctl kernels build failed: {(p.stderr.strip().splitlines() or ['no output'])[-1]}"}
    return json.loads(p.stdout)


def memory_aot(python: str, quick: bool) -> List[str]:
    """The controller's memory with the kernels compiled ahead of time (robotctl kernels build)."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="bench-aot-") as folder:
        built = build_aot(python, folder)
        if built.get("error"):
            return [f"With the kernels compiled ahead of time: _{built['error']}_", ""]
        size_mib = os.path.getsize(built["module"]) / 2**20
        r = run_worker(python, "memory_aot", quick, ROBOT_KERNELS="aot", ROBOT_KERNEL_DIR=folder)
    if r.get("error"):
        return [f"With the kernels compiled ahead of time: _{r['error']}_", ""]
    peak = _working_peak(r, "")
    return [f"With the kernels compiled ahead of time (`robotctl kernels build`: {built['seconds']:.0f} s here, "
            f"a module of {size_mib:.1f} MiB; then `ROBOT_KERNELS=aot`), "
            f"one window at 2 x 30 Hz in a fresh process: {r['rss_start_mib']:.0f} MiB after its imports, {peak}; numba "
            f"{'loaded' if r.get('numba_loaded') else 'not loaded'}; {r['localizations_per_s']:.0f} localizations per s, "
            f"{r['localize_ms']:.2f} ms each (the localizer's own clock). The same compiled code as the JIT's, bit for "
            "bit (tests/test_aot_kernels.py), without numba and LLVM in the process.", ""]


def worker(name: str, quick: bool) -> Dict[str, Any]:
    load0 = os.getloadavg()[0]
    m = machine_factor(5 if quick else 15)
    r = WORKERS[name](quick)
    r["machine"] = m
    r["load"] = (load0, os.getloadavg()[0])
    r["python"] = platform.python_version()
    r["numpy"] = np.__version__
    return r


def find_python38() -> Optional[str]:
    """The project's Python 3.8 venv (the Nano's Python), if this machine has one."""
    if sys.version_info[:2] == (3, 8):
        return None
    venv = ROOT / ".venv38" / "bin" / "python"
    if venv.exists() and glob.glob(PY38_GLOB):
        return str(venv)
    return None


def run_worker(python: str, name: str, quick: bool, **extra_env: str) -> Dict[str, Any]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT), **extra_env)
    cmd = [python, str(Path(__file__).resolve()), "--worker", name] + (["--quick"] if quick else [])
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300 if quick else 1500)
    except subprocess.TimeoutExpired:
        return {"error": f"{name} worker under {python} timed out"}
    for line in reversed(p.stdout.splitlines()):
        if line.startswith(JSON_TAG):
            return json.loads(line[len(JSON_TAG):])
    tail = (p.stderr.strip().splitlines() or ["no output"])[-1]
    return {"error": f"{name} worker under {python} failed (exit {p.returncode}): {tail}"}


def _f(v: Any, fmt: str = "{:.2f}") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def report_localizer(r: Dict[str, Any], m_here: Dict[str, float], speed: Optional[Dict[str, float]] = None
                     ) -> List[str]:
    """The step table of a localizer worker's result; ``speed``: the machine factor its Nano row
    scales by when not the worker's own (see :func:`speed_line`)."""
    if "error" in r:
        return [f"_{r['error']}_", ""]
    m = r["machine"]
    lines = [f"Python {r['python']}, numpy {r['numpy']}, load average {r['load'][0]:.1f} -> {r['load'][1]:.1f}. "
             f"{machine_line(m)}" + (f" {speed_line(speed)}" if speed else ""), ""]
    if speed:
        m = speed
    head = "| step (exclusive CPU, median ms) | " + " | ".join(f"{c['frames']} frame{'s' if c['frames'] > 1 else ''}, "
                                                                 f"{c['case'].split(':')[0]}" for c in r["cases"]) + " |"
    lines += [head, "|---|" + "---|" * len(r["cases"])]
    for s in STEP_ORDER:
        lines.append(f"| {s} | " + " | ".join(_f(c["steps"].get(s)) for c in r["cases"]) + " |")
    lines.append("| **total with hooks** | " + " | ".join(f"**{_f(c['hooked_ms'])}**" for c in r["cases"]) + " |")
    lines.append("| **total, no hooks (median / p95)** | "
                 + " | ".join(f"**{_f(c['ms'])}** / {_f(c['p95'])}" for c in r["cases"]) + " |")
    if any(c.get("numpy_ms") for c in r["cases"]):
        lines.append("| total with the numpy code (`ROBOT_KERNELS=numpy`), no hooks | "
                     + " | ".join(_f(c.get("numpy_ms")) for c in r["cases"]) + " |")
    lines.append("| Nano estimate, no hooks (x5 / x8) | " + " | ".join(nano(c["ms"], m) for c in r["cases"]) + " |")
    lines.append("| passes (mean), full fixes (ok or unprotected) | "
                 + " | ".join(f"{c['passes']:.2f}, {c['ok']}" for c in r["cases"]) + " |")
    lines.append("")
    if r["missing_hooks"]:
        lines.append("Hooks not found (the localizer changed; their time is in the step that calls them): "
                     + ", ".join(f"`{h}`" for h in r["missing_hooks"]) + ".")
        lines.append("")
    k = r.get("kernels", {})
    if k.get("backend") == "numba":
        if "compile_s" in k:
            first = (f"compiling them into an empty cache took {k['compile_s']:.1f} s for the plane fit's, "
                     f"{_f(k.get('integrity_compile_s'), '{:.1f}')} s for the integrity checks' and "
                     f"{_f(k.get('scan_compile_s'), '{:.1f}')} s for the obstacle scan's (a first start), ")
        else:
            first = "compiling them into an empty cache not measured (quick mode), "
        lines.append(f"Compiled kernels: {k['note']}; {first}loading all from the cache in a fresh process "
                     f"{_f(k.get('cached_s'), '{:.2f}')} s ({_f(k.get('cached_total_s'), '{:.2f}')} s with importing "
                     "numba and the modules). The numpy row alternates with the kernels' runs.")
    elif k:
        lines.append(f"Plane-fit kernels: {k.get('note') or k.get('backend')}.")
    lines.append("")
    sc = r["scaling"]
    lines.append(f"First call of a new `Localizer` (2 frames, tracking): {_f(r['first_call_ms'])} ms. "
                 f"CPU against ROI points (2 frames, tracking; pixel strides {', '.join(map(str, sc['strides']))}: "
                 + ", ".join(f"{int(p)} points {t:.2f} ms" for p, t in zip(sc["points"], sc["ms"]))
                 + f"): **{sc['fixed_ms']:.2f} ms per call that no point count reduces** "
                 f"({100 * sc['fixed_share_default']:.0f} % at the default stride), {sc['per_1000_points_ms']:.3f} ms "
                 "per 1000 points.")
    lines.append("")
    pc = r.get("paced")
    if pc:
        base = pc["ms"][0]
        lines.append("The same calls paced like the cameras (2 frames, tracking; the thread sleeps before each call): "
                     + "; ".join(("back to back" if g == 0.0 else f"after {1e3 * g:.0f} ms asleep") + f" {ms:.2f} ms"
                                 + ("" if g == 0.0 else f" (x{ms / base:.2f})")
                                 for g, ms in zip(pc["gaps_s"], pc["ms"]))
                     + f" (medians of {pc['n']} each). The step table above is back to back: code and data stay in "
                     "the caches. A call that comes after a wait finds them cold, more so on this shared machine, "
                     "where other guests of the host run while this thread waits; the real-time windows below pay "
                     "this, and the Nano budget is made from them.")
        lines.append("")
    pr = r["profile"]
    lines.append(f"cProfile (this thread's CPU clock, its own overhead included: {pr['total_ms']:.2f} ms per "
                 "localization), 2 frames, tracking, top by own time, per localization:")
    lines += ["", "| function | calls | own ms | cumulative ms |", "|---|---|---|---|"]
    for row in pr["rows"]:
        lines.append(f"| `{row['where']}` | {row['calls']:.1f} | {row['tottime_ms']:.3f} | {row['cumtime_ms']:.3f} |")
    lines.append("")
    return lines


def report_controller(r: Dict[str, Any]) -> Tuple[List[str], Optional[Dict[str, float]]]:
    """The tables of a controller worker's result, and its per-event costs (the Nano budget scales
    them by the run's median machine factor, see ``run``)."""
    if "error" in r:
        return [f"_{r['error']}_", ""], None
    m = r["machine"]
    lines = [f"Python {r['python']}, numpy {r['numpy']}, load average {r['load'][0]:.1f} -> {r['load'][1]:.1f}. "
             f"{machine_line(m)}", ""]
    if r.get("errors"):
        lines += ["Runs that failed: " + "; ".join(r["errors"]), ""]
    a, b = r.get("30"), r.get("10")
    if a is None:
        return lines + ["_no window at 30 Hz completed_", ""], None
    lines += ["| thread (share of one core, median over windows) | 2 x 30 Hz | 2 x 10 Hz |", "|---|---|---|"]
    for g in GROUPS:
        lines.append(f"| {g} | {100 * a['share'][g]:.1f} % | {100 * b['share'][g]:.1f} % |" if b else
                     f"| {g} | {100 * a['share'][g]:.1f} % | n/a |")
    lines.append(f"| **controller total** | **{100 * a['total']:.1f} %** | "
                 f"{'**%.1f %%**' % (100 * b['total']) if b else 'n/a'} |")
    for k in sorted(a["left_out"]):
        lines.append(f"| left out (simulator): {k} | {100 * a['left_out'][k]:.1f} % | "
                     f"{100 * b['left_out'].get(k, 0.0):.1f} % |" if b else f"| left out: {k} | {100 * a['left_out'][k]:.1f} % | |")
    lines.append(f"| frames delivered / localized per s, localizer ms (its own clock) | {a['frames_per_s']:.1f} / "
                 f"{a['localizations_per_s']:.1f}, {a['localize_ms']:.2f} | "
                 + (f"{b['frames_per_s']:.1f} / {b['localizations_per_s']:.1f}, {b['localize_ms']:.2f} |" if b else "|"))
    lines.append(f"| odometry / s, control ticks / s | {a['odometry_per_s']:.0f}, {a['ticks_per_s']:.0f} | "
                 + (f"{b['odometry_per_s']:.0f}, {b['ticks_per_s']:.0f} |" if b else "|"))
    lines.append(f"| windows, seconds measured | {a['windows']}, {a['seconds']:.0f} s | "
                 + (f"{b['windows']}, {b['seconds']:.0f} s |" if b else "|"))
    lines.append("")
    starved = [f"{lab}: {x['localizations_per_s']:.1f} of {x['frames_per_s']:.1f} frames/s localized, "
               f"{x['ticks_per_s']:.0f} control ticks/s" for lab, x in (("2 x 30 Hz", a), ("2 x 10 Hz", b)) if x
               and (x["localizations_per_s"] < 0.9 * x["frames_per_s"] or x["ticks_per_s"] < 45)]
    if starved:
        lines += [f"**The machine starved the controller** (load average {r['load'][0]:.1f} on {os.cpu_count()} "
                  f"cores; {'; '.join(starved)}): the shares above are what it got, not what it needs. The costs per "
                  "event below still hold; run again on a quieter machine for the shares.", ""]
    if a["other"]:
        lines.append("Other controller threads: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in a["other"].items()) + ".")
        lines.append("")
    al = r.get("alloc")
    if r.get("hwm_reset"):
        lines.append(f"RSS: **{r['rss_start_mib']:.0f} MiB after importing the controller**, before any run; peak "
                     f"(VmHWM) while the controller works **{r['window_peak_rss_mib']:.0f} MiB** in the first run "
                     f"(from {r['window_start_rss_mib'][0]:.0f} MiB at the window's start; freed heap returned and the "
                     "peak reset after start-up, where the fake cameras render their frames; the whole process, with "
                     f"start-up and later runs, peaked at {r['peak_rss_mib']:.0f} MiB). The simulator's share of the working "
                     "figure, the 2 x 8 cached frames (13 MiB) and the renderer's caches (a few tens of MiB), is not "
                     "the controller's: on the robot the peak lies between the two figures.")
    else:
        lines.append(f"Peak RSS (VmHWM) of the whole process: **{r['peak_rss_mib']:.0f} MiB** (this kernel cannot reset "
                     "it after start-up, so the fake cameras' rendering is in it; after imports, before the first run: "
                     f"{r['rss_start_mib']:.0f} MiB).")
    if al:
        where = (" in the run without the compiled kernels below (tracemalloc's raw-memory hook races numba's "
                 "kernels, which allocate without the GIL: CPython issues 128679 and 143143)") if r.get("alloc_numpy") else ""
        lines.append(f"Allocations (tracemalloc over {al['frames']} localized frames at 2 x 30 Hz{where}): "
                     f"{al['blocks_per_frame']:+.1f} live blocks and {al['bytes_per_frame']:+.0f} bytes per frame "
                     f"left behind (growth: {', '.join(f'{f} {c:+.1f}' for f, c in al['top'])}); peak traced memory "
                     f"{al['peak_above_mib']:.1f} MiB above the window's start. tracemalloc counts live blocks, not "
                     "how many were allocated and freed on the way.")
    lines.append("")
    fit = None
    if r.get("model"):
        fit = dict(r["model"])
    return lines, fit


def _working_peak(r: Dict[str, Any], how: str) -> str:
    """The phrase for a memory worker's peak RSS while it works (``how``: said of the measurement)."""
    if not r.get("hwm_reset"):
        return "its working peak could not be separated from start-up on this kernel"
    return (f"peak while it works **{r['window_peak_rss_mib']:.0f} MiB** (from {r['window_start_rss_mib']:.0f} MiB at "
            f"the window's start{how})")


def report_memory_numpy(r: Dict[str, Any]) -> List[str]:
    """The light install's memory: the same controller without numba (and LLVM) loaded."""
    if r.get("error"):
        return [f"Without the compiled kernels: _{r['error']}_", ""]
    if r.get("backend") != "numpy":
        return [f"Without the compiled kernels: _the run used {r.get('backend')}, not numpy_", ""]
    peak = _working_peak(r, ", measured as above")
    return [f"Without the compiled kernels (`ROBOT_KERNELS=numpy`, no numba or LLVM loaded; the install without "
            f"the `perf` extra), one window at 2 x 30 Hz in a fresh process: {r['rss_start_mib']:.0f} MiB after "
            f"its imports (the controller's and the benchmark's), {peak}. The difference to the figure above is what numba, LLVM and the "
            "compiled kernels hold.", ""]


def budget_lines(fit: Dict[str, float]) -> List[str]:
    per_frame, fixed = fit["per_frame"], fit["fixed"]
    lines = [f"Per event, from all {fit['windows']} windows: **{1e3 * per_frame:.2f} ms of controller CPU per localized "
             f"frame** (localization worker {1e3 * fit['worker_per_frame']:.2f} ms"
             + "".join(f"; {k} {1e3 * v:.2f} ms per call" for k, v in fit.get("inside", {}).items())
             + f", timed inside the worker; event loop {1e3 * fit['loop_per_frame']:.2f} ms), "
             f"{1e3 * fit['loop_per_tick']:.3f} ms per control tick (with the two odometry reports of each tick, which "
             "the loop also handles), "
             f"{1e3 * fit['reader_per_report']:.3f} ms per odometry report; at {fit['control_hz']:.0f} Hz control and "
             f"{ODOMETRY_HZ:.0f} Hz odometry that is **{100 * fixed:.1f} % of a core before any frame**, and "
             f"**{100 * (fixed + 60 * per_frame):.1f} % at 2 x 30 Hz**, on this machine.", "",
             "| Nano factor | controller at 2 x 30 Hz (cores) | largest camera rate that fits one core (per camera, "
             "both cameras) |", "|---|---|---|"]
    for k in NANO_FACTORS:
        s = k / max(fit["factor"], 1e-9)
        room = 1.0 / s - fixed
        rate = room / (2 * per_frame) if per_frame > 0 else float("inf")
        lines.append(f"| x{k:.0f} | {s * (fixed + 60 * per_frame):.2f} | "
                     + (f"{rate:.1f} Hz |" if rate > 0 else "none: the fixed part alone exceeds a core |"))
    lines += ["", "Every part of the process is scaled by the same factor (this machine's factor taken out first). "
              "The Nano's other three cores are left for librealsense, the OS and the recorder; the localization "
              "worker is one thread, so a rate that needs more than one core for it cannot be had by adding cores.",
              ""]
    return lines


def report_floor(f: Dict[str, Any], steps: Optional[Dict[str, Any]]) -> List[str]:
    ms = f["ms"]
    loc = ms["localizer"]
    lines = [f"Two frames, tracking, {f['walls']:.1f} walls and {f['points']:.0f} ROI points per localization on "
             "average (the localizer's own ROIs; ROI prediction is not in the floor's figures: "
             f"{f['roi_ms']:.2f} ms).", "",
             "| routine | CPU median ms | localizer / this | position error median (mm) |", "|---|---|---|---|"]
    for name, v in ms.items():
        lines.append(f"| {name} | {v:.3f} | {loc / v:.1f} | {f['err_mm'][name]:.3f} |")
    if not f["numba"]:
        lines.append("| numba floor | not run: numba is not importable (`pip install -e '.[perf]'`) | | |")
    lines.append("")
    roi_step = "ROI prediction (visibility, raster, erosion)"
    case = next((c for c in (steps or {}).get("cases", []) if c["frames"] == 2 and c["case"] == TRACKING[0]), None)
    if case is not None and roi_step in case["steps"]:
        share = 1.0 - case["steps"][roi_step] / max(case["ms"], 1e-9)
        lines.append(f"Without its ROI prediction (by the step table's share, {100 * share:.0f} % of its CPU is the rest) "
                     f"the localizer is {loc * share / ms['numpy floor']:.1f} x the numpy floor"
                     + (f" and {loc * share / ms['numba floor']:.1f} x the compiled one." if "numba floor" in ms else "."))
        lines.append("")
    lines.append("The floor does only the per-wall work (gather the ROI's depth, keep points inside the prior's offset "
                 "gate, least-squares plane in inverse depth, one refit in a 3-sigma band, its covariance) and a "
                 "linear 3-DoF pose from the walls: no identification among surfaces, no systematic errors, no "
                 "integrity checks." + (f" numba compiled the kernel in {f['numba_compile_s']:.1f} s (not counted)."
                                        if f["numba"] else ""))
    lines.append("")
    return lines


def report_anchors(a: Dict[str, Any]) -> List[str]:
    ours = a["methods"]["plane localizer (ours)"]["ms"]
    lines = [f"{a['frames']} frame pair(s), {a['trials']} starts in all, each 0.1 m off in a random direction and "
             f"10 deg off; the registrations get every {robot_and_map()[0].localizer.pixel_stride}th pixel of both "
             f"frames in the walls' height band ({a['source_points']} points), voxels of {1e3 * a['voxel']:.0f} mm, "
             f"correspondences within {1e3 * a['corr']:.0f} mm, against the map sampled every 10 mm; their CPU "
             "includes the per-frame deprojection, voxelization and (GICP) covariances. The row 'every pixel' is "
             "small_gicp GICP given every pixel in the band, no voxel grid, each point's covariance from its 20 "
             "neighbours: the thinned cloud's speed costs it accuracy, and this is what GICP costs where it "
             "matches the plane localizer's. Success: error under 10 mm and 0.5 deg.", "",
             "| method | CPU median ms | / ours | position error median / p95 (mm) | heading error median (deg) | "
             "success |", "|---|---|---|---|---|---|"]
    for name, r in a["methods"].items():
        lines.append(f"| {name} | {r['ms']:.2f} | {r['ms'] / ours:.1f} | {r['pos_mm']:.2f} / {r['pos_p95']:.2f} | "
                     f"{r['head_deg']:.3f} | {r['success']} |")
    for name, note in a["notes"].items():
        if name not in a["methods"]:
            lines.append(f"| {name} | {note} | | | | |")
    lines.append("")
    got = [f"{k}: {v}" for k, v in a["notes"].items() if k in a["methods"]]
    if got:
        lines += ["Versions: " + "; ".join(got) + ". Registration is 6-DoF (x, y, heading read from it).", ""]
    return lines


def report_imports(per_python: Dict[str, Dict[str, Any]]) -> List[str]:
    lines = ["| interpreter | module imported | RSS after (MiB) | import CPU (ms) | modules | scipy loaded |", "|---|---|---|---|---|---|"]
    chains = set()
    for py, r in per_python.items():
        lines.append(f"| {py} | (nothing: `import os`) | {r['baseline_rss']:.0f} | | | |")
        for mod in r["modules"]:
            i = r.get(mod, {})
            if "error" in i:
                lines.append(f"| {py} | `{mod}` | failed: {i['error']} | | | |")
                continue
            sp = f"yes ({i['scipy_modules']} modules)" if i["scipy"] else "no"
            lines.append(f"| {py} | `{mod}` | {i['rss']:.0f} | {i['cpu_ms']:.0f} | {i['modules']} | {sp} |")
            for t, c in i.get("chains", {}).items():
                if mod.startswith(("robot.app", "drivers")) and len(c) > 2:
                    chains.add((t, " -> ".join(c)))
    lines.append("")
    for t, c in sorted(chains):
        lines.append(f"- {t} is imported through `{c}`"
                     + (": filterpy's package `__init__` imports all its subpackages (common, stats, kalman, ...), so "
                        "any filterpy import loads scipy.linalg, scipy.stats and scipy.sparse." if "filterpy" in c else "."))
    lines.append("")
    return lines


def run(quick: bool = False) -> str:
    t0 = time.monotonic()
    py38 = find_python38()
    here = f"Python {platform.python_version()}"
    out = ["## CPU budget for the Jetson Nano", "",
           "CPU time per thread, never wall clock; medians over repetitions that alternate between the variants "
           "compared. The Nano (4 x Cortex-A57 at 1.43 GHz, Python 3.8, numpy 1.24) is taken as 5 to 8 times "
           "slower per core than the reference machine; estimates divide by this machine's factor first.", ""]
    m_here = machine_factor(5 if quick else 15)
    out += [f"This machine: {cpu_model()}, {os.cpu_count()} logical cores, load average {os.getloadavg()[0]:.1f} at "
            "the start.", "", machine_line(m_here), ""]

    out += ["### The localizer, step by step", "",
            "Each step is the CPU of the localizer's functions booked to it, wrapped from outside (a wrapped "
            "function's time less that of wrapped functions it calls); 'no hooks' runs alternate with hooked ones, "
            "and their difference is the wrapping's cost. Frames: 848x480, realistic D435i noise, "
            f"{len(frame_sets(2 if quick else 6))} poses in the paper arena; tracking = the EKF's prior (1 cm / 0.5 deg "
            "off, std 2 cm / 1 deg), cold = 0.1 m / 10 deg off with the default coarse std.", ""]
    out += [f"#### {here}", ""]
    # This machine's speed, read with the reference's interpreter at several times in the run: the
    # Nano budget scales by their median, so that one reading in a busy spell does not move it.
    readings = [m_here]
    steps_here = run_worker(sys.executable, "localizer", quick)
    if "machine" in steps_here:
        readings.append(steps_here["machine"])
    out += report_localizer(steps_here, m_here)
    out += ["#### Python 3.8", ""]
    if sys.version_info[:2] == (3, 8):
        out += ["This run is Python 3.8: see above.", ""]
    elif py38 is None:
        out += ["not present (no `.venv38` with Python 3.8: `make .venv38/.installed VENV=.venv38 "
                "PYTHON=python3.8`)", ""]
    else:
        speed = machine_factor(5 if quick else 15)
        readings.append(speed)
        out += report_localizer(run_worker(py38, "localizer", quick), m_here, speed)

    out += [f"### The floor: what the per-wall work costs at least ({here})", ""]
    try:
        out += report_floor(floor(quick), steps_here)
    except Exception as e:  # the localizer's internals moved: say so, keep the rest of the section
        out += [f"_floor not run: {type(e).__name__}: {e}_", ""]

    out += [f"### Anchors: general point-cloud registration on the same frames ({here})", ""]
    out += report_anchors(anchors(quick))

    out += ["### The whole controller in real time (simulator; renderer and board emulator left out)", "",
            "The real app (asyncio loop, localization worker, serial driver on the pty board emulator) with two fake "
            "cameras delivering 848x480 frames from a pre-rendered cycle, every frame localized, 50 Hz control, "
            "100 Hz odometry. Windows at 2 x 30 Hz and 2 x 10 Hz alternate, each in a fresh app, after the first "
            "localizations; CPU per thread from /proc. The fake cameras' threads (`camera-*`) and the board "
            "emulator's are left out by name: on the robot, librealsense's capture threads take their place and "
            "the board's work runs on its microcontroller.", ""]
    fits = []
    for label, python in ((here, sys.executable), ("Python 3.8", py38)):
        out += [f"#### {label}", ""]
        if python is None:
            out += ["This run is Python 3.8: see above." if sys.version_info[:2] == (3, 8) else "not present", ""]
            continue
        if quick and python != sys.executable:
            out += ["skipped in quick mode (the same worker as above, under Python 3.8)", ""]
            continue
        if python != sys.executable:  # (the machine's speed as the reference's interpreter reads it, for the budget)
            readings.append(machine_factor(5 if quick else 15))
        ctl = run_worker(python, "controller", quick)
        if python == sys.executable and "machine" in ctl:
            readings.append(ctl["machine"])
        mem = run_worker(python, "memory_numpy", quick, ROBOT_KERNELS="numpy")
        if not ctl.get("alloc") and mem.get("alloc"):
            ctl["alloc"], ctl["alloc_numpy"] = mem["alloc"], True
        lines, fit = report_controller(ctl)
        out += lines
        out += report_memory_numpy(mem)
        if not quick:
            out += memory_aot(python, quick)
        if fit is not None:
            fits.append((label, fit))
    out += ["### Nano budget", ""]
    if not fits:
        out += ["_no controller figures to scale_", ""]
    readings.append(machine_factor(5 if quick else 15))
    run_factor = median([r["factor"] for r in readings])
    out += [f"Scaled by this machine's median factor over the run, x{run_factor:.2f} ({len(readings)} readings with "
            f"Python {platform.python_version()}, from x{min(r['factor'] for r in readings):.2f} to "
            f"x{max(r['factor'] for r in readings):.2f}; each is the geometric mean of its numpy and pure-Python "
            "factors), not by each table's own.", ""]
    for label, fit in fits:
        out += [f"#### From {label}", ""] + budget_lines(dict(fit, factor=run_factor))

    out += ["### What importing the controller loads", ""]
    mods = IMPORTS[-3:] if quick else IMPORTS
    per_python = {here: imports(sys.executable, mods)}
    if py38 is not None and not quick:
        per_python["Python 3.8"] = imports(py38, mods)
    out += report_imports(per_python)
    out += [f"_(bench_cpu: {time.monotonic() - t0:.0f} s{', quick mode' if quick else ''})_", ""]
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions and shorter windows (a smoke run)")
    ap.add_argument("--worker", choices=sorted(WORKERS), help="run one part and print it as JSON")
    args = ap.parse_args()
    if args.worker:
        print(JSON_TAG + json.dumps(worker(args.worker, args.quick)), flush=True)
    else:
        print(run(quick=args.quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
