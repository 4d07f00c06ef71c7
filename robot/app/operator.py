"""What an operator or a fleet master may ask of the running controller, in one place.

The control socket (``robot.app.control_server``) and the VDA 5050 link (``robot.app.fleet``)
turn their requests into these calls, so both refuse the same things for the same reasons:

- ``status``: the fused pose and covariance, localization quality and reason, protection levels
  when the core reports them, the mission, the chassis link, battery and cameras;
- ``set_pose``: like AMCL's initial pose, but checked: refused outside the map, while the robot
  moves, or when the localizer, run from the given pose on the newest depth frames, finds no map
  wall there or puts the robot farther away than the given uncertainty allows; ``force`` skips
  the checks (the operator knows better, e.g. the cameras are covered);
- ``go`` / ``goto``: a path (parsed strictly, inside the map) or one target; refused while a
  mission runs unless ``replace`` (the running one then brakes to rest within the limits first);
- ``pause`` / ``resume`` / ``abort``; ``limits``: lower the speed limit (never above the config);
- ``relocalize``: the global search (``robot.localization.relocalize``) on the newest frames, in
  a worker thread; a unique answer becomes the pose, an ambiguous one is only reported.
- ``recover``: start the recovery supervisor's sequence afresh (relocalize, then the in-place
  turn and the move to tell places apart, as the config allows). A turn or move that something
  stopped (the protective stop, a fault) ends its sequence for good, so that a robot stopped by
  something beside it never starts moving again on its own; this is how a person who has looked
  lets it try again. Refused while a mission drives the robot, or with recovery disabled.

Everything here runs on the app's event loop, like the core itself; the localizer work runs on
this module's own worker thread with its own ``Localizer``, so it never shares state with the
app's localization thread. Refusals raise ``CommandRefused`` (or ``ConfigError`` for a bad path),
each with one sentence saying why.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import time
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import wrap_angle
from robot.config.schema import parse_yaml
from robot.control.core import CommandRefused
from robot.control.path_file import PathPlan, Waypoint, check_path_in_bounds, parse_path
from robot.localization.localizer import DEFAULT_COARSE_STD, FIX_STATUSES

if TYPE_CHECKING:
    from robot.app.controller import RobotApp

log = logging.getLogger(__name__)

STILL_SPEED = 1e-3  # m/s and rad/s: a command below this counts as standing still
MAX_STD_XY = 10.0  # m
MAX_STD_PHI = math.pi  # rad
RELOCALIZE_COV_FLOOR = (0.01, 0.01, math.radians(1.0))  # std added to a relocalized pose (m, m, rad)


def remote_services(app: RobotApp) -> list:
    """The services the robot config asks for: the control socket and, when enabled, the fleet link."""
    services: list = []
    operator = Operator(app)
    if app.robot.control_api.enabled:
        from robot.app.control_server import ControlServer

        services.append(ControlServer(operator, app.robot.control_api))
    if app.robot.fleet.enabled:
        from robot.app.fleet.link import FleetLink, app_vehicle, map_id_for  # paho and jsonschema load at start

        services.append(FleetLink(app_vehicle(app, operator), app.robot.fleet, map_id_for(app, app.robot.fleet)))
    services.append(operator)  # stopped last: its worker thread
    return services


def json_safe(value: Any) -> Any:
    """Plain JSON types only: numpy values become Python numbers, non-finite floats become None."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    if value is None or isinstance(value, str):
        return value
    return str(value)


class Operator:
    """The operator's commands on one running :class:`RobotApp` (call them on its event loop)."""

    def __init__(self, app: RobotApp):
        self.app = app
        self._executor: Optional[concurrent.futures.ThreadPoolExecutor] = None
        self._localizer = None
        self._relocalizer = None
        self._reloc_job: Optional[concurrent.futures.Future] = None

    # -- service lifecycle (the app starts and stops it with the others) ----------------------

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=False)  # a running relocalization finishes on its own; nobody waits

    # -- reading --------------------------------------------------------------------------------

    def status(self) -> Dict[str, Any]:
        app, core = self.app, self.app.core
        t = time.monotonic()
        s = app.status(t)
        out: Dict[str, Any] = {"t": t, "pose": None}
        if "x" in s:
            out["pose"] = {"x": s["x"], "y": s["y"], "phi": s["phi"], "cov": s.get("cov")}
        out["quality"] = {"state": s.get("quality"), "reason": s.get("reason", ""), "pos_std": s.get("pos_std"),
                          "localized": s.get("localized", False)}
        levels = {k: v for k, v in s.items() if "protection" in k}
        if levels:
            out["protection_levels"] = levels
        traj = core.trajectory
        out["mission"] = {"mode": core.mode, "active": core.mission_active, "paused": core.paused,
                          "state": traj.state if traj is not None else "idle",
                          "waypoint": traj.waypoint_index if traj is not None else None,
                          "waypoints": len(traj.plan.waypoints) if traj is not None else 0,
                          "source": traj.plan.source if traj is not None else None,
                          "speed_limit": core.speed_limit, "max_speed": app.robot.control.max_speed}
        last = app.last_output
        if last is not None:
            c = last.command
            out["command"] = {"vx": c.vx, "vy": c.vy, "wz": c.wz, "sent": last.wheels is not None,
                              "speed_scale": last.speed_scale, "reason": last.reason}
        board = app.chassis.status
        out["chassis"] = {"link": app.chassis.link_state.value}
        if board is not None:
            out["chassis"].update({"estop": board.estop, "motor_faults": list(board.motor_faults),
                                   "watchdog_tripped": board.watchdog_tripped})
        out["battery"] = {"voltage": board.battery_v if board is not None else None}
        out["cameras"] = dict(app.camera_states)
        rec = core.recovery
        out["recovery"] = {"state": rec.state, "reason": rec.reason, "hypotheses": rec.hypotheses}
        return json_safe(out)

    def moving(self) -> bool:
        last = self.app.last_output
        if last is None:
            return False
        c = last.command
        return max(abs(c.vx), abs(c.vy), abs(c.wz)) > STILL_SPEED

    def fresh_frames(self) -> List[Any]:
        """The newest frame of each camera, if younger than ``control_api.frame_max_age``."""
        now = time.monotonic()
        max_age = self.app.robot.control_api.frame_max_age
        return [f for f in self.app.latest_frames.values() if now - f.t_capture <= max_age]

    # -- the pose -------------------------------------------------------------------------------

    async def set_pose(self, pose: Sequence[float], std: Optional[Sequence[float]] = None, force: bool = False,
                       source: str = "operator") -> Dict[str, Any]:
        """Check (unless ``force``) and set the pose; the check's findings."""
        x, y, phi = (float(v) for v in pose)
        if not all(math.isfinite(v) for v in (x, y, phi)):
            raise CommandRefused(f"the pose must be finite, got ({x}, {y}, {phi})")
        if abs(phi) > 2.0 * math.pi:
            raise CommandRefused(f"the heading is in radians and must be within +-2 pi, got {phi:.6g} (degrees?)")
        phi = float(wrap_angle(phi))
        if std is None:
            sx, _, sp = self.app.options.initial_cov
        else:
            sx, sp = (float(v) for v in std)
            if not (math.isfinite(sx) and 0.0 < sx <= MAX_STD_XY and math.isfinite(sp) and 0.0 < sp <= MAX_STD_PHI):
                raise CommandRefused(f"std must be 0 < xy <= {MAX_STD_XY:g} m and 0 < phi <= pi rad, got ({sx}, {sp})")
        cov = np.diag([sx * sx, sx * sx, sp * sp])
        check: Dict[str, Any] = {"checked": False}
        if not force:
            self._check_inside_map(x, y)
            if self.moving():
                raise CommandRefused("the robot is moving: pause or abort first (the pose check needs it standing "
                                     "still), or force")
            check = await self._check_against_cameras((x, y, phi), cov, sx, sp)
        self.app.set_pose((x, y, phi), cov, source)
        return {"pose": [x, y, phi], "std": [sx, sp], "forced": bool(force), "check": check}

    def _check_inside_map(self, x: float, y: float) -> None:
        lo, hi = self.app.plane_map.bounds()
        if not (lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]):
            raise CommandRefused(f"({x:.3f}, {y:.3f}) is outside the map (x in [{lo[0]:.3f}, {hi[0]:.3f}], "
                                 f"y in [{lo[1]:.3f}, {hi[1]:.3f}])")

    async def _check_against_cameras(self, pose: Tuple[float, float, float], cov: np.ndarray, sx: float,
                                     sp: float) -> Dict[str, Any]:
        frames = self.fresh_frames()
        if not frames:
            raise CommandRefused("no fresh depth frame to check the pose against (cameras: "
                                 + ", ".join(f"{k} {v}" for k, v in self.app.camera_states.items()) + "); or force")
        localizer = await self._run(self._get_localizer)
        # Searched with at least the localizer's cold-start prior, so that walls a wrong pose
        # misplaces are still found where they really are, and the offset shows the error.
        wide = np.diag([s * s for s in DEFAULT_COARSE_STD])
        result = await self._run(localizer.localize, frames, pose, np.maximum(cov, wide), self.app.options.method)
        used = [p.id for p in result.planes if p.used]
        if result.status == "no_planes" or not used:
            reasons = sorted({p.reason for p in result.planes if not p.used})
            raise CommandRefused("the cameras see none of the walls the map predicts from that pose"
                                 + (f" ({'; '.join(reasons)[:200]})" if reasons else "") + "; or force")
        against = (getattr(result, "integrity", None) or {}).get("evidence_against") or []
        if result.status == "inconsistent" or against:
            raise CommandRefused(f"what the cameras see contradicts that pose ({result.status}"
                                 + (f"; depth behind {', '.join(map(str, against))[:120]}" if against else "")
                                 + "); or force")
        if result.status not in FIX_STATUSES:
            # A wall the pose predicts but the cameras do not find where it should be leaves a
            # direction unconfirmed: exactly the direction in which a wrong pose would be wrong.
            missed = "; ".join(f"{p.id} ({p.camera}): {p.reason}" for p in result.planes if not p.used)
            raise CommandRefused(f"the cameras cannot confirm that pose in every direction (walls found: "
                                 f"{', '.join(used)}" + (f"; not found: {missed}"[:240] if missed else "")
                                 + "); or force")
        moved = math.hypot(result.x - pose[0], result.y - pose[1])
        turned = abs(float(wrap_angle(result.phi - pose[2])))
        cfg = self.app.robot.control_api
        tol_xy = 3.0 * sx + cfg.pose_check_xy
        tol_phi = 3.0 * sp + math.radians(cfg.pose_check_phi_deg)
        found = [round(result.x, 4), round(result.y, 4), round(result.phi, 5)]
        if moved > tol_xy or turned > tol_phi:
            raise CommandRefused(f"the cameras put the robot at ({found[0]:.3f}, {found[1]:.3f}, "
                                 f"{math.degrees(found[2]):.1f} deg), {moved:.3f} m and {math.degrees(turned):.1f} deg "
                                 f"from the given pose (allowed: {tol_xy:.3f} m, {math.degrees(tol_phi):.1f} deg from the "
                                 "given std); give a larger std, or force")
        return {"checked": True, "cameras": [f.camera for f in frames], "walls": used, "found": found,
                "offset_m": moved, "offset_rad": turned}

    # -- missions -------------------------------------------------------------------------------

    def go_text(self, text: str, name: str = "<path>", replace: bool = False) -> Dict[str, Any]:
        """A path file's YAML text (never a file name: the controller opens no file a client names)."""
        plan = parse_path(parse_yaml(text, name), source=name)
        return self.go(plan, replace)

    def go(self, plan: PathPlan, replace: bool = False) -> Dict[str, Any]:
        core = self.app.core
        if not core.initialized:
            raise CommandRefused("the robot has no pose: set one first (set-pose or relocalize)")
        lo, hi = self.app.plane_map.bounds()
        check_path_in_bounds(plan, lo[:2], hi[:2])
        replaced = core.mission_active
        core.go(plan, replace=replace)
        out: Dict[str, Any] = {"waypoints": len(plan.waypoints), "replaced": bool(replaced), "paused": core.paused}
        if plan.start is not None:
            out["note"] = "the path's start is not used: the robot starts where it is"
        return out

    def goto(self, x: float, y: float, phi: Optional[float] = None, speed: Optional[float] = None,
             tolerance: Optional[float] = None, replace: bool = False) -> Dict[str, Any]:
        # The waypoint checks its own ranges (ConfigError naming the value), as in a path file.
        wp = Waypoint(x=float(x), y=float(y), heading=None if phi is None else float(phi),
                      **({} if speed is None else {"speed": float(speed)}),
                      **({} if tolerance is None else {"tolerance": float(tolerance)}))
        return self.go(PathPlan(waypoints=(wp,), source=f"goto ({x:.3f}, {y:.3f})"), replace)

    def pause(self) -> Dict[str, Any]:
        self.app.pause()
        return {"paused": True, "mission": self.app.core.mission_active}

    def resume(self) -> Dict[str, Any]:
        self.app.resume()
        return {"paused": False, "mission": self.app.core.mission_active}

    def abort(self, reason: str = "aborted by operator") -> Dict[str, Any]:
        had = self.app.core.mission_active
        self.app.abort(reason)
        return {"aborted": bool(had)}

    def limits(self, speed: Optional[float] = None, reset: bool = False) -> Dict[str, Any]:
        core = self.app.core
        if reset:
            core.set_speed_limit(None)
        elif speed is not None:
            core.set_speed_limit(speed)
        return {"speed": core.speed_limit, "max_speed": self.app.robot.control.max_speed}

    # -- relocalization -------------------------------------------------------------------------

    async def relocalize(self, apply: bool = True, region: Optional[Sequence[float]] = None) -> Dict[str, Any]:
        from robot.localization.relocalize import UNIQUE

        if self._reloc_job is not None and not self._reloc_job.done():
            raise CommandRefused("a relocalization is already running")
        if apply and self.moving():
            raise CommandRefused("the robot is moving: pause or abort first (relocalization needs it standing still)")
        frames = self.fresh_frames()
        if not frames:
            raise CommandRefused("no fresh depth frame to relocalize from")
        relocalizer = await self._run(self._get_relocalizer)
        self._reloc_job = self._pool().submit(relocalizer.relocalize, frames, region)
        res = await asyncio.wrap_future(self._reloc_job)
        applied = False
        if apply and res.verdict == UNIQUE:
            if self.moving():
                raise CommandRefused("the robot started moving during the search: its answer is stale")
            h = res.hypotheses[0]
            floor = np.diag([s * s for s in RELOCALIZE_COV_FLOOR])
            self.app.set_pose((h.x, h.y, h.phi), np.asarray(h.cov, float) + floor, "relocalize", h.hidden_walls)
            applied = True
        return {"verdict": res.verdict, "reason": res.reason, "applied": applied, "ms": res.ms,
                "walls_seen": res.walls_seen, "hypotheses": [h.to_json() for h in res.hypotheses[:5]]}

    def recover(self, why: str = "an operator asked to relocalize again") -> Dict[str, Any]:
        app = self.app
        if not app.robot.recovery.enabled:
            raise CommandRefused("recovery is disabled in the config (recovery.enabled: false)")
        if app.core.recovery.turning or app.core.recovery.moving:
            raise CommandRefused(f"a recovery sequence is driving already ({app.core.recovery.reason})")
        if self.moving():
            raise CommandRefused("the robot is moving: pause or abort first, and let it brake "
                                 "(relocalization needs it standing still)")
        app.restart_recovery(why)
        return app.core.recovery.to_json()

    # -- worker thread --------------------------------------------------------------------------

    def _pool(self) -> concurrent.futures.ThreadPoolExecutor:
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="operator")
        return self._executor

    async def _run(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self._pool(), fn, *args)

    def _get_localizer(self):
        if self._localizer is None:
            from robot.localization.localizer import Localizer

            self._localizer = Localizer(self.app.robot, self.app.plane_map)
        return self._localizer

    def _get_relocalizer(self):
        if self._relocalizer is None:
            from robot.localization.relocalize import Relocalizer

            self._relocalizer = Relocalizer(self.app.robot, self.app.plane_map, self._get_localizer())
        return self._relocalizer


__all__ = ["Operator", "json_safe", "remote_services", "STILL_SPEED"]
