"""``robotctl kernels``: build the compiled kernels ahead of time, and say which kernels run."""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
from pathlib import Path

from robot.base.errors import RobotError
from robot.cli.common import print_json


def register(subparsers) -> None:
    p = subparsers.add_parser("kernels", help="compile the kernels ahead of time (no numba at run time); "
                                              "which kernels run")
    sub = p.add_subparsers(dest="kernels_command", metavar="KERNELS_COMMAND")
    sub.required = True
    b = sub.add_parser("build", help="compile every kernel ahead of time into one module (needs numba, "
                                     "the perf extra, and a C compiler)")
    b.add_argument("--dir", help="where to write it (default: ROBOT_KERNEL_DIR, else NUMBA_CACHE_DIR, else the "
                                 "package's __pycache__; the controller looks there)")
    b.add_argument("--json", action="store_true", help="print JSON")
    b.set_defaults(func=cmd_build)
    s = sub.add_parser("status", help="which kernels this process would run, and where it looks for the "
                                      "ahead-of-time module")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=cmd_status)


def cmd_build(args: argparse.Namespace) -> int:
    from robot.app import kernel_build
    from robot.base import aot_kernels

    folder = Path(args.dir) if args.dir else aot_kernels.kernel_dir()
    try:
        path, seconds = kernel_build.build(folder)
    except RuntimeError as e:
        raise RobotError(f"kernels build: {e}") from None
    except OSError as e:
        raise RobotError(f"kernels build: cannot write {folder}: {e.strerror or e}") from None
    if args.json:
        print_json({"module": str(path), "seconds": round(seconds, 1)})
    else:
        print(f"built {path} in {seconds:.1f} s")
        if args.dir and Path(args.dir).resolve() != aot_kernels.kernel_dir().resolve():
            print(f"the controller finds it with {aot_kernels.ENV_DIR}={args.dir}")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from robot.base import aot_kernels
    from robot.control import scan_kernels
    from robot.localization import fit_kernels, integrity_kernels

    requested = (os.environ.get(fit_kernels.ENV, "auto") or "auto").strip().lower()
    if (requested in ("auto", "numba") and not aot_kernels.module_path().is_file()
            and importlib.util.find_spec("numba") is not None):
        # Saying which kernels run means loading them, and with an empty cache that is a compile:
        # an engineer who asked for a status should not wait minutes without knowing why.
        print("note: no module compiled ahead of time for these sources: loading the kernels with numba's JIT, "
              "which compiles whatever its cache lacks (about two minutes of CPU on the development machine, "
              "10 to 20 minutes on a Nano; `robotctl kernels build` makes the module)", file=sys.stderr, flush=True)
    try:
        backend = fit_kernels.backend()
    except RuntimeError as e:
        raise RobotError(str(e)) from None
    out = {"requested": os.environ.get(fit_kernels.ENV, "auto") or "auto", "backend": backend,
           "plane_fit": fit_kernels.backend_note(), "integrity": integrity_kernels.backend_note(),
           "scan": scan_kernels.backend_note(), "ahead_of_time_module": str(aot_kernels.module_path()),
           "ahead_of_time_built": aot_kernels.module_path().is_file()}
    if args.json:
        print_json(out)
    else:
        for k, v in out.items():
            print(f"{k}: {v}")
    return 0
