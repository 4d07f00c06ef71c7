"""The CPU-budget benchmark and ``robotctl localize --repeat`` work; their figures are never judged
here (timings belong in BENCHMARKS.md, and this machine's speed must not decide a test)."""

from __future__ import annotations

import importlib.util
import json
import math
import re
import threading

import pytest

from robot.cli.main import main
from robot.localization.localizer import FIX_STATUSES

ROBOT = "config/robot.yaml"
MAP = "config/maps/paper_arena.yaml"
HANG_GUARD_S = 900.0  # only against a hang: the quick mode takes about a minute, more with a first compile


def _load_bench_cpu(repo_root):
    spec = importlib.util.spec_from_file_location("bench_cpu", repo_root / "scripts" / "bench_cpu.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _cells(section: str, row_start: str):
    """The cells after the first column of the table row beginning with ``row_start``."""
    for line in section.splitlines():
        if line.startswith(row_start):
            return [c.strip() for c in line.strip().strip("|").split("|")[1:]]
    raise AssertionError(f"no row starting {row_start!r} in the section")


def _number(cell: str) -> float:
    m = re.search(r"-?\d+(\.\d+)?", cell)
    assert m, f"no number in {cell!r}"
    return float(m.group(0))


@pytest.mark.slow
def test_bench_cpu_quick_mode_returns_its_section(repo_root):
    bench = _load_bench_cpu(repo_root)
    box = {}

    def target():
        try:
            box["text"] = bench.run(quick=True)
        except BaseException as e:  # handed to the test thread
            box["error"] = e

    th = threading.Thread(target=target, name="bench-cpu-smoke", daemon=True)
    th.start()
    th.join(HANG_GUARD_S)
    assert not th.is_alive(), f"bench_cpu.run(quick=True) still running after {HANG_GUARD_S:.0f} s"
    if "error" in box:
        raise box["error"]
    text = box["text"]
    assert text.startswith("## CPU budget for the Jetson Nano")
    assert "MACHINE-FACTOR:" in text
    failed = [ln for ln in text.splitlines() if ln.startswith("Runs that failed")]
    assert not failed, failed[0]
    for header in ("| step (exclusive CPU, median ms) |",
                   "| routine | CPU median ms | localizer / this |",
                   "| method | CPU median ms | / ours |",
                   "| thread (share of one core, median over windows) | 2 x 30 Hz | 2 x 10 Hz |",
                   "| Nano factor | controller at 2 x 30 Hz (cores) |",
                   "| interpreter | module imported |"):
        # A worker that failed leaves one italic line in the table's place: say what it was.
        errors = [ln for ln in text.splitlines() if ln.startswith("_") and not ln.startswith("_(bench")]
        assert header in text, f"missing table: {header}; the section's error lines: {errors}"
    for sub in ("### The localizer, step by step", "#### Python 3.8", "### The floor", "### Anchors",
                "### The whole controller in real time", "### Nano budget", "### What importing the controller loads"):
        assert sub in text
    assert "worker under" not in text, "a measuring subprocess failed: " + text
    assert "floor not run" not in text
    # The same calls paced like the cameras, beside back to back (the figures are the run's own).
    paced = [ln for ln in text.splitlines() if ln.startswith("The same calls paced like the cameras")]
    assert paced and "back to back" in paced[0] and "after 33 ms asleep" in paced[0], paced
    # The figures exist and are CPU times (positive); what they are is for BENCHMARKS.md.
    totals = _cells(text, "| **total, no hooks (median / p95)** |")
    assert len(totals) == 4 and all(_number(c) > 0 for c in totals)
    ours = _cells(text, "| plane localizer (ours) |")
    assert _number(ours[0]) > 0 and re.fullmatch(r"\d+/\d+", ours[-1])
    assert _number(_cells(text, "| **controller total** |")[0]) > 0
    assert _number(_cells(text, "| localization worker |")[0]) > 0
    assert "left out (simulator): camera-" in text  # the renderer's threads are named and kept apart
    assert "| numpy floor |" in text


@pytest.fixture(scope="module")
def snapshots(tmp_path_factory):
    d = tmp_path_factory.mktemp("repeat")
    paths = []
    for cam in ("front", "left"):
        p = d / f"{cam}.npz"
        assert main(["render", "--robot", ROBOT, "--map", MAP, "--pose", "0.35", "0.7", "2.6", "--camera", cam,
                     "--out", str(p), "--seed", "5"]) == 0
        paths.append(str(p))
    return paths


def test_localize_repeat_adds_timing_and_keeps_the_result(capsys, snapshots):
    args = ["localize", "--robot", ROBOT, "--map", MAP, "--init", "0.36", "0.69", "2.61", "--json", *snapshots]
    assert main(args) == 0
    once = json.loads(capsys.readouterr().out)
    assert "timing" not in once
    assert main(args[:1] + ["--repeat", "4"] + args[1:]) == 0
    rep = json.loads(capsys.readouterr().out)
    t = rep.pop("timing")
    assert set(t) == {"cpu_median_ms", "cpu_p95_ms", "wall_median_ms", "repeats"} and t["repeats"] == 4
    assert all(math.isfinite(t[k]) and t[k] > 0 for k in ("cpu_median_ms", "cpu_p95_ms", "wall_median_ms"))
    assert t["cpu_p95_ms"] >= t["cpu_median_ms"]
    once.pop("ms")
    rep.pop("ms")
    assert rep == once  # the same localization, repeated: the same answer every time
    assert rep["status"] in FIX_STATUSES


def test_localize_repeat_text_output_has_a_timing_line(capsys, snapshots):
    assert main(["localize", "--robot", ROBOT, "--map", MAP, "--init", "0.36", "0.69", "2.61", "--repeat", "2",
                 *snapshots]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^timing: CPU median [\d.]+ ms, p95 [\d.]+ ms, wall median [\d.]+ ms per call over 2 calls",
                     out, re.M)


@pytest.mark.parametrize("value", ["0", "-3", "many", "1e9"])
def test_localize_repeat_rejects_bad_counts_with_one_line(capsys, snapshots, value):
    with pytest.raises(SystemExit) as e:
        main(["localize", "--robot", ROBOT, "--map", MAP, "--init", "0.36", "0.69", "2.61", "--repeat", value,
              *snapshots])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--repeat" in err[-1] and "integer from 1 to 100000" in err[-1]
    assert "Traceback" not in "\n".join(err)
