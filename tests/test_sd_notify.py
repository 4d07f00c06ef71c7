"""sd_notify against a real AF_UNIX datagram socket standing in for systemd's NOTIFY_SOCKET."""

from __future__ import annotations

import logging
import os
import socket
import uuid

import pytest

from robot.app import sd_notify


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    for name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
        monkeypatch.delenv(name, raising=False)
    sd_notify._reset_for_tests()
    yield
    sd_notify._reset_for_tests()


def _receiver(address):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(address)
    sock.settimeout(2.0)
    return sock


def _drain(sock) -> list:
    """Every datagram already queued on the socket."""
    out = []
    sock.setblocking(False)
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except BlockingIOError:
        pass
    finally:
        sock.settimeout(2.0)
    return out


@pytest.fixture
def fake_systemd(tmp_path, monkeypatch):
    path = str(tmp_path / "notify.sock")
    sock = _receiver(path)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    yield sock
    sock.close()


def test_ready_status_stopping_reach_the_socket(fake_systemd):
    assert sd_notify.ready("cameras 2/2, chassis ok, map 14 planes")
    assert fake_systemd.recv(4096).decode() == "READY=1\nSTATUS=cameras 2/2, chassis ok, map 14 planes"
    assert sd_notify.status("localization good\nsigma 4 mm")
    # A newline would start a new assignment; the status must stay one line.
    assert fake_systemd.recv(4096).decode() == "STATUS=localization good sigma 4 mm"
    assert sd_notify.watchdog()
    assert fake_systemd.recv(4096).decode() == "WATCHDOG=1"
    assert sd_notify.extend_timeout(12.5)
    assert fake_systemd.recv(4096).decode() == "EXTEND_TIMEOUT_USEC=12500000"
    assert sd_notify.stopping("stopping wheels")
    assert fake_systemd.recv(4096).decode() == "STOPPING=1\nSTATUS=stopping wheels"


def test_abstract_namespace_socket(monkeypatch):
    name = "robot-test-" + uuid.uuid4().hex
    sock = _receiver("\0" + name)
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert sd_notify.ready()
        assert sock.recv(4096) == b"READY=1"
    finally:
        sock.close()


def test_no_op_without_notify_socket():
    assert sd_notify.notify("READY=1") is False
    assert sd_notify.ready() is False
    assert sd_notify.status("x") is False
    assert sd_notify.watchdog() is False
    assert sd_notify.stopping() is False


def test_send_failure_returns_false_and_warns_once(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody-listens.sock"))
    with caplog.at_level(logging.WARNING, logger="robot.app.sd_notify"):
        assert sd_notify.ready() is False
        assert sd_notify.watchdog() is False
        assert sd_notify.status("still alive") is False
    warnings = [r for r in caplog.records if r.name == "robot.app.sd_notify"]
    assert len(warnings) == 1
    assert "nobody-listens.sock" in warnings[0].getMessage()


def test_unsupported_address_is_ignored(monkeypatch):
    monkeypatch.setenv("NOTIFY_SOCKET", "vsock:2:1234")
    assert sd_notify.ready() is False
    monkeypatch.setenv("NOTIFY_SOCKET", "@")
    assert sd_notify.ready() is False


def test_watchdog_interval_parsing(monkeypatch):
    assert sd_notify.watchdog_interval() is None
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    assert sd_notify.watchdog_interval() == pytest.approx(2.0)
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert sd_notify.watchdog_interval() == pytest.approx(2.0)
    # Inherited by a child process: the watchdog belongs to someone else.
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert sd_notify.watchdog_interval() is None
    monkeypatch.setenv("WATCHDOG_PID", "not-a-pid")
    assert sd_notify.watchdog_interval() is None
    monkeypatch.delenv("WATCHDOG_PID")
    for bad in ("0", "-5", "2s", ""):
        monkeypatch.setenv("WATCHDOG_USEC", bad)
        assert sd_notify.watchdog_interval() is None, bad


def test_pinger_sends_at_half_the_interval(fake_systemd, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    now = [100.0]
    pinger = sd_notify.WatchdogPinger(clock=lambda: now[0])
    assert pinger.enabled and pinger.interval == pytest.approx(2.0)
    sent = []
    for step in range(31):  # a 10 Hz control loop for 3 s
        now[0] = 100.0 + step * 0.1
        if pinger.tick():
            sent.append(round(now[0] - 100.0, 6))
    assert sent == [0.0, 1.0, 2.0, 3.0]
    assert _drain(fake_systemd) == ["WATCHDOG=1"] * 4


def test_pinger_is_inert_without_watchdog(fake_systemd):
    pinger = sd_notify.WatchdogPinger()
    assert not pinger.enabled
    assert pinger.tick() is False
    assert _drain(fake_systemd) == []
