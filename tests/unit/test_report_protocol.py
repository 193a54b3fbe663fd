"""Framing and codecs of the pose-reporting protocol: round trips and hostile input."""

from __future__ import annotations

import math
import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.report.messages import (
    Goodbye,
    GoodbyeReason,
    Hello,
    NavOrder,
    PoseUpdate,
    Segment,
    decode_goodbye,
    decode_hello,
    decode_nav_order,
    decode_pose,
    decode_segment,
    encode_goodbye,
    encode_hello,
    encode_nav_order,
    encode_pose,
    encode_segment,
)
from estimation.report.protocol import (
    MAX_FRAME_WIRE,
    MAX_PAYLOAD,
    Deframer,
    Frame,
    cobs_decode,
    cobs_encode,
    crc16_ccitt,
    encode_frame,
    seq_newer,
)


def _crc_reference(data: bytes) -> int:
    """Bitwise CRC-16/GENIBUS (CCITT polynomial, init and final xor 0xFFFF), independent of binascii."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc ^ 0xFFFF


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


finite32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
frames = st.builds(
    Frame,
    msg_type=st.integers(0, 15),
    robot_id=st.integers(0, 255),
    seq=st.integers(0, 0xFFFF),
    ack=st.integers(0, 0xFFFF),
    payload=st.binary(max_size=MAX_PAYLOAD),
)


def test_crc_check_value() -> None:
    # Catalogue check value of CRC-16/GENIBUS (reveng.sourceforge.io/crc-catalogue).
    assert crc16_ccitt(b"123456789") == 0xD64E
    assert _crc_reference(b"123456789") == 0xD64E


@given(st.binary(max_size=600))
def test_crc_matches_reference(data: bytes) -> None:
    assert crc16_ccitt(data) == _crc_reference(data)


def test_cobs_known_vectors() -> None:
    # Vectors from the COBS paper / Wikipedia examples.
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x00\x00") == b"\x01\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert cobs_encode(b"\x11\x00\x00\x00") == b"\x02\x11\x01\x01\x01"
    data = bytes(range(1, 255))
    assert cobs_encode(data) == b"\xff" + data + b"\x01"


@given(st.binary(max_size=1200))
def test_cobs_round_trip(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= len(data) + len(data) // 254 + 1
    assert cobs_decode(enc) == data


@given(frames)
def test_frame_round_trip(frame: Frame) -> None:
    wire = encode_frame(frame)
    assert wire.endswith(b"\x00") and 0 not in wire[:-1]
    assert len(wire) <= MAX_FRAME_WIRE
    d = Deframer()
    assert d.feed(wire) == [frame]


@given(st.lists(frames, max_size=8), st.integers(1, 40))
def test_frames_survive_any_chunking(frame_list: list[Frame], chunk: int) -> None:
    wire = b"".join(encode_frame(f) for f in frame_list)
    d = Deframer()
    out: list[Frame] = []
    for i in range(0, len(wire), chunk):
        out += d.feed(wire[i : i + chunk])
    assert out == frame_list


@given(st.binary(max_size=4000))
@settings(max_examples=300)
def test_arbitrary_bytes_never_crash_and_never_yield_bad_crc(data: bytes) -> None:
    d = Deframer()
    for frame in d.feed(data):
        raw = (
            bytes([(frame.version << 4) | frame.msg_type, frame.robot_id])
            + struct.pack("<HH", frame.seq, frame.ack)
            + frame.payload
        )
        # The frame must really be on the wire with a CRC that checks.
        enc = cobs_encode(raw + _crc_reference(raw).to_bytes(2, "big"))
        assert enc in data
        assert len(frame.payload) <= MAX_PAYLOAD


@given(st.lists(frames, min_size=1, max_size=6), st.data())
def test_bit_flips_are_counted_and_dropped(frame_list: list[Frame], data: st.DataObject) -> None:
    wire = bytearray(b"".join(encode_frame(f) for f in frame_list))
    pos = data.draw(st.integers(0, len(wire) - 1))
    bit = data.draw(st.integers(0, 7))
    wire[pos] ^= 1 << bit
    d = Deframer()
    out = d.feed(bytes(wire)) + d.feed(b"\x00")
    # A single bit flip corrupts at most two frames (it may merge two by killing a delimiter);
    # whatever comes out must be one of the sent frames, unchanged.
    for f in out:
        assert f in frame_list
    assert len(out) >= len(frame_list) - 2
    if len(out) < len(frame_list):
        assert d.stats.rejected >= 1


def test_every_single_bit_flip_of_a_stream_is_caught() -> None:
    sent = [Frame(k % 9, 1 + k, k * 7, k * 3, bytes(k)) for k in range(8)]
    wire = b"".join(encode_frame(f) for f in sent)
    for pos in range(len(wire)):
        for bit in range(8):
            bad = bytearray(wire)
            bad[pos] ^= 1 << bit
            d = Deframer()
            out = d.feed(bytes(bad)) + d.feed(b"\x00")
            assert all(f in sent for f in out), (pos, bit)
            assert len(out) >= len(sent) - 2


def test_oversized_and_truncated_frames_are_counted() -> None:
    good = encode_frame(Frame(3, 1, 5, 6, b"abc"))
    d = Deframer()
    assert d.feed(b"\x55" * (MAX_FRAME_WIRE + 50) + b"\x00" + good) == [Frame(3, 1, 5, 6, b"abc")]
    assert d.stats.oversized == 1
    assert d.feed(good[:5] + b"\x00") == []
    assert d.stats.rejected == 2
    assert d.feed(good) == [Frame(3, 1, 5, 6, b"abc")]


def test_wrong_version_is_counted_and_dropped() -> None:
    d = Deframer()
    assert d.feed(encode_frame(Frame(3, 1, 0, 0, b"", version=2))) == []
    assert d.stats.bad_version == 1


def test_seq_newer_wraps() -> None:
    assert seq_newer(1, 0) and not seq_newer(0, 1)
    assert seq_newer(0, 0xFFFF) and seq_newer(5, 0xFFF0)
    assert not seq_newer(7, 7)


@given(
    st.integers(0, 2**32 - 1),
    st.integers(0, 0xFFFF),
    st.integers(0, 0xFFFF),
    st.text(max_size=32).filter(lambda s: len(s.encode()) <= 32),
)
def test_hello_round_trip(inc: int, first: int, caps: int, name: str) -> None:
    msg = Hello(inc, first, caps, name)
    assert decode_hello(encode_hello(msg)) == msg
    assert len(encode_frame(Frame(0, 1, 0, 0, encode_hello(msg)))) <= MAX_FRAME_WIRE


@given(st.integers(-(2**63), 2**63 - 1), finite32, finite32, finite32, finite32, st.integers(0, 255))
def test_pose_round_trip(stamp: int, x: float, y: float, z: float, h: float, q: int) -> None:
    msg = PoseUpdate(stamp, x, y, z, h, q)
    assert decode_pose(encode_pose(msg)) == msg


@given(finite32, finite32, finite32, finite32)
def test_segment_round_trip(a: float, b: float, c: float, e: float) -> None:
    msg = Segment(a, b, c, e)
    assert decode_segment(encode_segment(msg)) == msg


@given(st.integers(0, 2**32 - 1), finite32, finite32, st.one_of(finite32, st.just(math.nan)))
def test_nav_order_round_trip(oid: int, x: float, y: float, z: float) -> None:
    out = decode_nav_order(encode_nav_order(NavOrder(oid, x, y, z)))
    assert (out.order_id, out.x, out.y) == (oid, x, y)
    assert (math.isnan(out.z) and math.isnan(z)) or out.z == z
    assert math.isnan(out.heading_rad)


@given(st.sampled_from(list(GoodbyeReason)), st.text(max_size=10))
def test_goodbye_round_trip(reason: GoodbyeReason, text: str) -> None:
    out = decode_goodbye(encode_goodbye(Goodbye(reason, text)))
    assert out.reason is reason
    assert out.text == text.encode()[:32].decode("utf-8", errors="ignore")


def test_long_names_are_cut_on_character_boundaries() -> None:
    name = "ü" * 40
    out = decode_hello(encode_hello(Hello(1, 2, 3, name)))
    assert out.name == "ü" * 16


def test_pose_frame_overhead_is_under_30_percent() -> None:
    payload = encode_pose(PoseUpdate(1_700_000_000_000_000, _f32(1.5), 2.0, 0.5, 0.1, 200))
    wire = encode_frame(Frame(3, 7, 1000, 2000, payload))
    overhead = 1 - len(payload) / len(wire)
    assert len(wire) <= 36
    assert overhead <= 0.30, (len(payload), len(wire))
