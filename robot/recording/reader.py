"""Read a recording made by ``robot.recording.recorder`` back as Python objects, in log-time order.

Depth channels come back as ``DepthFrame`` (bit-exact), every other channel as the dict that
was written. Reading is sequential, so a recording cut short (power loss, a full disk, a killed
process) still yields every message up to its last complete chunk; ``truncated`` lists the
segments that ended early.

A run rotated into several segments is read as one: give any segment and, with
``follow_segments``, the others of the same run (same recording id, found next to it) are
read too, in order. The ``/config`` message each segment repeats is yielded only when it changed.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

from robot.base.errors import ConfigError, InputError
from robot.base.samples import DepthFrame
from robot.recording import schema as ms

log = logging.getLogger(__name__)

PathLike = Union[str, Path]
_SEGMENT_RE = re.compile(r"[-_.]?\d+$")


@dataclass
class RecordedMessage:
    topic: str
    log_time_ns: int
    message: Any  # DepthFrame for /depth/<camera>, dict otherwise

    @property
    def t(self) -> float:
        """Log time in the app's monotonic seconds."""
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


def read_recording_metadata(path: PathLike) -> Dict[str, str]:
    """The ``recording`` metadata of one segment (id, segment, created, software); {} if absent."""
    StreamReader, _, _, Message, Metadata, exceptions = _mcap()
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f).records:
                if isinstance(record, Metadata) and record.name == "recording":
                    return dict(record.metadata)
                if isinstance(record, Message):
                    break  # the recorder writes its metadata before any message
    except FileNotFoundError:
        raise InputError(f"{path}: no such recording") from None
    except (exceptions.McapError, OSError, ValueError):
        pass
    return {}


def recording_segments(path: PathLike) -> List[Path]:
    """``path`` and the other segments of the same run beside it, in segment order."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such recording")
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
        other = meta if p == path else read_recording_metadata(p)
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
            if not p.is_file():
                raise InputError(f"{p}: no such recording")
        self.truncated: List[Path] = []

    def messages(self, topics: Optional[Iterable[str]] = None) -> Iterator[RecordedMessage]:
        """Every message (or those on ``topics``: exact names, or prefixes ending in '/')."""
        wanted = None if topics is None else list(topics)
        self.truncated = []
        last_config: Optional[bytes] = None
        for path in self.paths:
            for topic, log_ns, data in self._raw(path, wanted):
                if topic == ms.TOPIC_CONFIG:
                    if data == last_config:
                        continue
                    last_config = data
                yield RecordedMessage(topic, log_ns, self._decode(path, topic, log_ns, data))

    def config(self) -> Optional[Dict[str, Any]]:
        """The run's first ``/config`` message (robot config and map YAML text), if recorded."""
        for m in self.messages([ms.TOPIC_CONFIG]):
            return m.message
        return None

    def _raw(self, path: Path, wanted: Optional[List[str]]) -> Iterator[Tuple[str, int, bytes]]:
        StreamReader, Schema, Channel, Message, _, exceptions = _mcap()
        channels: Dict[int, Tuple[str, str]] = {}
        skipped: set = set()
        try:
            with open(path, "rb") as f:
                for record in StreamReader(f, validate_crcs=True).records:
                    if isinstance(record, Channel):
                        channels[record.id] = (record.topic, record.message_encoding)
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
                        yield topic, record.log_time, bytes(record.data)
        except InputError:
            raise
        except exceptions.EndOfFile:
            self.truncated.append(path)
            log.warning("%s ends early (the recording was not closed): read up to its last complete chunk; "
                        "`mcap recover` can rebuild its index for other tools", path)
        except exceptions.InvalidMagic:
            raise InputError(f"{path}: not an MCAP file") from None
        except (exceptions.McapError, ValueError) as e:
            raise InputError(f"{path}: corrupt recording ({e})") from None
        except OSError as e:
            raise InputError(f"{path}: cannot read ({e})") from None

    @staticmethod
    def _decode(path: Path, topic: str, log_ns: int, data: bytes) -> Any:
        try:
            message = json.loads(data)
            if topic.startswith(ms.DEPTH_PREFIX):
                return ms.decode_depth(message)
            return message
        except ValueError as e:
            raise InputError(f"{path}: {topic} message at {log_ns / 1e9:.3f} s: {e}") from None


def read_recording(path: Union[PathLike, Sequence[PathLike]], topics: Optional[Iterable[str]] = None,
                   follow_segments: bool = True) -> Iterator[RecordedMessage]:
    """Shorthand for ``RecordingReader(path, follow_segments).messages(topics)``."""
    return RecordingReader(path, follow_segments).messages(topics)


def depth_frames(path: Union[PathLike, Sequence[PathLike]]) -> Iterator[Tuple[float, DepthFrame]]:
    """(log time s, frame) for every depth frame of a recording."""
    for m in read_recording(path, [ms.DEPTH_PREFIX]):
        yield m.t, m.message
