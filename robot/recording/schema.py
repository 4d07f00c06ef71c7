"""Every channel the robot publishes: topic names, JSON schemas and the functions that build messages.

One schema set serves both sinks, the MCAP recording (``robot.recording.recorder``) and the
Foxglove live view (``robot.recording.live_view``): a topic has the same schema name, schema
text and message layout in both, so one Foxglove layout (``docs/foxglove-layout.json``) works
on a live robot and on a replay.

Every channel is JSON (message encoding ``json``, schema encoding ``jsonschema``), so Foxglove
opens a recording without protobuf and ``json.loads`` reads it back. Where a Foxglove
well-known schema fits, a message is a superset of it under that schema's name (extra fields
are ignored by Foxglove), so its panels work:

- ``/tf``: ``foxglove.FrameTransforms``, each element a ``foxglove.FrameTransform``: ``map ->
  odom`` (the localization's correction) and ``odom -> base_link`` (the wheel odometry), at the
  control rate. ``/tf_static``: the camera mounts, ``base_link -> <camera>_link ->
  <camera>_optical_frame`` (latched). Frames as REP-105 names them (``robot.fusion.frames``).
- ``/map``: ``foxglove.SceneUpdate``: every wall polygon filled (triangles) and outlined, its
  id as a label, plus ``planes`` (id, normal, d, polygons). Latched.
- ``/pose``: ``foxglove.PoseInFrame`` plus ``t``, ``x``, ``y``, ``phi``, ``cov`` (3x3
  row-major), ``pos_std`` and ``heading_std_deg`` (for plots), ``quality`` (localized |
  degraded | lost), ``quality_level`` (0 | 1 | 2) and ``reason``. At the control rate.
- ``/planes``: ``robot.PlaneReports``, the per-plane results of localizing one camera frame;
  the recording adds what replay needs to redo it (and the plane measurements it fused).
- ``/plane_fits``: ``foxglove.SceneUpdate``, the walls of the latest frame of each camera
  outlined green (fused) or red (fitted or predicted, not fused).
- ``/cmd``: ``robot.Command``, the body velocity command and the wheel speeds.
- ``/depth/<camera>``: ``foxglove.RawImage``, ``encoding: "16UC1"`` (little-endian depth units,
  ``step = 2 * width``) that Foxglove's Image panel colour-maps, plus what localization needs:
  ``K``, ``depth_scale``, ``t_capture``, ``frame_number``, ``timestamp_domain``, ``decimation``
  and ``truth`` in simulation. Lossless in a recording (replay sees the very pixels the robot
  saw); the live view may send every n-th pixel (``decimation``, ``K`` scaled to match).
- ``/roi/<camera>``: ``foxglove.CompressedImage``, the ROI label image as a colour PNG.
- ``/config`` (the YAML text loaded and the effective config), ``/odometry``, ``/status``:
  ``robot.*`` schemas.

Times. Foxglove headers (``timestamp``) and MCAP log times are wall-clock (``WallClock``: the
monotonic clock plus one offset taken once per process), so a recording shows the date it was
made and lines up with the journal. Every message also keeps the app's monotonic time in
seconds (``t``, ``t_capture``), the clock the core and replay use.

This module is pure encoding: no files, no sockets, and nothing here imports ``mcap``.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import math
import time
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from robot.base.samples import DepthFrame
from robot.fusion import frames
from robot.fusion.quality import DEGRADED, LOCALIZED, LOST
from robot.localization.measurements import PlaneMeasurement

TOPIC_CONFIG = "/config"
TOPIC_ODOMETRY = "/odometry"
TOPIC_POSE = "/pose"
TOPIC_PLANES = "/planes"
TOPIC_PLANE_FITS = "/plane_fits"
TOPIC_CMD = "/cmd"
TOPIC_STATUS = "/status"
TOPIC_MAP = "/map"
TOPIC_TF = "/tf"
TOPIC_TF_STATIC = "/tf_static"
DEPTH_PREFIX = "/depth/"
ROI_PREFIX = "/roi/"
MAP_FRAME = frames.MAP

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"

# Which sink publishes what: the live view leaves out only the replay inputs (config, odometry).
RECORDED_TOPICS = (TOPIC_CONFIG, TOPIC_MAP, TOPIC_TF, TOPIC_TF_STATIC, TOPIC_ODOMETRY, TOPIC_POSE, TOPIC_PLANES,
                   TOPIC_PLANE_FITS, TOPIC_CMD, TOPIC_STATUS, DEPTH_PREFIX, ROI_PREFIX)
LIVE_TOPICS = (TOPIC_MAP, TOPIC_TF, TOPIC_TF_STATIC, TOPIC_POSE, TOPIC_PLANES, TOPIC_PLANE_FITS, TOPIC_CMD,
               TOPIC_STATUS, DEPTH_PREFIX, ROI_PREFIX)
# Repeated at the start of every recording segment; the live view sends them to each new subscriber.
LATCHED_TOPICS = (TOPIC_CONFIG, TOPIC_MAP, TOPIC_TF_STATIC)

DEPTH_ENCODING = "16UC1"  # Foxglove's name for one little-endian uint16 channel
QUALITY_LEVELS = {LOCALIZED: 0, DEGRADED: 1, LOST: 2}  # a number a Plot panel can draw
FIT_LIFETIME = 1.0  # s a /plane_fits outline stays when its camera sends no newer frame

_NUMBER = {"type": "number"}
_STRING = {"type": "string"}
_INT = {"type": "integer"}
_BOOL = {"type": "boolean"}
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
}
_VEC = {"type": "array", "items": _NUMBER}
_POINT = {"type": "object", "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER}}
_QUAT = {"type": "object", "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER, "w": _NUMBER}}
_COLOR = {"type": "object", "properties": {"r": _NUMBER, "g": _NUMBER, "b": _NUMBER, "a": _NUMBER}}
_POSE = {"type": "object", "properties": {"position": _POINT, "orientation": _QUAT}}
_WHEELS = {"type": ["array", "null"], "items": _NUMBER, "minItems": 4, "maxItems": 4,
           "description": "front-left, front-right, rear-left, rear-right, rad/s"}
_SEQ = {"type": "integer", "description": "order in which the core consumed the recorded inputs (replay)"}
_T = {"type": "number", "description": "app monotonic time, s"}
_B64 = {"type": "string", "contentEncoding": "base64"}
_FRAME_TRANSFORM = {
    "type": "object", "title": "foxglove.FrameTransform",
    "properties": {"timestamp": _TIME, "parent_frame_id": _STRING, "child_frame_id": _STRING,
                   "translation": _POINT, "rotation": _QUAT}}
_SCENE_ENTITY = {"type": "object", "title": "foxglove.SceneEntity", "properties": {
    "timestamp": _TIME, "frame_id": _STRING, "id": _STRING, "frame_locked": _BOOL, "lifetime": _TIME,
    "lines": {"type": "array", "items": {"type": "object", "properties": {
        "type": {"type": "integer", "description": "0 strip, 1 loop, 2 list"}, "pose": _POSE, "thickness": _NUMBER,
        "scale_invariant": _BOOL, "points": {"type": "array", "items": _POINT}, "color": _COLOR}}},
    "triangles": {"type": "array", "items": {"type": "object", "properties": {
        "pose": _POSE, "points": {"type": "array", "items": _POINT}, "color": _COLOR}}},
    "texts": {"type": "array", "items": {"type": "object", "properties": {
        "pose": _POSE, "billboard": _BOOL, "font_size": _NUMBER, "scale_invariant": _BOOL, "color": _COLOR,
        "text": _STRING}}}}}
_SCENE_PROPERTIES = {"deletions": {"type": "array", "items": {"type": "object"}},
                     "entities": {"type": "array", "items": _SCENE_ENTITY}, "t": _T}


def _schema(title: str, description: str, properties: Dict[str, Any],
            required: Sequence[str]) -> Dict[str, Any]:
    return {"title": title, "description": description, "type": "object",
            "properties": properties, "required": list(required)}


SCHEMAS: Dict[str, Tuple[str, Dict[str, Any]]] = {
    TOPIC_CONFIG: ("robot.Config", _schema(
        "robot.Config", "Robot config and plane map of this run: the YAML text the app loaded, and the "
        "effective robot config (every key, defaults filled in, the map path used)",
        {"robot_config_yaml": _STRING, "map_yaml": _STRING,
         "robot_config_path": {"type": ["string", "null"]}, "map_path": {"type": ["string", "null"]},
         "effective_config": {"type": ["object", "null"],
                              "description": "what robot.config.parse_robot_config reads back"}},
        ["robot_config_yaml", "map_yaml"])),
    TOPIC_MAP: ("foxglove.SceneUpdate", _schema(
        "foxglove.SceneUpdate", "The plane map: walls filled and outlined, with their ids, for the 3D panel, and the "
        "planes themselves",
        dict(_SCENE_PROPERTIES, planes={"type": "array", "items": {"type": "object", "properties": {
            "id": _STRING, "normal": _VEC, "d": _NUMBER,
            "polygons": {"type": "array", "items": {"type": "array", "items": _VEC}}}}}),
        ["entities", "planes"])),
    TOPIC_PLANE_FITS: ("foxglove.SceneUpdate", _schema(
        "foxglove.SceneUpdate", "The walls of one camera's latest frame: green where the plane was fused, red where "
        "it was predicted or fitted but not fused",
        dict(_SCENE_PROPERTIES, camera=_STRING),
        ["entities"])),
    TOPIC_TF: ("foxglove.FrameTransforms", _schema(
        "foxglove.FrameTransforms", "map -> odom (the localization's correction) and odom -> base_link (the wheel "
        "odometry, continuous), REP-105",
        {"transforms": {"type": "array", "items": _FRAME_TRANSFORM}, "t": _T},
        ["transforms"])),
    TOPIC_TF_STATIC: ("foxglove.FrameTransforms", _schema(
        "foxglove.FrameTransforms", "The camera mounts: base_link -> <camera>_link -> <camera>_optical_frame",
        {"transforms": {"type": "array", "items": _FRAME_TRANSFORM}, "t": _T},
        ["transforms"])),
    TOPIC_ODOMETRY: ("robot.Odometry", _schema(
        "robot.Odometry", "An input of the EKF prediction: a wheel odometry report or a gyro yaw rate",
        {"t": {"type": "number", "description": "measurement time, app monotonic s"},
         "wheel_speeds": _WHEELS, "angles": _VEC, "dt": _NUMBER, "t_board": _NUMBER,
         "gyro_wz": {"type": "number", "description": "yaw rate about robot z, rad/s"},
         "variance": _NUMBER, "camera": _STRING, "seq": _SEQ},
        ["t"])),
    TOPIC_POSE: ("foxglove.PoseInFrame", _schema(
        "foxglove.PoseInFrame", "Fused pose (x, y, phi) in the map frame, its 3x3 covariance and the quality state",
        {"timestamp": _TIME, "frame_id": _STRING, "pose": _POSE,
         "t": _T, "x": _NUMBER, "y": _NUMBER, "phi": _NUMBER,
         "cov": {"type": "array", "items": _NUMBER, "minItems": 9, "maxItems": 9,
                 "description": "3x3 covariance of (x, y, phi), row-major"},
         "pos_std": {"type": ["number", "null"], "description": "position std along the worst direction, m"},
         "heading_std_deg": {"type": ["number", "null"], "description": "heading std, degrees"},
         "quality": {"type": ["string", "null"], "description": "localized | degraded | lost"},
         "quality_level": {"type": ["integer", "null"], "description": "0 localized, 1 degraded, 2 lost"},
         "reason": {"type": "string", "description": "why the quality is not 'localized'; empty when it is"},
         "seq": _SEQ},
        ["t", "x", "y", "phi", "cov"])),
    TOPIC_PLANES: ("robot.PlaneReports", _schema(
        "robot.PlaneReports", "Per-plane results of localizing one camera frame: which planes were fitted and "
        "used, and why not; a recording adds what replay needs to redo the localization",
        {"t": _NUMBER, "camera": _STRING,
         "planes": {"type": "array", "items": {"type": "object", "properties": {
             "id": _STRING, "camera": _STRING, "inliers": _INT,
             "normal": {"type": ["array", "null"], "items": _NUMBER, "description": "fitted normal, robot frame"},
             "d": {"type": ["number", "null"], "description": "fitted offset, robot frame, m"},
             "used": {"type": "boolean"}, "reason": _STRING}}},
         "frame_number": _INT, "method": _STRING,
         "fusion_step": {"type": "integer", "description": "frames whose messages share it were fused in one "
                         "filter update"},
         "coarse": {"type": "array", "items": _NUMBER, "minItems": 3, "maxItems": 3,
                    "description": "coarse pose (x, y, phi) the localization started from"},
         "coarse_cov": {"type": "array", "items": _NUMBER, "minItems": 9, "maxItems": 9},
         "status": _STRING, "accepted": {"type": "array", "items": _STRING},
         "rejected": {"type": "array", "items": {"type": "array", "items": _STRING},
                      "description": "(plane id, reason) pairs the fusion gate refused"},
         "measurements": {"type": "array", "description": "the plane measurements handed to the fusion: replay "
                          "fuses these when the frame itself was not recorded", "items": {
                              "type": "object", "properties": {
                                  "plane_id": _STRING, "camera": _STRING, "t_capture": _NUMBER, "n_ground": _VEC,
                                  "d_ground": _NUMBER, "z": _VEC, "R": _VEC, "inliers": _INT}}},
         "seq": _SEQ},
        ["t", "camera", "planes"])),
    TOPIC_CMD: ("robot.Command", _schema(
        "robot.Command", "Body velocity command of the controller (robot frame) and the wheel speeds it gives",
        {"t": _NUMBER, "vx": _NUMBER, "vy": _NUMBER, "wz": _NUMBER, "wheel_speeds": _WHEELS,
         "sent": {"type": "boolean", "description": "false when the command was withheld"},
         "state": _STRING, "scale": {"type": "number", "description": "speed scale applied by health"},
         "reason": _STRING},
        ["t", "vx", "vy", "wz"])),
    TOPIC_STATUS: ("robot.Status", _schema(
        "robot.Status", "Controller status and events (the app's status report; free-form beyond t)",
        {"t": _NUMBER, "event": _STRING, "quality": _STRING, "reason": _STRING, "seq": _SEQ},
        ["t"])),
}

DEPTH_SCHEMA_NAME = "foxglove.RawImage"
DEPTH_SCHEMA: Dict[str, Any] = _schema(
    "foxglove.RawImage", "Depth image in depth units (16UC1, little-endian), with what deprojection needs",
    {"timestamp": _TIME, "frame_id": _STRING, "width": _INT, "height": _INT, "encoding": _STRING,
     "step": {"type": "integer", "description": "bytes per row"}, "data": _B64,
     "camera": _STRING,
     "K": {"type": "array", "items": _NUMBER, "minItems": 9, "maxItems": 9},
     "depth_scale": {"type": "number", "description": "metres per depth unit"},
     "t_capture": _NUMBER, "frame_number": _INT, "timestamp_domain": _STRING,
     "decimation": {"type": "integer", "description": "every n-th pixel of the camera's image (1: all)"},
     "truth": {"type": ["array", "null"], "items": _NUMBER}},
    ["width", "height", "encoding", "step", "data", "camera", "K", "depth_scale", "t_capture"])

ROI_SCHEMA_NAME = "foxglove.CompressedImage"
ROI_SCHEMA: Dict[str, Any] = _schema(
    "foxglove.CompressedImage", "ROI label image: one colour per predicted plane, dark where no plane is expected",
    {"timestamp": _TIME, "frame_id": _STRING, "data": _B64, "format": _STRING, "camera": _STRING, "t": _T},
    ["timestamp", "frame_id", "data", "format"])

# Per-camera channels: the topic is the prefix plus the camera name.
PREFIX_SCHEMAS: Dict[str, Tuple[str, Dict[str, Any]]] = {
    DEPTH_PREFIX: (DEPTH_SCHEMA_NAME, DEPTH_SCHEMA),
    ROI_PREFIX: (ROI_SCHEMA_NAME, ROI_SCHEMA),
}

# Label colours (RGB): distinct hues, so neighbouring planes are told apart at a glance.
PALETTE = np.array([
    (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
    (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212), (0, 128, 128), (170, 110, 40),
], dtype=np.uint8)
NO_PLANE_RGB = (24, 24, 24)
ROI_MAX_WIDTH = 424  # px: the label image is a diagnostic; a larger one is decimated
ROI_MAX_HZ = 5.0  # per camera and sink: PNG encoding is the one per-message cost that is not trivial
FUSED_RGBA = (0.1, 0.9, 0.2, 1.0)
NOT_FUSED_RGBA = (0.95, 0.2, 0.15, 1.0)


# Time  --------------------------------------------------------------------------------------------

class WallClock:
    """The app's monotonic seconds as wall-clock nanoseconds: monotonic time plus one offset.

    The offset is read once (``time.time_ns() - time.monotonic_ns()``), so the mapping is as
    monotonic as the app's clock: a wall-clock step later on (NTP after boot) moves nothing and
    never reorders a recording. ``offset_ns`` is for tests and for reading a recording back.
    """

    def __init__(self, offset_ns: Optional[int] = None):
        self.offset_ns = int(time.time_ns() - time.monotonic_ns()) if offset_ns is None else int(offset_ns)

    def ns(self, t: float) -> int:
        """Wall-clock ns of app time ``t`` (s); ValueError when ``t`` is not finite."""
        if not math.isfinite(t):
            raise ValueError(f"time {t!r} is not finite")
        return max(0, self.offset_ns + int(round(t * 1e9)))

    def stamp(self, t: float) -> Dict[str, int]:
        """Foxglove's {sec, nsec} of app time ``t``."""
        ns = self.ns(t)
        return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}

    def monotonic(self, ns: int) -> float:
        """The app time (s) of a wall-clock ns this clock produced."""
        return (int(ns) - self.offset_ns) / 1e9


_clock: Optional[WallClock] = None


def wall_clock() -> WallClock:
    """The process's one mapping (taken on first use), shared by the recorder and the live view so
    a live session and its recording carry the same times."""
    global _clock
    if _clock is None:
        _clock = WallClock()
    return _clock


def set_wall_clock(clock: Optional[WallClock]) -> Optional[WallClock]:
    """Replace the process's mapping (tests; None: take a fresh one on next use). Returns the old one."""
    global _clock
    old, _clock = _clock, clock
    return old


def stamp(t: float) -> Dict[str, int]:
    """Foxglove's {sec, nsec}, wall-clock, of app time ``t`` (see ``WallClock``)."""
    return wall_clock().stamp(t)


# Registry  ----------------------------------------------------------------------------------------

def schema_for(topic: str) -> Tuple[str, Dict[str, Any]]:
    """(schema name, JSON schema) of a topic; ValueError for a topic nobody publishes."""
    for prefix, named in PREFIX_SCHEMAS.items():
        if topic.startswith(prefix) and len(topic) > len(prefix):
            return named
    try:
        return SCHEMAS[topic]
    except KeyError:
        raise ValueError(f"no schema for topic {topic!r}; known: {sorted(SCHEMAS)} "
                         f"and {', '.join(p + '<camera>' for p in PREFIX_SCHEMAS)}") from None


def schema_text(topic: str) -> str:
    """The JSON schema of a topic as the one text both sinks register (MCAP schema data, Foxglove
    ``advertise``), so Foxglove sees the very same schema live and in a recording."""
    return json.dumps(schema_for(topic)[1], separators=(",", ":"), sort_keys=True)


def depth_topic(camera: str) -> str:
    return DEPTH_PREFIX + camera


def roi_topic(camera: str) -> str:
    return ROI_PREFIX + camera


def camera_topics(cameras: Iterable[str], prefixes: Sequence[str]) -> List[str]:
    """Every topic of ``prefixes``, the per-camera ones spelled out for ``cameras``."""
    out: List[str] = []
    for p in prefixes:
        if p.endswith("/"):
            out.extend(p + c for c in cameras)
        else:
            out.append(p)
    return out


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return dataclasses.asdict(o)
    raise TypeError(f"cannot record a {type(o).__name__} as JSON")


def _finite_or_none(o: Any) -> Any:
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite_or_none(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_or_none(v) for v in o]
    return o


def dumps(message: Mapping[str, Any]) -> bytes:
    """JSON bytes. Non-finite floats become null: JSON has no NaN and Foxglove rejects it."""
    try:
        text = json.dumps(message, default=_json_default, allow_nan=False, separators=(",", ":"))
    except ValueError:
        plain = json.loads(json.dumps(message, default=_json_default))
        text = json.dumps(_finite_or_none(plain), allow_nan=False, separators=(",", ":"))
    return text.encode("utf-8")


def check_required(topic: str, message: Mapping[str, Any]) -> None:
    """Raise ValueError when a message lacks a field its schema requires (a programming error)."""
    _, schema = schema_for(topic)
    missing = [k for k in schema["required"] if k not in message]
    if missing:
        raise ValueError(f"{topic} message lacks {missing}")


# Depth  -------------------------------------------------------------------------------------------

def depth_message_bytes(width: int, height: int) -> int:
    """Size of a ``/depth/<camera>`` message of this many pixels (base64 data and the fields
    around it), known before encoding: what a bandwidth budget is charged."""
    return 4 * ((2 * int(width) * int(height) + 2) // 3) + 640


def decimation_for(width: int, max_width: int) -> int:
    """The pixel step that brings an image ``width`` wide to at most ``max_width``."""
    return max(1, int(math.ceil(int(width) / float(max(1, max_width)))))


def encode_depth(frame: DepthFrame, decimation: int = 1) -> Dict[str, Any]:
    """A ``/depth/<camera>`` message (16UC1 RawImage) of one frame; with ``decimation`` n > 1, of
    every n-th pixel in rows and columns, ``K`` scaled to match (for a view, never for replay)."""
    depth = np.asarray(frame.depth)
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise ValueError(f"depth frame from {frame.camera!r} must be (H, W) uint16, "
                         f"got {depth.dtype} {depth.shape}")
    n = int(decimation)
    if n < 1:
        raise ValueError(f"depth decimation must be >= 1, got {decimation}")
    K = np.asarray(frame.K, dtype=float).reshape(3, 3)
    if n > 1:
        depth = depth[::n, ::n]
        K = K.copy()
        K[:2, :] /= n  # pixel i of the decimated image is pixel n*i of the camera's
    data = np.ascontiguousarray(depth, dtype="<u2").tobytes()
    return {
        "timestamp": stamp(frame.t_capture),
        "frame_id": frames.camera_optical_frame(frame.camera),
        "width": int(depth.shape[1]),
        "height": int(depth.shape[0]),
        "encoding": DEPTH_ENCODING,
        "step": 2 * int(depth.shape[1]),
        "data": base64.b64encode(data).decode("ascii"),
        "camera": frame.camera,
        "K": [float(v) for v in K.reshape(9)],
        "depth_scale": float(frame.depth_scale),
        "t_capture": float(frame.t_capture),
        "frame_number": int(frame.frame_number),
        "timestamp_domain": str(frame.timestamp_domain),
        "decimation": n,
        "truth": None if frame.truth is None else [float(v) for v in frame.truth],
    }


def _decode_raw_depth(message: Mapping[str, Any]) -> np.ndarray:
    if message["encoding"] != DEPTH_ENCODING:
        raise ValueError(f"unsupported depth encoding {message['encoding']!r} (expected {DEPTH_ENCODING})")
    width, height, step = int(message["width"]), int(message["height"]), int(message["step"])
    if width <= 0 or height <= 0 or step < 2 * width or step % 2:
        raise ValueError(f"depth image {width}x{height} with step {step} is not a 16UC1 layout")
    raw = base64.b64decode(message["data"], validate=True)
    if len(raw) != step * height:
        raise ValueError(f"depth data holds {len(raw)} bytes, {width}x{height} with step {step} needs "
                         f"{step * height}")
    rows = np.frombuffer(raw, dtype="<u2").reshape(height, step // 2)
    return np.ascontiguousarray(rows[:, :width], dtype=np.uint16)


def _decode_png_depth(message: Mapping[str, Any]) -> np.ndarray:
    """Recordings made before depth was a RawImage: a 16-bit PNG in a CompressedImage."""
    import cv2

    if message["format"] != "png":
        raise ValueError(f"unsupported depth format {message['format']!r}")
    raw = np.frombuffer(base64.b64decode(message["data"]), dtype=np.uint8)
    try:
        depth = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
    except cv2.error:
        depth = None
    if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
        raise ValueError("depth data is not a 16-bit single-channel PNG")
    if "width" in message and (depth.shape[1], depth.shape[0]) != (message["width"], message["height"]):
        raise ValueError(f"depth image is {depth.shape[1]}x{depth.shape[0]}, message says "
                         f"{message['width']}x{message['height']}")
    return depth


def decode_depth(message: Mapping[str, Any]) -> DepthFrame:
    """The DepthFrame a ``/depth/<camera>`` message holds (bit-exact); ValueError when it is malformed."""
    try:
        depth = _decode_raw_depth(message) if "encoding" in message else _decode_png_depth(message)
        truth: Optional[Tuple[float, float, float]] = None
        if message.get("truth") is not None:
            x, y, phi = message["truth"]
            truth = (float(x), float(y), float(phi))
        return DepthFrame(
            camera=str(message["camera"]),
            depth=depth,
            depth_scale=float(message["depth_scale"]),
            K=np.array(message["K"], dtype=float).reshape(3, 3),
            t_capture=float(message["t_capture"]),
            frame_number=int(message.get("frame_number", 0)),
            timestamp_domain=str(message.get("timestamp_domain", "unknown")),
            truth=truth,
        )
    except (KeyError, TypeError, ValueError, OverflowError, binascii.Error) as e:  # OverflowError: int(inf)
        raise ValueError(f"malformed depth message: {e}") from e


# Pose, transforms  --------------------------------------------------------------------------------

def _worst_position_std(c: np.ndarray) -> float:
    """sqrt of the larger eigenvalue of the x/y block (closed form for 2x2, NaN when not finite)."""
    a, b, d = float(c[0, 0]), 0.5 * float(c[0, 1] + c[1, 0]), float(c[1, 1])
    if not all(math.isfinite(v) for v in (a, b, d)):
        return math.nan
    return math.sqrt(max(0.0, 0.5 * (a + d) + math.hypot(0.5 * (a - d), b)))


def pose_message(t: float, x: float, y: float, phi: float, cov: Any, quality: Optional[str] = None,
                 reason: str = "", frame_id: str = MAP_FRAME) -> Dict[str, Any]:
    """``/pose``; ``cov`` is the 3x3 covariance of (x, y, phi), ``quality`` localized | degraded | lost."""
    c = np.asarray(cov, dtype=float)
    if c.shape != (3, 3):
        raise ValueError(f"pose covariance must be 3x3, got shape {c.shape}")
    half = 0.5 * float(phi)
    var_phi = float(c[2, 2])
    return {
        "timestamp": stamp(t),
        "frame_id": frame_id,
        "pose": {"position": {"x": float(x), "y": float(y), "z": 0.0},
                 "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)}},
        "t": float(t), "x": float(x), "y": float(y), "phi": float(phi),
        "cov": [float(v) for v in c.reshape(9)],
        "pos_std": _worst_position_std(c),
        "heading_std_deg": math.degrees(math.sqrt(var_phi)) if math.isfinite(var_phi) and var_phi >= 0 else math.nan,
        "quality": None if quality is None else str(quality),
        "quality_level": QUALITY_LEVELS.get(str(quality)) if quality is not None else None,
        "reason": str(reason),
    }


def _quaternion(R: np.ndarray) -> Tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, w >= 0 (Shepperd's method: stable for any angle)."""
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    w, x, y, z = q
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    return x / norm, y / norm, z / norm, w / norm


def frame_transform(t: float, parent: str, child: str, T_parent_child: Any) -> Dict[str, Any]:
    """One ``foxglove.FrameTransform``: the child frame's pose in the parent frame (4x4)."""
    T = np.asarray(T_parent_child, dtype=float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"transform {parent} -> {child} must be a finite 4x4 matrix, got shape {T.shape}")
    qx, qy, qz, qw = _quaternion(T[:3, :3])
    return {"timestamp": stamp(t), "parent_frame_id": str(parent), "child_frame_id": str(child),
            "translation": {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])},
            "rotation": {"x": qx, "y": qy, "z": qz, "w": qw}}


def transforms_message(t: float, transforms: Iterable[Tuple[str, str, Any]]) -> Dict[str, Any]:
    """``/tf`` or ``/tf_static``: (parent, child, T_parent_child) triples stamped at ``t``."""
    return {"transforms": [frame_transform(t, p, c, T) for p, c, T in transforms], "t": float(t)}


def odometry_transforms(t: float, T_map_odom: Sequence[float], T_odom_base: Sequence[float]) -> Dict[str, Any]:
    """``/tf`` of one control tick: ``map -> odom`` and ``odom -> base_link`` as planar poses at ``t``."""
    return transforms_message(t, [(frames.MAP, frames.ODOM, frames.planar_to_T(T_map_odom)),
                                  (frames.ODOM, frames.BASE_LINK, frames.planar_to_T(T_odom_base))])


# Planes  ------------------------------------------------------------------------------------------

def _floats(values: Any) -> Optional[list]:
    return None if values is None else [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]


def _plane_report(r: Any) -> Dict[str, Any]:
    get = r.get if isinstance(r, Mapping) else (lambda k, _r=r: getattr(_r, k))
    d = get("d")
    return {"id": str(get("id")), "camera": str(get("camera")), "inliers": int(get("inliers")),
            "normal": _floats(get("normal")), "d": None if d is None else float(d),
            "used": bool(get("used")), "reason": str(get("reason"))}


def measurement_json(m: PlaneMeasurement) -> Dict[str, Any]:
    """A plane measurement as JSON; floats survive exactly (JSON writes the shortest round-trip repr)."""
    return {"plane_id": str(m.plane_id), "camera": str(m.camera), "t_capture": float(m.t_capture),
            "n_ground": _floats(m.n_ground), "d_ground": float(m.d_ground), "z": _floats(m.z), "R": _floats(m.R),
            "inliers": int(m.inliers)}


def measurement_from_json(d: Mapping[str, Any]) -> PlaneMeasurement:
    """The PlaneMeasurement ``measurement_json`` wrote; ValueError when it is malformed."""
    try:
        return PlaneMeasurement(plane_id=str(d["plane_id"]), camera=str(d["camera"]), t_capture=float(d["t_capture"]),
                                n_ground=np.array(d["n_ground"], dtype=float).reshape(3), d_ground=float(d["d_ground"]),
                                z=np.array(d["z"], dtype=float).reshape(2), R=np.array(d["R"], dtype=float).reshape(2, 2),
                                inliers=int(d.get("inliers", 0)))
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"malformed plane measurement: {e}") from e


def planes_message(t: float, camera: str, reports: Iterable[Any], *, frame_number: Optional[int] = None,
                   method: Optional[str] = None, coarse: Any = None, coarse_cov: Any = None,
                   status: Optional[str] = None, accepted: Optional[Iterable[str]] = None,
                   rejected: Optional[Iterable[Sequence[str]]] = None,
                   measurements: Optional[Iterable[PlaneMeasurement]] = None,
                   fusion_step: Optional[int] = None) -> Dict[str, Any]:
    """``/planes`` for one camera frame, from ``PlaneReport`` objects (robot.localization.localizer) or
    their ``to_json()`` mappings. The keyword fields are what replay needs; the live view leaves them out.
    ``fusion_step``: frames whose messages share it were fused in one filter update (replay does the same)."""
    msg: Dict[str, Any] = {"t": float(t), "camera": str(camera), "planes": [_plane_report(r) for r in reports]}
    if frame_number is not None:
        msg["frame_number"] = int(frame_number)
    if method is not None:
        msg["method"] = str(method)
    if coarse is not None:
        msg["coarse"] = _floats(coarse)
    if coarse_cov is not None:
        msg["coarse_cov"] = _floats(coarse_cov)
    if status is not None:
        msg["status"] = str(status)
    if accepted is not None:
        msg["accepted"] = [str(a) for a in accepted]
    if rejected is not None:
        msg["rejected"] = [[str(v) for v in r] for r in rejected]
    if measurements is not None:
        msg["measurements"] = [measurement_json(m) for m in measurements]
    if fusion_step is not None:
        msg["fusion_step"] = int(fusion_step)
    return msg


_IDENTITY_POSE = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def _point(p: Sequence[float]) -> Dict[str, float]:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def _rgba(c: Sequence[float]) -> Dict[str, float]:
    return {"r": float(c[0]), "g": float(c[1]), "b": float(c[2]), "a": float(c[3])}


def _entity(t: float, entity_id: str, lifetime: float = 0.0, **primitives: List[Dict[str, Any]]) -> Dict[str, Any]:
    life = {"sec": int(lifetime), "nsec": int(round((lifetime - int(lifetime)) * 1e9))}
    out = {"timestamp": stamp(t), "frame_id": MAP_FRAME, "id": entity_id, "lifetime": life, "frame_locked": True,
           "metadata": [], "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": [], "triangles": [],
           "texts": [], "models": []}
    out.update(primitives)
    return out


def plane_fits_message(t: float, camera: str, reports: Iterable[Any], plane_map: Any) -> Dict[str, Any]:
    """``/plane_fits``: the map outline of every plane reported for one camera frame, green when it
    was fused, red when not; the entity of each camera replaces its previous one."""
    by_id = {p.id: p for p in plane_map.planes}
    lines: List[Dict[str, Any]] = []
    for r in reports:
        rep = _plane_report(r)
        plane = by_id.get(rep["id"])
        if plane is None:
            continue
        color = _rgba(FUSED_RGBA if rep["used"] else NOT_FUSED_RGBA)
        for poly in plane.polygons:
            lines.append({"type": 1, "pose": _IDENTITY_POSE, "thickness": 6.0, "scale_invariant": True,
                          "points": [_point(p) for p in poly], "color": color, "colors": [], "indices": []})
    return {"deletions": [], "entities": [_entity(t, f"fits/{camera}", FIT_LIFETIME, lines=lines)], "t": float(t),
            "camera": str(camera)}


# Commands, odometry, status, config  ---------------------------------------------------------------

def cmd_message(t: float, vx: float, vy: float, wz: float, wheel_speeds: Optional[Sequence[float]] = None, *,
                sent: Optional[bool] = None, state: Optional[str] = None, scale: Optional[float] = None,
                reason: Optional[str] = None) -> Dict[str, Any]:
    """``/cmd``: the body velocity command (m/s, m/s, rad/s, robot frame), the wheel speeds when known,
    and (recorded) whether it was sent and what shaped it."""
    msg: Dict[str, Any] = {"t": float(t), "vx": float(vx), "vy": float(vy), "wz": float(wz),
                           "wheel_speeds": _floats(wheel_speeds)}
    if sent is not None:
        msg["sent"] = bool(sent)
    if state is not None:
        msg["state"] = str(state)
    if scale is not None:
        msg["scale"] = float(scale)
    if reason is not None:
        msg["reason"] = str(reason)
    return msg


def odometry_message(t: float, wheel_speeds: Sequence[float], angles: Sequence[float], dt: float,
                     t_board: float) -> Dict[str, Any]:
    """``/odometry``: one wheel odometry report as the EKF prediction consumed it."""
    return {"t": float(t), "wheel_speeds": _floats(wheel_speeds), "angles": _floats(angles), "dt": float(dt),
            "t_board": float(t_board)}


def gyro_message(t: float, gyro_wz: float, variance: float, camera: str) -> Dict[str, Any]:
    """``/odometry``: one gyro yaw rate (robot z, rad/s) as the EKF prediction consumed it."""
    return {"t": float(t), "gyro_wz": float(gyro_wz), "variance": float(variance), "camera": str(camera)}


def status_message(t: float, status: Mapping[str, Any]) -> Dict[str, Any]:
    """``/status``: the app's status report at ``t``."""
    msg = dict(status)
    msg["t"] = float(t)
    return msg


def set_pose_message(t: float, x: float, y: float, phi: float, cov: Any, source: str,
                     hidden_walls: Sequence[Mapping[str, Any]] = ()) -> Dict[str, Any]:
    """``/status`` event: the pose was set (replay sets it again at this point), with the walls a
    panel may hide that a relocalized pose leaves open (``ControllerCore.set_pose``)."""
    out = {"t": float(t), "event": "set_pose", "x": float(x), "y": float(y), "phi": float(phi),
           "cov": _floats(cov), "source": str(source)}
    if hidden_walls:
        out["hidden_walls"] = [{"plane": str(h["plane"]), "up_to_m": float(h["up_to_m"]),
                                "direction": [float(v) for v in h["direction"]]} for h in hidden_walls]
    return out


def recovery_request_message(t: float, why: str) -> Dict[str, Any]:
    """``/status`` event: an operator or the fleet restarted the recovery sequence at ``t``."""
    return {"t": float(t), "event": "recovery_request", "reason": str(why)}


def hidden_walls_from_json(value: Any) -> List[Dict[str, Any]]:
    """A set_pose event's ``hidden_walls`` checked (absent: none); ValueError names what is wrong."""
    if value is None:
        return []
    if not isinstance(value, list):
        raise ValueError(f"hidden_walls must be a list, got {type(value).__name__}")
    out = []
    for h in value:
        if not isinstance(h, dict) or not isinstance(h.get("plane"), str):
            raise ValueError(f"hidden_walls entry {h!r} has no plane id")
        try:
            up_to = float(h["up_to_m"])
            ux, uy = (float(v) for v in h["direction"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"hidden_walls entry for {h['plane']}: up_to_m and a 2-vector direction needed") from None
        if not (math.isfinite(up_to) and up_to >= 0.0 and math.isfinite(ux) and math.isfinite(uy)
                and abs(math.hypot(ux, uy) - 1.0) < 1e-3):
            raise ValueError(f"hidden_walls entry for {h['plane']}: up_to_m must be finite and >= 0, direction a unit vector")
        out.append({"plane": h["plane"], "up_to_m": up_to, "direction": [ux, uy]})
    return out


def config_message(robot_config_yaml: str, map_yaml: str, robot_config_path: Optional[str] = None,
                   map_path: Optional[str] = None,
                   effective_config: Optional[Mapping[str, Any]] = None) -> Dict[str, Any]:
    """``/config``: the YAML text the app loaded and the effective config (robot.config.dump)."""
    return {"robot_config_yaml": robot_config_yaml, "map_yaml": map_yaml,
            "robot_config_path": robot_config_path, "map_path": map_path,
            "effective_config": None if effective_config is None else dict(effective_config)}


# The map  -----------------------------------------------------------------------------------------

def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3): two orthonormal directions in the plane of ``normal``."""
    n = np.asarray(normal, dtype=float)
    helper = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return np.vstack([u, np.cross(n, u)])


def _triangulate(polygon: np.ndarray, normal: np.ndarray) -> List[Tuple[int, int, int]]:
    """Ear clipping of a simple planar polygon (convex or not) into vertex index triples.

    Walls split by doors and IFC faces are not always convex, so a triangle fan could fill the
    door. A polygon ear clipping cannot finish (self-intersecting) falls back to a fan.
    """
    pts = np.asarray(polygon, dtype=float) @ _plane_basis(normal).T
    idx = list(range(len(pts)))
    area = 0.5 * sum(pts[i][0] * pts[(i + 1) % len(pts)][1] - pts[(i + 1) % len(pts)][0] * pts[i][1]
                     for i in range(len(pts)))
    if area < 0:
        idx.reverse()  # counter-clockwise in the 2-D basis

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    out: List[Tuple[int, int, int]] = []
    guard = 0
    while len(idx) > 3 and guard < 10 * len(pts) ** 2:
        guard += 1
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = pts[i0], pts[i1], pts[i2]
            if cross(a, b, c) <= 1e-12:
                continue  # reflex or degenerate corner: not an ear
            if any(cross(a, b, pts[j]) >= 0 and cross(b, c, pts[j]) >= 0 and cross(c, a, pts[j]) >= 0
                   for j in idx if j not in (i0, i1, i2)):
                continue
            out.append((i0, i1, i2))
            del idx[k]
            break
        else:
            break
    if len(idx) == 3:
        out.append((idx[0], idx[1], idx[2]))
        return out
    return [(0, i, i + 1) for i in range(1, len(pts) - 1)]


def map_message(plane_map: Any, t: float = 0.0) -> Dict[str, Any]:
    """``/map``: a SceneUpdate with each polygon filled (translucent) and outlined, and each plane id as a label."""
    lines: List[Dict[str, Any]] = []
    triangles: List[Dict[str, Any]] = []
    texts: List[Dict[str, Any]] = []
    planes: List[Dict[str, Any]] = []
    for i, plane in enumerate(plane_map.planes):
        r, g, b = (PALETTE[i % len(PALETTE)] / 255.0).tolist()
        for poly in plane.polygons:
            lines.append({"type": 1, "pose": _IDENTITY_POSE, "thickness": 2.0, "scale_invariant": True,
                          "points": [_point(p) for p in poly], "color": _rgba((r, g, b, 1.0)), "colors": [],
                          "indices": []})
            tri = [_point(poly[j]) for corner in _triangulate(poly, plane.normal) for j in corner]
            triangles.append({"pose": _IDENTITY_POSE, "points": tri, "color": _rgba((r, g, b, 0.35)), "colors": [],
                              "indices": []})
        c = np.asarray(plane.vertices, dtype=float).mean(axis=0)
        texts.append({"pose": {"position": _point(c), "orientation": _IDENTITY_POSE["orientation"]},
                      "billboard": True, "font_size": 12.0, "scale_invariant": True,
                      "color": _rgba((r, g, b, 1.0)), "text": plane.id})
        planes.append({"id": plane.id, "normal": [float(v) for v in plane.normal], "d": float(plane.d),
                       "polygons": [[[float(v) for v in p] for p in poly] for poly in plane.polygons]})
    entity = _entity(t, "map", lines=lines, triangles=triangles, texts=texts)
    return {"deletions": [], "entities": [entity], "t": float(t), "planes": planes}


# ROI label images  --------------------------------------------------------------------------------

def check_label(label: Any) -> np.ndarray:
    """The label image as an array; ValueError unless it is a non-empty 2-D integer array."""
    lab = np.asarray(label)
    if lab.ndim != 2 or lab.size == 0 or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"ROI label image must be a non-empty 2-D integer array, got {lab.dtype} {lab.shape}")
    return lab


# OpenCV writes BGR; the last row is for pixels of no plane.
_LUT_BGR = np.ascontiguousarray(np.vstack([PALETTE, [NO_PLANE_RGB]]).astype(np.uint8)[:, ::-1])


def roi_png(label: Any, max_width: int = ROI_MAX_WIDTH) -> bytes:
    """Colour PNG of a label image (plane index per pixel, negative for none), decimated to fit."""
    import cv2

    lab = check_label(label)
    step = decimation_for(lab.shape[1], max_width)
    lab = lab[::step, ::step]
    idx = np.where(lab < 0, len(PALETTE), np.mod(lab, len(PALETTE))).astype(np.uint8)
    ok, png = cv2.imencode(".png", np.take(_LUT_BGR, idx, axis=0), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("PNG encoding of the ROI label image failed")
    return png.tobytes()


def roi_message(t: float, camera: str, label: Any) -> Dict[str, Any]:
    """``/roi/<camera>``: the ROI label image of one frame as a colour PNG."""
    return {"timestamp": stamp(t), "frame_id": frames.camera_optical_frame(camera), "format": "png",
            "data": base64.b64encode(roi_png(label)).decode("ascii"), "camera": str(camera), "t": float(t)}

