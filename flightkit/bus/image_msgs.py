"""The image messages: ``sensor_msgs/Image``, ``sensor_msgs/CompressedImage`` and
``sensor_msgs/CameraInfo``, with hand-written CDR codecs (what they share:
:mod:`flightkit.bus.msg_base`).

Images are the hot path: :meth:`Image.encode` writes the few header fields with
:mod:`struct` and copies the pixel buffer once into a caller-owned, reusable ``bytearray``
(no per-pixel Python objects, no fresh allocation per frame); :meth:`Image.decode` returns
the pixels as a numpy view onto the payload.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from flightkit.bus.cdr import CdrReader, CdrWriter
from flightkit.bus.msg_base import Header, decode_payload, schema_text
from flightkit.errors import BusError

__all__ = [
    "CameraInfo",
    "CompressedImage",
    "Image",
    "image_encoding_layout",
]

_SIMPLE_ENCODINGS: dict[str, tuple[str, int]] = {
    "rgb8": ("u1", 3), "bgr8": ("u1", 3), "rgba8": ("u1", 4), "bgra8": ("u1", 4),
    "rgb16": ("u2", 3), "bgr16": ("u2", 3), "rgba16": ("u2", 4), "bgra16": ("u2", 4),
    "mono8": ("u1", 1), "mono16": ("u2", 1),
    "bayer_rggb8": ("u1", 1), "bayer_bggr8": ("u1", 1), "bayer_gbrg8": ("u1", 1), "bayer_grbg8": ("u1", 1),
    "bayer_rggb16": ("u2", 1), "bayer_bggr16": ("u2", 1), "bayer_gbrg16": ("u2", 1), "bayer_grbg16": ("u2", 1),
    "yuv422": ("u1", 2), "uyvy": ("u1", 2), "yuyv": ("u1", 2), "yuv422_yuy2": ("u1", 2),
}
_CV_ENCODING = re.compile(r"^(8|16|32|64)(U|S|F)C([1-4])$")


def image_encoding_layout(encoding: str) -> tuple[np.dtype[Any], int]:
    """(little-endian element dtype, channels) of a ROS image encoding such as ``rgb8`` or ``32FC1``.

    Raises:
        BusError: for an encoding this module does not know.
    """
    if encoding in _SIMPLE_ENCODINGS:
        kind, ch = _SIMPLE_ENCODINGS[encoding]
        return np.dtype("<" + kind), ch
    m = _CV_ENCODING.match(encoding)
    if m:
        bits, sign, ch = int(m.group(1)), m.group(2), int(m.group(3))
        kind = {"U": "u", "S": "i", "F": "f"}[sign]
        return np.dtype(f"<{kind}{bits // 8}"), ch
    raise BusError(
        f"image encoding {encoding!r} is not supported; use rgb8, bgr8, mono8, mono16, 16UC1, 32FC1 or similar"
    )


@dataclass(frozen=True, slots=True)
class Image:
    """sensor_msgs/Image.

    Attributes:
        data: the pixel bytes as a numpy array, either flat ``uint8`` (as decoded: a view
            onto the payload) or shaped (H, W[, C]) as given to :meth:`from_array`.
            Use :meth:`array` for the (H, W[, C]) view in the right dtype.
        step: bytes per row.
    """

    TYPE: ClassVar[str] = "sensor_msgs/msg/Image"
    SCHEMA: ClassVar[str] = schema_text(TYPE)

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: npt.NDArray[Any] = field(repr=False)

    @staticmethod
    def from_array(header: Header, array: npt.NDArray[Any], encoding: str) -> Image:
        """Wrap an (H, W[, C]) array without copying it (the copy happens once, in :meth:`encode`).

        Raises:
            BusError: when the array's dtype or channels do not match ``encoding``.
        """
        dtype, ch = image_encoding_layout(encoding)
        arr = np.asarray(array)
        shape_ok = (arr.ndim == 2 and ch == 1) or (arr.ndim == 3 and arr.shape[2] == ch)
        if not shape_ok or arr.dtype.kind != dtype.kind or arr.dtype.itemsize != dtype.itemsize:
            raise BusError(
                f"array of shape {arr.shape} and dtype {arr.dtype} does not fit image encoding {encoding!r} "
                f"({ch} channel(s) of {dtype}); convert the array or pick the matching encoding"
            )
        h, w = arr.shape[:2]
        return Image(header, h, w, encoding, 0, w * ch * dtype.itemsize, arr)

    def array(self) -> npt.NDArray[Any]:
        """The pixels as an (H, W) or (H, W, C) array; a view, no copy, when rows are unpadded."""
        dtype, ch = image_encoding_layout(self.encoding)
        if self.data.ndim > 1:
            return self.data
        if self.is_bigendian:
            dtype = dtype.newbyteorder(">")
        row_bytes = self.width * ch * dtype.itemsize
        need = self.step * (self.height - 1) + row_bytes if self.height else 0
        flat = self.data.view(np.uint8).reshape(-1)
        if flat.size < need or self.step < row_bytes:
            raise BusError(
                f"image {self.width}x{self.height} {self.encoding} with step {self.step} needs {need} bytes, "
                f"has {flat.size}; the publisher sent an inconsistent image"
            )
        if self.step == row_bytes:
            pixels = flat[: row_bytes * self.height].view(dtype)
        else:
            pixels = flat[: self.step * self.height].reshape(self.height, self.step)[:, :row_bytes]
            pixels = np.ascontiguousarray(pixels).view(dtype)
        shape = (self.height, self.width) if ch == 1 else (self.height, self.width, ch)
        return pixels.reshape(shape)

    def encode(self, out: bytearray | None = None) -> bytearray:
        """The CDR payload, written into ``out`` (resized to fit, reused without reallocation
        when the size is unchanged) or a new bytearray. One copy of the pixels, no per-pixel work."""
        head = CdrWriter()
        self.header.write(head)
        head.u32(self.height)
        head.u32(self.width)
        head.string(self.encoding)
        head.u8(self.is_bigendian)
        head.u32(self.step)
        src = self.data
        nbytes = int(src.nbytes)
        head.u32(nbytes)
        return _assemble(head.buf, src, out)

    @staticmethod
    def read(r: CdrReader) -> Image:
        header = Header.read(r)
        height = r.u32()
        width = r.u32()
        encoding = r.string()
        is_bigendian = r.u8()
        step = r.u32()
        data = r.u8_seq()
        return Image(header, height, width, encoding, is_bigendian, step, data)

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Image:
        """Decode; ``data`` is a view onto ``payload`` (keep the payload alive and unchanged)."""
        return decode_payload(cls.TYPE, cls.read, payload)


def _assemble(prefix: bytearray, src: npt.NDArray[Any], out: bytearray | None) -> bytearray:
    """prefix + the bytes of ``src`` (C order, little-endian) into ``out``."""
    p = len(prefix)
    total = p + int(src.nbytes)
    if out is None:
        out = bytearray(total)
    elif len(out) != total:
        if len(out) > total:
            del out[total:]
        else:
            out.extend(bytes(total - len(out)))
    out[:p] = prefix
    if src.size:
        le = src.dtype.newbyteorder("<") if src.dtype.itemsize > 1 else src.dtype
        dst = np.frombuffer(out, dtype=le, count=src.size, offset=p).reshape(src.shape)
        np.copyto(dst, src, casting="equiv")
        del dst
    return out


@dataclass(frozen=True, slots=True)
class CompressedImage:
    """sensor_msgs/CompressedImage; ``format`` is e.g. ``"jpeg"`` or ``"png"``."""

    TYPE: ClassVar[str] = "sensor_msgs/msg/CompressedImage"
    SCHEMA: ClassVar[str] = schema_text(TYPE)

    header: Header
    format: str
    data: npt.NDArray[np.uint8] | bytes = field(repr=False)

    def encode(self, out: bytearray | None = None) -> bytearray:
        head = CdrWriter()
        self.header.write(head)
        head.string(self.format)
        src = np.frombuffer(self.data, np.uint8) if isinstance(self.data, bytes | bytearray) else self.data
        head.u32(int(src.nbytes))
        return _assemble(head.buf, src.view(np.uint8).reshape(-1), out)

    @staticmethod
    def read(r: CdrReader) -> CompressedImage:
        header = Header.read(r)
        fmt = r.string()
        return CompressedImage(header, fmt, r.u8_seq())

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> CompressedImage:
        return decode_payload(cls.TYPE, cls.read, payload)


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """sensor_msgs/CameraInfo (pinhole intrinsics, distortion, rectification, projection).

    Attributes:
        k: 3x3 intrinsics row-major; r: 3x3 rectification; p: 3x4 projection.
        roi: (x_offset, y_offset, height, width, do_rectify).
    """

    TYPE: ClassVar[str] = "sensor_msgs/msg/CameraInfo"
    SCHEMA: ClassVar[str] = schema_text(TYPE)

    header: Header
    height: int
    width: int
    distortion_model: str = "plumb_bob"
    d: tuple[float, ...] = ()
    k: tuple[float, ...] = (0.0,) * 9
    r: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    p: tuple[float, ...] = (0.0,) * 12
    binning_x: int = 0
    binning_y: int = 0
    roi: tuple[int, int, int, int, bool] = (0, 0, 0, 0, False)

    def __post_init__(self) -> None:
        for name, n in (("k", 9), ("r", 9), ("p", 12)):
            if len(getattr(self, name)) != n:
                raise BusError(f"CameraInfo.{name} needs {n} values, got {len(getattr(self, name))}")

    @staticmethod
    def from_intrinsics(
        header: Header, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
        d: tuple[float, ...] = (), distortion_model: str = "plumb_bob", baseline_tx: float = 0.0,
    ) -> CameraInfo:
        """A pinhole camera; ``baseline_tx`` is P[0,3] = -fx * baseline for the right camera of a stereo pair."""
        d = tuple(d) if d else (0.0,) * 5
        k = (fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0)
        p = (fx, 0.0, cx, baseline_tx, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0)
        return CameraInfo(header, height, width, distortion_model, d, k, p=p)

    def write(self, w: CdrWriter) -> None:
        self.header.write(w)
        w.u32(self.height)
        w.u32(self.width)
        w.string(self.distortion_model)
        w.f64_seq(self.d)
        w.f64s(tuple(self.k) + tuple(self.r) + tuple(self.p))
        w.u32(self.binning_x)
        w.u32(self.binning_y)
        x, y, h, wd, rect = self.roi
        w.u32(x)
        w.u32(y)
        w.u32(h)
        w.u32(wd)
        w.bool(rect)

    @staticmethod
    def read(r: CdrReader) -> CameraInfo:
        header = Header.read(r)
        height = r.u32()
        width = r.u32()
        model = r.string()
        d = r.f64_seq()
        krp = r.f64s(30)
        bx = r.u32()
        by = r.u32()
        roi = (r.u32(), r.u32(), r.u32(), r.u32(), r.bool())
        return CameraInfo(header, height, width, model, d, krp[:9], krp[9:18], krp[18:], bx, by, roi)

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> CameraInfo:
        return decode_payload(cls.TYPE, cls.read, payload)

