"""A V4L2 / USB camera or a video file as a bus camera, through ``cv2.VideoCapture``.

:class:`OpenCVCameraPublisher` owns one ``cv2.VideoCapture`` on its own thread (OpenCV's
calls block) and publishes::

    <ns>/camera/<name>/image              sensor_msgs/Image bgr8 (or rgb8)      format "bgr8"/"rgb8"
    <ns>/camera/<name>/image/compressed   sensor_msgs/CompressedImage jpeg      format "jpeg", or jpeg_quality > 0
    <ns>/camera/<name>/camera_info        sensor_msgs/CameraInfo from the calibration file

Sources: a device index (``0``), a device path (``/dev/video2``), a stream URL, or a video
file. A device delivers at its own rate (``grab`` blocks until the next frame); a file is
paced at its frame rate on the injected clock (so a :class:`~flightkit.clock.SimClock`
plays it faster) and ends at its last frame (or loops).

Stamps: a live V4L2 device's buffer time (OpenCV's ``CAP_PROP_POS_MSEC`` on the V4L2 backend
is the kernel's ``CLOCK_MONOTONIC`` stamp of the buffer), moved onto the epoch by
:func:`v4l2_buffer_stamp_ns` (``capture_stamp=device``); otherwise (a file, another backend, or
a buffer time that is not plausible) ``clock.time_ns()`` right after ``grab()`` returns, i.e.
when the frame reached us (``host``, said once in the log).

Calibration: the video-dataset format (:mod:`flightkit.datasets.video`: JSON or OpenCV
YAML with fx, fy, cx, cy, width, height, dist and an optional rolling-shutter ``readout_s``),
found beside a video file or given explicitly; a :class:`~flightkit.bus.streams.CameraModel`
may be passed instead. It is served on ``<ns>/camera/<name>/calibration`` as well
(:mod:`flightkit.bus.camera_calibration`), which is how the readout reaches a recording.

A device that vanishes (unplugged, driver reset) is reported once (WARNING) and reopened
every ``retry_s`` until it is back (INFO); frames in between are simply missing.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import numpy.typing as npt
import zenoh

from capture.sources._runner import SourceThread
from flightkit.bus.camera_calibration import CalibrationServer
from flightkit.bus.image_msgs import CameraInfo, CompressedImage
from flightkit.bus.keys import Keys
from flightkit.bus.msg_base import Header
from flightkit.bus.pubsub import BusPublisher
from flightkit.bus.streams import CameraModel, CameraStream, has_subscribers, optical_frame_id
from flightkit.clock import STAMP_DEVICE, STAMP_HOST, Clock
from flightkit.errors import BusError, CaptureError, DatasetError

__all__ = [
    "COLOR_FORMATS",
    "OpenCVCameraPublisher",
    "camera_model_from_calibration",
    "parse_device",
    "v4l2_buffer_stamp_ns",
]

_MAX_BUFFER_AGE_NS = 1_000_000_000  # a buffer stamp older than this (or in the future) is not believed


def v4l2_buffer_stamp_ns(buffer_ms: float, now_ns: int, monotonic_now_ns: int) -> int | None:
    """A V4L2 buffer time (ms on ``CLOCK_MONOTONIC``) as ns since the epoch, given the epoch and
    monotonic times now; None when it is not a plausible capture time (0, ahead of now, or more
    than a second old: the driver stamps another clock, or gives none)."""
    age_ns = monotonic_now_ns - round(buffer_ms * 1e6)
    if buffer_ms <= 0.0 or not 0 <= age_ns <= _MAX_BUFFER_AGE_NS:
        return None
    return now_ns - age_ns

logger = logging.getLogger(__name__)

COLOR_FORMATS = ("bgr8", "rgb8", "jpeg")


def parse_device(spec: str | int) -> int | str:
    """``"0"`` -> 0 (device index); anything else (path, URL, file) stays a string."""
    if isinstance(spec, int):
        return spec
    text = str(spec).strip()
    return int(text) if text.isdigit() else text


def _is_live(device: int | str) -> bool:
    """Devices and stream URLs are live (blocking grab, retry when lost); regular files are not."""
    if isinstance(device, int):
        return True
    return device.startswith("/dev/") or "://" in device or not Path(device).is_file()


def camera_model_from_calibration(path: str | os.PathLike[str]) -> CameraModel:
    """Read a calibration file (the video-dataset JSON/YAML format) into a :class:`CameraModel`,
    with its ``readout_s`` (rolling shutter, s; 0 when absent).

    Raises:
        CaptureError: the file is missing, unreadable, lacks a key (named) or gives a bad readout.
    """
    from flightkit.datasets.video import read_calibration

    p = Path(path)
    if not p.is_file():
        raise CaptureError(
            f"calibration file {p} does not exist; write one with fx, fy, cx, cy, width, height"
        )
    try:
        cal = read_calibration(p)
    except DatasetError as exc:
        raise CaptureError(str(exc)) from exc
    dist = tuple(float(d) for d in cal.get("dist", ()) or ())
    try:
        return CameraModel(
            int(cal["width"]),
            int(cal["height"]),
            float(cal["fx"]),
            float(cal["fy"]),
            float(cal["cx"]),
            float(cal["cy"]),
            dist,
            readout_s=cal.get("readout_s", 0.0),
        )
    except BusError as exc:
        raise CaptureError(f"calibration file {p}: {exc}") from exc


class _JpegStream:
    """JPEG-only publishing: image/compressed + camera_info (no raw image), and the calibration
    served as :class:`~flightkit.bus.streams.CameraStream` serves it."""

    def __init__(
        self, session: zenoh.Session, keys: Keys, name: str, model: CameraModel, quality: int, clock: Clock
    ) -> None:
        self.model = model
        self.frame_id = optical_frame_id(keys, name)
        self.image_key = keys.camera_compressed(name)
        self.info_key = keys.camera_info(name)
        self._quality = quality
        self._jpeg = BusPublisher(
            session, self.image_key, CompressedImage, reliable=False, drop_when_congested=True, clock=clock
        )
        self._info = BusPublisher(
            session, self.info_key, CameraInfo, reliable=True, drop_when_congested=False, clock=clock
        )
        self._calibration = CalibrationServer(session, keys.camera_calibration(name), model.as_metadata())
        self._buf = bytearray()

    @property
    def stamp_source(self) -> str:
        return self._jpeg.stamp_source

    @stamp_source.setter
    def stamp_source(self, source: str) -> None:
        self._jpeg.stamp_source = self._info.stamp_source = source

    def publish(self, stamp_ns: int, bgr: npt.NDArray[Any]) -> int:
        ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self._quality])
        if not ok:
            raise CaptureError("OpenCV could not JPEG-encode a frame; check the frame format")
        header = Header(stamp_ns, self.frame_id)
        seq = self._jpeg.put(CompressedImage(header, "jpeg", jpg.reshape(-1)).encode(self._buf), stamp_ns)
        self._info.put(self.model.camera_info(stamp_ns, self.frame_id).encode(), stamp_ns)
        return seq

    def close(self) -> None:
        self._jpeg.close()
        self._info.close()
        self._calibration.close()


class OpenCVCameraPublisher(SourceThread):
    """Publish a camera or video file read with ``cv2.VideoCapture``.

    Args:
        session: an open Zenoh session.
        keys: the vehicle namespace.
        device: device index, ``/dev/videoN``, stream URL or video file (see :func:`parse_device`).
        clock: stamps frames; paces video files.
        model: the calibration; None reads ``calibration`` (or, for a video file, the
            calibration file beside it).
        calibration: a calibration file (video-dataset format).
        name: camera name in the keys (``color``).
        color_format: ``bgr8`` (OpenCV's order, no conversion), ``rgb8``, or ``jpeg``
            (CompressedImage only).
        jpeg_quality: JPEG quality; with ``bgr8``/``rgb8``, > 0 also publishes JPEG.
        rate_hz: video files: playback rate (default: the file's fps); devices: asked of the driver.
        loop: video files: start again at the end instead of finishing.
        retry_s: live sources: how often to try reopening a vanished device.
        backend: OpenCV capture API (``cv2.CAP_V4L2``...; default any).

    Raises:
        CaptureError: no calibration, a bad format, or (for a video file) one OpenCV cannot open.
    """

    thread_name = "opencv-camera"
    what = "frames"

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        device: int | str,
        clock: Clock,
        *,
        model: CameraModel | None = None,
        calibration: str | os.PathLike[str] | None = None,
        name: str = "color",
        color_format: str = "bgr8",
        jpeg_quality: int = 90,
        rate_hz: float | None = None,
        loop: bool = False,
        retry_s: float = 1.0,
        backend: int = cv2.CAP_ANY,
    ) -> None:
        super().__init__(clock)
        if color_format not in COLOR_FORMATS:
            raise CaptureError(f"colour format {color_format!r} is not known; use {', '.join(COLOR_FORMATS)}")
        self.device = parse_device(device)
        self.live = _is_live(self.device)
        self.thread_name = f"opencv-camera {self.device}"
        if model is None:
            if calibration is None and not self.live:
                from flightkit.datasets.video import find_calibration

                try:
                    calibration = find_calibration(Path(str(self.device)))
                except DatasetError as exc:
                    raise CaptureError(str(exc)) from exc
            if calibration is None:
                raise CaptureError(
                    f"camera {self.device} has no calibration; pass --calibration FILE (JSON with fx, fy, cx, cy, "
                    "width, height; see docs/capture.md)"
                )
            model = camera_model_from_calibration(calibration)
        self.model = model
        self.color_format = color_format
        self.rate_hz = rate_hz
        self.loop = loop
        self.retry_s = retry_s
        self.backend = backend
        self.frames_lost = 0  # grab failures on a live device
        self.reconnects = 0
        self._cap: cv2.VideoCapture | None = None
        self._fps = 0.0
        if not self.live:
            cap = self._open()  # fail early, in the caller's thread, for a bad file
            self._fps = float(rate_hz or cap.get(cv2.CAP_PROP_FPS) or 0.0)
            cap.release()
            if not self._fps > 0:
                raise CaptureError(f"video {self.device} reports no frame rate; pass rate_hz (--rate)")
        self._raw: CameraStream | None = None
        self._jpeg: _JpegStream | None = None
        if color_format == "jpeg":
            self._jpeg = _JpegStream(session, keys, name, model, jpeg_quality, clock)
            self.image_key = self._jpeg.image_key
            self.info_key = self._jpeg.info_key
        else:
            self._raw = CameraStream(
                session, keys, name, model, color_format, jpeg_quality=jpeg_quality if jpeg_quality > 0 else 0,
                clock=clock,
            )
            self.image_key = self._raw.image_key
            self.info_key = self._raw.info_key
        self._rgb: npt.NDArray[np.uint8] | None = None
        self._frame: npt.NDArray[np.uint8] | None = None
        self._stamp_source = ""  # device or host, once the first frame said

    @property
    def keys(self) -> list[str]:
        return [self.image_key, self.info_key]

    @property
    def has_subscribers(self) -> bool:
        """Whether a subscriber (e.g. a recorder) matches the image key right now."""
        if self._raw is not None:
            return self._raw.has_subscribers
        assert self._jpeg is not None
        return has_subscribers(self._jpeg._jpeg)  # noqa: SLF001

    # ------------------------------------------------------------------ capture thread

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self.device, self.backend)
        if not cap.isOpened():
            cap.release()
            if self.live:
                raise OSError(f"cannot open {self.device}")
            raise CaptureError(f"video {self.device} cannot be opened by OpenCV; is the codec supported?")
        if self.live:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.model.width_px)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.model.height_px)
            if self.rate_hz:
                cap.set(cv2.CAP_PROP_FPS, self.rate_hz)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # newest frame, not a stale queue
        return cap

    def _publish(self, stamp_ns: int, bgr: npt.NDArray[np.uint8]) -> None:
        if bgr.ndim == 2:
            bgr = cast("npt.NDArray[np.uint8]", cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR))
        if self._jpeg is not None:
            self._jpeg.publish(stamp_ns, bgr)
        else:
            assert self._raw is not None
            if self.color_format == "rgb8":
                if self._rgb is None or self._rgb.shape != bgr.shape:
                    self._rgb = np.empty_like(bgr)
                cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=self._rgb)
                bgr = self._rgb
            self._raw.publish(stamp_ns, bgr)
        self._count()

    def _retrieve(self, cap: cv2.VideoCapture) -> npt.NDArray[np.uint8] | None:
        ok, retrieved = cap.retrieve(self._frame)
        if not ok or retrieved is None:
            return None
        frame = cast("npt.NDArray[np.uint8]", retrieved)  # 8-bit BGR (or gray)
        self._frame = frame  # OpenCV writes the next frame into this buffer (no fresh allocation)
        return frame

    def _run_file(self) -> None:
        period = 1.0 / self._fps
        cap = self._open()
        self._cap = cap
        try:
            t0 = self.clock.monotonic_s()
            n = 0
            while not self.stopping:
                if not self._sleep_until(t0 + n * period):
                    return
                if not cap.grab():
                    if self.loop and n > 0:
                        cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                        if cap.grab():
                            self._handle_grab(cap)
                            n += 1
                            continue
                    logger.info("video %s ended after %d frames", self.device, self.published)
                    return
                self._handle_grab(cap)
                n += 1
        finally:
            cap.release()
            self._cap = None

    def _handle_grab(self, cap: cv2.VideoCapture) -> None:
        stamp_ns = self.clock.time_ns()
        if self.live:
            device_ns = None
            if cap.getBackendName() == "V4L2":
                device_ns = v4l2_buffer_stamp_ns(cap.get(cv2.CAP_PROP_POS_MSEC), stamp_ns, time.monotonic_ns())
            self._note_stamp_source(STAMP_HOST if device_ns is None else STAMP_DEVICE)
            stamp_ns = device_ns or stamp_ns
        elif not self._stamp_source:
            self._note_stamp_source(STAMP_HOST)
        frame = self._retrieve(cap)
        if frame is None:
            self.frames_lost += 1
            return
        self._publish(stamp_ns, frame)

    def _run_live(self) -> None:
        cap: cv2.VideoCapture | None = None
        lost_since: float | None = None
        try:
            while not self.stopping:
                if cap is None:
                    try:
                        cap = self._open()
                    except OSError:
                        if lost_since is None:
                            lost_since = self.clock.monotonic_s()
                            logger.warning(
                                "camera %s is not available; retrying every %g s (is it plugged in and free?)",
                                self.device,
                                self.retry_s,
                            )
                        self._pause(self.retry_s)
                        continue
                    if lost_since is not None:
                        self.reconnects += 1
                        logger.info(
                            "camera %s is back after %.1f s",
                            self.device,
                            self.clock.monotonic_s() - lost_since,
                        )
                        lost_since = None
                if cap.grab():
                    self._handle_grab(cap)
                    continue
                # The device vanished (or the driver reset): say so once, reopen until it is back.
                self.frames_lost += 1
                cap.release()
                cap = None
                lost_since = self.clock.monotonic_s()
                logger.warning(
                    "camera %s stopped delivering frames after %d; reopening every %g s",
                    self.device,
                    self.published,
                    self.retry_s,
                )
                self._pause(self.retry_s)
        finally:
            if cap is not None:
                cap.release()

    def _note_stamp_source(self, source: str) -> None:
        if source == self._stamp_source:
            return
        self._stamp_source = source
        if self._raw is not None:
            self._raw.stamp_source = source
        if self._jpeg is not None:
            self._jpeg.stamp_source = source
        if source == STAMP_HOST:
            logger.info("camera %s gives no capture time with its frames; stamping them on arrival", self.device)

    def _run_loop(self) -> None:
        if self.live:
            logger.info("camera %s publishing %s on %s", self.device, self.color_format, self.image_key)
            self._run_live()
        else:
            logger.info(
                "video %s publishing %s at %g Hz on %s",
                self.device,
                self.color_format,
                self._fps,
                self.image_key,
            )
            self._run_file()

    def _close_outputs(self) -> None:
        for s in (self._raw, self._jpeg):
            if s is not None:
                s.close()
