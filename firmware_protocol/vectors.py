"""Writes ``test_vectors.json``: the golden bytes both codecs (Python and C) are tested against.

Run once per protocol change (``python -m firmware_protocol.vectors``), review the diff, commit.
The tests never regenerate the file; they check both codecs against the frozen bytes. The CRC
check value and the COBS cases are independent of this code (the CRC catalogue's check value,
the COBS examples of Cheshire and Baker as listed on Wikipedia).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any, Dict, List

from firmware_protocol import messages as M
from firmware_protocol.codec import encode
from firmware_protocol.frame import PROTOCOL_VERSION, encode_frame

PATH = Path(__file__).with_name("test_vectors.json")

FRAMES: List[M.Message] = [
    M.Hello(minor=0, nonce=0x12345678, seq=0),
    M.Hello(minor=0, nonce=0, seq=255),
    M.SetWheelSpeeds((0, 0, 0, 0), seq=0),
    M.SetWheelSpeeds((1500, -1500, 20000, -20000), seq=1),
    M.SetWheelSpeeds((2147483647, -2147483648, 1, -1), seq=128),
    M.Stop(seq=2),
    M.Heartbeat(seq=3),
    M.HelloReply(minor=0, nonce=0x12345678, fw_major=1, fw_minor=2, fw_patch=3, ticks_per_rev=1320,
                 max_speed_mrad_s=20000, max_accel_mrad_s2=40000, watchdog_ms=200, report_period_us=10000,
                 capabilities=0, seq=0),
    M.EncoderReport(t_us=1_000_000, ticks=(1320, -1320, 0, 123456), seq=17),
    M.EncoderReport(t_us=0xFFFFFFFF, ticks=(-1, -1, -1, -1), seq=254),
    M.EncoderReport(t_us=0, ticks=(2147483647, -2147483648, 0, 0), seq=0),
    M.Status(t_us=5_000_000, battery_mv=12150, motor_faults=0, flags=0, rx_errors=0, seq=40),
    M.Status(t_us=123, battery_mv=65535, motor_faults=0x0F, flags=0x1F, rx_errors=65535, seq=41),
    M.Ack(ref_id=0x02, ref_seq=1, seq=42),
    M.Nack(ref_id=0x02, ref_seq=128, reason=int(M.NackReason.CLAMPED), detail=0x03, seq=43),
    M.UnknownMessage(msg_id=0x7F, data=bytes([0x00, 0x01, 0xFF, 0x00]), seq=9),
]

COBS = [  # (plain, encoded without delimiter)
    ("", "01"),
    ("00", "0101"),
    ("0000", "010101"),
    ("001100", "01021101"),
    ("11220033", "03112202 33".replace(" ", "")),
    ("11223344", "0511223344"),
    ("11000000", "0211010101"),
    (bytes(range(1, 255)).hex(), "ff" + bytes(range(1, 255)).hex()),
    ("00" + bytes(range(1, 255)).hex(), "01ff" + bytes(range(1, 255)).hex()),
    (bytes(range(1, 256)).hex(), "ff" + bytes(range(1, 255)).hex() + "02ff"),
    (bytes(range(2, 256)).hex() + "00", "ff" + bytes(range(2, 256)).hex() + "0101"),
    (bytes(range(3, 256)).hex() + "0001", "fe" + bytes(range(3, 256)).hex() + "0201"),
]


def message_fields(m: M.Message) -> Dict[str, Any]:
    out: Dict[str, Any] = {}
    for f in dataclasses.fields(m):
        v = getattr(m, f.name)
        out[f.name] = v.hex() if isinstance(v, bytes) else (list(v) if isinstance(v, tuple) else v)
    return out


def message_from_json(type_name: str, fields: Dict[str, Any]) -> M.Message:
    cls = getattr(M, type_name)
    kw = {}
    for k, v in fields.items():
        kw[k] = bytes.fromhex(v) if k == "data" else (tuple(v) if isinstance(v, list) else v)
    return cls(**kw)


def _must_fail() -> List[Dict[str, Any]]:
    good = encode(M.SetWheelSpeeds((1500, -1500, 20000, -20000), seq=1))
    flipped = bytearray(good)
    flipped[-3] ^= 0x01  # inside the CRC, never a code byte of this frame
    return [
        {"name": "crc_bit_flip", "wire": bytes(flipped).hex(), "counter": "crc_errors"},
        {"name": "version_2", "wire": encode(M.Stop(seq=5), version=PROTOCOL_VERSION + 1).hex(),
         "counter": "version_mismatch"},
        {"name": "too_short", "wire": "00" + "0701020304050600", "counter": "too_short"},
        {"name": "bad_length", "wire": encode_frame(M.SetWheelSpeeds.MSG_ID, 3, bytes(range(1, 16))).hex(),
         "counter": "bad_length"},
        {"name": "cobs_code_past_end", "wire": "000501020300", "counter": "cobs_errors"},
        {"name": "oversize", "wire": "00" + "01" * 100 + "00", "counter": "oversize"},
    ]


def build() -> Dict[str, Any]:
    return {
        "protocol_version": PROTOCOL_VERSION,
        "crc32": [{"data": b"123456789".hex(), "crc": "cbf43926"}, {"data": "", "crc": "00000000"}],
        "cobs": [{"plain": p, "encoded": e} for p, e in COBS],
        "frames": [
            {"type": type(m).__name__, "fields": message_fields(m), "wire": encode(m).hex()} for m in FRAMES
        ],
        "must_fail": _must_fail(),
    }


def main() -> int:
    PATH.write_text(json.dumps(build(), indent=1) + "\n", encoding="utf-8")
    sys.stdout.write(f"wrote {PATH}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
