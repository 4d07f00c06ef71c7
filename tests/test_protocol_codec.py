"""The Python codec against the golden vectors, every frame length, and Hypothesis round trips."""

from __future__ import annotations

import json
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import firmware_protocol as fp
from firmware_protocol.frame import MAX_ENCODED, encode_frame
from firmware_protocol.vectors import PATH as VECTORS_PATH
from firmware_protocol.vectors import message_from_json

VECTORS = json.loads(VECTORS_PATH.read_text(encoding="utf-8"))
FRAMES = [(v["type"], message_from_json(v["type"], v["fields"]), bytes.fromhex(v["wire"])) for v in VECTORS["frames"]]
FRAME_IDS = [f"{i}-{t}" for i, (t, _, _) in enumerate(FRAMES)]


def feed_bytewise(data: bytes, decoder=None):
    d = decoder or fp.Decoder()
    out = []
    for i in range(len(data)):
        out += d.feed(data[i:i + 1])
    return out, d


# Independent anchors  ---------------------------------------------------------------------------

def test_crc32_matches_catalogue_check_value():
    assert fp.crc32(b"123456789") == 0xCBF43926
    for v in VECTORS["crc32"]:
        assert fp.crc32(bytes.fromhex(v["data"])) == int(v["crc"], 16)


@pytest.mark.parametrize("case", VECTORS["cobs"], ids=lambda c: c["plain"][:12] or "empty")
def test_cobs_reference_vectors(case):
    plain, enc = bytes.fromhex(case["plain"]), bytes.fromhex(case["encoded"])
    assert fp.cobs_encode(plain) == enc
    assert fp.cobs_decode(enc) == plain


@pytest.mark.parametrize("bad", [b"\x02", b"\x05\x01\x02", b"\x03\x11\x00", b"\x00", b"\xff" + b"\x01" * 10])
def test_cobs_decode_rejects_malformed(bad):
    with pytest.raises(fp.CobsError):
        fp.cobs_decode(bad)


# Golden frames  ---------------------------------------------------------------------------------

def test_vectors_are_for_this_protocol_version():
    assert VECTORS["protocol_version"] == fp.PROTOCOL_VERSION


@pytest.mark.parametrize("type_name,msg,wire", FRAMES, ids=FRAME_IDS)
def test_golden_encode(type_name, msg, wire):
    assert fp.encode(msg) == wire


@pytest.mark.parametrize("type_name,msg,wire", FRAMES, ids=FRAME_IDS)
def test_golden_decode_whole_and_bytewise(type_name, msg, wire):
    d = fp.Decoder()
    assert d.feed(wire) == [msg]
    assert feed_bytewise(wire)[0] == [msg]
    assert d.stats.dropped_frames == 0 and d.stats.bytes_dropped == 0


def test_golden_stream_concatenated_with_garbage_between_frames():
    rng = random.Random(7)
    stream = bytearray()
    for _, _, wire in FRAMES:
        stream += bytes(rng.randrange(256) for _ in range(rng.randrange(0, 40)))  # zeros included
        stream += wire
    expected = [m for _, m, _ in FRAMES]
    assert fp.Decoder().feed(bytes(stream)) == expected
    assert feed_bytewise(bytes(stream))[0] == expected


@pytest.mark.parametrize("case", VECTORS["must_fail"], ids=lambda c: c["name"])
def test_must_fail_vectors_are_counted_and_the_next_frame_survives(case):
    good = fp.encode(fp.Stop(seq=9))
    d = fp.Decoder()
    out = d.feed(bytes.fromhex(case["wire"]) + good)
    assert out == [fp.Stop(seq=9)]
    assert getattr(d.stats, case["counter"]) == 1
    assert d.stats.dropped_frames == 1
    assert d.stats.bytes_dropped > 0


def test_version_mismatch_names_the_foreign_version():
    d = fp.Decoder()
    assert d.feed(fp.encode(fp.Hello(0, 1), version=3)) == []
    assert d.stats.version_mismatch == 1 and d.stats.foreign_version == 3


def test_decoder_for_another_version_accepts_only_that_version():
    d = fp.Decoder(version=2)
    assert d.feed(fp.encode(fp.Stop(seq=1), version=2) + fp.encode(fp.Stop(seq=2))) == [fp.Stop(seq=1)]
    assert d.stats.foreign_version == 1


# Every length  ----------------------------------------------------------------------------------

@pytest.mark.parametrize("pattern", ["zeros", "ones", "ff", "random"])
def test_every_payload_length_round_trips(pattern):
    rng = random.Random(len(pattern))
    for n in range(fp.MAX_PAYLOAD + 1):
        payload = {"zeros": bytes(n), "ones": b"\x01" * n, "ff": b"\xff" * n,
                   "random": bytes(rng.randrange(256) for _ in range(n))}[pattern]
        wire = encode_frame(0x70, n & 0xFF, payload)
        assert wire[0] == 0 and wire[-1] == 0 and 0 not in wire[1:-1]
        assert len(wire) <= MAX_ENCODED + 2
        expected = [fp.UnknownMessage(msg_id=0x70, data=payload, seq=n & 0xFF)]
        assert fp.Decoder().feed(wire) == expected, n
        assert feed_bytewise(wire)[0] == expected, n


def test_payload_longer_than_max_cannot_be_encoded():
    with pytest.raises(ValueError, match="MAX_PAYLOAD"):
        encode_frame(0x70, 0, bytes(fp.MAX_PAYLOAD + 1))


def test_partial_frame_is_kept_across_every_split_point():
    wire = fp.encode(fp.HelloReply(minor=0, nonce=0xDEADBEEF, ticks_per_rev=1320, seq=5))
    for cut in range(len(wire) + 1):
        d = fp.Decoder()
        out = d.feed(wire[:cut])
        out += d.feed(wire[cut:])
        assert out == [fp.HelloReply(minor=0, nonce=0xDEADBEEF, ticks_per_rev=1320, seq=5)], cut


def test_longer_payload_from_a_newer_minor_version_is_accepted():
    base = fp.SetWheelSpeeds((1, -2, 3, -4), seq=6)
    wire = encode_frame(base.MSG_ID, 6, base.payload() + b"\x01\x02\x03")
    assert fp.Decoder().feed(wire) == [base]


def test_oversize_noise_is_dropped_and_the_buffer_stays_bounded():
    d = fp.Decoder()
    noise = bytes(range(1, 256)) * 4  # no zero byte anywhere
    assert d.feed(noise) == []
    assert len(d._buf) <= MAX_ENCODED
    assert d.feed(fp.encode(fp.Stop(seq=1))) == [fp.Stop(seq=1)]
    assert d.stats.oversize == 1
    assert d.stats.bytes_dropped == len(noise)


def test_oversize_is_detected_fed_byte_by_byte():
    out, d = feed_bytewise(b"\x01" * 300 + fp.encode(fp.Stop(seq=3)))
    assert out == [fp.Stop(seq=3)]
    assert d.stats.oversize == 1 and d.stats.bytes_dropped == 300


@pytest.mark.parametrize("kind", [bytes, bytearray, memoryview])
def test_feed_accepts_bytes_like(kind):
    wire = fp.encode(fp.Ack(2, 3, seq=4))
    assert fp.Decoder().feed(kind(wire)) == [fp.Ack(2, 3, seq=4)]


def test_reset_drops_a_partial_frame_but_keeps_counters():
    d = fp.Decoder()
    d.feed(fp.encode(fp.Stop(seq=1))[:-1] + b"\x01")  # unfinished
    d.feed(b"\x00\x05\x00")  # one cobs error
    d.feed(fp.encode(fp.Stop(seq=2))[:5])
    d.reset()
    assert d.feed(fp.encode(fp.Stop(seq=3))[1:]) == [fp.Stop(seq=3)]
    assert d.stats.cobs_errors == 1


# Field validation at the encoder  ---------------------------------------------------------------

@pytest.mark.parametrize("msg", [
    fp.SetWheelSpeeds((2 ** 31, 0, 0, 0)),
    fp.SetWheelSpeeds((0, 0, 0)),
    fp.EncoderReport(t_us=-1),
    fp.Status(battery_mv=70000),
    fp.Hello(minor=256),
    fp.Stop(seq=256),
])
def test_encode_rejects_fields_that_do_not_fit(msg):
    with pytest.raises(ValueError):
        fp.encode(msg)


@pytest.mark.parametrize("bad", [[1.0, 2.0, 3.0], [float("nan"), 0, 0, 0], [float("inf"), 0, 0, 0]])
def test_speeds_in_rad_s_must_be_four_finite_numbers(bad):
    with pytest.raises(ValueError, match="4 finite"):
        fp.SetWheelSpeeds.from_rad_s(bad)


def test_rad_s_conversion_rounds_to_mrad():
    m = fp.SetWheelSpeeds.from_rad_s([1.2344, -1.2346, 0.0, 19.9995])
    assert m.speeds_mrad_s == (1234, -1235, 0, 20000)
    assert m.rad_s == (1.234, -1.235, 0.0, 20.0)


# Hypothesis round trips  ------------------------------------------------------------------------

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
i32 = st.integers(-(2 ** 31), 2 ** 31 - 1)
quad = st.tuples(i32, i32, i32, i32)
MESSAGES = st.one_of(
    st.builds(fp.Hello, minor=u8, nonce=u32, seq=u8),
    st.builds(fp.SetWheelSpeeds, speeds_mrad_s=quad, seq=u8),
    st.builds(fp.Stop, seq=u8),
    st.builds(fp.Heartbeat, seq=u8),
    st.builds(fp.HelloReply, minor=u8, nonce=u32, fw_major=u8, fw_minor=u8, fw_patch=u8, ticks_per_rev=u32,
              max_speed_mrad_s=u32, max_accel_mrad_s2=u32, watchdog_ms=u16, report_period_us=u16,
              capabilities=u16, seq=u8),
    st.builds(fp.EncoderReport, t_us=u32, ticks=quad, seq=u8),
    st.builds(fp.Status, t_us=u32, battery_mv=u16, motor_faults=u8, flags=u8, rx_errors=u16, seq=u8),
    st.builds(fp.Ack, ref_id=u8, ref_seq=u8, seq=u8),
    st.builds(fp.Nack, ref_id=u8, ref_seq=u8, reason=u8, detail=u8, seq=u8),
    st.builds(fp.UnknownMessage, msg_id=u8.filter(lambda i: i not in fp.MESSAGE_TYPES),
              data=st.binary(max_size=fp.MAX_PAYLOAD), seq=u8),
)


@settings(max_examples=300, deadline=None)
@given(MESSAGES)
def test_round_trip_any_message(msg):
    wire = fp.encode(msg)
    assert 0 not in wire[1:-1]
    assert fp.Decoder().feed(wire) == [msg]


@settings(max_examples=150, deadline=None)
@given(st.lists(MESSAGES, min_size=1, max_size=12), st.lists(st.integers(0, 10_000), max_size=20))
def test_round_trip_stream_split_anywhere(msgs, cuts):
    stream = b"".join(fp.encode(m) for m in msgs)
    points = sorted({c % (len(stream) + 1) for c in cuts})
    d = fp.Decoder()
    out = []
    prev = 0
    for p in points + [len(stream)]:
        out += d.feed(stream[prev:p])
        prev = p
    assert out == msgs
    assert d.stats.frames == len(msgs) and d.stats.dropped_frames == 0


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=253) | st.lists(st.sampled_from([0, 1, 255]), max_size=253).map(bytes))
def test_cobs_short_data_takes_the_one_block_path_with_the_general_encoding(data):
    """Data shorter than 254 bytes (every protocol frame) is encoded without the block loop; the
    bytes are the general encoder's."""
    from firmware_protocol.cobs import _cobs_encode_blocks, cobs_decode, cobs_encode

    assert cobs_encode(data) == _cobs_encode_blocks(data)
    assert cobs_decode(cobs_encode(data)) == data


def test_wheel_commands_keep_their_checks_and_wire_bytes():
    """The written-out checks of a speed command refuse and accept what they did, and the frame
    of a command is the bytes the general path gives."""
    import math

    from drivers.chassis.session import check_wheels, scale_into
    from firmware_protocol.cobs import _cobs_encode_blocks
    from firmware_protocol.frame import crc32

    for bad in ((1.0, 2.0, 3.0), (1.0, math.nan, 0.0, 0.0), (math.inf, 0.0, 0.0, 0.0), ("a", 0, 0, 0), None):
        with pytest.raises(ValueError):
            check_wheels(bad)
    for bad in ((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, -math.inf)):
        with pytest.raises(ValueError):
            fp.SetWheelSpeeds.from_rad_s(bad)
    rng = random.Random(3)
    for _ in range(500):
        w = [rng.uniform(-40.0, 40.0) for _ in range(4)]
        assert check_wheels(tuple(w)) == w
        scaled, did = scale_into(w, 20.0)
        peak = max(abs(v) for v in w)
        assert did == (peak > 20.0) and scaled == ([v * 20.0 / peak for v in w] if did else w)
        msg = fp.SetWheelSpeeds.from_rad_s(scaled, seq=rng.randrange(256))
        assert msg.speeds_mrad_s == tuple(int(round(v * fp.MRAD)) for v in scaled)
        body = bytes([fp.PROTOCOL_VERSION, msg.MSG_ID, msg.seq]) + msg.payload()
        expected = b"\x00" + _cobs_encode_blocks(body + crc32(body).to_bytes(4, "little")) + b"\x00"
        assert fp.encode(msg) == expected
