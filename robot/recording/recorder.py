"""Record a run to MCAP files with bounded disk use; never take the robot down with it.

``Recorder`` writes the channels described in ``robot.recording.schema`` (the schema set the live
view uses too, so one Foxglove layout opens both). It rotates to a new file
(a *segment*) when one grows past ``max_file_bytes``, deletes its own oldest segments when they
add up to more than ``max_total_bytes``, and stops recording for good, with one warning and
``stopped_reason`` set, when free disk space falls under ``min_free_bytes`` or a write fails
(ENOSPC, EIO, a filesystem gone read-only). It never raises for disk trouble: recording is a
diagnostic, driving is the job.

Every segment is a complete recording on its own: it starts with the latest ``/config`` and
``/map`` messages again, so a replay or Foxglove can open any one of them.

Depth images are the one heavy channel (a 848x480 frame is 1.1 MB as a 16UC1 RawImage in
JSON): ``set_depth_budget`` caps them in Mbit/s, and a frame over the budget is skipped whole
(counted in ``depth_skipped``), never shrunk, so every recorded frame replays bit for bit. ROI
label images are recorded at most ``schema.ROI_MAX_HZ`` per camera.

``NullRecorder`` has the same methods and does nothing: the robot's default.
``BackgroundRecorder`` moves image encoding and file writes off the caller's thread.

Log times: callers pass ``t`` in the app's monotonic seconds; the file stores wall-clock
nanoseconds (``schema.wall_clock()``, whose offset each segment's ``recording`` metadata keeps as
``clock_offset_ns``), so Foxglove shows when the run happened. Log times are kept non-decreasing
(a late caller is clamped to the latest time), so file order, replay order and log-time order
are one and the same.
"""

from __future__ import annotations

import datetime
import errno
import logging
import os
import platform
import queue
import shutil
import threading
import uuid
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

from robot.base.errors import ConfigError
from robot.base.samples import DepthFrame
from robot.recording import schema as ms
from robot.recording.budget import ByteBudget

log = logging.getLogger(__name__)

MiB = 1024 * 1024
# Message record (opcode, length, channel, sequence, two times) + its message-index entry.
_MESSAGE_OVERHEAD = 31 + 16
_MCAP_MAGIC = b"\x89MCAP0\r\n"  # the MCAP format's leading and trailing magic bytes


def _software_version() -> str:
    try:
        from importlib.metadata import version

        return version("planeloc-robot")
    except Exception:  # not installed (running from a checkout) or no metadata
        return "unknown"


def _default_free_bytes(directory: str) -> int:
    return shutil.disk_usage(directory).free


class _TrackedFile:
    """An unbuffered file that knows its size and can undo a write that failed half way.

    ``mcap.Writer`` uses any object with ``write``/``tell``/``flush`` as is (it only wraps
    ``RawIOBase`` instances in its own buffer), so every ``write`` here is a whole MCAP record
    group and ``good`` is always a record boundary.
    """

    def __init__(self, raw):
        self._raw = raw
        self.good = 0  # bytes that are on disk and end at a record boundary

    def write(self, data) -> int:
        view = memoryview(data)
        start = self.good
        try:
            done = 0
            while done < len(view):
                n = self._raw.write(view[done:])
                if n is None or n <= 0:
                    raise OSError(errno.EIO, "short write")
                done += n
        except OSError:
            self._rollback(start)
            raise
        self.good = start + done
        return done

    def _rollback(self, offset: int) -> None:
        try:
            self._raw.truncate(offset)
            self._raw.seek(offset)
        except OSError:
            pass

    def tell(self) -> int:
        return self.good

    def flush(self) -> None:
        pass

    def close(self) -> None:
        try:
            self._raw.close()
        except OSError:
            pass

    def terminate(self) -> bool:
        """End a data section cut short by a failed write with DataEnd + Footer (no summary).

        The result is a valid, unindexed MCAP file. Returns False when even these few bytes
        cannot be written; the file is then left ending at its last complete record, which
        ``robot.recording.reader`` (and ``mcap recover``) still read.
        """
        from mcap.data_stream import RecordBuilder
        from mcap.records import DataEnd, Footer

        rb = RecordBuilder()
        DataEnd(data_section_crc=0).write(rb)
        Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
        try:
            self.write(rb.end() + _MCAP_MAGIC)
            return True
        except OSError:
            return False


class Recorder:
    """Writes a run to MCAP segments under a disk budget. See the module docstring.

    A segment stays within ``max_file_bytes`` (a new one starts before a message would push it
    over) unless a single message is larger.

    ``path_pattern`` names the first segment; it may contain ``{start}`` (the local start time,
    ``YYYYmmdd-HHMMSS``) and ``{index}`` (segment number, e.g. ``{index:03d}``). Without
    ``{index}``, segment 0 is the path itself and segment n is ``<stem>_<nnn><suffix>``.

    ``free_bytes`` (directory -> free bytes) and ``opener`` (path -> binary file with
    ``write``/``truncate``/``seek``/``close``) are for tests; the defaults use the real disk.
    """

    def __init__(self, path_pattern: str, max_file_bytes: int = 256 * MiB, max_total_bytes: int = 2048 * MiB,
                 min_free_bytes: int = 512 * MiB, *, chunk_bytes: int = MiB, compression: str = "none",
                 free_bytes: Optional[Callable[[str], int]] = None,
                 opener: Optional[Callable[[str], Any]] = None):
        try:
            from mcap.writer import CompressionType, Writer
        except ImportError:
            raise ConfigError("recording needs the 'mcap' package: "
                              "pip install 'planeloc-robot[record]'") from None
        compressions = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4,
                        "zstd": CompressionType.ZSTD}
        if compression not in compressions:
            raise ConfigError(f"recording compression must be one of {sorted(compressions)}, "
                              f"got {compression!r}")
        try:
            if compression == "lz4":
                import lz4.frame  # noqa: F401
            elif compression == "zstd":
                import zstandard  # noqa: F401
        except ImportError:
            raise ConfigError(f"recording compression {compression!r} needs the "
                              f"{'lz4' if compression == 'lz4' else 'zstandard'} package") from None
        if min(max_file_bytes, max_total_bytes, chunk_bytes) <= 0 or min_free_bytes < 0:
            raise ConfigError("recording limits: max_file_bytes, max_total_bytes and chunk_bytes must be "
                              "positive, min_free_bytes not negative")
        self._Writer = Writer
        self._compression = compressions[compression]
        self.max_file_bytes = int(max_file_bytes)
        self.max_total_bytes = int(max_total_bytes)
        self.min_free_bytes = int(min_free_bytes)
        # Rotation is checked per message, but bytes reach the disk a chunk at a time.
        self._chunk_bytes = int(min(chunk_bytes, max(64 * 1024, max_file_bytes // 4)))
        self._free_bytes = free_bytes or _default_free_bytes
        self._opener = opener or (lambda p: open(p, "wb", buffering=0))
        self._pattern = str(path_pattern)
        self._start = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        self._segment_path(0)  # fail now on a bad pattern
        self.recording_id = uuid.uuid4().hex
        self.stopped_reason: Optional[str] = None
        self.files: List[str] = []  # segments that exist, oldest first (the last one is open)
        self._closed_sizes: Dict[str, int] = {}
        self._lock = threading.RLock()
        self._index = 0
        self._writer = None
        self._file: Optional[_TrackedFile] = None
        self._channels: Dict[str, int] = {}
        self._schemas: Dict[Tuple[str, str], int] = {}  # by (name, text): two image schemas share a name
        self._pending = 0
        self._segment_messages = 0
        self._segment_chunks = 0
        self._last_ns = 0
        self._sequence = 0
        self._latched: Dict[str, bytes] = {}  # latest message of each latched topic
        self._depth_budget: Optional[ByteBudget] = None  # None: every depth frame
        self.depth_skipped = 0
        self._last_roi: Dict[str, float] = {}
        with self._lock:
            self._open_segment()

    # ----------------------------------------------------------------- public API

    @property
    def active(self) -> bool:
        return self._writer is not None

    def write_config(self, t: float, robot_config_yaml: str, map_yaml: str,
                     robot_config_path: Optional[str] = None, map_path: Optional[str] = None,
                     effective_config: Optional[Mapping[str, Any]] = None) -> bool:
        """The robot config and map of this run (YAML text) and the effective config
        (``robot.config.dump.effective_config_dict``). Repeated at the start of each segment."""
        msg = ms.config_message(robot_config_yaml, map_yaml, robot_config_path, map_path, effective_config)
        return self._write(ms.TOPIC_CONFIG, t, ms.dumps(msg), latch=True)

    def set_depth_budget(self, max_mbit_s: Optional[float]) -> None:
        """Cap the depth images at ``max_mbit_s`` (0: none at all; None: no cap)."""
        self._depth_budget = None if max_mbit_s is None else ByteBudget(max_mbit_s)

    def admit_depth(self, t: float, frame: DepthFrame) -> bool:
        """Charge the depth budget for this frame at ``t``; False, counted in ``depth_skipped``,
        when it is spent. ``write_depth`` asks this itself."""
        depth = frame.depth
        if self._depth_budget is None or getattr(depth, "ndim", 0) != 2:
            return True  # no cap; a malformed frame is refused by the encoding, as a bug
        if self._depth_budget.admit(t, ms.depth_message_bytes(depth.shape[1], depth.shape[0])):
            return True
        self.depth_skipped += 1
        return False

    def write_depth(self, t: float, frame: DepthFrame) -> bool:
        """One depth frame on ``/depth/<camera>`` (16UC1, lossless), unless the depth budget is
        spent (then False, and ``depth_skipped`` counts it)."""
        if not self.active or not self.admit_depth(t, frame):
            return False  # skip the encoding when nothing will be written
        return self._write_depth(t, frame)

    def _write_depth(self, t: float, frame: DepthFrame) -> bool:
        return self._write(ms.depth_topic(frame.camera), t, ms.dumps(ms.encode_depth(frame)))

    def write_roi(self, t: float, camera: str, label: Any) -> bool:
        """The ROI label image of one camera frame on ``/roi/<camera>``, at most ``ROI_MAX_HZ``
        per camera (by ``t``); False when skipped."""
        if not self.active:
            return False
        last = self._last_roi.get(camera)
        if last is not None and 0.0 <= t - last < 1.0 / ms.ROI_MAX_HZ:
            return False
        self._last_roi[camera] = t
        return self._write(ms.roi_topic(camera), t, ms.dumps(ms.roi_message(t, camera, label)))

    def write_pose(self, t: float, x: float, y: float, phi: float, cov: Any, quality: Optional[str] = None,
                   reason: str = "", pose_time: Optional[float] = None, frame_id: str = ms.MAP_FRAME) -> bool:
        """A fused pose; ``cov`` is 3x3 over (x, y, phi); ``pose_time`` defaults to ``t``."""
        msg = ms.pose_message(t if pose_time is None else pose_time, x, y, phi, cov, quality=quality, reason=reason,
                              frame_id=frame_id)
        return self._write(ms.TOPIC_POSE, t, ms.dumps(msg))

    def write_odometry(self, t: float, message: Mapping[str, Any]) -> bool:
        return self.write(ms.TOPIC_ODOMETRY, t, message)

    def write_planes(self, t: float, message: Mapping[str, Any]) -> bool:
        return self.write(ms.TOPIC_PLANES, t, message)

    def write_cmd(self, t: float, message: Mapping[str, Any]) -> bool:
        return self.write(ms.TOPIC_CMD, t, message)

    def write_status(self, t: float, message: Mapping[str, Any]) -> bool:
        return self.write(ms.TOPIC_STATUS, t, message)

    def write(self, topic: str, t: float, message: Mapping[str, Any]) -> bool:
        """A dict message (built by ``robot.recording.schema``) on one of the JSON topics; its ``t``
        defaults to the log time. ``/map`` is repeated at the start of each segment.

        A message missing a required field raises ValueError: that is a bug, not disk trouble.
        """
        if topic == ms.TOPIC_CONFIG or topic.startswith(ms.DEPTH_PREFIX):
            raise ValueError(f"use write_config/write_depth for {topic}")
        msg = dict(message)
        msg.setdefault("t", float(t))
        ms.check_required(topic, msg)
        return self._write(topic, t, ms.dumps(msg), latch=topic in ms.LATCHED_TOPICS)

    def close(self) -> None:
        """Finish the open segment properly. Safe to call twice."""
        with self._lock:
            if self._writer is not None:
                error = self._finish_segment()
                if error:
                    self._stop(error)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ----------------------------------------------------------------- internals

    def _segment_path(self, index: int) -> str:
        try:
            if "{index" in self._pattern:
                return self._pattern.format(index=index, start=self._start)
            path = self._pattern.format(start=self._start)
        except (KeyError, IndexError, ValueError) as e:
            raise ConfigError(f"recording path pattern {self._pattern!r}: only {{start}} and {{index}} "
                              f"may be used ({e})") from None
        if index == 0:
            return path
        stem, suffix = os.path.splitext(path)
        return f"{stem}_{index:03d}{suffix or '.mcap'}"

    def _write(self, topic: str, t: float, data: bytes, latch: bool = False) -> bool:
        with self._lock:
            if latch:
                self._latched[topic] = data
            if self._writer is None:
                return False
            log_ns = max(ms.wall_clock().ns(t), self._last_ns)
            try:
                if self._segment_messages > 0 and self._projected_size(len(data)) > self.max_file_bytes:
                    self._rotate()
                    if self._writer is None:
                        return False
                self._add(topic, log_ns, data)
            except OSError as e:
                self._stop(f"write to {self.files[-1]} failed: {e}", failed=True)
                return False
            return True

    def _projected_size(self, message_bytes: int) -> int:
        """The segment's size once this message and the closing summary are written."""
        summary = 4096 + 128 * self._segment_chunks  # schemas, channels, statistics, chunk indexes
        return self._file.good + self._pending + message_bytes + _MESSAGE_OVERHEAD + summary

    def _add(self, topic: str, log_ns: int, data: bytes) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            name, _ = ms.schema_for(topic)
            text = ms.schema_text(topic)
            schema_id = self._schemas.get((name, text))
            if schema_id is None:
                schema_id = self._writer.register_schema(name=name, encoding=ms.SCHEMA_ENCODING,
                                                         data=text.encode("utf-8"))
                self._schemas[(name, text)] = schema_id
            channel = self._writer.register_channel(topic=topic, message_encoding=ms.MESSAGE_ENCODING,
                                                    schema_id=schema_id)
            self._channels[topic] = channel
        before = self._file.good
        self._sequence += 1
        self._writer.add_message(channel, log_time=log_ns, data=data, publish_time=log_ns,
                                 sequence=self._sequence & 0xFFFFFFFF)
        self._last_ns = log_ns
        self._segment_messages += 1
        if self._file.good != before:  # a chunk (holding this message too) went to disk
            self._pending = 0
            self._segment_chunks += 1
            self._check_free_space()
        else:
            self._pending += len(data) + _MESSAGE_OVERHEAD

    def _check_free_space(self) -> None:
        directory = os.path.dirname(os.path.abspath(self.files[-1]))
        free = self._free_bytes(directory)
        if free < self.min_free_bytes:
            self._stop(f"free disk space on {directory} is {free / MiB:.1f} MiB, under the "
                       f"{self.min_free_bytes / MiB:.1f} MiB reserve")

    def _open_segment(self) -> None:
        path = self._segment_path(self._index)
        directory = os.path.dirname(os.path.abspath(path))
        try:
            os.makedirs(directory, exist_ok=True)
            free = self._free_bytes(directory)
            if free < self.min_free_bytes:
                self._stop(f"free disk space on {directory} is {free / MiB:.1f} MiB, under the "
                           f"{self.min_free_bytes / MiB:.1f} MiB reserve")
                return
            self._file = _TrackedFile(self._opener(path))
        except OSError as e:
            self._stop(f"cannot open {path}: {e}")
            return
        self.files.append(path)
        self._writer = self._Writer(self._file, chunk_size=self._chunk_bytes, compression=self._compression)
        self._channels = {}
        self._schemas = {}
        self._pending = 0
        self._segment_messages = 0
        self._segment_chunks = 0
        try:
            self._writer.start(profile="", library="planeloc-robot recorder")
            self._writer.add_metadata("recording", {
                "id": self.recording_id, "segment": str(self._index),
                "created": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                "software": "planeloc-robot " + _software_version(),
                "clock_offset_ns": str(ms.wall_clock().offset_ns),
                "python": platform.python_version(), "host": platform.node()})
            for topic, data in list(self._latched.items()):
                self._add(topic, self._last_ns, data)
        except OSError as e:
            self._stop(f"write to {path} failed: {e}", failed=True)
            return
        log.info("recording to %s", path)

    def _finish_segment(self) -> Optional[str]:
        """Write the summary and close. On failure the file keeps what reached the disk, and the
        reason is returned."""
        writer, f, path = self._writer, self._file, self.files[-1]
        self._writer = None
        error = None
        try:
            writer.finish()
        except OSError as e:
            error = f"could not finish {path} ({e}); it ends at its last complete record"
            f.terminate()
        f.close()
        self._closed_sizes[path] = f.good
        return error

    def _rotate(self) -> None:
        error = self._finish_segment()
        if error:
            self._stop(error)
            return
        self._index += 1
        self._open_segment()
        self._prune()

    def _prune(self) -> None:
        """Delete this run's oldest closed segments so that, with the new segment grown to its
        full size, the run stays within max_total_bytes (or max_file_bytes, if that is larger)."""
        current = self.files[-1] if self._writer is not None else None
        total = sum(self._closed_sizes.get(p, 0) for p in self.files)
        if current is not None:
            total += self.max_file_bytes
        for path in list(self.files):
            if total <= self.max_total_bytes or path == current:
                break
            try:
                os.remove(path)
                log.info("recording over its %.0f MiB budget: deleted %s", self.max_total_bytes / MiB, path)
            except FileNotFoundError:
                pass
            except OSError as e:
                log.warning("cannot delete old recording %s: %s", path, e)
                continue
            total -= self._closed_sizes.pop(path, 0)
            self.files.remove(path)

    def _stop(self, reason: str, failed: bool = False) -> None:
        if self.stopped_reason is None:
            self.stopped_reason = reason
            log.warning("recording stopped: %s", reason)
        if self._writer is None:
            return
        if failed:
            # The writer's state no longer matches the file; end the file by hand instead.
            f = self._file
            self._writer = None
            f.terminate()
            f.close()
            self._closed_sizes[self.files[-1]] = f.good
        else:
            self._finish_segment()


class NullRecorder:
    """Recording off: every method of ``Recorder``, doing nothing."""

    stopped_reason: Optional[str] = None
    recording_id: Optional[str] = None
    files: List[str] = []
    active = False

    def write_config(self, t: float, robot_config_yaml: str, map_yaml: str,
                     robot_config_path: Optional[str] = None, map_path: Optional[str] = None,
                     effective_config: Optional[Mapping[str, Any]] = None) -> bool:
        return False

    def set_depth_budget(self, max_mbit_s: Optional[float]) -> None:
        pass

    def admit_depth(self, t: float, frame: DepthFrame) -> bool:
        return False

    def write_depth(self, t: float, frame: DepthFrame) -> bool:
        return False

    def write_roi(self, t: float, camera: str, label: Any) -> bool:
        return False

    def write_pose(self, t: float, x: float, y: float, phi: float, cov: Any, quality: Optional[str] = None,
                   reason: str = "", pose_time: Optional[float] = None, frame_id: str = ms.MAP_FRAME) -> bool:
        return False

    def write_odometry(self, t: float, message: Mapping[str, Any]) -> bool:
        return False

    def write_planes(self, t: float, message: Mapping[str, Any]) -> bool:
        return False

    def write_cmd(self, t: float, message: Mapping[str, Any]) -> bool:
        return False

    def write_status(self, t: float, message: Mapping[str, Any]) -> bool:
        return False

    def write(self, topic: str, t: float, message: Mapping[str, Any]) -> bool:
        return False

    def close(self) -> None:
        pass

    def __enter__(self) -> NullRecorder:
        return self

    def __exit__(self, *exc) -> None:
        pass


_STOP = object()


class BackgroundRecorder:
    """A ``Recorder`` fed through a bounded queue and written by one worker thread.

    The caller's thread (the control loop) only enqueues; image encoding (base64, ROI PNGs)
    and disk writes happen on the worker. When the queue is full the message is dropped and
    counted in ``dropped``: a slow SD card must delay the recording, never the robot. Messages
    keep their order. Do not modify a DepthFrame's or a label image's array after handing it over.

    The depth budget is charged here, on the caller's thread, so a frame over it never takes a
    place in the queue: the queue (about 10 s of the small channels at their rates) holds at most
    the few depth frames per second the budget lets through.
    """

    def __init__(self, recorder: Recorder, max_queue: int = 2048):
        self.recorder = recorder
        self.dropped = 0
        self._queue: queue.Queue = queue.Queue(maxsize=max_queue)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    @property
    def active(self) -> bool:
        return self.recorder.active

    @property
    def stopped_reason(self) -> Optional[str]:
        return self.recorder.stopped_reason

    @property
    def files(self) -> List[str]:
        return self.recorder.files

    @property
    def depth_skipped(self) -> int:
        return self.recorder.depth_skipped

    def set_depth_budget(self, max_mbit_s: Optional[float]) -> None:
        self.recorder.set_depth_budget(max_mbit_s)  # before the first write: the worker only reads it

    def _submit(self, name: str, *args, **kwargs) -> bool:
        if not self.recorder.active:
            return False
        try:
            self._queue.put_nowait((name, args, kwargs))
            return True
        except queue.Full:
            self.dropped += 1
            if self.dropped == 1 or self.dropped % 100 == 0:
                log.warning("recorder queue full: %d messages dropped so far", self.dropped)
            return False

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            name, args, kwargs = item
            try:
                getattr(self.recorder, name)(*args, **kwargs)
            except Exception:  # a bad message must not kill the worker and silently end recording
                log.exception("recorder: %s failed", name)

    def write_config(self, *args, **kwargs) -> bool:
        return self._submit("write_config", *args, **kwargs)

    def write_depth(self, t: float, frame: DepthFrame) -> bool:
        if not self.recorder.active or not self.recorder.admit_depth(t, frame):
            return False
        return self._submit("_write_depth", t, frame)

    def write_roi(self, t: float, camera: str, label: Any) -> bool:
        return self._submit("write_roi", t, camera, label)

    def write_pose(self, *args, **kwargs) -> bool:
        return self._submit("write_pose", *args, **kwargs)

    def write_odometry(self, t: float, message: Mapping[str, Any]) -> bool:
        return self._submit("write_odometry", t, dict(message))

    def write_planes(self, t: float, message: Mapping[str, Any]) -> bool:
        return self._submit("write_planes", t, dict(message))

    def write_cmd(self, t: float, message: Mapping[str, Any]) -> bool:
        return self._submit("write_cmd", t, dict(message))

    def write_status(self, t: float, message: Mapping[str, Any]) -> bool:
        return self._submit("write_status", t, dict(message))

    def write(self, topic: str, t: float, message: Mapping[str, Any]) -> bool:
        return self._submit("write", topic, t, dict(message))

    def close(self, timeout: float = 10.0) -> None:
        """Write what is queued (up to ``timeout`` seconds), then finish the file."""
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join(timeout)
        self.recorder.close()

    def __enter__(self) -> BackgroundRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
