"""Live view for engineers: a Foxglove WebSocket server inside the app's event loop.

Channels (``schema.LIVE_TOPICS``): ``/map`` and ``/tf_static`` (latched: sent when published and
to every client that subscribes), ``/tf``, ``/pose``, ``/planes``, ``/plane_fits``, ``/cmd``,
``/status``, ``/depth/<camera>`` and ``/roi/<camera>``. Their topic names, schemas and messages
come from ``robot.recording.schema``, the schema set the MCAP recording uses too, so one
Foxglove layout (``docs/foxglove-layout.json``) serves a live robot and a replay of its recording.

Cost and safety: ``publish_*`` are plain calls that never block and never raise. With no
client subscribed to a channel they return after one set lookup, before building anything.
Otherwise the message is encoded once and queued per client; each client has its own writer
task and a queue bounded in messages and in bytes, so a slow or stalled client loses its oldest
messages (counted in ``stats``) without delaying the caller or the other clients. Images, the
messages that cost milliseconds to encode on a Nano, are encoded in a worker thread, one at a
time per camera: ROI images at most ``schema.ROI_MAX_HZ``, depth images decimated to at most
``DEPTH_MAX_WIDTH`` pixels wide and within the depth budget (``set_depth_budget``, Mbit/s).

``foxglove-websocket`` (the optional ``live`` extra) is imported only by ``LiveView.start``.
It is an inactive package (frozen at 0.1.4) built on websockets' legacy server; per-client
queues and the latched map use two of its internals (the client list and the text-message
hook), which is why the extra pins ``<0.2``. ``NullLiveView`` has the same methods and does
nothing: the default, and what the app uses when the extra is missing.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
import warnings
from typing import Any, Callable, Deque, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import ConfigError, DriverError
from robot.base.samples import DepthFrame
from robot.recording import schema as ms
from robot.recording.budget import ByteBudget

log = logging.getLogger(__name__)

SUBPROTOCOL = "foxglove.websocket.v1"
INSTALL_HINT = "pip install 'planeloc-robot[live]'"

DEFAULT_CLIENT_QUEUE = 256  # messages per client: about 1 s of pose, tf and command at 50 Hz, planes at 30 Hz
DEFAULT_CLIENT_BYTES = 8 * 1024 * 1024  # and bytes: a stalled client holds a few depth images, not hundreds
ROI_MAX_HZ = ms.ROI_MAX_HZ
DEPTH_MAX_WIDTH = 424  # px: a live depth image is for looking at; every n-th pixel is enough
DEFAULT_DEPTH_MBIT_S = 8.0  # until the app sets the robot config's budget


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

    async def start(self, plane_map=None, cameras: Sequence[str] = ()) -> None:
        pass

    async def stop(self) -> None:
        pass

    def set_depth_budget(self, max_mbit_s: float) -> None:
        pass

    def publish_map(self, plane_map, t: float = 0.0) -> None:
        pass

    def publish_static_transforms(self, t: float, transforms: Sequence[Tuple[str, str, Any]]) -> None:
        pass

    def publish_tf(self, t: float, T_map_odom: Sequence[float], T_odom_base: Sequence[float]) -> None:
        pass

    def publish_depth(self, t: float, frame: DepthFrame) -> None:
        pass

    def publish_status(self, t: float, status: Mapping[str, Any]) -> None:
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

    def __init__(self, connection, limit: int, closed_exc, max_bytes: int = DEFAULT_CLIENT_BYTES):
        self.connection = connection
        self.limit = max(1, int(limit))
        self.max_bytes = max(1, int(max_bytes))
        self.items: Deque[bytes] = collections.deque()
        self.queued_bytes = 0
        self.latched: Dict[int, bytes] = {}  # by subscription: the latest map, the latest mounts
        self.sent = 0
        self.dropped = 0
        self._closed_exc = closed_exc
        self._wake = asyncio.Event()
        self.task: Optional[asyncio.Task] = None

    def push(self, frame: bytes) -> None:
        while self.items and (len(self.items) >= self.limit or self.queued_bytes + len(frame) > self.max_bytes):
            self.queued_bytes -= len(self.items.popleft())
            self.dropped += 1
        self.items.append(frame)
        self.queued_bytes += len(frame)
        self._wake.set()

    def push_latched(self, subscription: int, frame: bytes) -> None:
        self.latched[subscription] = frame  # a newer one replaces one not sent yet
        self._wake.set()

    async def run(self) -> None:
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                while self.latched or self.items:
                    if self.latched:
                        frame = self.latched.pop(next(iter(self.latched)))
                    else:
                        frame = self.items.popleft()
                        self.queued_bytes -= len(frame)
                    # waits only when the socket's buffer is full: a slow client, whose queue then drops
                    await self.connection.send(frame)
                    self.sent += 1
        except self._closed_exc:
            pass
        except Exception as e:  # the transport failed under us: this client is gone either way
            log.debug("live view: writer for %s stopped: %r", getattr(self.connection, "remote_address", "?"), e)


class _Latched:
    """A latched channel's latest message: built on first demand, then kept as bytes."""

    def __init__(self, t: float, build: Callable[[], Dict[str, Any]]):
        self.t = t
        self.build = build
        self.payload: Optional[bytes] = None

    def bytes(self) -> bytes:
        if self.payload is None:
            self.payload = ms.dumps(self.build())
        return self.payload


class LiveView:
    """Foxglove WebSocket server in the running event loop. ``await start()``, publish, ``await stop()``.

    ``publish_*`` may be called from any thread (calls from other threads are handed to the loop),
    and before ``start`` or after ``stop``: they do nothing then, except that the latched
    messages (the map, the camera mounts) are kept.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, cameras: Sequence[str] = (),
                 name: str = "planeloc robot", client_queue: int = DEFAULT_CLIENT_QUEUE,
                 roi_max_hz: float = ROI_MAX_HZ, client_bytes: int = DEFAULT_CLIENT_BYTES,
                 depth_max_mbit_s: float = DEFAULT_DEPTH_MBIT_S):
        self.host = host
        self.port = int(port)
        self.name = name
        self.client_queue = int(client_queue)
        self.client_bytes = int(client_bytes)
        self.roi_min_period = 1.0 / roi_max_hz if roi_max_hz > 0 else 0.0
        self._cameras = list(cameras)
        self._server = None
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._loop_thread: Optional[int] = None
        self._channels: Dict[str, int] = {}
        self._adding: Dict[str, asyncio.Task] = {}
        self._subscribed: set = set()  # channel ids with at least one subscriber (the server's listener)
        self._outboxes: Dict[int, _Outbox] = {}  # by id(connection)
        self._latched: Dict[str, _Latched] = {}  # by topic: the latest map and camera mounts
        self._map = None  # the latest plane map (also what /plane_fits outlines)
        self._depth_budget = ByteBudget(depth_max_mbit_s)
        self._last_roi: Dict[str, float] = {}
        self._busy: set = set()  # topics whose last image is being encoded
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
                "errors": self._counts["errors"], "depth_skipped": self._counts["depth_skipped"]}

    async def start(self, plane_map=None, cameras: Sequence[str] = ()) -> None:
        """Listen and advertise the channels, the per-camera ones for ``cameras`` (and those given
        at construction); publish ``plane_map`` if given. DriverError naming the address if it
        cannot listen."""
        if plane_map is not None:
            self.publish_map(plane_map)
        self._cameras.extend(c for c in cameras if c not in self._cameras)
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
        for topic in ms.camera_topics(self._cameras, ms.LIVE_TOPICS):
            await self._add_channel(topic)
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

    def set_depth_budget(self, max_mbit_s: float) -> None:
        """Cap the depth images sent (all clients together) at ``max_mbit_s``; 0 sends none."""
        self._depth_budget = ByteBudget(max_mbit_s)

    def publish_map(self, plane_map, t: float = 0.0) -> None:
        """Publish the plane map, and keep it for every client that subscribes later (also before start)."""
        if self._server is not None and not self._on_loop(self.publish_map, plane_map, t):
            return
        self._map = plane_map
        self._latch(ms.TOPIC_MAP, t, lambda: ms.map_message(plane_map, t))

    def publish_static_transforms(self, t: float, transforms: Sequence[Tuple[str, str, Any]]) -> None:
        """The fixed transforms (parent, child, 4x4 T_parent_child), e.g. the camera mounts; kept
        for every client that subscribes later, like the map."""
        if self._server is not None and not self._on_loop(self.publish_static_transforms, t, transforms):
            return
        fixed = list(transforms)
        self._latch(ms.TOPIC_TF_STATIC, t, lambda: ms.transforms_message(t, fixed))

    def publish_tf(self, t: float, T_map_odom: Sequence[float], T_odom_base: Sequence[float]) -> None:
        """``map -> odom`` and ``odom -> base_link`` (planar poses) at ``t``."""
        if self._wanted(ms.TOPIC_TF) and self._on_loop(self.publish_tf, t, T_map_odom, T_odom_base):
            self._send(ms.TOPIC_TF, t, lambda: ms.odometry_transforms(t, T_map_odom, T_odom_base))

    def publish_pose(self, t: float, x: float, y: float, phi: float, cov: Any, quality: Optional[str] = None,
                     reason: str = "") -> None:
        """The fused pose, its covariance and the quality state (localized | degraded | lost) with its reason."""
        if self._wanted(ms.TOPIC_POSE) and self._on_loop(self.publish_pose, t, x, y, phi, cov, quality, reason):
            self._send(ms.TOPIC_POSE, t, lambda: ms.pose_message(t, x, y, phi, cov, quality=quality, reason=reason))

    def publish_planes(self, t: float, camera: str, reports: Iterable[Any]) -> None:
        """Per-plane results of localizing one camera's frame (``PlaneReport``s or their ``to_json()``),
        and their walls outlined on ``/plane_fits``."""
        planes, fits = self._wanted(ms.TOPIC_PLANES), self._wanted(ms.TOPIC_PLANE_FITS) and self._map is not None
        if not (planes or fits) or not self._on_loop(self.publish_planes, t, camera, reports):
            return
        reports = list(reports)
        if planes:
            self._send(ms.TOPIC_PLANES, t, lambda: ms.planes_message(t, camera, reports))
        if fits:
            plane_map = self._map
            self._send(ms.TOPIC_PLANE_FITS, t, lambda: ms.plane_fits_message(t, camera, reports, plane_map))

    def publish_cmd(self, t: float, vx: float, vy: float, wz: float,
                    wheel_speeds: Optional[Sequence[float]] = None) -> None:
        """The body velocity command (m/s, m/s, rad/s in the robot frame) and optionally the wheel speeds."""
        if self._wanted(ms.TOPIC_CMD) and self._on_loop(self.publish_cmd, t, vx, vy, wz, wheel_speeds):
            self._send(ms.TOPIC_CMD, t, lambda: ms.cmd_message(t, vx, vy, wz, wheel_speeds))

    def publish_status(self, t: float, status: Mapping[str, Any]) -> None:
        """The app's status report (what the recording's ``/status`` holds)."""
        if self._wanted(ms.TOPIC_STATUS) and self._on_loop(self.publish_status, t, status):
            self._send(ms.TOPIC_STATUS, t, lambda: ms.status_message(t, status))

    def publish_roi(self, t: float, camera: str, label: np.ndarray) -> None:
        """The ROI label image of one camera frame (plane index per pixel, negative for none).

        At most ``roi_max_hz`` per camera, and one at a time, are encoded, in a worker thread: PNG
        encoding is a publish that costs milliseconds on a Nano, and the loop must not pay it.
        """
        topic = ms.roi_topic(camera)
        if not self._ready(topic, self.publish_roi, t, camera, label):
            return
        last = self._last_roi.get(camera)
        if topic in self._busy or (last is not None and 0.0 <= t - last < self.roi_min_period):
            self._counts["roi_skipped"] += 1
            return
        try:
            lab = np.array(ms.check_label(label), copy=True)  # the caller may reuse its buffer
        except ValueError as e:
            self._error(topic, e)
            return
        self._last_roi[camera] = t
        self._encode_later(topic, t, lambda: ms.dumps(ms.roi_message(t, camera, lab)))

    def publish_depth(self, t: float, frame: DepthFrame) -> None:
        """A depth frame as a 16UC1 image, every n-th pixel so it is at most ``DEPTH_MAX_WIDTH``
        wide, within the depth budget, one at a time per camera, encoded in a worker thread."""
        topic = ms.depth_topic(frame.camera)
        if not self._ready(topic, self.publish_depth, t, frame):
            return
        depth = np.asarray(frame.depth)
        if depth.ndim != 2:
            self._error(topic, ValueError(f"depth image must be 2-D, got shape {depth.shape}"))
            return
        step = ms.decimation_for(depth.shape[1], DEPTH_MAX_WIDTH)
        size = ms.depth_message_bytes(-(-depth.shape[1] // step), -(-depth.shape[0] // step))
        if topic in self._busy or not self._depth_budget.admit(t, size):
            self._counts["depth_skipped"] += 1
            return
        self._encode_later(topic, t, lambda: ms.dumps(ms.encode_depth(frame, step)))

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

    def _ready(self, topic: str, method, *args) -> bool:
        """For a per-camera channel: True when it is watched and we are on the loop. A camera not
        named at start gets its channel advertised; its frames before that are not sent."""
        if topic not in self._channels:
            if self._server is not None and self._on_loop(method, *args):
                self._advertise_later(topic)
            return False
        return self._wanted(topic) and self._on_loop(method, *args)

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

    def _encode_later(self, topic: str, t: float, encode: Callable[[], bytes]) -> None:
        self._busy.add(topic)
        fut = self._loop.run_in_executor(None, encode)
        fut.add_done_callback(lambda f: self._encoded(topic, t, f))

    def _encoded(self, topic: str, t: float, fut) -> None:
        self._busy.discard(topic)
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
        # the same wall-clock time the recorder logs: a live session and its recording line up
        return self._header.pack(self._opcode, subscription, ms.wall_clock().ns(t)) + payload

    def _clients(self) -> Sequence[Any]:
        return self._server._clients if self._server is not None else ()

    def _outbox(self, client) -> _Outbox:
        key = id(client.connection)
        box = self._outboxes.get(key)
        if box is None or box.connection is not client.connection:
            self._prune()
            box = self._outboxes[key] = _Outbox(client.connection, self.client_queue, self._closed_exc,
                                                self.client_bytes)
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

    def _latch(self, topic: str, t: float, build: Callable[[], Dict[str, Any]]) -> None:
        """Keep the latest message of a latched channel and send it to its current subscribers."""
        self._latched[topic] = _Latched(t, build)
        chan = self._channels.get(topic)
        if chan is None or chan not in self._subscribed:
            return  # encoded when someone subscribes
        for client in self._clients():
            sub = client.subscriptions_by_channel.get(chan)
            if sub is not None:
                self._send_latched(topic, client, sub)

    def _on_subscribe(self, client, subscriptions: List[Mapping[str, Any]]) -> None:
        """A client subscribed: send it the latched messages of the channels it asked for at once."""
        by_channel = {self._channels.get(topic): topic for topic in self._latched}
        for sub in subscriptions:
            sub_id = sub.get("id")
            topic = by_channel.get(sub.get("channelId"))
            if topic is not None and client.subscriptions.get(sub_id) == sub.get("channelId"):
                self._send_latched(topic, client, sub_id)

    def _send_latched(self, topic: str, client, sub_id: int) -> None:
        latched = self._latched[topic]
        try:
            self._outbox(client).push_latched(sub_id, self._frame(sub_id, latched.t, latched.bytes()))
        except Exception as e:
            self._error(topic, e)

    async def _add_channel(self, topic: str) -> None:
        name, _ = ms.schema_for(topic)
        self._channels[topic] = await self._server.add_channel({
            "topic": topic, "encoding": ms.MESSAGE_ENCODING, "schemaName": name, "schema": ms.schema_text(topic),
            "schemaEncoding": ms.SCHEMA_ENCODING})

    def _advertise_later(self, topic: str) -> None:
        """A camera not named at start: advertise its channel; frames before that are not sent."""
        if topic in self._adding or self._server is None:
            return

        async def add():
            try:
                await self._add_channel(topic)
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


__all__ = ["LiveView", "NullLiveView", "make_live_view", "live_view_missing"]
