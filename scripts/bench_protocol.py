"""Benchmark of the motor board protocol's Python codec: decoder frames/s, encoder frames/s, link load.

    python scripts/bench_protocol.py [--quick]
"""

from __future__ import annotations

import platform
import random
import sys
import time
from pathlib import Path
from typing import Callable, List

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import firmware_protocol as fp  # noqa: E402

BAUD = 115200


def _traffic(seconds: float) -> List[fp.Message]:
    """What the board sends in ``seconds``: reports at 100 Hz, status at 10 Hz, acks at 50 Hz."""
    rng = random.Random(0)
    out: List[fp.Message] = []
    ticks = [0, 0, 0, 0]
    seq = 0
    for k in range(int(seconds * 100)):
        ticks = [t + rng.randrange(-60, 61) for t in ticks]
        out.append(fp.EncoderReport(t_us=k * 10000, ticks=tuple(ticks), seq=seq & 0xFF))
        seq += 1
        if k % 2 == 0:
            out.append(fp.Ack(ref_id=0x02, ref_seq=(k // 2) & 0xFF, seq=seq & 0xFF))
            seq += 1
        if k % 10 == 0:
            out.append(fp.Status(t_us=k * 10000, battery_mv=12100, seq=seq & 0xFF))
            seq += 1
    return out


def _best_rate(n_items: int, fn: Callable[[], object], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n_items / best


def run(quick: bool = False) -> str:
    seconds = 5.0 if quick else 30.0
    repeats = 2 if quick else 5
    msgs = _traffic(seconds)
    frames = [fp.encode(m) for m in msgs]
    stream = b"".join(frames)
    n = len(msgs)

    def chunked() -> None:
        d = fp.Decoder()
        for i in range(0, len(stream), 4096):
            d.feed(stream[i:i + 4096])
        assert d.stats.frames == n

    def per_frame() -> None:
        d = fp.Decoder()
        for f in frames:
            d.feed(f)
        assert d.stats.frames == n

    def bytewise() -> None:
        d = fp.Decoder()
        for i in range(len(stream)):
            d.feed(stream[i:i + 1])
        assert d.stats.frames == n

    def encode_all() -> None:
        for m in msgs:
            fp.encode(m)

    rates = {
        "decode, 4 KiB chunks (as the reader thread reads)": _best_rate(n, chunked, repeats),
        "decode, each frame whole": _best_rate(n, per_frame, repeats),
        "decode, byte by byte": _best_rate(n, bytewise, max(1, repeats // 2)),
        "encode": _best_rate(n, encode_all, repeats),
    }
    need = n / seconds
    bytes_per_s = len(stream) / seconds
    lines = [
        "## Serial protocol codec (firmware_protocol)",
        "",
        f"Board-to-host traffic of {seconds:.0f} s (ENCODER_REPORT 100 Hz, ACK 50 Hz, STATUS 10 Hz): "
        f"{n} frames, {len(stream)} bytes, {need:.0f} frames/s and {bytes_per_s:.0f} bytes/s needed "
        f"({100 * bytes_per_s * 10 / BAUD:.0f} % of {BAUD} baud 8N1). Best of {repeats} runs.",
        "",
        f"| operation | frames/s | headroom over the link's {need:.0f} frames/s |",
        "|---|---|---|",
    ]
    for name, r in rates.items():
        lines.append(f"| {name} | {r:,.0f} | {r / need:,.0f}x |")
    lines += [
        "",
        "Wire size per message (both delimiters included): "
        + ", ".join(f"{type(m).__name__} {len(fp.encode(m))} B" for m in (
            fp.EncoderReport(), fp.Status(), fp.Ack(), fp.SetWheelSpeeds(), fp.HelloReply())) + ".",
        "",
        f"Machine: {platform.machine()}, Python {platform.python_version()}, {platform.system()}. The Jetson Nano "
        "is roughly 5 to 8 times slower per core; the byte-by-byte figure is the worst case (a read per byte).",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(run(quick="--quick" in sys.argv))
