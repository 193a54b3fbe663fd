"""What a camera or mocap driver publishes: camera, pose and tf streams, separate from where they go.

A :class:`CameraStream` owns the bus publishers of one camera (``<ns>/camera/<name>/image``,
optionally ``.../image/compressed``, and ``.../camera_info``) and a reusable encode buffer,
so publishing a frame costs one copy of the pixels into the CDR payload and no fresh
allocation (a page fault costs ~3 us per 4 KiB; an 848x480 RGB frame is 300 pages).

Policies (see :mod:`flightkit.bus.pubsub`): images are best effort and may be dropped by
Zenoh under congestion (the receiver sees a sequence gap); camera_info, poses and tf are
reliable and block rather than drop.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import zenoh

from flightkit.bus.camera_calibration import CalibrationServer
from flightkit.bus.image_msgs import CameraInfo, CompressedImage, Image
from flightkit.bus.keys import Keys
from flightkit.bus.msg_base import Header
from flightkit.bus.pose_msgs import PoseStamped, TFMessage, TransformStamped
from flightkit.bus.pubsub import STAMP_HOST, BusPublisher
from flightkit.clock import Clock
from flightkit.errors import BusError
from flightkit.frames import MOCAP_FRAME_ID, Transform

__all__ = [
    "CameraModel",
    "CameraStream",
    "CameraStreamSelection",
    "PosePublisher",
    "TfPublisher",
    "check_readout_s",
    "is_best_effort",
    "optical_frame_id",
]

logger = logging.getLogger(__name__)

_NAN = float("nan")

_BEST_EFFORT_TYPES = frozenset({Image.TYPE, CompressedImage.TYPE})


def is_best_effort(msgtype: str) -> bool:
    """Whether streams of this type may drop under pressure (images) or must not (everything else)."""
    return msgtype in _BEST_EFFORT_TYPES


def has_subscribers(pub: BusPublisher) -> bool:
    """Whether a subscriber matches ``pub``'s key right now (Zenoh's matching status)."""
    return pub.has_subscribers


def optical_frame_id(keys: Keys, camera: str) -> str:
    """The frame id of a camera's optical frame (OpenCV convention), e.g. ``uav1/camera_color_optical``."""
    return f"{keys.namespace}/camera_{camera}_optical"


@dataclass(frozen=True, slots=True)
class CameraStreamSelection:
    """Which streams a camera publishes (the ``[capture]`` section's publisher switches).

    Attributes:
        color: the colour image (rgb8) and its camera_info.
        depth: 16-bit depth in millimetres (16UC1) and its camera_info.
        stereo: the rectified stereo pair (left/right mono8) and camera_info.
        tf: the camera extrinsics (and, from a simulator, the exact camera pose) on ``<ns>/tf``.
        jpeg_quality: also publish colour as JPEG CompressedImage (0 = off).
    """

    color: bool = True
    depth: bool = True
    stereo: bool = False
    tf: bool = True
    jpeg_quality: int = 0


def check_readout_s(value: object) -> float:
    """A rolling-shutter readout (s) as a float, checked finite and >= 0.

    Raises:
        BusError: any other value.
    """
    try:
        readout = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        readout = math.nan
    if not (math.isfinite(readout) and readout >= 0.0):
        raise BusError(
            f"camera readout_s is {value!r}; give the rolling shutter's readout in seconds "
            "(first row to last), or 0 for a global shutter"
        )
    return readout


@dataclass(frozen=True, slots=True)
class CameraModel:
    """Pinhole calibration of one published camera.

    Attributes:
        width_px, height_px: image size.
        fx_px, fy_px, cx_px, cy_px: intrinsics in pixels.
        dist: OpenCV (plumb_bob) distortion ``k1 k2 p1 p2 k3``; empty when rectified.
        baseline_tx: ``P[0,3] = -fx * baseline`` for the right camera of a rectified pair, else 0.
        readout_s: rolling-shutter readout, first row to last, s; 0 for a global shutter (or unknown).
            CameraInfo has no field for it: it is served on ``.../calibration``
            (:mod:`flightkit.bus.camera_calibration`).

    Raises:
        BusError: a readout that is not a finite number >= 0.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist: tuple[float, ...] = ()
    baseline_tx: float = 0.0
    readout_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "readout_s", check_readout_s(self.readout_s))

    def camera_info(self, stamp_ns: int, frame_id: str) -> CameraInfo:
        return CameraInfo.from_intrinsics(
            Header(stamp_ns, frame_id), self.width_px, self.height_px, self.fx_px, self.fy_px, self.cx_px,
            self.cy_px, d=self.dist, baseline_tx=self.baseline_tx,
        )

    def as_metadata(self) -> dict[str, str]:
        """String map for MCAP metadata records."""
        return {
            "width": str(self.width_px), "height": str(self.height_px), "fx": repr(self.fx_px),
            "fy": repr(self.fy_px), "cx": repr(self.cx_px), "cy": repr(self.cy_px),
            "distortion_model": "plumb_bob", "d": " ".join(repr(d) for d in self.dist),
            "baseline_tx": repr(self.baseline_tx), "readout_s": repr(self.readout_s),
        }


class CameraStream:
    """The publishers of one camera: image (+ optional JPEG) and camera_info, and its calibration
    served on ``<ns>/camera/<name>/calibration`` (:mod:`flightkit.bus.camera_calibration`).

    Args:
        session: an open Zenoh session.
        keys: the vehicle namespace.
        name: camera name in the key (``color``, ``depth``, ``left``, ``right``).
        model: calibration published as camera_info with every frame.
        encoding: ROS image encoding of the arrays given to :meth:`publish` (``rgb8``,
            ``bgr8``, ``mono8``, ``16UC1``, ...).
        jpeg_quality: 1-100 also publishes ``image/compressed`` (8-bit images only); 0 = off.
        frame_id: the header frame id (default: the camera's optical frame).
        clock: stamps the bus time of each sample (default the wall clock).
        stamp_source: ``device`` when the stamps given to :meth:`publish` are the camera's own
            capture times, ``host`` when the driver gives none (see :mod:`flightkit.bus.pubsub`).

    :meth:`publish` is meant for one thread (the camera's); it returns once Zenoh holds a
    copy of the payload.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        name: str,
        model: CameraModel,
        encoding: str,
        *,
        jpeg_quality: int = 0,
        frame_id: str | None = None,
        clock: Clock | None = None,
        stamp_source: str = STAMP_HOST,
    ) -> None:
        self.name = name
        self.model = model
        self.encoding = encoding
        self.frame_id = frame_id or optical_frame_id(keys, name)
        self.image_key = keys.camera_image(name)
        self.info_key = keys.camera_info(name)
        stamping: dict[str, Any] = {"clock": clock, "stamp_source": stamp_source}
        self._image = BusPublisher(session, self.image_key, Image, reliable=False, drop_when_congested=True, **stamping)
        self._info = BusPublisher(session, self.info_key, CameraInfo, reliable=True, drop_when_congested=False,
                                  **stamping)
        self._jpeg: BusPublisher | None = None
        self._jpeg_quality = int(jpeg_quality)
        if jpeg_quality:
            self._jpeg = BusPublisher(
                session, keys.camera_compressed(name), CompressedImage, reliable=False, drop_when_congested=True,
                **stamping,
            )
        self._calibration = CalibrationServer(session, keys.camera_calibration(name), model.as_metadata())
        self._buf = bytearray()
        self.frames = 0

    @property
    def has_subscribers(self) -> bool:
        """Whether anyone subscribes to the image right now."""
        return has_subscribers(self._image)

    @property
    def stamp_source(self) -> str:
        """``device`` or ``host`` (see the constructor); a driver sets it before its first frame
        once it knows whether the device gives capture times."""
        return self._image.stamp_source

    @stamp_source.setter
    def stamp_source(self, source: str) -> None:
        for pub in (self._image, self._info, self._jpeg):
            if pub is not None:
                pub.stamp_source = source

    def publish(self, stamp_ns: int, array: npt.NDArray[Any]) -> int:
        """Publish one frame (and its camera_info) stamped ``stamp_ns``; returns the image's sequence number.

        Raises:
            BusError: the array does not match the stream's size or encoding.
        """
        h, w = array.shape[:2]
        if (w, h) != (self.model.width_px, self.model.height_px):
            raise BusError(
                f"camera {self.name}: frame is {w}x{h} but its calibration is "
                f"{self.model.width_px}x{self.model.height_px}; publish frames of the calibrated size"
            )
        header = Header(stamp_ns, self.frame_id)
        try:
            msg = Image.from_array(header, array, self.encoding)
        except Exception as exc:
            raise BusError(f"camera {self.name}: {exc}") from exc
        seq = self._image.put(msg.encode(self._buf), stamp_ns)
        self._info.put(self.model.camera_info(stamp_ns, self.frame_id).encode(), stamp_ns)
        if self._jpeg is not None and array.dtype == np.uint8:
            bgr = array
            if self.encoding == "rgb8":
                bgr = cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
            ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self._jpeg_quality])
            if ok:
                self._jpeg.put(CompressedImage(header, "jpeg", jpg.reshape(-1)).encode(), stamp_ns)
        self.frames += 1
        return seq

    def close(self) -> None:
        for pub in (self._image, self._info, self._jpeg):
            if pub is not None:
                pub.close()
        self._calibration.close()


class PosePublisher:
    """PoseStamped on ``<ns>/mocap/<body>/pose``: reliable, never dropped, sent at once (express).

    Poses are published in the mocap system's own frame (``frame_id`` ``mocap``), as a mocap
    driver would; consumers map them into the world with ``T_world_mocap``. A lost body is
    published as a NaN pose (:meth:`publish` with None). ``clock`` stamps the bus time;
    ``stamp_source`` says whether the stamps given are the mocap system's frame times (``device``)
    or the host's arrival times (``host``).
    """

    def __init__(self, session: zenoh.Session, keys: Keys, body: str, frame_id: str = MOCAP_FRAME_ID, *,
                 clock: Clock | None = None, stamp_source: str = STAMP_HOST) -> None:
        self.key = keys.mocap_pose(body)
        self.frame_id = frame_id
        self._pub = BusPublisher(session, self.key, PoseStamped, reliable=True, drop_when_congested=False, express=True,
                                 clock=clock, stamp_source=stamp_source)
        self._lock = threading.Lock()

    @property
    def has_subscribers(self) -> bool:
        return has_subscribers(self._pub)

    def publish(self, stamp_ns: int, T_frame_body: Transform | None) -> int:  # noqa: N803
        """Publish a pose in this publisher's frame, or "lost" (NaN) for None; returns the sequence number."""
        if T_frame_body is None:
            msg = PoseStamped(Header(stamp_ns, self.frame_id), (_NAN,) * 3, (_NAN,) * 4)
        else:
            msg = PoseStamped.from_transform(stamp_ns, self.frame_id, T_frame_body)
        with self._lock:
            return self._pub.put(msg.encode(), stamp_ns)

    def close(self) -> None:
        self._pub.close()


class TfPublisher:
    """tf2_msgs/TFMessage on ``<ns>/tf``: extrinsics and ground-truth camera poses (reliable)."""

    def __init__(self, session: zenoh.Session, keys: Keys, clock: Clock | None = None,
                 stamp_source: str = STAMP_HOST) -> None:
        self.key = keys.tf()
        self._pub = BusPublisher(session, self.key, TFMessage, reliable=True, drop_when_congested=False, clock=clock,
                                 stamp_source=stamp_source)

    def publish(self, stamp_ns: int, transforms: list[tuple[str, str, Transform]]) -> int:
        """Publish ``(parent, child, T_parent_child)`` triples in one message."""
        msg = TFMessage(
            tuple(TransformStamped.from_transform(stamp_ns, p, c, T) for p, c, T in transforms)
        )
        return self._pub.put(msg.encode(), stamp_ns)

    def close(self) -> None:
        self._pub.close()
