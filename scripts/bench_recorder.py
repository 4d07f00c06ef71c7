"""Cost of recording: 16UC1 RawImage encode and decode per depth frame, bytes per frame, recorder throughput.

Run alone: ``.venv/bin/python scripts/bench_recorder.py [--quick]``.
"""

from __future__ import annotations

import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from robot.base.samples import DepthFrame  # noqa: E402
from robot.recording import schema as ms  # noqa: E402


def _frame(rng, i: int, width: int = 848, height: int = 480) -> DepthFrame:
    """A tilted wall 1.8 m away with D435i-like stereo noise (z^2 growth) and 3 % dropouts."""
    f = 0.5 * width / math.tan(math.radians(87) / 2)
    u = (np.arange(width) - (width - 1) / 2.0) / f
    z = 1.8 / (1.0 - 0.4 * u)[None, :] * np.ones((height, 1))
    z += rng.normal(0.0, 1.0, z.shape) * z ** 2 * 0.08 / (f * 0.050)
    depth = np.round(z / 0.001).astype(np.uint16)
    depth[rng.random(depth.shape) < 0.03] = 0
    K = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])
    return DepthFrame("front", depth, 0.001, K, t_capture=i / 30.0, frame_number=i)


def _median_ms(fn, n: int) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def run(quick: bool = False) -> str:
    from robot.recording.recorder import Recorder

    rng = np.random.default_rng(0)
    n = 5 if quick else 30
    frames = [_frame(rng, i) for i in range(n)]
    raw_bytes = frames[0].depth.nbytes
    encoded = [ms.encode_depth(f) for f in frames]
    msg_bytes = float(np.mean([len(ms.dumps(m)) for m in encoded]))
    default_budget = 40.0  # Mbit/s, robot.config.sections.RecordingConfig.depth_max_mbit_s
    enc_ms = _median_ms(lambda: ms.encode_depth(frames[0]), n)
    dumps_ms = _median_ms(lambda: ms.dumps(encoded[0]), n)
    dec_ms = _median_ms(lambda: ms.decode_depth(encoded[0]), n)

    with tempfile.TemporaryDirectory() as d:
        rec = Recorder(os.path.join(d, "bench.mcap"), min_free_bytes=0)
        t0 = time.perf_counter()
        for i, f in enumerate(frames):
            rec.write_depth(i / 30.0, f)
            rec.write_pose(i / 30.0, 0.1, 0.2, 0.3, np.eye(3) * 1e-4)
        rec.close()
        per_frame_ms = (time.perf_counter() - t0) * 1e3 / n
        file_bytes = sum(os.path.getsize(p) for p in rec.files)

    mb_per_min = msg_bytes * 2 * 30 * 60 / 1e6
    lines = [
        "## Recording (MCAP, depth as 16UC1 RawImage)",
        "",
        f"{n} synthetic 848x480 D435i-like frames (tilted wall at 1.8 m, stereo noise, 3 % dropouts).",
        "",
        "| measure | value |",
        "|---|---|",
        f"| raw depth frame | {raw_bytes / 1e3:.0f} kB |",
        f"| JSON message (base64) | {msg_bytes / 1e3:.0f} kB |",
        f"| frames per second within the default {default_budget:.0f} Mbit/s budget | "
        f"{default_budget * 1e6 / 8 / msg_bytes:.1f} |",
        f"| 16UC1 + base64 encode, median | {enc_ms:.1f} ms |",
        f"| JSON dump of a depth message, median | {dumps_ms:.2f} ms |",
        f"| decode back to a DepthFrame, median | {dec_ms:.1f} ms |",
        f"| Recorder.write_depth + write_pose, mean incl. file I/O | {per_frame_ms:.1f} ms |",
        f"| file size per frame | {file_bytes / n / 1e3:.0f} kB |",
        f"| disk use at 2 cameras x 30 Hz, no budget | {mb_per_min:.0f} MB/min |",
        "",
        f"Machine: {platform.machine()}, {platform.processor() or 'cpu n/a'}, "
        f"Python {platform.python_version()}, "
        f"{os.cpu_count()} cores. The Jetson Nano's A57 cores are several times slower: "
        "record only the frames the localizer uses, or use BackgroundRecorder.",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
