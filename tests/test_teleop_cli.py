"""`robotctl teleop --sim` in a real pseudo-terminal: keys drive the simulated robot."""

from __future__ import annotations

import os
import re
import select
import subprocess
import sys
import time


def _read(fd, seconds):
    out = b""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.05)
        if r:
            try:
                out += os.read(fd, 65536)
            except OSError:
                break
    return out.decode(errors="replace")


def test_teleop_sim_drives_forward_with_w_and_quits_with_x():
    master, slave = os.openpty()
    env = dict(os.environ, COLUMNS="200")
    p = subprocess.Popen([sys.executable, "-m", "robot.cli.main", "teleop", "--sim", "--init", "0.5", "0.5", "0"],
                         stdin=slave, stdout=slave, stderr=slave, env=env, close_fds=True)
    os.close(slave)
    try:
        text = _read(master, 6.0)  # start-up: emulator, cameras, first localizations
        for _ in range(40):  # hold W: the terminal's auto-repeat at ~30 Hz
            os.write(master, b"w")
            text += _read(master, 0.033)
        text += _read(master, 1.5)  # released: the deadman stops it
        os.write(master, b"x")
        text += _read(master, 4.0)
        rc = p.wait(timeout=15)
    finally:
        if p.poll() is None:
            p.kill()
        os.close(master)
    assert rc == 0, text[-2000:]
    xs = [float(m) for m in re.findall(r"x ([+-][0-9.]+) y ", text)]
    assert xs, text[-2000:]
    assert max(xs) > 0.55, text[-3000:]
