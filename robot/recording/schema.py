"""What a recording contains: topics, their JSON schemas, and the encoding of each message.

Every channel is JSON (MCAP message encoding ``json``, schema encoding ``jsonschema``), so
Foxglove opens a recording without protobuf and ``json.loads`` reads it back. Where a Foxglove
well-known schema fits, a message is a superset of it under that schema's name (extra fields
are ignored by Foxglove), so its panels work:

- ``/depth/<camera>``: ``foxglove.CompressedImage`` with ``format: "png"``; ``data`` is a
  16-bit PNG (lossless, so replay sees the very pixels the robot saw), base64 as JSON requires.
  Extra fields carry what localization needs: ``K``, ``depth_scale``, ``t_capture``,
  ``frame_number``, ``timestamp_domain``, and ``truth`` in simulation.
- ``/pose``: ``foxglove.PoseInFrame`` plus ``x``, ``y``, ``phi``, ``cov`` (3x3 row-major) and
  ``quality``.
- ``/config``, ``/odometry``, ``/planes``, ``/cmd``, ``/status``: our own schemas (``robot.*``).

Times inside messages are the app's monotonic clock in seconds, like everywhere in the app.
This module is pure encoding: no files, and nothing here imports ``mcap``.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import math
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

from robot.base.samples import DepthFrame

TOPIC_CONFIG = "/config"
TOPIC_ODOMETRY = "/odometry"
TOPIC_POSE = "/pose"
TOPIC_PLANES = "/planes"
TOPIC_CMD = "/cmd"
TOPIC_STATUS = "/status"
DEPTH_PREFIX = "/depth/"

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"

# PNG level 1 with zlib's RLE strategy: depth noise defeats long LZ matches, so higher levels
# and the default strategy cost more CPU for a larger or equal file (scripts/bench_recorder.py);
# runs (holes, flat residuals after PNG's row filters) are what compresses.
PNG_COMPRESSION_LEVEL = 1

_NUMBER = {"type": "number"}
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
}
_VEC = {"type": "array", "items": _NUMBER}
_FOUR_WHEELS = {"type": "array", "items": _NUMBER, "minItems": 4, "maxItems": 4,
                "description": "front-left, front-right, rear-left, rear-right, rad/s"}


def _schema(title: str, description: str, properties: Dict[str, Any],
            required: Sequence[str]) -> Dict[str, Any]:
    return {"title": title, "description": description, "type": "object",
            "properties": properties, "required": list(required)}


SCHEMAS: Dict[str, Tuple[str, Dict[str, Any]]] = {
    TOPIC_CONFIG: ("robot.Config", _schema(
        "robot.Config", "Robot config and plane map of this run, as the YAML text the app loaded",
        {"robot_config_yaml": {"type": "string"}, "map_yaml": {"type": "string"},
         "robot_config_path": {"type": ["string", "null"]}, "map_path": {"type": ["string", "null"]}},
        ["robot_config_yaml", "map_yaml"])),
    TOPIC_ODOMETRY: ("robot.Odometry", _schema(
        "robot.Odometry", "Wheel odometry as fed to the EKF prediction",
        {"t": {"type": "number", "description": "measurement time, app monotonic s"},
         "wheel_speeds": _FOUR_WHEELS, "ticks": {"type": "array", "items": {"type": "integer"}},
         "vx": _NUMBER, "vy": _NUMBER, "wz": _NUMBER},
        ["t"])),
    TOPIC_POSE: ("foxglove.PoseInFrame", _schema(
        "foxglove.PoseInFrame", "Fused pose (x, y, phi) in the map frame with its 3x3 covariance",
        {"timestamp": _TIME, "frame_id": {"type": "string"},
         "pose": {"type": "object", "properties": {
             "position": {"type": "object", "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER}},
             "orientation": {"type": "object",
                             "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER, "w": _NUMBER}}}},
         "t": {"type": "number"}, "x": _NUMBER, "y": _NUMBER, "phi": _NUMBER,
         "cov": {"type": "array", "items": _NUMBER, "minItems": 9, "maxItems": 9,
                 "description": "3x3 covariance of (x, y, phi), row-major"},
         "quality": {"type": ["number", "string", "null"]}},
        ["t", "x", "y", "phi", "cov"])),
    TOPIC_PLANES: ("robot.PlaneFits", _schema(
        "robot.PlaneFits", "Planes fitted in one camera frame (n . p + d = 0, camera optical frame)",
        {"t": {"type": "number"}, "camera": {"type": "string"},
         "planes": {"type": "array", "items": {"type": "object", "properties": {
             "id": {"type": "string"}, "n": _VEC, "d": _NUMBER, "inliers": {"type": "integer"},
             "rms": _NUMBER, "cov": _VEC}}}},
        ["t", "planes"])),
    TOPIC_CMD: ("robot.WheelCommand", _schema(
        "robot.WheelCommand", "Wheel speed command sent to the motor board",
        {"t": {"type": "number"}, "wheel_speeds": _FOUR_WHEELS, "vx": _NUMBER, "vy": _NUMBER, "wz": _NUMBER},
        ["t", "wheel_speeds"])),
    TOPIC_STATUS: ("robot.Status", _schema(
        "robot.Status", "Controller status (the app's status report; free-form beyond t)",
        {"t": {"type": "number"}, "state": {"type": "string"}, "text": {"type": "string"}},
        ["t"])),
}

DEPTH_SCHEMA_NAME = "foxglove.CompressedImage"
DEPTH_SCHEMA: Dict[str, Any] = _schema(
    "foxglove.CompressedImage", "Depth image as a 16-bit PNG in depth units, with what deprojection needs",
    {"timestamp": _TIME, "frame_id": {"type": "string"},
     "data": {"type": "string", "contentEncoding": "base64"}, "format": {"type": "string"},
     "camera": {"type": "string"}, "width": {"type": "integer"}, "height": {"type": "integer"},
     "K": {"type": "array", "items": _NUMBER, "minItems": 9, "maxItems": 9},
     "depth_scale": {"type": "number", "description": "metres per depth unit"},
     "t_capture": {"type": "number"}, "frame_number": {"type": "integer"},
     "timestamp_domain": {"type": "string"},
     "truth": {"type": ["array", "null"], "items": _NUMBER}},
    ["data", "format", "camera", "K", "depth_scale", "t_capture"])


def schema_for(topic: str) -> Tuple[str, Dict[str, Any]]:
    """(schema name, JSON schema) of a topic; ValueError for a topic we do not record."""
    if topic.startswith(DEPTH_PREFIX) and len(topic) > len(DEPTH_PREFIX):
        return DEPTH_SCHEMA_NAME, DEPTH_SCHEMA
    try:
        return SCHEMAS[topic]
    except KeyError:
        raise ValueError(f"no schema for topic {topic!r}; known: {sorted(SCHEMAS)} "
                         f"and {DEPTH_PREFIX}<camera>") from None


def depth_topic(camera: str) -> str:
    return DEPTH_PREFIX + camera


def stamp(t: float) -> Dict[str, int]:
    """Foxglove's {sec, nsec} from app seconds (monotonic times are never negative)."""
    ns = max(0, int(round(t * 1e9)))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


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


def encode_depth(frame: DepthFrame) -> Dict[str, Any]:
    """A ``/depth/<camera>`` message for one frame (PNG-16, lossless)."""
    import cv2

    depth = np.asarray(frame.depth)
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise ValueError(f"depth frame from {frame.camera!r} must be (H, W) uint16, "
                         f"got {depth.dtype} {depth.shape}")
    ok, png = cv2.imencode(".png", np.ascontiguousarray(depth),
                           [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION_LEVEL,
                            cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE])
    if not ok:
        raise ValueError(f"PNG encoding of a depth frame from {frame.camera!r} failed")
    return {
        "timestamp": stamp(frame.t_capture),
        "frame_id": frame.camera,
        "format": "png",
        "data": base64.b64encode(png.tobytes()).decode("ascii"),
        "camera": frame.camera,
        "width": int(depth.shape[1]),
        "height": int(depth.shape[0]),
        "K": [float(v) for v in np.asarray(frame.K, dtype=float).reshape(9)],
        "depth_scale": float(frame.depth_scale),
        "t_capture": float(frame.t_capture),
        "frame_number": int(frame.frame_number),
        "timestamp_domain": str(frame.timestamp_domain),
        "truth": None if frame.truth is None else [float(v) for v in frame.truth],
    }


def decode_depth(message: Mapping[str, Any]) -> DepthFrame:
    """The DepthFrame a ``/depth/<camera>`` message holds; ValueError when it is malformed."""
    import cv2

    try:
        if message["format"] != "png":
            raise ValueError(f"unsupported depth format {message['format']!r}")
        raw = np.frombuffer(base64.b64decode(message["data"]), dtype=np.uint8)
        depth = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
        if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
            raise ValueError("depth data is not a 16-bit single-channel PNG")
        if "width" in message and (depth.shape[1], depth.shape[0]) != (message["width"], message["height"]):
            raise ValueError(f"depth image is {depth.shape[1]}x{depth.shape[0]}, message says "
                             f"{message['width']}x{message['height']}")
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
    except (KeyError, TypeError, ValueError, binascii.Error) as e:
        raise ValueError(f"malformed depth message: {e}") from e


def pose_message(t: float, x: float, y: float, phi: float, cov: Any, quality: Any = None,
                 frame_id: str = "map") -> Dict[str, Any]:
    """A ``/pose`` message; ``cov`` is the 3x3 covariance of (x, y, phi)."""
    c = np.asarray(cov, dtype=float)
    if c.shape != (3, 3):
        raise ValueError(f"pose covariance must be 3x3, got shape {c.shape}")
    half = 0.5 * float(phi)
    return {
        "timestamp": stamp(t),
        "frame_id": frame_id,
        "pose": {"position": {"x": float(x), "y": float(y), "z": 0.0},
                 "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)}},
        "t": float(t), "x": float(x), "y": float(y), "phi": float(phi),
        "cov": [float(v) for v in c.reshape(9)],
        "quality": quality,
    }
