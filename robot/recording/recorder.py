"""Record a run to MCAP files with bounded disk use; never take the robot down with it.

``Recorder`` writes the channels described in ``robot.recording.schema``. It rotates to a new file
(a *segment*) when one grows past ``max_file_bytes``, deletes its own oldest segments when they
add up to more than ``max_total_bytes``, and stops recording for good, with one warning and
``stopped_reason`` set, when free disk space falls under ``min_free_bytes`` or a write fails
(ENOSPC, EIO, a filesystem gone read-only). It never raises for disk trouble: recording is a
diagnostic, driving is the job.

Every segment is a complete recording on its own: it starts with the latest ``/config``
message again, so a replay or Foxglove can open any one of them.

``NullRecorder`` has the same methods and does nothing: the robot's default.
``BackgroundRecorder`` moves PNG encoding and file writes off the caller's thread.

Log times are the app's monotonic clock: callers pass ``t`` in seconds, the file stores
nanoseconds. Log times are kept non-decreasing (a late caller is clamped to the latest time), so
file order, replay order and log-time order are one and the same.
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
        self._schemas: Dict[str, int] = {}
        self._pending = 0
        self._segment_messages = 0
        self._segment_chunks = 0
        self._last_ns = 0
        self._sequence = 0
        self._latched: Optional[Tuple[str, bytes]] = None
        with self._lock:
            self._open_segment()

    # ----------------------------------------------------------------- public API

    @property
    def active(self) -> bool:
        return self._writer is not None

    def write_config(self, t: float, robot_config_yaml: str, map_yaml: str,
                     robot_config_path: Optional[str] = None, map_path: Optional[str] = None) -> bool:
        """The robot config and map of this run (YAML text). Repeated at the start of each segment."""
        msg = {"robot_config_yaml": robot_config_yaml, "map_yaml": map_yaml,
               "robot_config_path": robot_config_path, "map_path": map_path}
        return self._write(ms.TOPIC_CONFIG, t, ms.dumps(msg), latch=True)

    def write_depth(self, t: float, frame: DepthFrame) -> bool:
        """One depth frame on ``/depth/<camera>`` (16-bit PNG, lossless)."""
        if not self.active:
            return False  # skip the PNG encoding when nothing will be written
        return self._write(ms.depth_topic(frame.camera), t, ms.dumps(ms.encode_depth(frame)))

    def write_pose(self, t: float, x: float, y: float, phi: float, cov: Any, quality: Any = None,
                   pose_time: Optional[float] = None, frame_id: str = "map") -> bool:
        """A fused pose; ``cov`` is 3x3 over (x, y, phi); ``pose_time`` defaults to ``t``."""
        msg = ms.pose_message(t if pose_time is None else pose_time, x, y, phi, cov, quality, frame_id)
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
        """A dict message on one of the JSON topics; its ``t`` defaults to the log time.

        A message missing a required field raises ValueError: that is a bug, not disk trouble.
        """
        if topic == ms.TOPIC_CONFIG or topic.startswith(ms.DEPTH_PREFIX):
            raise ValueError(f"use write_config/write_depth for {topic}")
        msg = dict(message)
        msg.setdefault("t", float(t))
        ms.check_required(topic, msg)
        return self._write(topic, t, ms.dumps(msg))

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
                self._latched = (topic, data)
            if self._writer is None:
                return False
            log_ns = max(int(round(t * 1e9)), self._last_ns)
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
            name, schema = ms.schema_for(topic)
            schema_id = self._schemas.get(name)
            if schema_id is None:
                schema_id = self._writer.register_schema(name=name, encoding=ms.SCHEMA_ENCODING,
                                                         data=ms.dumps(schema))
                self._schemas[name] = schema_id
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
                "python": platform.python_version(), "host": platform.node()})
            if self._latched is not None:
                topic, data = self._latched
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
                     robot_config_path: Optional[str] = None, map_path: Optional[str] = None) -> bool:
        return False

    def write_depth(self, t: float, frame: DepthFrame) -> bool:
        return False

    def write_pose(self, t: float, x: float, y: float, phi: float, cov: Any, quality: Any = None,
                   pose_time: Optional[float] = None, frame_id: str = "map") -> bool:
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

    The caller's thread (the control loop) only enqueues; PNG encoding (OpenCV releases the GIL)
    and disk writes happen on the worker. When the queue is full the message is dropped and
    counted in ``dropped``: a slow SD card must delay the recording, never the robot. Messages
    keep their order. Do not modify a DepthFrame's array after handing it over.
    """

    def __init__(self, recorder: Recorder, max_queue: int = 256):
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
        return self._submit("write_depth", t, frame)

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
