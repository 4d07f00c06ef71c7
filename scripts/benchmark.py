"""Run every benchmark section and write BENCHMARKS.md (figures are never typed in by hand).

    python scripts/benchmark.py [--quick] [--only NAME ...] [--out BENCHMARKS.md]

Each ``scripts/bench_<topic>.py`` has ``run(quick) -> str`` (a Markdown section), or
``section(quick) -> str`` when its ``run`` returns figures rather than Markdown.
"""

from __future__ import annotations

import os

# Small matrices on one core: multi-threaded BLAS only adds contention (and on the Nano, stalls).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import importlib  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Dict  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

SECTIONS = ["bench_localizer", "bench_controller", "bench_cpu", "bench_buildings", "bench_protocol", "bench_ifc", "bench_realsense",
            "bench_render", "bench_calibration", "bench_relocalize", "bench_unbuilt", "bench_safety", "bench_integrity",
            "bench_fuzz"]


def git_describe() -> str:
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        # The benchmark's own outputs (this file, its figures) do not make the code it measured dirty.
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":!BENCHMARKS.md",
                                ":!docs/bench"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        return rev + (" (with uncommitted changes)" if dirty else "")
    except OSError:
        return "unknown"


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


SECTION_START = "<!-- section {name} -->"
SECTION_END = "<!-- end of section {name} -->"


def split_sections(text: str) -> Dict[str, str]:
    """The sections of an existing BENCHMARKS.md by module name, each with its markers."""
    out: Dict[str, str] = {}
    for name in SECTIONS:
        start, end = SECTION_START.format(name=name), SECTION_END.format(name=name)
        i, j = text.find(start), text.find(end)
        if i >= 0 and j > i:
            out[name] = text[i:j + len(end)]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions (for a smoke run; do not publish)")
    ap.add_argument("--only", nargs="*", help="section module names to run; with an existing --out, the other "
                                              "sections are kept as they are, each with the commit it was run at")
    ap.add_argument("--out", default=str(ROOT / "BENCHMARKS.md"))
    ap.add_argument("--merge", nargs="+", metavar="FILE", help="take the sections found in these files (written by "
                                                                "this script, stamps and all) into --out; runs only "
                                                                "the --only sections, none without it")
    args = ap.parse_args()
    unknown = [n for n in (args.only or []) if n not in SECTIONS]
    if unknown:
        ap.error(f"unknown section(s) {', '.join(unknown)} (choose from {', '.join(SECTIONS)})")
    commit = git_describe()
    partial = bool(args.only) or bool(args.merge)
    kept = split_sections(Path(args.out).read_text()) if partial and Path(args.out).exists() else {}
    for extra in args.merge or []:
        kept.update(split_sections(Path(extra).read_text()))
    header = [
        "# Benchmarks",
        "",
        "Written by `scripts/benchmark.py` (`make bench`); do not edit by hand. Each section ends with the "
        "commit it was run at and its mode; `--only NAME` runs one section again and keeps the others.",
        "",
        f"- last run: commit {commit}, {datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}, "
        + ("merged sections run elsewhere (" + ", ".join(Path(f).name for f in args.merge) + "), each stamped where it ran"
           + (f"; ran {', '.join(args.only)}" if args.only else "") if args.merge
           else ('quick (smoke run)' if args.quick else 'full') + (f", sections {', '.join(args.only)}" if args.only else "")),
        f"- machine of the last run: {cpu_name()}, {os.cpu_count()} logical cores, Python {platform.python_version()}, "
        f"numpy {__import__('numpy').__version__}, OpenCV {__import__('cv2').__version__}; BLAS threads pinned to 1 "
        "(each CPU section has its own machine-factor line)",
        "",
    ]
    run = args.only or ([] if args.merge else SECTIONS)
    done: Dict[str, str] = {}

    def write() -> None:
        # Every section this run has not (yet) redone stays as it was: a run cut short loses nothing.
        body = []
        for name in SECTIONS:
            text = done.get(name, kept.get(name))
            if text is not None:
                body += [text, ""]
        Path(args.out).write_text("\n".join(header + body) + "\n")

    for name in run:
        t0 = time.perf_counter()
        print(f"running {name} ...", file=sys.stderr, flush=True)
        try:
            mod = importlib.import_module(name)
            text = getattr(mod, "section", mod.run)(quick=args.quick)
        except ImportError as e:
            text = f"## {name}\n\n_not run: {e}_"
        stamp = (f"_{name}: {time.perf_counter() - t0:.0f} s, commit {commit}, "
                 f"{'quick' if args.quick else 'full'}, {datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}_")
        done[name] = "\n".join([SECTION_START.format(name=name), text, "", stamp, SECTION_END.format(name=name)])
        write()
    write()
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
