"""Serial protocol between the Jetson and the Mecanum motor board (see PROTOCOL.md).

Pure codec, no I/O: ``encode(message) -> bytes`` and ``Decoder().feed(data) -> [message, ...]``.
"""

from __future__ import annotations

from firmware_protocol.cobs import CobsError, cobs_decode, cobs_encode
from firmware_protocol.codec import Decoder, DecoderStats, encode
from firmware_protocol.frame import (
    MAX_ENCODED,
    MAX_PAYLOAD,
    PROTOCOL_MINOR,
    PROTOCOL_VERSION,
    crc32,
    encode_frame,
)
from firmware_protocol.messages import (
    MESSAGE_TYPES,
    MRAD,
    Ack,
    EncoderReport,
    Heartbeat,
    Hello,
    HelloReply,
    Message,
    Nack,
    NackReason,
    SetWheelSpeeds,
    Status,
    StatusFlag,
    Stop,
    UnknownMessage,
)

__all__ = [
    "MAX_ENCODED", "MAX_PAYLOAD", "MESSAGE_TYPES", "MRAD", "PROTOCOL_MINOR", "PROTOCOL_VERSION",
    "Ack", "CobsError", "Decoder", "DecoderStats", "EncoderReport", "Heartbeat", "Hello", "HelloReply",
    "Message", "Nack", "NackReason", "SetWheelSpeeds", "Status", "StatusFlag", "Stop", "UnknownMessage",
    "cobs_decode", "cobs_encode", "crc32", "encode", "encode_frame",
]
