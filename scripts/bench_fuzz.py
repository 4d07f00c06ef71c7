"""The long fuzz run: every loader and file-taking command of tests/test_fuzz_inputs.py.

    python scripts/bench_fuzz.py                 # ROBOT_FUZZ_LONG=1: 10,000 examples per loader
    python scripts/bench_fuzz.py --examples 500  # a shorter run, same tests
    python scripts/bench_fuzz.py -k snapshot     # only the tests whose name holds this

One Markdown section: per test, the examples it ran, wall seconds, examples per second and the
result (each test asserts exit status 2 or one clear error, one line, no traceback, no hang and
no wheel commanded; a failure prints the test's output). The tests never look at the clock; the
timing lives here. CI runs the same tests with a few dozen examples each.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import List, Optional, Tuple

ROOT = Path(__file__).resolve().parents[1]
LOADERS = [
    "test_yaml_parsing_is_bounded", "test_robot_config_loader", "test_path_loader", "test_map_loader",
    "test_map_check", "test_yaml_loaders_on_random_bytes", "test_snapshot_loader",
    "test_recording_reader_on_mutated_bytes", "test_recording_reader_on_hostile_content",
    "test_ifc_open_model",
]
# Each example of these starts a whole command (config, map, sometimes a simulated run): the
# long mode gives them 300 examples each (test_fuzz_inputs.CLI_EXAMPLES), replay and IFC import
# a quarter of the loaders' count.
COMMANDS = ["test_commands_taking_yaml_files", "test_localize_command", "test_replay_command", "test_import_ifc_command"]
QUARTER = ("test_recording_reader_on_hostile_content", "test_ifc_open_model", "test_replay_command")
CLI_EXAMPLES_LONG = 300


def examples_of(name: str, loader_examples: int) -> int:
    """How many examples the test runs in the long mode (mirrors tests/test_fuzz_inputs.py)."""
    if name == "test_replay_command":
        return max(CLI_EXAMPLES_LONG, loader_examples // 4)
    if name in QUARTER:
        return max(10, loader_examples // 4)
    if name in COMMANDS:
        return CLI_EXAMPLES_LONG
    return loader_examples


def run_one(name: str, loader_examples: int) -> Tuple[str, int, float, str, str]:
    env = dict(os.environ, ROBOT_FUZZ_LONG="1", ROBOT_FUZZ_EXAMPLES=str(loader_examples))
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-o", "addopts=", "-p", "no:cacheprovider",
                        "-p", "no:warnings", f"tests/test_fuzz_inputs.py::{name}"], cwd=str(ROOT), env=env,
                       capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    tail = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else ""
    if p.returncode == 0 and "passed" not in tail and "skipped" in tail:
        result = "skipped (" + (p.stdout.split("SKIPPED", 1)[1].split(":", 2)[-1].strip().splitlines()[0]
                                if "SKIPPED" in p.stdout else "not available") + ")"
    elif p.returncode == 0:
        result = "pass"
    else:
        result = "FAIL"
    n = examples_of(name, loader_examples)
    if name == "test_commands_taking_yaml_files":  # parametrized: one test per command
        n *= sum(int(k) for k in re.findall(r"(\d+) (?:passed|failed)", tail)) or 1
    # The head holds the assertion; hypothesis prints the falsifying input (a whole file) after it.
    out = p.stdout if len(p.stdout) <= 8000 else p.stdout[:4000] + "\n[...]\n" + p.stdout[-4000:]
    return name, n, seconds, result, (out + p.stderr[-2000:]) if result == "FAIL" else ""


def fuzz_section(loader_examples: int, only: Optional[str] = None) -> Tuple[str, bool]:
    rows: List[str] = []
    failed = False
    total_n, total_s = 0, 0.0
    for name in LOADERS + COMMANDS:
        if only and only not in name:
            continue
        name, n, seconds, result, output = run_one(name, loader_examples)
        failed |= result == "FAIL"
        if output:
            sys.stderr.write(output)
        if result == "pass":
            total_n += n
            total_s += seconds
        rows.append(f"| {name[5:]} | {n} | {seconds:.0f} | {n / max(seconds, 1e-9):.0f} | {result} |")
    lines = ["## Hostile inputs: the long fuzz run", "",
             f"`ROBOT_FUZZ_LONG=1` over tests/test_fuzz_inputs.py: {loader_examples:,} generated inputs per loader "
             "(random bytes, mutated valid files, hostile YAML trees, alias bombs, cut and spliced recordings and IFC "
             "files); each must end in one clear error (exit status 2 and one line for a command), no traceback, no "
             "hang, no wheel commanded. The commands start a whole process step per example and get fewer.", "",
             "| test | examples | wall s | examples/s | result |", "|---|---|---|---|---|", *rows, "",
             f"- {total_n:,} inputs passed in {total_s:.0f} s; "
             + ("**failures: see the stderr of the run**." if failed else "0 tracebacks, 0 hangs, 0 failures."), ""]
    return "\n".join(lines), failed


def run(quick: bool = False) -> str:
    return fuzz_section(200 if quick else 10_000)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--examples", type=int, default=10_000, help="examples per loader (default: %(default)s)")
    ap.add_argument("-k", dest="only", help="only the tests whose name contains this")
    args = ap.parse_args(argv)
    text, failed = fuzz_section(args.examples, args.only)
    print(text)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
