"""Consistent Overhead Byte Stuffing (Cheshire and Baker, 1999). Pure functions, no I/O.

After encoding, a frame contains no 0x00 byte, so 0x00 can delimit frames on the wire and a
receiver resynchronises after any corruption by dropping bytes up to the next 0x00.
"""

from __future__ import annotations


class CobsError(ValueError):
    """The bytes are not a valid COBS encoding."""


def cobs_encode(data: bytes) -> bytes:
    """Encode canonically: a final run of exactly 254k non-zero bytes gets no trailing 0x01 block."""
    data = bytes(data)
    if len(data) < 254:
        # Every frame of the protocol: no run reaches 254 bytes, so each run is one block (its
        # length + 1, then its bytes) and the canonical rule never applies (what the loop below
        # does for such data, without its bookkeeping, fifty times a second).
        out = bytearray()
        for part in data.split(b"\x00"):
            out.append(len(part) + 1)
            out += part
        return bytes(out)
    return _cobs_encode_blocks(data)


def _cobs_encode_blocks(data: bytes) -> bytes:
    """``cobs_encode`` of any length: runs of 254 non-zero bytes and more split into 0xFF blocks."""
    out = bytearray()
    parts = bytes(data).split(b"\x00")
    last = len(parts) - 1
    for k, part in enumerate(parts):
        pos = 0
        size = len(part)
        while size - pos >= 254:
            out.append(0xFF)
            out += part[pos:pos + 254]
            pos += 254
        if k == last and size > 0 and pos == size:
            break
        out.append(size - pos + 1)
        out += part[pos:]
    return bytes(out)


def cobs_decode(enc: bytes) -> bytes:
    """Decode one frame (delimiter already removed). Raises CobsError on a malformed encoding."""
    if 0 in enc:
        raise CobsError("zero byte inside a COBS frame")
    out = bytearray()
    i = 0
    n = len(enc)
    while i < n:
        code = enc[i]
        end = i + code
        if end > n:
            raise CobsError(f"COBS code {code} at offset {i} runs past the end of the {n}-byte frame")
        out += enc[i + 1:end]
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)
