"""ROS 2 message types flightkit puts on the bus, with hand-written CDR codecs.

Each message class carries ``TYPE`` (the ROS 2 name, ``"geometry_msgs/msg/PoseStamped"``)
and ``SCHEMA`` (the ``ros2msg`` text MCAP wants: the message definition followed by every
nested definition after a line of 80 ``=`` and ``MSG: pkg/Type``), so recordings open in
Foxglove, ``rosbags`` and ROS 2 tools. ``encode()`` returns the CDR payload (4-byte
encapsulation header included); ``decode(payload)`` reads one.

Images are the hot path: :meth:`Image.encode` writes the few header fields with
:mod:`struct` and copies the pixel buffer once into a caller-owned, reusable ``bytearray``
(no per-pixel Python objects, no fresh allocation per frame); :meth:`Image.decode` returns
the pixels as a numpy view onto the payload.

Types: ``builtin_interfaces/Time``, ``std_msgs/Header``, ``geometry_msgs/PoseStamped``,
``sensor_msgs/Image``, ``sensor_msgs/CompressedImage``, ``sensor_msgs/CameraInfo``,
``geometry_msgs/TransformStamped``, ``tf2_msgs/TFMessage``, ``nav_msgs/Odometry``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, Self

import numpy as np
import numpy.typing as npt

from flightkit.bus.cdr import CdrReader, CdrWriter
from flightkit.errors import BusError
from flightkit.frames import Transform, Vec3Tuple

__all__ = [
    "MESSAGE_TYPES",
    "CameraInfo",
    "CompressedImage",
    "Header",
    "Image",
    "Message",
    "Odometry",
    "PoseStamped",
    "TFMessage",
    "TransformStamped",
    "decode_message",
    "image_encoding_layout",
    "schema_text",
]

QuatTuple = tuple[float, float, float, float]

# --------------------------------------------------------------------------- schemas

_DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    "geometry_msgs/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
    ),
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "nav_msgs/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n"
    ),
    "sensor_msgs/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n"
    ),
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
        "sensor_msgs/RegionOfInterest roi\n"
    ),
}

_SEPARATOR = "=" * 80


def _short(msgtype: str) -> str:
    """'geometry_msgs/msg/Pose' -> 'geometry_msgs/Pose'."""
    parts = msgtype.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) == 3 else msgtype


def _nested(short_name: str) -> list[str]:
    out: list[str] = []
    for line in _DEFINITIONS[short_name].splitlines():
        ftype = line.split()[0].split("[")[0]
        if "/" in ftype and ftype not in out:
            out.append(ftype)
    return out


def schema_text(msgtype: str) -> str:
    """The ``ros2msg`` schema text of ``msgtype`` (full or short name) for MCAP channels.

    Raises:
        BusError: for a type flightkit does not define.
    """
    short = _short(msgtype)
    if short not in _DEFINITIONS:
        known = ", ".join(sorted(MESSAGE_TYPES))
        raise BusError(f"no schema for message type {msgtype!r}; known types: {known}")
    deps: list[str] = []

    def visit(name: str) -> None:
        for dep in _nested(name):
            if dep not in deps:
                deps.append(dep)
                visit(dep)

    visit(short)
    parts = [_DEFINITIONS[short]]
    for dep in deps:
        parts.append(f"{_SEPARATOR}\nMSG: {dep}\n{_DEFINITIONS[dep]}")
    return "".join(parts)


# --------------------------------------------------------------------------- building blocks


class Message(Protocol):
    """What every message class offers."""

    TYPE: ClassVar[str]
    SCHEMA: ClassVar[str]

    def encode(self) -> bytearray: ...

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Self: ...


@dataclass(frozen=True, slots=True)
class Header:
    """std_msgs/Header: stamp (ns since the epoch) and the frame the data is expressed in."""

    stamp_ns: int = 0
    frame_id: str = ""

    def write(self, w: CdrWriter) -> None:
        sec, nanosec = divmod(int(self.stamp_ns), 1_000_000_000)
        w.i32(sec)
        w.u32(nanosec)
        w.string(self.frame_id)

    @staticmethod
    def read(r: CdrReader) -> Header:
        sec = r.i32()
        nanosec = r.u32()
        return Header(sec * 1_000_000_000 + nanosec, r.string())


def _vec3(values: Any) -> Vec3Tuple:
    x, y, z = (float(v) for v in values)
    return (x, y, z)


def _quat(values: Any) -> QuatTuple:
    x, y, z, w = (float(v) for v in values)
    return (x, y, z, w)


def _decode(cls: Any, payload: bytes | bytearray | memoryview) -> Any:
    r = CdrReader(payload, cls.TYPE)
    return cls.read(r)


# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True, slots=True)
class PoseStamped:
    """geometry_msgs/PoseStamped: the pose of something in ``header.frame_id``.

    Attributes:
        position_m: (x, y, z) in metres.
        quat_xyzw: orientation quaternion in ROS order x, y, z, w.
    """

    TYPE: ClassVar[str] = "geometry_msgs/msg/PoseStamped"
    SCHEMA: ClassVar[str]

    header: Header
    position_m: Vec3Tuple = (0.0, 0.0, 0.0)
    quat_xyzw: QuatTuple = (0.0, 0.0, 0.0, 1.0)

    @staticmethod
    def from_transform(stamp_ns: int, frame_id: str, T: Transform) -> PoseStamped:
        return PoseStamped(Header(stamp_ns, frame_id), _vec3(T.translation), _quat(T.quat_xyzw))

    def to_transform(self) -> Transform:
        """The pose as ``T_frame_thing`` (raises ValueError on a zero quaternion)."""
        return Transform.from_quat_xyzw(self.position_m, self.quat_xyzw)

    def write(self, w: CdrWriter) -> None:
        self.header.write(w)
        w.f64s(self.position_m + self.quat_xyzw)

    @staticmethod
    def read(r: CdrReader) -> PoseStamped:
        header = Header.read(r)
        v = r.f64s(7)
        return PoseStamped(header, (v[0], v[1], v[2]), (v[3], v[4], v[5], v[6]))

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> PoseStamped:
        return _decode(cls, payload)  # type: ignore[no-any-return]


@dataclass(frozen=True, slots=True)
class TransformStamped:
    """geometry_msgs/TransformStamped: ``T_parent_child`` with parent = ``header.frame_id``."""

    TYPE: ClassVar[str] = "geometry_msgs/msg/TransformStamped"
    SCHEMA: ClassVar[str]

    header: Header
    child_frame_id: str
    translation_m: Vec3Tuple = (0.0, 0.0, 0.0)
    quat_xyzw: QuatTuple = (0.0, 0.0, 0.0, 1.0)

    @staticmethod
    def from_transform(stamp_ns: int, parent: str, child: str, T_parent_child: Transform) -> TransformStamped:
        return TransformStamped(
            Header(stamp_ns, parent), child, _vec3(T_parent_child.translation), _quat(T_parent_child.quat_xyzw)
        )

    def to_transform(self) -> Transform:
        return Transform.from_quat_xyzw(self.translation_m, self.quat_xyzw)

    def write(self, w: CdrWriter) -> None:
        self.header.write(w)
        w.string(self.child_frame_id)
        w.f64s(self.translation_m + self.quat_xyzw)

    @staticmethod
    def read(r: CdrReader) -> TransformStamped:
        header = Header.read(r)
        child = r.string()
        v = r.f64s(7)
        return TransformStamped(header, child, (v[0], v[1], v[2]), (v[3], v[4], v[5], v[6]))

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> TransformStamped:
        return _decode(cls, payload)  # type: ignore[no-any-return]


@dataclass(frozen=True, slots=True)
class TFMessage:
    """tf2_msgs/TFMessage: a batch of transforms."""

    TYPE: ClassVar[str] = "tf2_msgs/msg/TFMessage"
    SCHEMA: ClassVar[str]

    transforms: tuple[TransformStamped, ...] = ()

    def write(self, w: CdrWriter) -> None:
        w.u32(len(self.transforms))
        for t in self.transforms:
            t.write(w)

    @staticmethod
    def read(r: CdrReader) -> TFMessage:
        n = r.u32()
        if n > r.remaining:
            raise BusError(f"{r.msgtype} claims {n} transforms in {r.remaining} bytes; the payload is corrupt")
        return TFMessage(tuple(TransformStamped.read(r) for _ in range(n)))

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> TFMessage:
        return _decode(cls, payload)  # type: ignore[no-any-return]


_ZERO36: tuple[float, ...] = (0.0,) * 36


@dataclass(frozen=True, slots=True)
class Odometry:
    """nav_msgs/Odometry: pose in ``header.frame_id``, twist in ``child_frame_id``.

    Attributes:
        pose_covariance, twist_covariance: row-major 6x6 (x, y, z, rot x, rot y, rot z).
    """

    TYPE: ClassVar[str] = "nav_msgs/msg/Odometry"
    SCHEMA: ClassVar[str]

    header: Header
    child_frame_id: str = ""
    position_m: Vec3Tuple = (0.0, 0.0, 0.0)
    quat_xyzw: QuatTuple = (0.0, 0.0, 0.0, 1.0)
    pose_covariance: tuple[float, ...] = _ZERO36
    linear_m_s: Vec3Tuple = (0.0, 0.0, 0.0)
    angular_rad_s: Vec3Tuple = (0.0, 0.0, 0.0)
    twist_covariance: tuple[float, ...] = _ZERO36

    def __post_init__(self) -> None:
        for name in ("pose_covariance", "twist_covariance"):
            if len(getattr(self, name)) != 36:
                raise BusError(f"Odometry.{name} needs 36 values (6x6 row-major), got {len(getattr(self, name))}")

    def to_transform(self) -> Transform:
        return Transform.from_quat_xyzw(self.position_m, self.quat_xyzw)

    def write(self, w: CdrWriter) -> None:
        self.header.write(w)
        w.string(self.child_frame_id)
        w.f64s(self.position_m + self.quat_xyzw + tuple(self.pose_covariance))
        w.f64s(self.linear_m_s + self.angular_rad_s + tuple(self.twist_covariance))

    @staticmethod
    def read(r: CdrReader) -> Odometry:
        header = Header.read(r)
        child = r.string()
        p = r.f64s(43)
        t = r.f64s(42)
        return Odometry(
            header, child, (p[0], p[1], p[2]), (p[3], p[4], p[5], p[6]), p[7:],
            (t[0], t[1], t[2]), (t[3], t[4], t[5]), t[6:],
        )

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Odometry:
        return _decode(cls, payload)  # type: ignore[no-any-return]


# --------------------------------------------------------------------------- images

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
    SCHEMA: ClassVar[str]

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
        return _decode(cls, payload)  # type: ignore[no-any-return]


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
    SCHEMA: ClassVar[str]

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
        return _decode(cls, payload)  # type: ignore[no-any-return]


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """sensor_msgs/CameraInfo (pinhole intrinsics, distortion, rectification, projection).

    Attributes:
        k: 3x3 intrinsics row-major; r: 3x3 rectification; p: 3x4 projection.
        roi: (x_offset, y_offset, height, width, do_rectify).
    """

    TYPE: ClassVar[str] = "sensor_msgs/msg/CameraInfo"
    SCHEMA: ClassVar[str]

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
        return _decode(cls, payload)  # type: ignore[no-any-return]


# --------------------------------------------------------------------------- registry

MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (PoseStamped, TransformStamped, TFMessage, Odometry, Image, CompressedImage, CameraInfo)
}
"""Full ROS 2 type name -> message class."""

for _cls in MESSAGE_TYPES.values():
    _cls.SCHEMA = schema_text(_cls.TYPE)


def decode_message(msgtype: str, payload: bytes | bytearray | memoryview) -> Message:
    """Decode a payload of the named type (full ROS 2 name).

    Raises:
        BusError: for an unknown type or a malformed payload.
    """
    cls = MESSAGE_TYPES.get(msgtype)
    if cls is None:
        known = ", ".join(sorted(MESSAGE_TYPES))
        raise BusError(f"cannot decode message type {msgtype!r}; known types: {known}")
    return cls.decode(payload)

