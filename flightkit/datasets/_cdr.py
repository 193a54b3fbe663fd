"""Minimal ROS 2 CDR (XCDR1, little endian) decoding of the few messages recordings hold.

Decodes ``sensor_msgs/msg/Image``, ``CompressedImage``, ``CameraInfo`` and
``geometry_msgs/msg/PoseStamped`` straight from the payload; image data is returned as a
zero-copy view of the buffer. (``flightkit.bus`` owns the general codecs; this private
decoder keeps the dataset readers independent of it.)
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from flightkit.errors import DatasetError

__all__ = [
    "CameraInfoMsg",
    "ImageMsg",
    "PoseMsg",
    "decode_camera_info",
    "decode_compressed",
    "decode_image",
    "decode_pose",
]


class _Reader:
    __slots__ = ("buf", "pos")

    def __init__(self, data: bytes | memoryview) -> None:
        buf = memoryview(data)
        if len(buf) < 4:
            raise DatasetError("CDR payload shorter than its 4-byte header")
        if buf[1] not in (0x01, 0x03):  # CDR_LE / PL_CDR_LE
            raise DatasetError(f"CDR payload is not little endian (representation id {bytes(buf[:2]).hex()})")
        self.buf = buf[4:]
        self.pos = 0

    def _align(self, n: int) -> None:
        self.pos += (-self.pos) % n

    def u8(self) -> int:
        v = self.buf[self.pos]
        self.pos += 1
        return int(v)

    def u32(self) -> int:
        self._align(4)
        (v,) = struct.unpack_from("<I", self.buf, self.pos)
        self.pos += 4
        return int(v)

    def i32(self) -> int:
        self._align(4)
        (v,) = struct.unpack_from("<i", self.buf, self.pos)
        self.pos += 4
        return int(v)

    def f64s(self, n: int) -> tuple[float, ...]:
        self._align(8)
        v = struct.unpack_from(f"<{n}d", self.buf, self.pos)
        self.pos += 8 * n
        return tuple(float(x) for x in v)

    def string(self) -> str:
        n = self.u32()
        raw = bytes(self.buf[self.pos : self.pos + n])
        self.pos += n
        return raw.rstrip(b"\x00").decode("utf-8", errors="replace")

    def octets(self) -> memoryview:
        n = self.u32()
        out = self.buf[self.pos : self.pos + n]
        if len(out) != n:
            raise DatasetError(f"CDR sequence of {n} bytes runs past the end of the message")
        self.pos += n
        return out

    def header(self) -> tuple[int, str]:
        sec = self.i32()
        nsec = self.u32()
        return sec * 1_000_000_000 + nsec, self.string()


@dataclass(frozen=True, slots=True, eq=False)
class ImageMsg:
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str
    step: int
    data: memoryview


@dataclass(frozen=True, slots=True, eq=False)
class CameraInfoMsg:
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    distortion_model: str
    d: tuple[float, ...]
    k: tuple[float, ...]
    p: tuple[float, ...]


@dataclass(frozen=True, slots=True, eq=False)
class PoseMsg:
    stamp_ns: int
    frame_id: str
    position: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]


def decode_image(data: bytes | memoryview) -> ImageMsg:
    r = _Reader(data)
    stamp, frame_id = r.header()
    height, width = r.u32(), r.u32()
    encoding = r.string()
    r.u8()  # is_bigendian
    step = r.u32()
    return ImageMsg(stamp, frame_id, height, width, encoding, step, r.octets())


def decode_compressed(data: bytes | memoryview) -> tuple[int, str, memoryview]:
    """``(stamp_ns, format, data)`` of a CompressedImage."""
    r = _Reader(data)
    stamp, _ = r.header()
    fmt = r.string()
    return stamp, fmt, r.octets()


def decode_camera_info(data: bytes | memoryview) -> CameraInfoMsg:
    r = _Reader(data)
    stamp, frame_id = r.header()
    height, width = r.u32(), r.u32()
    model = r.string()
    n = r.u32()
    d = r.f64s(n) if n else ()
    k = r.f64s(9)
    r.f64s(9)  # R
    p = r.f64s(12)
    return CameraInfoMsg(stamp, frame_id, height, width, model, d, k, p)


def decode_pose(data: bytes | memoryview) -> PoseMsg:
    r = _Reader(data)
    stamp, frame_id = r.header()
    px, py, pz, qx, qy, qz, qw = r.f64s(7)
    return PoseMsg(stamp, frame_id, (px, py, pz), (qx, qy, qz, qw))


_DTYPES: dict[str, tuple[np.dtype[np.generic], int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgra8": (np.dtype(np.uint8), 4),
    "rgba8": (np.dtype(np.uint8), 4),
    "mono16": (np.dtype("<u2"), 1),
    "16UC1": (np.dtype("<u2"), 1),
    "32FC1": (np.dtype("<f4"), 1),
}


def image_array(msg: ImageMsg) -> npt.NDArray[np.generic]:
    """The pixels as an (H, W) or (H, W, C) array (a copy; row padding removed)."""
    if msg.encoding not in _DTYPES:
        raise DatasetError(
            f"image encoding {msg.encoding!r} is not supported; use one of {', '.join(_DTYPES)}"
        )
    dtype, channels = _DTYPES[msg.encoding]
    row = msg.width * channels * dtype.itemsize
    if msg.step < row or len(msg.data) < msg.step * msg.height:
        raise DatasetError(
            f"image {msg.width}x{msg.height} {msg.encoding} has step {msg.step} and {len(msg.data)} bytes; it is truncated"
        )
    raw = np.frombuffer(msg.data, dtype=np.uint8, count=msg.step * msg.height).reshape(msg.height, msg.step)
    pixels = raw[:, :row].copy().view(dtype)
    return (
        pixels.reshape(msg.height, msg.width, channels)
        if channels > 1
        else pixels.reshape(msg.height, msg.width)
    )
