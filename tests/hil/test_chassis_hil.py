"""Hardware-in-the-loop tests of the motor board and the serial chassis driver (``pytest --hil``).

Setup:
- The robot is ON BLOCKS, with all four wheels off the ground and free to turn. These tests
  spin them.
- The motor board is connected over USB, and its port is reachable by the configured udev name
  (``chassis.port`` of the robot config, see tests/hil/conftest.py, overridden by
  ``$ROBOT_CHASSIS_PORT``).
- The battery is charged, the e-stop is released, and no other process (the robot service)
  holds the port.

The tests are skipped when the port does not exist. They use the same measurements as
``robotctl chassis --motion`` and ``robotctl bench`` (robot.app.bench_checks), at full length.
``test_unplugging_the_serial_adapter_is_survived`` needs a person to pull the adapter and put it
back (see tests/hil/conftest.py: it runs from a terminal or with ``HIL_MANUAL=1``).
"""

from __future__ import annotations

import asyncio
import os
import time

import pytest

from drivers.chassis.base import LinkState
from drivers.chassis.serial_chassis import SerialChassis
from robot.app.bench_checks import PASS, TEST_WHEEL_SPEED, judge_handshake
from robot.app.chassis_checks import SPEED_TOLERANCE, WATCHDOG_LIMIT, measure_watchdog, measure_wheel
from robot.config import ChassisConfig

pytestmark = pytest.mark.hil

TEST_SPEED = TEST_WHEEL_SPEED  # rad/s: slow enough to be safe on blocks, fast enough for 5 % by encoder


@pytest.fixture(scope="module")
def chassis_config(robot) -> ChassisConfig:
    cfg = robot.chassis
    port = os.environ.get("ROBOT_CHASSIS_PORT", cfg.port)
    if not os.path.exists(port):
        pytest.skip(f"motor board port {port} is absent (set ROBOT_CHASSIS_PORT or chassis.port)")
    return ChassisConfig(**{**cfg.__dict__, "port": port})


def run(coro, timeout: float = 60.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


async def with_chassis(cfg: ChassisConfig, body):
    ch = SerialChassis(cfg)
    q = ch.odometry_queue(maxsize=4096)
    await ch.connect()
    try:
        return await body(ch, q)
    finally:
        await ch.close()


def test_handshake_reports_a_board_matching_the_config(chassis_config):
    """Setup: the board connected and powered (the wheels do not turn)."""
    async def body(ch, q):
        while not q.empty():
            q.get_nowait()
        await asyncio.sleep(0.5)
        samples = []
        while not q.empty():
            samples.append(q.get_nowait())
        return ch.board_info, ch.status, ch.link_state, ch.stats, judge_handshake(ch, samples, 0.5)

    info, status, state, stats, verdict = run(with_chassis(chassis_config, body))
    print(f"handshake: {verdict.status}: {verdict.detail}")
    assert verdict.status == PASS, verdict.detail
    assert state is LinkState.READY
    assert info.ticks_per_rev == chassis_config.ticks_per_rev
    assert info.watchdog_ms <= 250
    assert 1e6 / info.report_period_us >= 100.0
    assert status is not None and status.battery_v > 6.0 and not status.estop
    assert not any(status.motor_faults)
    assert stats.get("odometry_samples", 0) >= 40  # 0.5 s at >= 100 Hz, first report is the baseline


@pytest.mark.parametrize("wheel", [0, 1, 2, 3], ids=["FL", "FR", "RL", "RR"])
def test_each_wheel_follows_its_command_within_5_percent(chassis_config, wheel):
    """Setup: ON BLOCKS. The wheel alone, both directions, 1.5 s each, measured by its encoder."""
    async def body(ch, q):
        fwd = await measure_wheel(ch, q, wheel, TEST_SPEED, hold=1.5)
        back = await measure_wheel(ch, q, wheel, -TEST_SPEED, hold=1.5)
        return fwd, back

    for res in run(with_chassis(chassis_config, body)):
        assert abs(res["error_pct"]) <= 100 * SPEED_TOLERANCE, res
        assert res["others_max"] <= SPEED_TOLERANCE * TEST_SPEED, res  # wiring: only this wheel turned


def test_board_watchdog_stops_the_wheels_within_250_ms(chassis_config):
    """Setup: ON BLOCKS. The host stops commanding (heartbeats go on): the board must stop the wheels."""
    async def body(ch, q):
        return await measure_watchdog(ch, q, TEST_SPEED)

    res = run(with_chassis(chassis_config, body))
    # measured on the host: includes the STATUS frame's transport delay, so the board was faster
    assert res["trip_s"] <= WATCHDOG_LIMIT, res
    assert res["stopped_s"] <= WATCHDOG_LIMIT + TEST_SPEED / chassis_config.max_wheel_accel + 0.3, res


def test_close_stops_the_wheels(chassis_config):
    """Setup: ON BLOCKS. Closing the driver while the wheels turn sends STOP."""
    async def spin(ch, q):
        for _ in range(25):
            ch.send_wheel_speeds([TEST_SPEED] * 4)
            await asyncio.sleep(0.02)

    run(with_chassis(chassis_config, spin))  # closes while the wheels turn: STOP goes out

    async def watch(ch, q):
        await asyncio.sleep(1.0)
        samples = []
        while not q.empty():
            samples.append(q.get_nowait())
        return samples

    samples = run(with_chassis(chassis_config, watch))
    assert samples and max(abs(v) for s in samples[-10:] for v in s.speeds) < 0.05 * TEST_SPEED


def test_unplugging_the_serial_adapter_is_survived(chassis_config, operator):
    """Setup: ON BLOCKS, and a person at the robot to pull the motor board's USB-serial adapter and
    put it back. A control loop commands a slow turn all along: the driver refuses commands while
    the link is LOST, reconnects by itself (READY) when the adapter is back, and the wheels follow
    the commands again with odometry that continues where it was."""
    slow = 1.0  # rad/s

    async def body(ch, q):
        log = []  # (host time, link state when sending, accepted)
        running = True

        async def control_loop():
            while running:
                t, state = time.monotonic(), ch.link_state
                log.append((t, state, ch.send_wheel_speeds([slow] * 4)))
                await asyncio.sleep(0.02)

        task = asyncio.get_running_loop().create_task(control_loop())
        try:
            await asyncio.sleep(1.0)
            before = _drain(q)
            operator.ask(f"UNPLUG the motor board's USB-serial adapter ({ch.port}) now")
            await operator.wait_for_async(lambda: ch.link_state is LinkState.LOST, "the link to be lost")
            t_lost = time.monotonic()
            operator.ask("PLUG the adapter back in")
            await operator.wait_for_async(lambda: ch.link_state is LinkState.READY, "the link to come back")
            t_back = time.monotonic()
            operator.say(f"link back {t_back - t_lost:.1f} s after it was lost")
            _drain(q)
            await asyncio.sleep(2.0)  # the wheels ramp up again and turn steadily
            after = _drain(q)
        finally:
            running = False
            await task
        return log, before, after, t_lost, t_back, dict(ch.stats)

    timeout = 2 * operator.timeout + 30
    log, before, after, t_lost, t_back, stats = run(with_chassis(chassis_config, body), timeout)
    assert stats.get("link_losses", 0) >= 1 and stats.get("reconnects", 0) >= 1, stats
    not_ready = [ok for t, state, ok in log if state is not LinkState.READY]
    assert not_ready and not any(not_ready), "a command went out while the link was down"
    assert all(ok for t, state, ok in log if t > t_back + 0.1), "commands refused after the link came back"
    assert before and after
    # angles are host-side cumulative: they carry on from before the unplug, never jump back to 0
    assert all(a >= b - 0.05 for a, b in zip(after[0].angles, before[-1].angles))
    half = after[len(after) // 2:]
    span = half[-1].t_board - half[0].t_board
    speeds = [(b - a) / span for a, b in zip(half[0].angles, half[-1].angles)]
    assert all(abs(v - slow) <= SPEED_TOLERANCE * slow for v in speeds), speeds


def _drain(q: asyncio.Queue) -> list:
    out = []
    while not q.empty():
        out.append(q.get_nowait())
    return out
