"""Read a recording made by ``robot.recording.recorder`` back as Python objects, in log-time order.

Depth channels come back as ``DepthFrame`` (bit-exact; 16UC1 RawImage, or the 16-bit PNG of
recordings made before), every other channel as the dict that was written. Log times are
wall-clock; ``RecordedMessage.t`` is the app's monotonic time again, by the clock offset the
segment's metadata keeps (recordings without one logged monotonic time itself).

Reading is sequential, so a recording cut short (power loss, a full disk, a killed process)
still yields every message up to its last complete chunk; ``truncated`` lists the segments that
ended early.

A run rotated into several segments is read as one: give any segment and, with
``follow_segments``, the others of the same run (same recording id, found next to it) are
read too, in order. The latched messages each segment repeats (``/config``, ``/map``,
``/tf_static``) are yielded only when they changed.
"""

from __future__ import annotations

import json
import logging
import re
import struct
from dataclasses import dataclass
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

from robot.base.errors import ConfigError, InputError
from robot.base.files import RECORDING, check_regular_file, open_regular_file
from robot.config import RobotConfig, parse_robot_config
from robot.recording import schema as ms

log = logging.getLogger(__name__)

PathLike = Union[str, Path]
_SEGMENT_RE = re.compile(r"[-_.]?\d+$")


@dataclass
class RecordedMessage:
    topic: str
    log_time_ns: int  # wall-clock ns (monotonic ns in recordings without a clock offset)
    message: Any  # DepthFrame for /depth/<camera>, dict otherwise
    clock_offset_ns: int = 0  # wall-clock minus monotonic, from the segment's metadata

    @property
    def t(self) -> float:
        """Log time in the app's monotonic seconds."""
        return (self.log_time_ns - self.clock_offset_ns) / 1e9

    @property
    def wall_time(self) -> float:
        """Log time in seconds since the epoch (for a recording that has a clock offset)."""
        return self.log_time_ns / 1e9


def _mcap():
    try:
        from mcap import exceptions
        from mcap.records import Channel, Message, Metadata, Schema
        from mcap.stream_reader import StreamReader
    except ImportError:
        raise ConfigError("reading recordings needs the 'mcap' package: "
                          "pip install 'planeloc-robot[record]'") from None
    return StreamReader, Schema, Channel, Message, Metadata, exceptions


class _BoundedFile:
    """A file that never hands out more than it holds: a corrupt record length (2**60) makes the
    MCAP reader ask for that many bytes at once, which would be a MemoryError instead of a short
    read the reader reports as the end of the file."""

    def __init__(self, f):
        self._f = f
        self.size = max(0, f.seek(0, 2))
        self.pos = f.seek(0)  # kept here too: messages name it after the file is closed

    def read(self, n: int = -1) -> bytes:
        left = max(0, self.size - self.pos)
        data = self._f.read(left if n is None or n < 0 else min(n, left))
        self.pos += len(data)
        return data

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = 0) -> int:
        self.pos = self._f.seek(offset, whence)
        return self.pos

    def seekable(self) -> bool:
        return True


# What the mcap package lets through on a cut or corrupt file besides its own McapError.
_DECODE_ERRORS = (ValueError, struct.error, MemoryError, OverflowError, KeyError, IndexError, TypeError)


def _check_exists(path: Path) -> None:
    if not path.exists():
        raise InputError(f"{path}: no such recording")
    check_regular_file(path, RECORDING)  # a directory, FIFO or device: refused, never read


def read_recording_metadata(path: PathLike) -> Dict[str, str]:
    """The ``recording`` metadata of one segment (id, segment, created, software); {} if absent."""
    StreamReader, _, _, Message, Metadata, exceptions = _mcap()
    _check_exists(Path(path))
    try:
        with open_regular_file(path, RECORDING) as raw:
            for record in StreamReader(_BoundedFile(raw)).records:
                if isinstance(record, Metadata) and record.name == "recording":
                    return dict(record.metadata)
                if isinstance(record, Message):
                    break  # the recorder writes its metadata before any message
    except FileNotFoundError:
        raise InputError(f"{path}: no such recording") from None
    except (exceptions.McapError, OSError) + _DECODE_ERRORS:
        pass
    return {}


def recording_segments(path: PathLike) -> List[Path]:
    """``path`` and the other segments of the same run beside it, in segment order."""
    path = Path(path)
    _check_exists(path)
    meta = read_recording_metadata(path)
    if "id" not in meta:
        return [path]
    # Segment names differ from each other in a trailing number (run.mcap, run_001.mcap or
    # rec-000.mcap, rec-001.mcap); the recording id decides which candidates belong.
    base = _SEGMENT_RE.sub("", path.stem) or path.stem
    candidates = {path}
    candidates.update(path.parent.glob(glob_escape(base) + "*" + path.suffix))
    found: List[Tuple[int, Path]] = []
    for p in candidates:
        try:
            other = meta if p == path else read_recording_metadata(p)
        except InputError:  # a FIFO or directory that happens to match the name: not a segment
            continue
        if other.get("id") == meta["id"]:
            try:
                found.append((int(other.get("segment", "0")), p))
            except ValueError:
                found.append((0, p))
    return [p for _, p in sorted(found)]


def _wanted(topic: str, topics: Optional[Sequence[str]]) -> bool:
    if topics is None:
        return True
    return any(topic == w or (w.endswith("/") and topic.startswith(w)) for w in topics)


class RecordingReader:
    """Messages of one run (one file, or all its segments)."""

    def __init__(self, path: Union[PathLike, Sequence[PathLike]], follow_segments: bool = True):
        if isinstance(path, (str, Path)):
            self.paths = recording_segments(path) if follow_segments else [Path(path)]
        else:
            self.paths = [Path(p) for p in path]
        for p in self.paths:
            _check_exists(p)
        self.truncated: List[Path] = []

    def messages(self, topics: Optional[Iterable[str]] = None) -> Iterator[RecordedMessage]:
        """Every message (or those on ``topics``: exact names, or prefixes ending in '/')."""
        wanted = None if topics is None else list(topics)
        self.truncated = []
        last_latched: Dict[str, bytes] = {}
        for path in self.paths:
            for topic, log_ns, data, offset in self._raw(path, wanted):
                if topic in ms.LATCHED_TOPICS:
                    if last_latched.get(topic) == data:
                        continue
                    last_latched[topic] = data
                yield RecordedMessage(topic, log_ns, self._decode(path, topic, log_ns - offset, data), offset)

    def config(self) -> Optional[Dict[str, Any]]:
        """The run's first ``/config`` message (robot config and map YAML text, effective config), if recorded."""
        for m in self.messages([ms.TOPIC_CONFIG]):
            return m.message
        return None

    def robot_config(self) -> Optional[RobotConfig]:
        """The robot config the run used, defaults as they were then (its ``effective_config``), or
        None when the recording has none (made before recordings carried it). ConfigError, naming
        the recording, when this code cannot read it any more (a key since removed)."""
        cfg = self.config()
        effective = cfg.get("effective_config") if isinstance(cfg, dict) else None
        if effective is None:
            return None
        return parse_robot_config(effective, source=f"{self.paths[0]}:{ms.TOPIC_CONFIG}")

    def _raw(self, path: Path, wanted: Optional[List[str]]) -> Iterator[Tuple[str, int, bytes, int]]:
        StreamReader, Schema, Channel, Message, Metadata, exceptions = _mcap()
        channels: Dict[int, Tuple[str, str]] = {}
        skipped: set = set()
        offset = 0
        f = None
        messages = 0
        try:
            with open_regular_file(path, RECORDING) as raw:
                f = _BoundedFile(raw)
                for record in StreamReader(f, validate_crcs=True).records:
                    messages += isinstance(record, Message)
                    if isinstance(record, Channel):
                        channels[record.id] = (record.topic, record.message_encoding)
                    elif isinstance(record, Metadata) and record.name == "recording":
                        offset = _clock_offset(path, record.metadata)
                    elif isinstance(record, Message):
                        if record.channel_id not in channels:
                            raise InputError(f"{path}: message on unknown channel {record.channel_id}")
                        topic, encoding = channels[record.channel_id]
                        if not _wanted(topic, wanted):
                            continue
                        if encoding != ms.MESSAGE_ENCODING:
                            if topic not in skipped:
                                skipped.add(topic)
                                log.warning("%s: skipping %s (encoding %r, not json)", path, topic, encoding)
                            continue
                        yield topic, record.log_time, bytes(record.data), offset
        except InputError:
            raise
        except (exceptions.EndOfFile, struct.error):  # struct.error: cut inside a record's header
            if messages == 0:  # nothing intact to go on with: one error, not a warning and an empty run
                raise InputError(f"{path}: cut short at byte {f.size if f is not None else 0}, before its first "
                                 f"complete message: nothing to read") from None
            self.truncated.append(path)
            log.warning("%s ends early at byte %s (the recording was not closed): read up to its last complete "
                        "chunk; `mcap recover` can rebuild its index for other tools", path,
                        f.size if f is not None else 0)
        except exceptions.InvalidMagic:
            raise InputError(f"{path}: not an MCAP file") from None
        except (exceptions.McapError,) + _DECODE_ERRORS as e:
            at = f" at byte {f.pos}" if f is not None else ""
            raise InputError(f"{path}: corrupt recording{at} ({type(e).__name__}: {str(e)[:100]})") from None
        except OSError as e:
            raise InputError(f"{path}: cannot read ({e})") from None

    @staticmethod
    def _decode(path: Path, topic: str, log_ns: int, data: bytes) -> Any:
        """``log_ns``: monotonic, for the message naming a bad record."""
        try:
            message = json.loads(data)
            if topic.startswith(ms.DEPTH_PREFIX):
                return ms.decode_depth(message)
            return message
        except (ValueError, RecursionError, MemoryError) as e:  # RecursionError: JSON nested 100,000 deep
            raise InputError(f"{path}: {topic} message at {log_ns / 1e9:.3f} s: {type(e).__name__}: "
                             f"{str(e)[:100]}") from None


def _clock_offset(path: Path, metadata: Dict[str, str]) -> int:
    raw = metadata.get("clock_offset_ns")
    if raw is None:
        return 0  # recorded when log times were the monotonic clock itself
    try:
        return int(raw)
    except ValueError:
        raise InputError(f"{path}: recording metadata clock_offset_ns is not an integer: {raw[:40]!r}") from None


def read_recording(path: Union[PathLike, Sequence[PathLike]], topics: Optional[Iterable[str]] = None,
                   follow_segments: bool = True) -> Iterator[RecordedMessage]:
    """Shorthand for ``RecordingReader(path, follow_segments).messages(topics)``."""
    return RecordingReader(path, follow_segments).messages(topics)
