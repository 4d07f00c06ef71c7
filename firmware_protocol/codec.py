"""``encode(message) -> bytes`` and the incremental ``Decoder``. Pure: no I/O, no clocks.

The decoder never raises on received bytes: every problem is a counter in ``Decoder.stats``.
"""

from __future__ import annotations

import struct
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional

from firmware_protocol.frame import MAX_ENCODED, PROTOCOL_VERSION, FrameError, encode_frame, parse_frame
from firmware_protocol.messages import MESSAGE_TYPES, Message, UnknownMessage


def encode(message: Message, version: int = PROTOCOL_VERSION, seq: Optional[int] = None) -> bytes:
    """Wire bytes (0x00, COBS frame, 0x00) of a message; ValueError if a field does not fit its type.
    ``seq`` numbers the frame instead of ``message.seq`` (a sender numbering every frame it makes
    need not copy a frozen message for it)."""
    msg_id = message.msg_id if isinstance(message, UnknownMessage) else message.MSG_ID
    return encode_frame(msg_id, message.seq if seq is None else seq, message.payload(), version=version)


@dataclass
class DecoderStats:
    """What the decoder accepted and what it threw away, and why."""

    frames: int = 0  # messages returned (known and unknown ids)
    unknown: int = 0  # of those, intact frames with an id this side does not know
    crc_errors: int = 0
    cobs_errors: int = 0
    too_short: int = 0  # fewer bytes than version + id + seq + CRC
    bad_length: int = 0  # known id, payload shorter than its layout
    version_mismatch: int = 0  # intact frame of another major version (see foreign_version)
    oversize: int = 0  # no delimiter within MAX_ENCODED bytes: a lost delimiter or noise
    bytes_dropped: int = 0  # bytes of every rejected frame and of overflowed buffers
    foreign_version: Optional[int] = None  # the last other version seen: names a mismatch loudly

    @property
    def dropped_frames(self) -> int:
        return (self.crc_errors + self.cobs_errors + self.too_short + self.bad_length
                + self.version_mismatch + self.oversize)

    def as_dict(self) -> Dict[str, object]:
        d = asdict(self)
        d["dropped_frames"] = self.dropped_frames
        return d


class Decoder:
    """Incremental frame decoder: feed it whatever bytes arrived, get every intact message back.

    Partial frames are kept between calls. The buffer is bounded by MAX_ENCODED: past that the
    bytes are dropped up to the next delimiter, so noise without zeros cannot grow memory.
    """

    def __init__(self, version: int = PROTOCOL_VERSION):
        self.version = version
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._skipping = False  # overflowed: discard until the next delimiter

    def reset(self) -> None:
        """Forget a partial frame (after reopening a port); the counters stay."""
        self._buf.clear()
        self._skipping = False

    def feed(self, data: bytes) -> List[Message]:
        """Decode every frame completed by ``data`` (bytes-like); never raises on its content."""
        data = bytes(data)
        out: List[Message] = []
        start = 0
        while True:
            end = data.find(0, start)
            if end < 0:
                self._keep(data, start)
                return out
            if self._skipping:
                self.stats.bytes_dropped += end - start
                self._skipping = False
            elif self._buf:
                self._buf += data[start:end]
                frame = bytes(self._buf)
                self._buf.clear()
                self._decode(frame, out)
            elif end > start:
                self._decode(data[start:end], out)
            # else: an empty frame (two delimiters in a row) is a legal no-op, used to resync
            start = end + 1

    def _keep(self, data: bytes, start: int) -> None:
        n = len(data) - start
        if n == 0:
            return
        if self._skipping:
            self.stats.bytes_dropped += n
        elif len(self._buf) + n > MAX_ENCODED:
            self.stats.oversize += 1
            self.stats.bytes_dropped += len(self._buf) + n
            self._buf.clear()
            self._skipping = True
        else:
            self._buf += data[start:]

    def _decode(self, encoded: bytes, out: List[Message]) -> None:
        stats = self.stats
        try:
            raw = parse_frame(encoded)
        except FrameError as e:
            setattr(stats, e.kind, getattr(stats, e.kind) + 1)
            stats.bytes_dropped += len(encoded)
            return
        if raw.version != self.version:
            stats.version_mismatch += 1
            stats.foreign_version = raw.version
            stats.bytes_dropped += len(encoded)
            return
        cls = MESSAGE_TYPES.get(raw.msg_id)
        if cls is None:
            stats.unknown += 1
            stats.frames += 1
            out.append(UnknownMessage(msg_id=raw.msg_id, data=raw.payload, seq=raw.seq))
            return
        try:
            msg = cls.from_payload(raw.payload, raw.seq)
        except struct.error:
            stats.bad_length += 1
            stats.bytes_dropped += len(encoded)
            return
        stats.frames += 1
        out.append(msg)
