"""Wire framing of the pose-reporting protocol: header, CRC-16, COBS, zero delimiter.

A frame on the wire is::

    COBS( header(6) | payload(0..MAX_PAYLOAD) | crc16(2, big endian) ) | 0x00

Header (little endian)::

    byte 0     version (high nibble) | message type (low nibble)
    byte 1     robot id (1..254; 0 and 255 are reserved)
    bytes 2-3  seq  (u16): reliable sequence number, or the pose counter for POSE frames
    bytes 4-5  ack  (u16): cumulative acknowledgement of the peer's reliable stream

The CRC is the CCITT polynomial 0x1021 with init 0xFFFF, no reflection and a final xor of
0xFFFF (the catalogue name is CRC-16/GENIBUS; check value 0xD64E for ``b"123456789"``) over
header and payload. The final xor matters with COBS: without it (CRC-16/CCITT-FALSE), a
frame's own CRC bytes followed by a zero check as valid, so a delimiter flipped from 0x00
to 0x01 could turn a good frame into a wrong one that passes; the property tests found
exactly that. It is computed with the standard library's :func:`binascii.crc_hqx` (the
same polynomial, in C).
COBS (consistent overhead byte stuffing) is implemented here; it removes every zero byte
from the frame so a single zero marks the end of each frame and a receiver resynchronises
on the next zero after any corruption.

:class:`Deframer` is the receive side: it accepts arbitrary byte chunks and returns only
frames whose length, CRC and version are right, counting every rejection by reason. It
never raises on input bytes.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, field

from flightkit.errors import ProtocolError

__all__ = [
    "CRC_SIZE",
    "HEADER_SIZE",
    "MAX_FRAME_WIRE",
    "MAX_PAYLOAD",
    "PROTOCOL_VERSION",
    "DeframerStats",
    "Deframer",
    "Frame",
    "cobs_decode",
    "cobs_encode",
    "crc16_ccitt",
    "encode_frame",
    "seq_newer",
]

PROTOCOL_VERSION = 1
HEADER_SIZE = 6
CRC_SIZE = 2
MAX_PAYLOAD = 64
_MAX_RAW = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE
# COBS adds one byte per 254 data bytes (plus one); the delimiter adds one more.
MAX_FRAME_WIRE = _MAX_RAW + _MAX_RAW // 254 + 2

_HEADER = struct.Struct("<BBHH")


def crc16_ccitt(data: bytes) -> int:
    """CRC-16/GENIBUS of ``data``: CCITT poly 0x1021, init 0xFFFF, final xor 0xFFFF."""
    return binascii.crc_hqx(data, 0xFFFF) ^ 0xFFFF


def seq_newer(a: int, b: int) -> bool:
    """True when u16 sequence number ``a`` comes after ``b`` (RFC 1982 serial arithmetic)."""
    d = (a - b) & 0xFFFF
    return 0 < d < 0x8000


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data``; the result contains no zero byte (delimiter not included)."""
    out = bytearray()
    for chunk in data.split(b"\x00"):
        # Each zero-free run becomes blocks of at most 254 bytes with a length code in front.
        while len(chunk) >= 254:
            out.append(0xFF)
            out += chunk[:254]
            chunk = chunk[254:]
        out.append(len(chunk) + 1)
        out += chunk
    # The split yields one run more than there are zeros; a trailing 0xFF block already
    # implies "no zero follows", which the decoder handles; nothing else to strip.
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Decode a COBS block (without delimiter).

    Raises:
        ProtocolError: when the block is not valid COBS (a zero byte, or a code running past
            the end).
    """
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError(
                f"zero byte inside a COBS block at offset {i}; split frames at zero bytes before decoding",
            )
        end = i + code
        if end > n:
            raise ProtocolError(f"COBS code {code} at offset {i} runs past the end ({n} bytes); the frame is truncated")
        block = data[i + 1 : end]
        if 0 in block:
            raise ProtocolError(
                f"zero byte inside the COBS block at offset {i}; split frames at zero bytes before decoding",
            )
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame (CRC already verified).

    Attributes:
        msg_type: message type number (see :class:`~estimation.report.messages.MsgType`).
        robot_id: the robot this frame is from (robot to server) or for (server to robot).
        seq: reliable sequence number, or the pose counter for pose updates.
        ack: cumulative acknowledgement of the peer's reliable stream.
        payload: message body, at most :data:`MAX_PAYLOAD` bytes.
        version: protocol version of the frame.
    """

    msg_type: int
    robot_id: int
    seq: int
    ack: int
    payload: bytes = b""
    version: int = PROTOCOL_VERSION


def encode_frame(frame: Frame) -> bytes:
    """The wire bytes of ``frame``, delimiter included.

    Raises:
        ProtocolError: when a field is out of range or the payload is too long.
    """
    if len(frame.payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(frame.payload)} bytes exceeds {MAX_PAYLOAD}; shorten it")
    if not 0 <= frame.msg_type <= 15 or not 0 <= frame.version <= 15:
        raise ProtocolError(
            f"msg_type {frame.msg_type} / version {frame.version} must fit in 4 bits (0-15); use a MsgType",
        )
    raw = (
        _HEADER.pack((frame.version << 4) | frame.msg_type, frame.robot_id, frame.seq, frame.ack)
        + frame.payload
    )
    raw += crc16_ccitt(raw).to_bytes(2, "big")
    return cobs_encode(raw) + b"\x00"


@dataclass(slots=True)
class DeframerStats:
    """Counters of a :class:`Deframer` (all rejected frames are counted, never delivered)."""

    frames_ok: int = 0
    bytes_in: int = 0
    crc_errors: int = 0
    cobs_errors: int = 0
    too_short: int = 0
    oversized: int = 0
    bad_version: int = 0
    empty: int = 0

    @property
    def rejected(self) -> int:
        return self.crc_errors + self.cobs_errors + self.too_short + self.oversized + self.bad_version


@dataclass(slots=True)
class Deframer:
    """Split a byte stream into verified frames; survives any input.

    Feed it whatever the port returned; it returns the good frames completed by those bytes.
    Frames longer than :data:`MAX_FRAME_WIRE` are discarded up to the next delimiter.
    """

    stats: DeframerStats = field(default_factory=DeframerStats)
    _buf: bytearray = field(default_factory=bytearray)
    _overflow: bool = False

    def reset(self) -> None:
        """Forget a partial frame (e.g. after the port was reopened)."""
        self._buf.clear()
        self._overflow = False

    def feed(self, data: bytes) -> list[Frame]:
        """Consume ``data``; returns the frames it completed (possibly none)."""
        self.stats.bytes_in += len(data)
        frames: list[Frame] = []
        start = 0
        while True:
            z = data.find(b"\x00", start)
            if z < 0:
                self._append(data[start:])
                return frames
            self._append(data[start:z])
            start = z + 1
            if self._overflow:
                self.stats.oversized += 1
            elif not self._buf:
                self.stats.empty += 1  # back-to-back delimiters are legal padding
            else:
                frame = self._decode(bytes(self._buf))
                if frame is not None:
                    frames.append(frame)
            self._buf.clear()
            self._overflow = False

    def _append(self, chunk: bytes) -> None:
        if self._overflow or not chunk:
            return
        if len(self._buf) + len(chunk) > MAX_FRAME_WIRE:
            self._overflow = True
            self._buf.clear()
        else:
            self._buf += chunk

    def _decode(self, block: bytes) -> Frame | None:
        try:
            raw = cobs_decode(block)
        except ProtocolError:
            self.stats.cobs_errors += 1
            return None
        if len(raw) < HEADER_SIZE + CRC_SIZE:
            self.stats.too_short += 1
            return None
        if len(raw) > _MAX_RAW:
            self.stats.oversized += 1
            return None
        body, crc = raw[:-CRC_SIZE], int.from_bytes(raw[-CRC_SIZE:], "big")
        if crc16_ccitt(body) != crc:
            self.stats.crc_errors += 1
            return None
        vt, robot_id, seq, ack = _HEADER.unpack_from(body)
        version = vt >> 4
        if version != PROTOCOL_VERSION:
            self.stats.bad_version += 1
            return None
        self.stats.frames_ok += 1
        return Frame(vt & 0x0F, robot_id, seq, ack, body[HEADER_SIZE:], version)
