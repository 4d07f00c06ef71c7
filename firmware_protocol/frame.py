"""Frame layout shared by every message: version, id, sequence, payload, CRC-32. No I/O.

    wire  = 0x00 + COBS(body) + 0x00
    body  = version u8 | msg_id u8 | seq u8 | payload (0..MAX_PAYLOAD) | crc32 u32 LE
    crc32 = CRC-32/ISO-HDLC (zlib.crc32) over version, msg_id, seq and payload

There is no length field: delimiters bound a frame, so one corrupted byte can cost at most the
frame it sits in (or, if it hits a delimiter, that frame and its neighbour), never the frames
after it. The leading 0x00 costs one byte and means garbage on the line before a frame (a
board rebooting mid-frame, noise while idle) never spoils that frame.
"""

from __future__ import annotations

import struct
import zlib
from typing import NamedTuple

from firmware_protocol.cobs import CobsError, cobs_decode, cobs_encode

# Major version, carried in every frame and covered by the CRC: a board speaking another major
# version has every frame rejected and counted, so a mismatch fails loudly instead of being
# misread. Bump it only for an incompatible change (PROTOCOL.md, "Extending the protocol").
PROTOCOL_VERSION = 1
# Minor version, exchanged in HELLO / HELLO_REPLY only: additive changes that old peers ignore.
PROTOCOL_MINOR = 0

HEADER_LEN = 3
CRC_LEN = 4
# Largest payload a v1 peer accepts; the biggest v1 message (HELLO_REPLY) uses 26 bytes, the rest
# is room for appended fields. It bounds the receive buffer of the 2 KB-RAM class of boards.
MAX_PAYLOAD = 64
MIN_BODY = HEADER_LEN + CRC_LEN
MAX_BODY = HEADER_LEN + MAX_PAYLOAD + CRC_LEN
# COBS adds one byte per started 254-byte block; MAX_BODY < 254 so exactly one.
MAX_ENCODED = MAX_BODY + 1
DELIMITER = b"\x00"

_HEADER = struct.Struct("<BBB")
_CRC = struct.Struct("<I")


def crc32(data: bytes) -> int:
    """CRC-32/ISO-HDLC: poly 0x04C11DB7 reflected, init and xorout 0xFFFFFFFF; check 0xCBF43926."""
    return zlib.crc32(data) & 0xFFFFFFFF


class RawFrame(NamedTuple):
    version: int
    msg_id: int
    seq: int
    payload: bytes


class FrameError(ValueError):
    """A received frame is unusable; ``kind`` names the DecoderStats counter it belongs to."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


def encode_frame(msg_id: int, seq: int, payload: bytes, version: int = PROTOCOL_VERSION) -> bytes:
    """Wire bytes of one frame, both delimiters included."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds MAX_PAYLOAD ({MAX_PAYLOAD})")
    if not (0 <= version <= 0xFF and 0 <= msg_id <= 0xFF and 0 <= seq <= 0xFF):
        for name, value in (("version", version), ("msg_id", msg_id), ("seq", seq)):
            if not 0 <= value <= 0xFF:
                raise ValueError(f"{name} {value} does not fit in one byte")
    body = _HEADER.pack(version, msg_id, seq) + bytes(payload)
    return DELIMITER + cobs_encode(body + _CRC.pack(crc32(body))) + DELIMITER


def parse_frame(encoded: bytes) -> RawFrame:
    """Check one COBS-encoded frame (delimiters removed); raise FrameError naming the fault."""
    if len(encoded) > MAX_ENCODED:
        raise FrameError("oversize", f"frame of {len(encoded)} encoded bytes exceeds {MAX_ENCODED}")
    try:
        body = cobs_decode(encoded)
    except CobsError as e:
        raise FrameError("cobs_errors", str(e)) from None
    if len(body) < MIN_BODY:
        raise FrameError("too_short", f"frame of {len(body)} bytes is shorter than {MIN_BODY}")
    if len(body) > MAX_BODY:
        raise FrameError("oversize", f"frame of {len(body)} bytes exceeds {MAX_BODY}")
    covered = body[:-CRC_LEN]
    (crc,) = _CRC.unpack_from(body, len(covered))
    if crc != crc32(covered):
        raise FrameError("crc_errors", "CRC mismatch")
    version, msg_id, seq = _HEADER.unpack_from(covered)
    return RawFrame(version, msg_id, seq, covered[HEADER_LEN:])
