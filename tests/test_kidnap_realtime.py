"""The kidnapped robot in the real-time app: the asyncio shell (``RobotApp``) with the pty firmware
emulator and fake cameras, as ``robotctl sim --realtime --kidnap-at`` runs it. The sim-clock
version of the same story is tests/test_kidnap.py.

Every wait is for a state the app reached (on_tick samples), with a hang guard only; nothing is
asserted about how many seconds or ticks anything took, since that depends on the machine.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional, Tuple

import pytest

from firmware_protocol import SetWheelSpeeds
from robot.app.controller import AppOptions, RobotApp
from robot.app.operator import Operator
from robot.config import load_robot_config
from robot.control.path_file import load_path
from robot.control.recovery import AMBIGUOUS, CONFIRMING, MOVING, RELOCALIZING, TRACKING
from robot.maps.plane_map import load_plane_map
from robot.recording.recorder import NullRecorder
from robot.recording.schema import TOPIC_STATUS
from robot.sim.realtime import RealtimeSimSettings, sim_rig
from robot.sim.runner import DwellWatcher

ROBOT = load_robot_config("config/robot.yaml")
HOUSE = load_plane_map("config/maps/fzk_haus_ground.yaml")
# The room tour's first leg and the turn at its end: the kidnap happens on that leg, so this is
# all of the tour that tells a resumed path from a fresh one. The robot drives it in real time
# and slowly (the room's protection level keeps it degraded), so the whole tour would take the
# test two to three and a half minutes; tests/test_kidnap.py drives the whole tour on the sim clock.
TOUR = replace(load_path("config/paths/fzk_house_room.yaml"), description="FZK house, first leg of the room tour")
TOUR = replace(TOUR, waypoints=TOUR.waypoints[:2])
KIDNAP_TO = (9.6, 7.2, 0.6)  # free floor of the same room, off the first leg (as in test_kidnap.py)
MOVED_BEFORE_KIDNAP = 0.3  # m along the first leg: the robot is cruising, well clear of its start
HANG = 600.0  # s, a guard against a hung app only (the whole test takes under a minute on a loaded 2-core machine)
# The board gets wheel speeds in whole mrad/s: a braking sequence may round up by half of one per wheel.
WIRE_ROUNDING = 4 * 0.5e-3  # rad/s, bound on the norm of the four wheels' rounding


@dataclass
class Tick:
    t: float
    state: str  # the recovery supervisor's
    reason: str
    twist: Tuple[float, float, float]  # the body command (vx, vy, wz) after limits
    wheels: Optional[Tuple[float, float, float, float]]  # what the tick commanded (None: nothing sent)
    truth: Tuple[float, float, float]  # the emulated robot's true pose
    fused: Optional[Tuple[float, float, float]]
    t_board: float
    link: str  # the chassis driver's link state
    goal: Optional[Tuple[float, float, float]] = None  # the recovery move's goal while moving


@dataclass
class Watch:
    """What the app did, tick by tick, filled on its loop and waited on from the test's thread."""

    ticks: List[Tick] = field(default_factory=list)
    targets: List[Tuple[int, float]] = field(default_factory=list)  # (waypoint, true distance to it) at dwell end
    relocalized: List[Tuple[float, float, float]] = field(default_factory=list)  # poses set by relocalization
    cond: threading.Condition = field(default_factory=threading.Condition)
    stopped_why: Callable[[], str] = lambda: "?"
    # Every change of the recovery state as it happens, (ticks so far, state, reason): a state
    # may last less than a control tick (both cameras' frames confirm a relocalization in one
    # fusion step), so sampling it at the ticks could miss it.
    states: List[List[Any]] = field(default_factory=list)
    reasons: List[Tuple[int, str]] = field(default_factory=list)  # (ticks so far, reason) at every reason set

    def log_states_of(self, recovery) -> None:
        watch = self

        class Logged(type(recovery)):
            def __setattr__(self, name, value):
                super().__setattr__(name, value)
                with watch.cond:
                    if name == "state" and (not watch.states or watch.states[-1][1] != value):
                        watch.states.append([len(watch.ticks), value, ""])
                        watch.cond.notify_all()
                    elif name == "reason" and watch.states:
                        watch.states[-1][2] = value
                        watch.reasons.append((len(watch.ticks), value))

        recovery.__class__ = Logged
        self.states.append([0, recovery.state, recovery.reason])

    def wait(self, predicate: Callable[[], bool], what: str, alive: Callable[[], bool]) -> None:
        deadline = time.monotonic() + HANG
        with self.cond:
            while not predicate():
                assert alive(), f"the app stopped before {what}: {self.stopped_why()}"
                left = deadline - time.monotonic()
                assert left > 0, f"hang guard: no {what} within {HANG:.0f} s"
                self.cond.wait(min(left, 1.0))


class _SetPoseTap(NullRecorder):
    """Recording off, except that the poses the app sets from a relocalization are kept (it says
    it records: the app builds recording messages only for a recorder that does)."""

    active = True

    def __init__(self, watch: Watch):
        self.watch = watch

    def write(self, topic: str, t: float, message: Mapping[str, Any]) -> bool:
        if topic == TOPIC_STATUS and message.get("event") == "set_pose" and message.get("source") == "relocalization":
            with self.watch.cond:
                self.watch.relocalized.append((message["x"], message["y"], message["phi"]))
                self.watch.cond.notify_all()
        return False


@contextlib.contextmanager
def _app_running(rig, watch: Watch) -> Iterator[Tuple[threading.Thread, List[int]]]:
    """The rig's app on a thread of its own: (the thread, its exit status once it ended); stopped
    before the rig is torn down if the test ends first (a failed wait)."""
    rc: List[int] = []
    errors: List[BaseException] = []

    def run_app() -> None:
        try:
            rc.append(asyncio.run(rig.app.run()))
        except BaseException as e:  # shown by the failing wait, not lost in the thread
            errors.append(e)

    watch.stopped_why = lambda: f"exit status {rc}, reason {rig.app.exit_reason!r}, errors {errors!r}"
    watch.log_states_of(rig.app.core.recovery)
    thread = threading.Thread(target=run_app, daemon=True)
    thread.start()
    try:
        yield thread, rc
    finally:
        while thread.is_alive():
            rig.app.request_stop("test end")
            thread.join(1.0)


def _angle(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2.0 * math.pi))


def _norm(w) -> float:
    return math.sqrt(sum(v * v for v in w))


def _around(ticks: List[Tick], k: int, n: int = 6) -> str:
    """The ticks next to ``k``, for a failure message: index, time since the previous tick, link, wheels."""
    rows = []
    for j in range(max(k - n, 1), min(k + n, len(ticks))):
        s = ticks[j]
        wheels = "none" if s.wheels is None else "(" + ", ".join(f"{w:+.4f}" for w in s.wheels) + ")"
        rows.append(f"{j}: +{(s.t - ticks[j - 1].t) * 1e3:.0f} ms {s.state} {s.link} {wheels}")
    return "; ".join(rows)


def _transitions(watch: Watch) -> List[Tuple[int, str, str]]:
    """(index of the first tick after it, state, reason) at every change of the recovery state."""
    return [(k, st, why) for k, st, why in watch.states]


@pytest.mark.slow
def test_realtime_kidnapped_robot_holds_relocalizes_and_finishes_its_path():
    watch = Watch()
    dwell = DwellWatcher()
    rig_ref: Dict[str, Any] = {}

    def on_tick(app: RobotApp, t: float) -> None:
        emu = rig_ref["rig"].emulator
        out = app.last_output
        fused = app.core.pose(t)[0] if app.core.initialized else None
        rec = app.core.recovery
        c = out.command
        tick = Tick(t, rec.state, rec.reason, (c.vx, c.vy, c.wz), out.wheels, emu.pose, fused, emu.t_board, app.chassis.link_state.value)
        reached = dwell.finished_dwell(app.core.trajectory)
        with watch.cond:
            watch.ticks.append(tick)
            if reached is not None:
                wp = TOUR.waypoints[reached]
                watch.targets.append((reached, math.hypot(tick.truth[0] - wp.x, tick.truth[1] - wp.y)))
            watch.cond.notify_all()

    start = (TOUR.start.x, TOUR.start.y, TOUR.start.heading)
    opts = AppOptions(install_signal_handlers=False)
    with sim_rig(ROBOT, HOUSE, start, RealtimeSimSettings(fps=10, decimation=4), opts, plan=TOUR,
                 recorder=_SetPoseTap(watch), on_tick=on_tick) as rig:
        rig_ref["rig"] = rig
        with _app_running(rig, watch) as (thread, rc):
            def moved() -> bool:
                x, y, _ = watch.ticks[-1].truth if watch.ticks else start
                return math.hypot(x - start[0], y - start[1]) > MOVED_BEFORE_KIDNAP

            watch.wait(moved, f"{MOVED_BEFORE_KIDNAP} m driven along the first leg", thread.is_alive)
            with watch.cond:
                k_kidnap = len(watch.ticks)  # the first tick that may see the robot at its new place
            rig.emulator.teleport(*KIDNAP_TO)
            watch.wait(lambda: any(st == RELOCALIZING for k, st, _ in watch.states if k >= k_kidnap),
                       "relocalization after the kidnap", thread.is_alive)
            watch.wait(lambda: any(st == CONFIRMING for k, st, _ in watch.states if k >= k_kidnap),
                       "a unique relocalization", thread.is_alive)
            watch.wait(lambda: watch.states[-1][1] == TRACKING and any(
                st == CONFIRMING for k, st, _ in watch.states if k >= k_kidnap), "tracking again", thread.is_alive)
            thread.join(HANG)  # the app ends by itself once the path is complete
            assert not thread.is_alive(), "hang guard: the path did not end"
        received = rig.emulator.received()
        truth_end = rig.emulator.pose
    assert rc == [0] and rig.app.exit_reason == "path complete", (rc, rig.app.exit_reason)

    ticks = watch.ticks
    changes = _transitions(watch)
    # Before the kidnap the views agreed with the pose all along.
    assert all(s.state == TRACKING for s in ticks[:k_kidnap]), changes
    after = [c for c in changes if c[0] >= k_kidnap]
    assert after and after[0][1] == RELOCALIZING and "kidnapped" in after[0][2], changes
    k_hold = after[0][0]
    i_confirm = next(i for i, (_, st, _) in enumerate(after) if st == CONFIRMING)
    k_confirm = after[i_confirm][0]
    k_back = next(k for k, st, _ in after[i_confirm + 1:] if st == TRACKING)  # may be the same tick
    # It came back to tracking only by way of a unique verdict (relocalizing -> confirming), once.
    assert [st for _, st, _ in after][-2:] == [CONFIRMING, TRACKING], changes
    assert all(st != TRACKING for k, st, _ in after if k_hold <= k < k_confirm), changes

    # While it did not know where it was it only braked: on every axis the command kept its sign
    # and shrank, the wheel speed never grew, and once at zero it stayed there until confirmed.
    held = ticks[k_hold:k_back]
    sent = [(k_hold + i, s) for i, s in enumerate(held) if s.wheels is not None]
    assert sent, "nothing was commanded while holding"
    not_braking = [(k, axis, a.twist[axis], b.twist[axis]) for (_, a), (k, b) in zip(sent, sent[1:]) for axis in range(3)
                   if abs(b.twist[axis]) > abs(a.twist[axis]) or b.twist[axis] * a.twist[axis] < 0.0]
    assert not not_braking, ("commanded twist grew or reversed while holding (tick, axis, before, after): "
                             f"{not_braking[:5]}; {_around(ticks, not_braking[0][0])}")
    speeds = [(k, _norm(s.wheels)) for k, s in sent]
    grew = [(k, a, b) for (_, a), (k, b) in zip(speeds, speeds[1:]) if b > a + 1e-9]
    assert not grew, f"wheel speed grew while holding (tick, before, after, rad/s): {grew[:5]}; {_around(ticks, grew[0][0])}"
    k_still = next((k for k, v in speeds if v == 0.0), None)
    assert k_still is not None and k_still < k_confirm, "still moving when the verdict came"
    assert all(v == 0.0 for k, v in speeds if k >= k_still)
    p0, p1 = ticks[k_still].truth, ticks[k_back].truth
    drift = math.hypot(p1[0] - p0[0], p1[1] - p0[1])
    assert drift < 1e-3, f"the robot moved {drift * 1e3:.1f} mm while holding still"
    # ... and so the board saw it (on its own clock: from the last tick before the hold, whose
    # cruising command may still have been on the wire, to the last tick of the hold).
    t0, t1 = ticks[k_hold - 1].t_board, ticks[k_back - 1].t_board
    on_board = [_norm(m.rad_s) for t, m in received if isinstance(m, SetWheelSpeeds) and t0 <= t <= t1]
    grew = [(a, b) for a, b in zip(on_board, on_board[1:]) if b > a + WIRE_ROUNDING]
    assert on_board and not grew, f"the board got faster wheel commands while holding (rad/s): {grew[:5]}"

    # The relocalized pose, and the fused pose when it resumed, are where the robot truly stands.
    assert watch.relocalized, "no pose was set by a relocalization"
    x, y, phi = watch.relocalized[-1]
    tx, ty, tphi = ticks[k_confirm].truth
    assert math.hypot(x - tx, y - ty) < 0.02 and _angle(phi, tphi) < math.radians(1.0), (watch.relocalized, ticks[k_confirm].truth)
    back = ticks[k_back]
    (fx, fy, fphi), (tx, ty, tphi) = back.fused, back.truth
    err, err_phi = math.hypot(fx - tx, fy - ty), _angle(fphi, tphi)
    assert err < 0.02 and err_phi < math.radians(1.0), f"fused pose off by {err * 1e3:.1f} mm, {math.degrees(err_phi):.2f} deg"

    # Then it drove the rest of its path: every target once, in order, truly within its tolerance.
    assert [i for i, _ in watch.targets] == list(range(len(TOUR.waypoints))), watch.targets
    for i, e in watch.targets:
        assert e < TOUR.waypoints[i].tolerance, f"target {i + 1}: true error {e * 1e3:.1f} mm"
    last = TOUR.waypoints[-1]
    assert math.hypot(truth_end[0] - last.x, truth_end[1] - last.y) < last.tolerance


@pytest.mark.slow
def test_realtime_ambiguous_start_moves_to_tell_the_places_apart_then_tracks(twin_rooms):
    """Started without a pose in one of two rooms that look alike from where it stands (conftest's
    twin_rooms), with recovery.move_to_tell_apart: the app plans a move off its loop, drives it
    (turn, then straight ahead), relocalizes with both views and tracks where the robot truly is.

    The first move is stopped by a stalled control loop (the app's test hook), as a starved host
    can stall it. The safe answer is checked: the robot holds, keeps the verdict, and does not
    start moving again on its own. Then the test asks for a new try as an operator would
    (``recover``), and the story is checked on the move that ran to its end. A busy machine may
    stall a later move as well: that is answered the same way. Where the stall came late enough
    that the views of the stopped move already tell the rooms apart, the robot is unique from
    where it stands: then it must be right, confirmed and tracked without moving again."""
    robot = replace(ROBOT, recovery=replace(ROBOT.recovery, move_to_tell_apart=True))
    plane_map, start = twin_rooms
    watch = Watch()
    rig_ref: Dict[str, Any] = {}

    def on_tick(app: RobotApp, t: float) -> None:
        out = app.last_output
        rec = app.core.recovery
        c = out.command
        tick = Tick(t, rec.state, rec.reason, (c.vx, c.vy, c.wz), out.wheels, rig_ref["rig"].emulator.pose,
                    app.core.pose(t)[0] if app.core.initialized else None, 0.0, app.chassis.link_state.value,
                    rec.move_goal if rec.moving else None)
        with watch.cond:
            watch.ticks.append(tick)
            watch.cond.notify_all()

    def entered(state: str, since: int) -> bool:
        return any(st == state for k, st, _ in watch.states if k >= since)

    def tracking_after_a_move(since: int) -> bool:
        # A control tick in the state 'tracking' after a confirmation: the pose it fused then.
        return (entered(CONFIRMING, since) and bool(watch.ticks) and watch.ticks[-1].state == TRACKING
                and watch.ticks[-1].fused is not None)

    def stop_reason(since: int) -> str:
        return next((why for k, why in watch.reasons if k >= since and "the move was stopped" in why), "")

    retries = 0
    stopped_short = False  # the stopped move alone told the rooms apart (no move ran to its end)
    with sim_rig(robot, plane_map, start, RealtimeSimSettings(fps=10, decimation=4), AppOptions(install_signal_handlers=False),
                 recorder=_SetPoseTap(watch), on_tick=on_tick) as rig:
        rig_ref["rig"] = rig
        operator = Operator(rig.app)
        with _app_running(rig, watch) as (thread, _):
            since = 0  # the tick from which this try's states count
            while True:
                watch.wait(lambda since=since: entered(MOVING, since), "a planned move", thread.is_alive)
                if retries == 0:
                    watch.wait(lambda: watch.ticks[-1].state == MOVING and watch.ticks[-1].wheels is not None
                               and _norm(watch.ticks[-1].wheels) > 0.0, "the move under way", thread.is_alive)
                    rig.app.stall_control_loop(0.5)
                watch.wait(lambda since=since: tracking_after_a_move(since) or bool(stop_reason(since)),
                           "tracking after the move", thread.is_alive)
                with watch.cond:
                    if tracking_after_a_move(since):
                        k_back = len(watch.ticks) - 1
                        break
                    why = stop_reason(since)
                assert "obstacle" not in why, f"the protective stop saw something in the empty rooms: {why}"
                # The host stalled: the robot holds with the verdict and brakes to rest...
                watch.wait(lambda: watch.ticks[-1].state == AMBIGUOUS and watch.ticks[-1].twist == (0.0, 0.0, 0.0)
                           and _norm(rig.emulator.true_wheel_speeds) < 1e-3, "the robot at rest after the stop",
                           thread.is_alive)
                with watch.cond:
                    k_rest = len(watch.ticks)
                # ... and stays there: it plans no new move on its own over further relocalizations.
                # What the stopped move saw may already tell the rooms apart: then one of them is
                # unique from where the robot stands, and it is confirmed without a move.
                attempts = rig.app.core.recovery.attempts
                watch.wait(lambda attempts=attempts, k_rest=k_rest: (rig.app.core.recovery.attempts >= attempts + 2
                                                                   or entered(CONFIRMING, k_rest)),
                           "two more relocalizations, or a unique answer from where it stands", thread.is_alive)
                with watch.cond:
                    assert not entered(MOVING, k_rest), watch.states
                    k_unique = next((k for k, st, _ in watch.states if k >= k_rest and st == CONFIRMING), None)
                    assert all(s.twist == (0.0, 0.0, 0.0) for s in watch.ticks[k_rest:k_unique])
                retries += 1
                if k_unique is not None:
                    stopped_short = True
                    watch.wait(lambda k_rest=k_rest: tracking_after_a_move(k_rest), "tracking after the unique answer",
                               thread.is_alive)
                    with watch.cond:
                        k_back = len(watch.ticks) - 1
                    break
                assert retries <= 5, f"every move was stopped: {why}"
                with watch.cond:
                    since = len(watch.ticks)
                rig.app.call_on_loop(lambda: operator.recover("the test asks again after a host stall")).result(HANG)
    assert retries >= 1, "the stalled loop did not stop the first move"
    if stopped_short:
        # Tracking where it truly stands, without having moved after the stop.
        truth = watch.ticks[k_back].truth
        x, y, phi = watch.relocalized[-1]
        assert math.hypot(x - truth[0], y - truth[1]) < 0.02 and _angle(phi, truth[2]) < math.radians(1.0)
        fx, fy, fphi = watch.ticks[k_back].fused
        assert math.hypot(fx - truth[0], fy - truth[1]) < 0.02 and _angle(fphi, truth[2]) < math.radians(1.0)
        return
    # The last move ran to its end: the ticks from its first one on.
    k_move = next(k for k in range(k_back, -1, -1) if watch.ticks[k].state == MOVING)
    while k_move > 0 and watch.ticks[k_move - 1].state == MOVING:
        k_move -= 1
    goal, start = watch.ticks[k_move].goal, watch.ticks[k_move - 1].truth
    states = [st for k, st, _ in watch.states if k >= since]
    assert MOVING in states and states.index(MOVING) < states.index(CONFIRMING), watch.states
    # It moved about as far as planned, and the pose it set and then tracked is where it truly stands.
    truth = watch.ticks[k_back].truth
    assert abs(math.hypot(truth[0] - start[0], truth[1] - start[1]) - math.hypot(goal[0], goal[1])) < 0.05
    x, y, phi = watch.relocalized[-1]
    assert math.hypot(x - truth[0], y - truth[1]) < 0.02 and _angle(phi, truth[2]) < math.radians(1.0)
    fx, fy, fphi = watch.ticks[k_back].fused
    assert math.hypot(fx - truth[0], fy - truth[1]) < 0.02 and _angle(fphi, truth[2]) < math.radians(1.0)
    # The move: a turn on the spot, then straight ahead, never faster than the move's speed.
    driving = [s.twist for s in watch.ticks if s.state == MOVING and s.wheels is not None]
    assert driving and all(math.hypot(vx, vy) <= robot.recovery.move_speed + 1e-9 for vx, vy, _ in driving)
    assert all(vx >= 0.99 * math.hypot(vx, vy) for vx, vy, wz in driving if wz == 0.0)  # ahead, as the robot faces
