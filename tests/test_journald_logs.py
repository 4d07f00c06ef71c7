"""Logs for journald: on the journal stream every line carries its syslog priority (so that
``journalctl -p warning`` shows exactly the warnings and errors) and no second time stamp;
anywhere else the usual plain lines. Normal lifecycle events are info, trouble is a warning."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.camera.base import CameraState
from robot.app import logs

ROOT = Path(__file__).resolve().parents[1]
PRIORITY = re.compile(r"^<([0-7])>(.*)$")

# What a run logs: every level, a multi-line message and an exception with its traceback.
CHILD = """
import logging, sys
from robot.app.logs import setup_logging
print("journal" if setup_logging(verbose=True) else "plain", flush=True)
log = logging.getLogger("robot.app.controller")
log.debug("debug detail")
log.info("camera front: streaming")
log.warning("motor board not reachable (timeout); retrying every 1.0 s")
log.info("two lines:\\nsecond line")
try:
    1 / 0
except ZeroDivisionError:
    log.exception("localization failed")
log.critical("giving up")
"""


def run_child(code: str, journal: bool, env_value=None, args=None):
    """Run ``code`` (or robotctl ``args``) with stderr on a pipe; with ``journal``, JOURNAL_STREAM
    names that very pipe, as systemd does for the journal's stream socket."""
    r, w = os.pipe()
    env = dict(os.environ)
    env.pop("JOURNAL_STREAM", None)
    if journal:
        st = os.fstat(w)
        env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}"
    elif env_value is not None:
        env["JOURNAL_STREAM"] = env_value
    cmd = [sys.executable, "-m", "robot.cli.main", *args] if args else [sys.executable, "-c", code]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=w, env=env, cwd=ROOT, text=True)
    os.close(w)
    with os.fdopen(r, encoding="utf-8") as f:
        err = f.read()
    out, _ = p.communicate(timeout=120)
    return p.returncode, out.strip(), err.splitlines()


def test_on_the_journal_every_line_has_its_priority_and_warning_means_warnings_and_errors():
    rc, mode, lines = run_child(CHILD, journal=True)
    assert rc == 0 and mode == "journal"
    parsed = [PRIORITY.match(line) for line in lines]
    assert all(parsed), [line for line, m in zip(lines, parsed) if not m]  # a line without one would be info
    entries = [(int(m.group(1)), m.group(2)) for m in parsed]
    # no time of our own: the journal stamps each line
    assert not any(re.match(r"\d{4}-\d\d-\d\d", text) for _, text in entries)
    by_text = {text: prio for prio, text in entries}
    assert by_text["DEBUG robot.app.controller: debug detail"] == 7
    assert by_text["INFO robot.app.controller: camera front: streaming"] == 6
    assert by_text["WARNING robot.app.controller: motor board not reachable (timeout); retrying every 1.0 s"] == 4
    assert by_text["second line"] == 6  # a continuation line keeps its record's priority
    assert by_text["CRITICAL robot.app.controller: giving up"] == 2
    # `journalctl -p warning` keeps priorities 0..4: exactly the warning, the error with its traceback, the critical
    shown = [text for prio, text in entries if prio <= 4]
    assert shown[0] == "WARNING robot.app.controller: motor board not reachable (timeout); retrying every 1.0 s"
    assert shown[1] == "ERROR robot.app.controller: localization failed"
    assert shown[2] == "Traceback (most recent call last):" and "ZeroDivisionError: division by zero" in shown
    assert shown[-1] == "CRITICAL robot.app.controller: giving up"
    assert not any("debug detail" in s or "streaming" in s or "two lines" in s for s in shown)


def test_robotctl_user_errors_and_crashes_are_errors_on_the_journal(tmp_path):
    rc, _, lines = run_child("", journal=True, args=["replay", str(tmp_path / "none.mcap")])
    assert rc == 2 and len(lines) == 1
    assert lines[0].startswith("<3>robotctl replay: error: ") and "no such recording" in lines[0]
    crash = "from robot.app.logs import setup_logging\nsetup_logging()\nraise RuntimeError('boom')\n"
    rc, _, lines = run_child(crash, journal=True)
    assert rc == 1 and lines and all(line.startswith("<2>") for line in lines)
    assert lines[0] == "<2>CRITICAL robotctl: uncaught exception:" and lines[-1] == "<2>RuntimeError: boom"


def test_off_the_journal_lines_are_plain_with_their_time():
    for env_value in (None, "12345:67890", "garbage"):  # unset, another stream's, malformed
        rc, mode, lines = run_child(CHILD, journal=False, env_value=env_value)
        assert rc == 0 and mode == "plain", env_value
        assert not any(PRIORITY.match(line) for line in lines)
        warning = [line for line in lines if "motor board not reachable" in line]
        assert len(warning) == 1 and re.match(
            r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} WARNING robot.app.controller: motor board", warning[0]), warning
    rc, _, lines = run_child("", journal=False, args=["replay", "/nonexistent/none.mcap"])
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("robotctl replay: error: ")


def test_priorities_of_python_levels():
    assert [logs.syslog_priority(lv) for lv in (5, logging.DEBUG, logging.INFO, 25, logging.WARNING, logging.ERROR,
                                                logging.CRITICAL, 60)] == [7, 7, 6, 6, 4, 3, 2, 2]


@pytest.mark.parametrize("state,level", [(CameraState.STARTING, logging.INFO), (CameraState.STREAMING, logging.INFO),
                                         (CameraState.STOPPED, logging.INFO), (CameraState.STALLED, logging.WARNING),
                                         (CameraState.GONE, logging.WARNING)])
def test_camera_lifecycle_is_info_and_trouble_is_a_warning(caplog, state, level):
    from robot.app.controller import RobotApp
    from robot.config import load_robot_config
    from robot.maps.plane_map import load_plane_map

    class _Chassis:
        pass

    app = RobotApp(load_robot_config(ROOT / "config" / "robot.yaml"),
                   load_plane_map(ROOT / "config" / "maps" / "paper_arena.yaml"), [], _Chassis())
    app.camera_states["front"] = "something else"
    with caplog.at_level(logging.DEBUG, logger="robot.app.controller"):
        app._camera_state("front", state)
    (record,) = [r for r in caplog.records if r.name == "robot.app.controller"]
    assert record.levelno == level and record.getMessage() == f"camera front: {state.value}"
