"""Live view for engineers: a Foxglove WebSocket server inside the app's event loop.

Channels (JSON encoding, JSON Schema; Foxglove well-known schemas where one fits, as supersets,
so the 3D, Image and Plot panels work without configuration):

- ``/map``: ``foxglove.SceneUpdate`` drawing every wall polygon and its id, plus ``planes``
  (id, normal, d, polygons). Latched: sent when published and to every client that subscribes.
- ``/pose``: ``foxglove.PoseInFrame`` plus ``t``, ``x``, ``y``, ``phi``, ``cov`` (3x3 row-major),
  ``quality`` (localized | degraded | lost) and ``reason`` (same fields as the recording's).
- ``/planes``: per-plane fit results of one camera frame: camera, and per plane id, inliers,
  used, reason.
- ``/roi/<camera>``: ``foxglove.CompressedImage``, the ROI label image as a colour PNG.
- ``/cmd``: the body velocity command (vx, vy, wz) and, when given, the wheel speeds.

Cost and safety: ``publish_*`` are plain calls that never block and never raise. With no
client subscribed to a channel they return after one set lookup, before building anything.
Otherwise the message is encoded once and queued per client; each client has its own writer
task and a bounded queue, so a slow or stalled client loses its oldest messages (counted in
``stats``) without delaying the caller or the other clients. ROI images, the one message that
costs milliseconds to encode on a Nano, are rate-limited and PNG-encoded in a worker thread.

``foxglove-websocket`` (the optional ``live`` extra) is imported only by ``LiveView.start``.
It is an inactive package (frozen at 0.1.4) built on websockets' legacy server; per-client
queues and the latched map use two of its internals (the client list and the text-message
hook), which is why the extra pins ``<0.2``. ``NullLiveView`` has the same methods and does
nothing: the default, and what the app uses when the extra is missing.
"""

from __future__ import annotations

import asyncio
import base64
import collections
import json
import logging
import math
import threading
import warnings
from typing import Any, Callable, Deque, Dict, Iterable, List, Mapping, Optional, Sequence

import numpy as np

from robot.base.errors import ConfigError, DriverError
from robot.recording import schema as ms

log = logging.getLogger(__name__)

TOPIC_MAP = "/map"
TOPIC_POSE = "/pose"
TOPIC_PLANES = "/planes"
TOPIC_CMD = "/cmd"
ROI_PREFIX = "/roi/"
MAP_FRAME = "map"
SUBPROTOCOL = "foxglove.websocket.v1"
INSTALL_HINT = "pip install 'planeloc-robot[live]'"

DEFAULT_CLIENT_QUEUE = 32  # messages per client: about 1 s of pose and planes at 30 Hz
ROI_MAX_WIDTH = 424  # px: the label image is a diagnostic; a larger one is decimated
ROI_MAX_HZ = 5.0  # per camera: PNG encoding is the only per-message cost that is not trivial

_NUM = {"type": "number"}
_STR = {"type": "string"}
_POINT = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}
_COLOR = {"type": "object", "properties": {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM}}
_POSE = {"type": "object", "properties": {
    "position": _POINT, "orientation": {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM}}}}


def _schema(title: str, description: str, properties: Dict[str, Any]) -> Dict[str, Any]:
    return {"title": title, "description": description, "type": "object", "properties": properties}


MAP_SCHEMA = ("foxglove.SceneUpdate", _schema(
    "foxglove.SceneUpdate", "The plane map: wall outlines and ids for the 3D panel, and the planes themselves",
    {"deletions": {"type": "array", "items": {"type": "object"}},
     "entities": {"type": "array", "items": {"type": "object", "properties": {
         "timestamp": ms._TIME, "frame_id": _STR, "id": _STR, "frame_locked": {"type": "boolean"},
         "lifetime": ms._TIME,
         "lines": {"type": "array", "items": {"type": "object", "properties": {
             "type": {"type": "integer"}, "pose": _POSE, "thickness": _NUM, "scale_invariant": {"type": "boolean"},
             "points": {"type": "array", "items": _POINT}, "color": _COLOR}}},
         "texts": {"type": "array", "items": {"type": "object", "properties": {
             "pose": _POSE, "billboard": {"type": "boolean"}, "font_size": _NUM,
             "scale_invariant": {"type": "boolean"}, "color": _COLOR, "text": _STR}}}}}},
     "planes": {"type": "array", "items": {"type": "object", "properties": {
         "id": _STR, "normal": {"type": "array", "items": _NUM}, "d": _NUM,
         "polygons": {"type": "array", "items": {"type": "array", "items": {"type": "array", "items": _NUM}}}}}}}))

POSE_SCHEMA = ("foxglove.PoseInFrame", _schema(
    "foxglove.PoseInFrame", "Fused pose (x, y, phi) in the map frame, its 3x3 covariance and the quality state",
    {"timestamp": ms._TIME, "frame_id": _STR, "pose": _POSE, "t": _NUM, "x": _NUM, "y": _NUM, "phi": _NUM,
     "cov": {"type": "array", "items": _NUM, "minItems": 9, "maxItems": 9,
             "description": "3x3 covariance of (x, y, phi), row-major"},
     "quality": {"type": ["string", "null"], "description": "localized | degraded | lost"},
     "reason": {"type": "string", "description": "why the quality is not 'localized'; empty when it is"}}))

PLANES_SCHEMA = ("robot.PlaneReports", _schema(
    "robot.PlaneReports", "Per-plane results of localizing one camera frame: which planes were fitted and used, "
    "and why not", {"t": _NUM, "camera": _STR, "planes": {"type": "array", "items": {"type": "object", "properties": {
        "id": _STR, "camera": _STR, "inliers": {"type": "integer"}, "used": {"type": "boolean"},
        "reason": _STR}}}}))

CMD_SCHEMA = ("robot.VelocityCommand", _schema(
    "robot.VelocityCommand", "Body velocity command of the trajectory controller (robot frame)",
    {"t": _NUM, "vx": _NUM, "vy": _NUM, "wz": _NUM,
     "wheel_speeds": {"type": ["array", "null"], "items": _NUM,
                      "description": "front-left, front-right, rear-left, rear-right, rad/s"}}))

ROI_SCHEMA = ("foxglove.CompressedImage", _schema(
    "foxglove.CompressedImage", "ROI label image: one colour per predicted plane, dark where no plane is expected",
    {"timestamp": ms._TIME, "frame_id": _STR, "data": {"type": "string", "contentEncoding": "base64"},
     "format": _STR}))

# Label colours (RGB): distinct hues, so neighbouring planes are told apart at a glance.
PALETTE = np.array([
    (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
    (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212), (0, 128, 128), (170, 110, 40),
], dtype=np.uint8)
NO_PLANE_RGB = (24, 24, 24)


# Message encoding (pure)  -------------------------------------------------------------------------

def map_message(plane_map, t: float = 0.0) -> Dict[str, Any]:
    """``/map``: a SceneUpdate with each polygon as a closed line and each plane id as a label."""
    lines: List[Dict[str, Any]] = []
    texts: List[Dict[str, Any]] = []
    planes: List[Dict[str, Any]] = []
    identity = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
    for i, plane in enumerate(plane_map.planes):
        r, g, b = (PALETTE[i % len(PALETTE)] / 255.0).tolist()
        for poly in plane.polygons:
            lines.append({"type": 1, "pose": identity, "thickness": 2.0, "scale_invariant": True,
                          "points": [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in poly],
                          "color": {"r": r, "g": g, "b": b, "a": 1.0}, "colors": [], "indices": []})
        c = np.asarray(plane.vertices, dtype=float).mean(axis=0)
        texts.append({"pose": {"position": {"x": float(c[0]), "y": float(c[1]), "z": float(c[2])},
                               "orientation": identity["orientation"]},
                      "billboard": True, "font_size": 12.0, "scale_invariant": True,
                      "color": {"r": r, "g": g, "b": b, "a": 1.0}, "text": plane.id})
        planes.append({"id": plane.id, "normal": [float(v) for v in plane.normal], "d": float(plane.d),
                       "polygons": [[[float(v) for v in p] for p in poly] for poly in plane.polygons]})
    entity = {"timestamp": ms.stamp(t), "frame_id": MAP_FRAME, "id": "map", "lifetime": {"sec": 0, "nsec": 0},
              "frame_locked": True, "metadata": [], "arrows": [], "cubes": [], "spheres": [], "cylinders": [],
              "lines": lines, "triangles": [], "texts": texts, "models": []}
    return {"deletions": [], "entities": [entity], "planes": planes}


def pose_message(t: float, x: float, y: float, phi: float, cov: Any, quality: Optional[str] = None,
                 reason: str = "") -> Dict[str, Any]:
    """``/pose``: the recording's pose message plus the quality's reason."""
    msg = ms.pose_message(t, x, y, phi, cov, quality=quality, frame_id=MAP_FRAME)
    msg["reason"] = str(reason)
    return msg


def planes_message(t: float, camera: str, reports: Iterable[Any]) -> Dict[str, Any]:
    """``/planes`` for one camera frame, from ``PlaneReport`` objects (robot.localization.localizer) or their
    ``to_json()`` mappings."""
    out = []
    for r in reports:
        get = r.get if isinstance(r, Mapping) else (lambda k, _r=r: getattr(_r, k))
        out.append({"id": str(get("id")), "camera": str(get("camera")), "inliers": int(get("inliers")),
                    "used": bool(get("used")), "reason": str(get("reason"))})
    return {"t": float(t), "camera": str(camera), "planes": out}


def cmd_message(t: float, vx: float, vy: float, wz: float,
                wheel_speeds: Optional[Sequence[float]] = None) -> Dict[str, Any]:
    return {"t": float(t), "vx": float(vx), "vy": float(vy), "wz": float(wz),
            "wheel_speeds": None if wheel_speeds is None else [float(v) for v in wheel_speeds]}


def _check_label(label) -> np.ndarray:
    lab = np.asarray(label)
    if lab.ndim != 2 or lab.size == 0 or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"ROI label image must be a non-empty 2-D integer array, got {lab.dtype} {lab.shape}")
    return lab


# OpenCV writes BGR; the last row is for pixels of no plane.
_LUT_BGR = np.ascontiguousarray(np.vstack([PALETTE, [NO_PLANE_RGB]]).astype(np.uint8)[:, ::-1])


def roi_png(label: np.ndarray, max_width: int = ROI_MAX_WIDTH) -> bytes:
    """Colour PNG of a label image (plane index per pixel, negative for none), decimated to fit."""
    import cv2

    lab = _check_label(label)
    step = max(1, int(math.ceil(lab.shape[1] / float(max_width))))
    lab = lab[::step, ::step]
    idx = np.where(lab < 0, len(PALETTE), np.mod(lab, len(PALETTE))).astype(np.uint8)
    ok, png = cv2.imencode(".png", np.take(_LUT_BGR, idx, axis=0), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("PNG encoding of the ROI label image failed")
    return png.tobytes()


def roi_message(t: float, camera: str, label: np.ndarray) -> Dict[str, Any]:
    return {"timestamp": ms.stamp(t), "frame_id": camera, "format": "png",
            "data": base64.b64encode(roi_png(label)).decode("ascii")}


def roi_topic(camera: str) -> str:
    return ROI_PREFIX + camera


# Availability and choice  ---------------------------------------------------------------------

def _import_foxglove():
    # websockets >= 14 flags its legacy server, which foxglove-websocket is built on, as deprecated
    # at import: a warning the robot's operator can do nothing about.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import foxglove_websocket.server as fws
        from foxglove_websocket.types import BinaryOpcode
        from websockets.exceptions import ConnectionClosed
    return fws, BinaryOpcode, ConnectionClosed


def live_view_missing() -> Optional[str]:
    """Why the live view cannot run here (the ``live`` extra is not installed), or None."""
    try:
        _import_foxglove()
    except ImportError as e:
        return f"foxglove-websocket is not usable ({e})"
    return None


def make_live_view(port: Optional[int], host: str = "127.0.0.1", cameras: Sequence[str] = ()) -> Any:
    """A ``LiveView`` on ``host:port``, or a ``NullLiveView`` when ``port`` is None (the view is off).

    ConfigError (one line, with the install command) when it is asked for and the extra is missing.
    """
    if port is None:
        return NullLiveView()
    missing = live_view_missing()
    if missing:
        raise ConfigError(f"--live needs the optional 'live' extra: {missing}; install it with {INSTALL_HINT}")
    return LiveView(host, int(port), cameras=cameras)


# The null object  ---------------------------------------------------------------------------------

class NullLiveView:
    """The live view switched off: every method does nothing."""

    url: Optional[str] = None

    @property
    def active(self) -> bool:
        return False

    @property
    def stats(self) -> Dict[str, int]:
        return {"clients": 0, "sent": 0, "dropped": 0, "errors": 0}

    async def start(self, plane_map=None) -> None:
        pass

    async def stop(self) -> None:
        pass

    def publish_map(self, plane_map, t: float = 0.0) -> None:
        pass

    def publish_pose(self, t: float, x: float, y: float, phi: float, cov: Any, quality: Optional[str] = None,
                     reason: str = "") -> None:
        pass

    def publish_planes(self, t: float, camera: str, reports: Iterable[Any]) -> None:
        pass

    def publish_roi(self, t: float, camera: str, label: np.ndarray) -> None:
        pass

    def publish_cmd(self, t: float, vx: float, vy: float, wz: float,
                    wheel_speeds: Optional[Sequence[float]] = None) -> None:
        pass


# The server  --------------------------------------------------------------------------------------

class _Outbox:
    """What waits to go to one client: a latched slot (the map) and a bounded queue, oldest dropped."""

    def __init__(self, connection, limit: int, closed_exc):
        self.connection = connection
        self.limit = max(1, int(limit))
        self.items: Deque[bytes] = collections.deque()
        self.latched: Optional[bytes] = None
        self.sent = 0
        self.dropped = 0
        self._closed_exc = closed_exc
        self._wake = asyncio.Event()
        self.task: Optional[asyncio.Task] = None

    def push(self, frame: bytes) -> None:
        if len(self.items) >= self.limit:
            self.items.popleft()
            self.dropped += 1
        self.items.append(frame)
        self._wake.set()

    def push_latched(self, frame: bytes) -> None:
        self.latched = frame  # a newer map replaces one not sent yet
        self._wake.set()

    async def run(self) -> None:
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                while self.latched is not None or self.items:
                    if self.latched is not None:
                        frame, self.latched = self.latched, None
                    else:
                        frame = self.items.popleft()
                    # waits only when the socket's buffer is full: a slow client, whose queue then drops
                    await self.connection.send(frame)
                    self.sent += 1
        except self._closed_exc:
            pass
        except Exception as e:  # the transport failed under us: this client is gone either way
            log.debug("live view: writer for %s stopped: %r", getattr(self.connection, "remote_address", "?"), e)


class LiveView:
    """Foxglove WebSocket server in the running event loop. ``await start()``, publish, ``await stop()``.

    ``publish_*`` may be called from any thread (calls from other threads are handed to the loop),
    and before ``start`` or after ``stop``: they do nothing then, except that the map is kept.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, cameras: Sequence[str] = (),
                 name: str = "planeloc robot", client_queue: int = DEFAULT_CLIENT_QUEUE,
                 roi_max_hz: float = ROI_MAX_HZ):
        self.host = host
        self.port = int(port)
        self.name = name
        self.client_queue = int(client_queue)
        self.roi_min_period = 1.0 / roi_max_hz if roi_max_hz > 0 else 0.0
        self._cameras = list(cameras)
        self._server = None
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._loop_thread: Optional[int] = None
        self._channels: Dict[str, int] = {}
        self._adding: Dict[str, asyncio.Task] = {}
        self._subscribed: set = set()  # channel ids with at least one subscriber (the server's listener)
        self._outboxes: Dict[int, _Outbox] = {}  # by id(connection)
        self._map = None  # the latest plane map, encoded on first demand
        self._map_t = 0.0
        self._map_bytes: Optional[bytes] = None
        self._last_roi: Dict[str, float] = {}
        self._roi_busy: set = set()  # cameras whose last image is being encoded
        self._counts = collections.Counter()
        self._logged: set = set()
        self._header = None
        self._opcode = 1
        self._closed_exc: Any = ()  # websockets' ConnectionClosed, once imported

    # Public interface  --------------------------------------------------------------------------

    @property
    def active(self) -> bool:
        return self._server is not None

    @property
    def url(self) -> Optional[str]:
        return f"ws://{self.host}:{self.port}" if self._server is not None else None

    @property
    def stats(self) -> Dict[str, int]:
        boxes = list(self._outboxes.values())
        return {"clients": len(self._clients()), "subscribed_channels": len(self._subscribed),
                "sent": self._counts["sent"] + sum(b.sent for b in boxes),
                "dropped": self._counts["dropped"] + sum(b.dropped for b in boxes),
                "errors": self._counts["errors"]}

    async def start(self, plane_map=None) -> None:
        """Listen and advertise the channels (and publish ``plane_map`` if given); DriverError naming
        the address if it cannot listen."""
        if plane_map is not None:
            self.publish_map(plane_map)
        if self._server is not None:
            return
        fws, opcode, closed_exc = _import_foxglove()
        self._closed_exc = closed_exc
        self._header = fws.MessageDataHeader
        self._opcode = int(opcode.MESSAGE_DATA)
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        server = _make_server(fws, self, self.host, self.port, self.name)
        server.start()
        opened = asyncio.ensure_future(server.wait_opened())
        # The library's task ends with the error when it cannot listen and never resolves wait_opened.
        done, _ = await asyncio.wait({opened, server._task}, timeout=10.0, return_when=asyncio.FIRST_COMPLETED)
        if opened not in done:
            opened.cancel()
            task = server._task
            if task.done():
                err = task.exception() if not task.cancelled() else None
            else:
                err = None
                server.close()
                try:
                    await server.wait_closed()
                except Exception:  # the failure is reported below
                    pass
            raise DriverError(f"live view: cannot listen on {self.host}:{self.port}: {err or 'timed out'}")
        ws_server = opened.result()
        sockets = list(getattr(ws_server, "sockets", None) or [])
        if sockets:
            self.port = int(sockets[0].getsockname()[1])  # the real one when 0 asked for any free port
        self._server = server
        for topic, schema in ((TOPIC_MAP, MAP_SCHEMA), (TOPIC_POSE, POSE_SCHEMA), (TOPIC_PLANES, PLANES_SCHEMA),
                              (TOPIC_CMD, CMD_SCHEMA)):
            await self._add_channel(topic, schema)
        for cam in self._cameras:
            await self._add_channel(roi_topic(cam), ROI_SCHEMA)
        log.info("live view: Foxglove WebSocket server on %s", self.url)

    async def stop(self) -> None:
        """Close every connection and the listening socket. Idempotent."""
        server, self._server = self._server, None
        if server is None:
            return
        for task in list(self._adding.values()):
            task.cancel()
        boxes, self._outboxes = list(self._outboxes.values()), {}
        for b in boxes:
            self._counts["sent"] += b.sent
            self._counts["dropped"] += b.dropped
            if b.task is not None:
                b.task.cancel()
        server.close()
        try:
            await asyncio.wait_for(server.wait_closed(), 5.0)
        except asyncio.TimeoutError:
            log.warning("live view: the server did not close within 5 s")
        self._channels.clear()
        self._subscribed.clear()

    def publish_map(self, plane_map, t: float = 0.0) -> None:
        """Publish the plane map, and keep it for every client that subscribes later (also before start)."""
        if self._server is not None and not self._on_loop(self.publish_map, plane_map, t):
            return
        self._map, self._map_t, self._map_bytes = plane_map, t, None
        chan = self._channels.get(TOPIC_MAP)
        if chan is None or chan not in self._subscribed:
            return  # encoded when someone subscribes
        for client in self._clients():
            sub = client.subscriptions_by_channel.get(chan)
            if sub is not None:
                self._send_map(client, sub)

    def publish_pose(self, t: float, x: float, y: float, phi: float, cov: Any, quality: Optional[str] = None,
                     reason: str = "") -> None:
        """The fused pose, its covariance and the quality state (localized | degraded | lost) with its reason."""
        if self._wanted(TOPIC_POSE) and self._on_loop(self.publish_pose, t, x, y, phi, cov, quality, reason):
            self._send(TOPIC_POSE, t, lambda: pose_message(t, x, y, phi, cov, quality, reason))

    def publish_planes(self, t: float, camera: str, reports: Iterable[Any]) -> None:
        """Per-plane results of localizing one camera's frame (``PlaneReport``s or their ``to_json()``)."""
        if self._wanted(TOPIC_PLANES) and self._on_loop(self.publish_planes, t, camera, reports):
            self._send(TOPIC_PLANES, t, lambda: planes_message(t, camera, reports))

    def publish_cmd(self, t: float, vx: float, vy: float, wz: float,
                    wheel_speeds: Optional[Sequence[float]] = None) -> None:
        """The body velocity command (m/s, m/s, rad/s in the robot frame) and optionally the wheel speeds."""
        if self._wanted(TOPIC_CMD) and self._on_loop(self.publish_cmd, t, vx, vy, wz, wheel_speeds):
            self._send(TOPIC_CMD, t, lambda: cmd_message(t, vx, vy, wz, wheel_speeds))

    def publish_roi(self, t: float, camera: str, label: np.ndarray) -> None:
        """The ROI label image of one camera frame (plane index per pixel, negative for none).

        At most ``roi_max_hz`` per camera, and one at a time, are encoded, in a worker thread: PNG
        encoding is the one publish that costs milliseconds on a Nano, and the loop must not pay it.
        """
        topic = roi_topic(camera)
        if topic not in self._channels:
            if self._server is not None and self._on_loop(self.publish_roi, t, camera, label):
                self._advertise_later(topic, ROI_SCHEMA)
            return
        if not (self._wanted(topic) and self._on_loop(self.publish_roi, t, camera, label)):
            return
        last = self._last_roi.get(camera)
        if camera in self._roi_busy or (last is not None and 0.0 <= t - last < self.roi_min_period):
            self._counts["roi_skipped"] += 1
            return
        try:
            lab = np.array(_check_label(label), copy=True)  # the caller may reuse its buffer
        except ValueError as e:
            self._error(topic, e)
            return
        self._last_roi[camera] = t
        self._roi_busy.add(camera)
        build = roi_message  # looked up now: the module's function (tests may replace it)
        fut = self._loop.run_in_executor(None, lambda: ms.dumps(build(t, camera, lab)))
        fut.add_done_callback(lambda f: self._roi_encoded(topic, camera, t, f))

    # Private interface  -------------------------------------------------------------------------

    def _wanted(self, topic: str) -> bool:
        """Is anyone subscribed? The one check a publish costs when nobody watches."""
        chan = self._channels.get(topic)
        return chan is not None and chan in self._subscribed

    def _on_loop(self, method, *args) -> bool:
        """True when the caller is on the loop's thread; otherwise hand the call to the loop."""
        if self._server is None:
            return False
        if threading.get_ident() == self._loop_thread:
            return True
        try:
            self._loop.call_soon_threadsafe(method, *args)
        except RuntimeError:  # the loop is closed
            pass
        return False

    def _send(self, topic: str, t: float, build: Callable[[], Dict[str, Any]]) -> bool:
        """Encode once and queue for each subscriber. Nothing is built when nobody listens."""
        if not self._wanted(topic):
            return False
        try:
            payload = ms.dumps(build())
        except Exception as e:  # a bad value from the app must not reach back into its loop
            self._error(topic, e)
            return False
        return self._queue(topic, t, payload)

    def _roi_encoded(self, topic: str, camera: str, t: float, fut) -> None:
        self._roi_busy.discard(camera)
        if fut.cancelled():
            return
        if fut.exception() is not None:
            self._error(topic, fut.exception())
        elif self._wanted(topic):  # still running, still watched
            self._queue(topic, t, fut.result())

    def _queue(self, topic: str, t: float, payload: bytes) -> bool:
        chan = self._channels[topic]
        try:
            clients = self._clients()
            if len(self._outboxes) > len(clients):
                self._prune()
            for client in clients:
                sub = client.subscriptions_by_channel.get(chan)
                if sub is not None:
                    self._outbox(client).push(self._frame(sub, t, payload))
        except Exception as e:  # e.g. a non-finite time stamp: counted, never raised
            self._error(topic, e)
            return False
        return True

    def _frame(self, subscription: int, t: float, payload: bytes) -> bytes:
        ts = max(0, int(round(t * 1e9))) if math.isfinite(t) else 0
        return self._header.pack(self._opcode, subscription, ts) + payload

    def _clients(self) -> Sequence[Any]:
        return self._server._clients if self._server is not None else ()

    def _outbox(self, client) -> _Outbox:
        key = id(client.connection)
        box = self._outboxes.get(key)
        if box is None or box.connection is not client.connection:
            self._prune()
            box = self._outboxes[key] = _Outbox(client.connection, self.client_queue, self._closed_exc)
            box.task = self._loop.create_task(box.run())
        return box

    def _prune(self) -> None:
        """Forget the outboxes of clients that have gone."""
        live = {id(c.connection) for c in self._clients()}
        for key in [k for k in self._outboxes if k not in live]:
            box = self._outboxes.pop(key)
            self._counts["sent"] += box.sent
            self._counts["dropped"] += box.dropped
            if box.task is not None:
                box.task.cancel()

    def _on_subscribe(self, client, subscriptions: List[Mapping[str, Any]]) -> None:
        """A client subscribed: send it the latched map at once if it asked for the map."""
        chan = self._channels.get(TOPIC_MAP)
        if chan is None or self._map is None:
            return
        for sub in subscriptions:
            sub_id = sub.get("id")
            if sub.get("channelId") == chan and client.subscriptions.get(sub_id) == chan:
                self._send_map(client, sub_id)

    def _send_map(self, client, sub_id: int) -> None:
        try:
            if self._map_bytes is None:
                self._map_bytes = ms.dumps(map_message(self._map, self._map_t))
            self._outbox(client).push_latched(self._frame(sub_id, self._map_t, self._map_bytes))
        except Exception as e:
            self._error(TOPIC_MAP, e)

    async def _add_channel(self, topic: str, schema) -> None:
        name, body = schema
        self._channels[topic] = await self._server.add_channel({
            "topic": topic, "encoding": "json", "schemaName": name, "schema": json.dumps(body),
            "schemaEncoding": "jsonschema"})

    def _advertise_later(self, topic: str, schema) -> None:
        """A camera not named at start: advertise its channel; frames before that are not sent."""
        if topic in self._adding or self._server is None:
            return

        async def add():
            try:
                await self._add_channel(topic, schema)
            except Exception as e:
                self._error(topic, e)

        self._adding[topic] = self._loop.create_task(add())

    def _error(self, what: str, e: Exception) -> None:
        self._counts["errors"] += 1
        if what not in self._logged:
            self._logged.add(what)
            log.warning("live view: cannot publish %s: %r (further errors counted, not logged)", what, e)


def _make_server(fws, live: LiveView, host: str, port: int, name: str):
    """A FoxgloveServer that tells ``live`` about subscriptions (first/last via the public listener,
    every subscribe through the message hook, for the latched map)."""

    class Listener(fws.FoxgloveServerListener):
        def on_subscribe(self, server, channel_id):
            live._subscribed.add(channel_id)

        def on_unsubscribe(self, server, channel_id):
            live._subscribed.discard(channel_id)

    class Server(fws.FoxgloveServer):
        async def _handle_connection(self, connection, path: Optional[str] = None) -> None:
            # one-argument handler: websockets' legacy server deprecates the (connection, path) form
            await super()._handle_connection(connection, path if path is not None else getattr(connection, "path", ""))

        async def _handle_client_text_message(self, client, message) -> None:
            await super()._handle_client_text_message(client, message)
            if isinstance(message, dict) and message.get("op") == "subscribe":
                live._on_subscribe(client, list(message.get("subscriptions") or []))

    server = Server(host, port, name, capabilities=[], supported_encodings=["json"],
                    logger=logging.getLogger(__name__ + ".server"),
                    server_kwargs={"compression": None, "close_timeout": 1.0, "max_size": 1 << 20})
    server.set_listener(Listener())
    return server


__all__ = ["LiveView", "NullLiveView", "make_live_view", "live_view_missing", "map_message", "pose_message",
           "planes_message", "cmd_message", "roi_message", "roi_png", "roi_topic"]
