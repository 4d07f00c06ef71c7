"""Time the long fuzz run: every loader of tests/test_fuzz_inputs.py with 10,000 examples each.

    python scripts/bench_fuzz.py                 # ROBOT_FUZZ_LONG=1: 10,000 examples per loader
    python scripts/bench_fuzz.py --examples 500  # a shorter run, same tests

Prints one Markdown table (loader, examples, wall seconds, examples per second, result). The
tests themselves never look at the clock; the timing lives here.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOADERS = [
    "test_yaml_parsing_is_bounded", "test_robot_config_loader", "test_path_loader", "test_map_loader",
    "test_map_check", "test_yaml_loaders_on_random_bytes", "test_snapshot_loader",
    "test_recording_reader_on_mutated_bytes", "test_recording_reader_on_hostile_content",
    "test_ifc_open_model",
]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--examples", type=int, default=10_000, help="examples per loader (default: %(default)s)")
    ap.add_argument("-k", dest="only", help="only the loaders whose test name contains this")
    args = ap.parse_args(argv)
    env = dict(os.environ, ROBOT_FUZZ_LONG="1", ROBOT_FUZZ_EXAMPLES=str(args.examples))
    rows = []
    failed = False
    for name in LOADERS:
        if args.only and args.only not in name:
            continue
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:warnings",
                            f"tests/test_fuzz_inputs.py::{name}"], cwd=str(ROOT), env=env, capture_output=True,
                           text=True)
        seconds = time.perf_counter() - t0
        # two tests run a quarter of the examples (each one replays or re-imports a whole file)
        n = max(10, args.examples // 4) if name in ("test_recording_reader_on_hostile_content",
                                                    "test_ifc_open_model") else args.examples
        result = "pass" if p.returncode == 0 else ("skip" if "skipped" in p.stdout and p.returncode == 0 else "FAIL")
        failed |= p.returncode != 0
        rows.append(f"| {name[5:]} | {n} | {seconds:.0f} | {n / seconds:.0f} | {result} |")
        if p.returncode != 0:
            sys.stderr.write(p.stdout[-4000:] + p.stderr[-2000:])
    print("| loader | examples | wall s | examples/s | result |")
    print("|---|---|---|---|---|")
    print("\n".join(rows))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
