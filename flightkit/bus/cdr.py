"""ROS 2 CDR (XCDR1, little-endian) primitives, written by hand.

A ROS 2 payload is a 4-byte encapsulation header (``00 01 00 00`` = CDR little-endian)
followed by the message fields in declaration order. Every primitive is aligned to its own
size (8 for ``float64``), counted from the end of the encapsulation header. Strings are a
``uint32`` length that includes the terminating NUL, the bytes and the NUL; sequences are a
``uint32`` count followed by the elements; fixed arrays have no count.

:class:`CdrWriter` appends to a ``bytearray``; :class:`CdrReader` reads from any buffer
without copying (``uint8[]`` and ``float64[]`` come back as numpy views onto the payload).
The message types built from these live in :mod:`flightkit.bus.pose_msgs` and
:mod:`flightkit.bus.image_msgs` (the shared parts in :mod:`flightkit.bus.msg_base`).
"""

from __future__ import annotations

import struct
from typing import Final

import numpy as np
import numpy.typing as npt

from flightkit.errors import BusError

__all__ = ["CDR_LE_HEADER", "CdrReader", "CdrWriter"]

CDR_LE_HEADER: Final = b"\x00\x01\x00\x00"
"""Encapsulation header of a little-endian plain CDR payload."""

_U8 = struct.Struct("<B")
_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")
_F64 = struct.Struct("<d")
_ZEROS = bytes(8)


class CdrWriter:
    """Append CDR fields to a growing ``bytearray`` (starts with the encapsulation header).

    Args:
        buf: a buffer to reuse; it is cleared first. None allocates a new one.
    """

    __slots__ = ("buf",)

    def __init__(self, buf: bytearray | None = None) -> None:
        if buf is None:
            buf = bytearray()
        else:
            del buf[:]
        buf += CDR_LE_HEADER
        self.buf = buf

    @property
    def offset(self) -> int:
        """Current position counted from the end of the encapsulation header."""
        return len(self.buf) - 4

    def align(self, size: int) -> None:
        pad = (-(len(self.buf) - 4)) % size
        if pad:
            self.buf += _ZEROS[:pad]

    def u8(self, value: int) -> None:
        self.buf += _U8.pack(value)

    def bool(self, value: bool) -> None:
        self.buf += b"\x01" if value else b"\x00"

    def u32(self, value: int) -> None:
        self.align(4)
        self.buf += _U32.pack(value)

    def i32(self, value: int) -> None:
        self.align(4)
        self.buf += _I32.pack(value)

    def f64(self, value: float) -> None:
        self.align(8)
        self.buf += _F64.pack(value)

    def f64s(self, values: tuple[float, ...] | list[float] | npt.NDArray[np.float64]) -> None:
        """A fixed-size ``float64[N]`` array (no count)."""
        self.align(8)
        self.buf += np.ascontiguousarray(values, dtype="<f8").tobytes()

    def f64_seq(self, values: tuple[float, ...] | list[float] | npt.NDArray[np.float64]) -> None:
        """A ``float64[]`` sequence (count, then the values)."""
        arr = np.ascontiguousarray(values, dtype="<f8").reshape(-1)
        self.u32(arr.size)
        if arr.size:
            self.align(8)
            self.buf += arr.tobytes()

    def string(self, value: str) -> None:
        raw = value.encode("utf-8")
        self.u32(len(raw) + 1)
        self.buf += raw
        self.buf += b"\x00"

    def u8_seq_header(self, length: int) -> None:
        """The count of a ``uint8[]`` sequence; the caller appends ``length`` bytes next."""
        self.u32(length)

    def raw(self, data: bytes | bytearray | memoryview) -> None:
        self.buf += data


class CdrReader:
    """Read CDR fields from a payload (bytes, bytearray or memoryview) without copying.

    Raises:
        BusError: on a payload that is not little-endian CDR, or that ends early.
    """

    __slots__ = ("_data", "_end", "_pos", "msgtype")

    def __init__(self, data: bytes | bytearray | memoryview, msgtype: str = "message") -> None:
        mv = memoryview(data)
        if mv.format != "B" or mv.ndim != 1:
            mv = mv.cast("B")
        self.msgtype = msgtype
        if len(mv) < 4:
            raise BusError(
                f"{msgtype} payload has {len(mv)} bytes, fewer than the 4-byte CDR header; "
                "the publisher is not sending ROS 2 CDR"
            )
        if bytes(mv[:2]) != CDR_LE_HEADER[:2]:
            raise BusError(
                f"{msgtype} payload starts with {bytes(mv[:4]).hex()}, not the little-endian CDR header 00010000; "
                "only little-endian plain CDR is supported"
            )
        self._data = mv
        self._pos = 4
        self._end = len(mv)

    @property
    def remaining(self) -> int:
        return self._end - self._pos

    def _need(self, n: int) -> int:
        pos = self._pos
        if pos + n > self._end:
            raise BusError(
                f"{self.msgtype} payload ends at byte {self._end} but a field needs bytes {pos}..{pos + n}; "
                "publisher and subscriber disagree on the message type"
            )
        self._pos = pos + n
        return pos

    def align(self, size: int) -> None:
        self._pos += (-(self._pos - 4)) % size

    def u8(self) -> int:
        return int(self._data[self._need(1)])

    def bool(self) -> bool:
        return self._data[self._need(1)] != 0

    def u32(self) -> int:
        self.align(4)
        return int(_U32.unpack_from(self._data, self._need(4))[0])

    def i32(self) -> int:
        self.align(4)
        return int(_I32.unpack_from(self._data, self._need(4))[0])

    def f64(self) -> float:
        self.align(8)
        return float(_F64.unpack_from(self._data, self._need(8))[0])

    def f64s(self, count: int) -> tuple[float, ...]:
        """A fixed-size ``float64[count]`` array as a tuple."""
        self.align(8)
        return struct.unpack_from(f"<{count}d", self._data, self._need(8 * count))

    def f64_seq(self) -> tuple[float, ...]:
        count = self.u32()
        if count == 0:
            return ()
        return self.f64s(count)

    def string(self) -> str:
        n = self.u32()
        if n == 0:  # some writers send an empty string without the NUL
            return ""
        start = self._need(n)
        raw = self._data[start : start + n - 1]
        try:
            return str(raw, "utf-8")
        except UnicodeDecodeError as exc:
            raise BusError(f"{self.msgtype} has a string that is not UTF-8 at byte {start}") from exc

    def u8_seq(self) -> npt.NDArray[np.uint8]:
        """A ``uint8[]`` sequence as a numpy view onto the payload (no copy)."""
        n = self.u32()
        start = self._need(n)
        return np.frombuffer(self._data, dtype=np.uint8, count=n, offset=start)
