"""The kernels compiled ahead of time (robot.base.aot_kernels): the same results as the JIT, no
numba in the process, and no call with arguments of a type they were not built for."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from robot.base import aot_kernels

NUMPY_PASS = os.environ.get("ROBOT_KERNELS", "").strip().lower() == "numpy"

# Renders frames with clutter and the realistic camera, localizes them (tracking and cold), runs
# the protective stop's scan on them, and prints every number as JSON; "numba" in sys.modules too.
PROBE = r"""
import json, math, sys
import numpy as np
from drivers.sim.clutter import leaning_boards, parallel_panel
from drivers.sim.render import Box, SimScene, render_depth_frame
from robot.config import load_robot_config
from robot.config.safety import SafetyConfig
from robot.control.protective_stop import ProtectiveStop
from robot.localization import fit_kernels
from robot.localization.localizer import Localizer, coarse_covariance
from robot.maps.plane_map import load_plane_map

robot = load_robot_config("config/robot.yaml")
arena = load_plane_map("config/maps/paper_arena.yaml")
west = arena["wall_west"]
scenes = [(SimScene(arena, [parallel_panel(west, 0.15, 1.0, None, region=(0.0, 0.9)), Box(0.6, 0.2, 0.8, 0.4, 0.3)]),
           (0.5, 0.5, math.pi)),
          (SimScene(arena, [leaning_boards(west, 0.9, np.random.default_rng(5))]), (0.4, 0.6, 2.9)),
          (SimScene(arena), (0.35, 0.7, 2.6))]
out = {"backend": fit_kernels.backend(), "note": fit_kernels.backend_note(), "runs": []}
for k, (scene, truth) in enumerate(scenes):
    rng = np.random.default_rng(40 + k)
    frames = [render_depth_frame(robot, scene, c.name, truth, rng=rng, frame_number=k) for c in robot.cameras]
    for off, cov in (((0.007, -0.007, 0.008), coarse_covariance(0.02, math.radians(1.0))),
                     ((0.07, -0.07, math.radians(10.0)), None)):
        coarse = (truth[0] + off[0], truth[1] + off[1], truth[2] + off[2])
        r = Localizer(robot, arena).localize(frames, coarse, cov)
        out["runs"].append([r.status, repr(r.x), repr(r.y), repr(r.phi), repr(r.horizontal_pl), repr(r.heading_pl),
                            [repr(v) for v in np.ravel(r.cov)],
                            [(p.id, p.camera, p.inliers, p.used, p.reason) for p in r.planes]])
    stop = ProtectiveStop(SafetyConfig(), robot, arena)
    for f in frames:
        scan = stop.update_scan_frame(f, truth)
        out["runs"].append([scan.camera, scan.walls_ignored, scan.near_blind, [repr(v) for v in np.ravel(scan.points_xy)]])
out["numba_imported"] = "numba" in sys.modules or "llvmlite" in sys.modules
print(json.dumps(out))
"""


def _env(**extra: str) -> dict:
    env = dict(os.environ, **extra)
    env.pop("PYTHONHASHSEED", None)
    return env


def _probe(repo_root, **env: str) -> dict:
    p = subprocess.run([sys.executable, "-c", PROBE], cwd=str(repo_root), env=_env(**env), capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def built(repo_root, tmp_path_factory):
    """One build for the module: numba's JIT compiles (or loads) the kernels, numba.pycc exports them."""
    pytest.importorskip("numba", reason="building the kernels ahead of time needs numba (the perf extra)")
    if NUMPY_PASS:
        pytest.skip("the pass on the numpy code (ROBOT_KERNELS=numpy): the pass with the compiled kernels builds them")
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler: numba.pycc links the module with one")
    folder = tmp_path_factory.mktemp("kernels")
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "kernels", "build", "--dir", str(folder), "--json"],
                       cwd=str(repo_root), env=_env(), capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    report = json.loads(p.stdout)
    assert os.path.isfile(report["module"]) and report["module"].startswith(str(folder))
    assert "gcc" not in p.stdout + p.stderr  # the compiler's command lines are not the user's business
    return folder


def test_the_module_gives_the_jits_results_bit_for_bit_without_numba(repo_root, built):
    jit = _probe(repo_root, ROBOT_KERNELS="numba")
    aot = _probe(repo_root, ROBOT_KERNELS="aot", ROBOT_KERNEL_DIR=str(built))
    assert "ahead of time" in aot["note"] and "ahead of time" not in jit["note"]
    assert aot["numba_imported"] is False  # the point: no numba, no LLVM in the process
    assert jit["numba_imported"] is True
    assert aot["runs"] == jit["runs"]
    statuses = {run[0] for run in jit["runs"] if isinstance(run, list)}
    assert "ok" in statuses or "unprotected" in statuses  # the scenes reach real fixes


def test_auto_takes_the_module_and_an_argument_of_another_type_is_refused_without_numba(repo_root, built):
    code = ("import numpy as np, sys\n"
            "sys.modules['numba'] = None\n"  # as on a robot installed without the perf extra
            "from robot.localization import fit_kernels as fk\n"
            "assert fk.backend() == 'numba' and 'ahead of time' in fk.backend_note(), fk.backend_note()\n"
            "g = fk._nb['_gather_kernel']\n"
            "idx = np.arange(3, dtype=np.int32)\n"
            "z = g(np.full(16, 1500, np.uint16), idx, idx, 4, 1, 0.001, 0.2, 10.0, np.zeros(4), np.zeros(4))[0]\n"
            "assert np.allclose(z, 1.5)\n"
            "for bad in (np.full(16, 1.5, np.float32), np.full((4, 4), 1500, np.uint16), np.full(32, 1500, np.uint16)[::2]):\n"
            "    try:\n"
            "        g(bad, idx, idx, 4, 1, 0.001, 0.2, 10.0, np.zeros(4), np.zeros(4))\n"
            "    except TypeError as e:\n"
            "        print('refused:', e)\n"
            "    else:\n"
            "        sys.exit('called with ' + str(bad.dtype))\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=str(repo_root),
                       env=_env(ROBOT_KERNELS="auto", ROBOT_KERNEL_DIR=str(built)), capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr[-3000:] + p.stdout
    assert p.stdout.count("refused: _gather_kernel: no ahead-of-time variant") == 3, p.stdout
    assert p.stdout.count("and no numba to compile one") == 3, p.stdout


def test_an_argument_type_not_built_is_compiled_by_numba_where_it_is_installed(repo_root, built):
    code = ("import numpy as np, sys\n"
            "from robot.localization import fit_kernels as fk\n"
            "assert 'ahead of time' in fk.backend_note()\n"
            "idx = np.arange(3, dtype=np.int32)\n"
            "args = (idx, idx, 4, 1, 1.0, 0.2, 10.0, np.zeros(4), np.zeros(4))\n"
            "z = fk._nb['_gather_kernel'](np.full(16, 1.5, np.float32), *args)[0]\n"  # float32: not built
            "assert np.allclose(z, 1.5) and 'numba' in sys.modules\n"
            "print('ok')\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=str(repo_root),
                       env=_env(ROBOT_KERNELS="aot", ROBOT_KERNEL_DIR=str(built)), capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr[-3000:] + p.stdout
    assert "no variant compiled ahead of time for (float32[1d]" in p.stderr


def test_without_a_module_for_this_source_auto_compiles_and_aot_is_one_clear_error(repo_root, tmp_path):
    stale = tmp_path / ("robot_kernels_0000000000000000" + importlib.machinery.EXTENSION_SUFFIXES[0])
    stale.write_bytes(b"not a module")  # another source's module: never loaded
    env = _env(ROBOT_KERNEL_DIR=str(tmp_path))
    # auto: numba's JIT where it is installed (the numpy pass skips it: it would compile every kernel)
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "kernels", "status", "--json"], cwd=str(repo_root),
                       env=dict(env, ROBOT_KERNELS="numpy" if NUMPY_PASS else "auto"), capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    status = json.loads(p.stdout)
    assert status["ahead_of_time_built"] is False and "ahead of time" not in status["plane_fit"]
    # Loading the JIT's kernels may be a compile of minutes: the status says so before it starts.
    assert ("no module compiled ahead of time" in p.stderr) is (not NUMPY_PASS and importlib.util.find_spec("numba")
                                                                  is not None), p.stderr
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "kernels", "status"], cwd=str(repo_root),
                       env=dict(env, ROBOT_KERNELS="aot"), capture_output=True, text=True, timeout=300)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "robotctl kernels build" in lines[0] and str(tmp_path) in lines[0], p.stderr


def test_the_module_is_named_by_the_kernels_source():
    name = aot_kernels.module_name()
    assert name.startswith("robot_kernels_") and len(name) == len("robot_kernels_") + 16
    assert aot_kernels.module_path().name.startswith(name)


@pytest.mark.parametrize("arg, accepted", [
    (np.zeros(3), True),
    (np.zeros(3, np.float32), False),  # another dtype: would be read as float64
    (np.zeros((3, 1)), False),  # another number of dimensions
    (np.zeros(6)[::2], False),  # strided where the variant needs C order
    (np.zeros(3).astype(">f8"), False),  # another byte order
    ([0.0, 0.0, 0.0], False),  # not an array
])
def test_typed_calls_take_only_the_types_built(arg, accepted):
    seen = []
    typed = aot_kernels._Typed("k", [(lambda a, n: seen.append((a, n)) or "called",
                                      [("array", "float64", 1, True, False), ("int64",)])])
    if accepted:
        assert typed(arg, 3) == "called" and len(seen) == 1
    else:
        with pytest.raises(TypeError, match="no ahead-of-time variant"):
            typed(arg, 3)
        assert not seen
    with pytest.raises(TypeError):
        typed(np.zeros(3), 3.0)  # a float where the variant takes an integer
    with pytest.raises(TypeError):
        typed(np.zeros(3), True)  # a bool is no integer here


def test_a_read_only_array_goes_only_to_a_variant_built_for_one():
    ro = np.zeros(3)
    ro.flags.writeable = False
    writes = aot_kernels._Typed("k", [(lambda a: "writable variant", [("array", "float64", 1, True, False)])])
    with pytest.raises(TypeError):
        writes(ro)
    both = aot_kernels._Typed("k", [(lambda a: "writable variant", [("array", "float64", 1, True, False)]),
                                    (lambda a: "read-only variant", [("array", "float64", 1, True, True)])])
    assert both(ro) == "read-only variant" and both(np.zeros(3)) == "writable variant"
