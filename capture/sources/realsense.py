"""An Intel RealSense camera (D4xx) as a bus camera, through ``pyrealsense2`` (optional extra).

``pip install flightkit[realsense]``. :class:`RealSensePublisher` runs the RealSense pipeline
on its own thread and publishes::

    <ns>/camera/color/image         sensor_msgs/Image rgb8 (as the camera delivers it)
    <ns>/camera/color/camera_info   intrinsics of the colour stream profile
    <ns>/camera/depth/image         sensor_msgs/Image 16UC1, millimetres, aligned to colour
    <ns>/camera/depth/camera_info   = the colour intrinsics (depth is aligned: same optical frame)

Depth is aligned to colour with ``rs.align(rs.stream.color)``, so pixel (u, v) of the depth
image sees the same point as pixel (u, v) of the colour image, and both share the colour
camera's intrinsics and frame id. The camera's depth unit (``depth_scale``, metres per
count: 0.001 on most D4xx, 0.0001 on some presets) is converted to millimetres, the unit of
the bus's 16UC1 depth; counts beyond 65.535 m and invalid (0) pixels stay 0.

Rolling shutter: the D4xx colour sensors are rolling shutter, but librealsense does not give the
readout time; the colour stream carries ``readout_s`` only when the caller gives it (0 otherwise).

Stamps: the frameset's timestamp when the camera clock is the global time domain (the
librealsense default on D4xx maps the hardware clock into the host clock: the device's capture
time, ``capture_stamp=device`` on the bus and in a recording), otherwise the injected clock at
the moment the frameset arrived (``host``; said once in the log).

The pure parts (:func:`camera_model_from_intrinsics`, :func:`depth_to_mm`) need no package
and are what the unit tests cover; the device loop needs the package and a camera.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
from types import ModuleType
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh

from capture.sources._runner import SourceThread
from flightkit.bus.keys import Keys
from flightkit.bus.streams import CameraModel, CameraStream, check_readout_s, optical_frame_id
from flightkit.clock import STAMP_DEVICE, STAMP_HOST, Clock
from flightkit.errors import BusError, CaptureError

__all__ = [
    "RealSensePublisher",
    "camera_model_from_intrinsics",
    "depth_to_mm",
    "import_realsense",
]

logger = logging.getLogger(__name__)

# librealsense distortion models and how they map onto OpenCV's plumb_bob (k1 k2 p1 p2 k3).
_PLUMB_BOB_LIKE = {"brown_conrady", "inverse_brown_conrady", "modified_brown_conrady", "none"}


def import_realsense() -> ModuleType:
    """Import ``pyrealsense2`` or say how to install it.

    Raises:
        CaptureError: the package is not installed.
    """
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as exc:
        raise CaptureError(
            "the RealSense source needs pyrealsense2, which is not installed; "
            "install it with 'pip install flightkit[realsense]' (or 'pip install pyrealsense2')"
        ) from exc


def _model_name(model: Any) -> str:
    name = getattr(model, "name", None)
    text = str(name if name is not None else model)
    return text.rsplit(".", 1)[-1].lower()


def camera_model_from_intrinsics(intr: Any) -> CameraModel:
    """A :class:`CameraModel` from ``rs.intrinsics`` (anything with width, height, fx, fy, ppx,
    ppy, model, coeffs).

    Brown-Conrady coefficients are OpenCV's ``k1 k2 p1 p2 k3`` in the same order; an
    all-zero set (D4xx colour streams report zeros) becomes "no distortion".

    Raises:
        CaptureError: a distortion model with no plumb_bob equivalent (e.g. Kannala-Brandt
            fisheye on a T265) with non-zero coefficients.
    """
    coeffs = tuple(float(c) for c in getattr(intr, "coeffs", ()) or ())
    model = _model_name(getattr(intr, "model", "none"))
    if any(coeffs) and model not in _PLUMB_BOB_LIKE:
        raise CaptureError(
            f"RealSense distortion model {model!r} has no plumb_bob equivalent; "
            "publish a rectified stream or calibrate the camera with OpenCV"
        )
    dist = coeffs[:5] if any(coeffs) else ()
    width, height = int(intr.width), int(intr.height)
    if width <= 0 or height <= 0 or not (float(intr.fx) > 0 and float(intr.fy) > 0):
        raise CaptureError(
            f"RealSense intrinsics are not usable ({width}x{height}, fx={intr.fx}, fy={intr.fy})"
        )
    return CameraModel(width, height, float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy), dist)


def depth_to_mm(
    raw: npt.NDArray[Any], depth_scale_m: float, out: npt.NDArray[np.uint16] | None = None
) -> npt.NDArray[np.uint16]:
    """Depth counts (or float metres with ``depth_scale_m=1``) to uint16 millimetres.

    ``mm = round(raw * depth_scale_m * 1000)``; 0 stays 0 (no data), non-finite values become
    0, values beyond 65535 mm saturate to 0 (too far to be trusted, as 0 means "no data").
    With ``depth_scale_m == 0.001`` and uint16 input this is a plain copy.

    Args:
        out: a reusable (H, W) uint16 buffer (avoids an allocation per frame).
    """
    arr = np.asarray(raw)
    if out is None or out.shape != arr.shape:
        out = np.empty(arr.shape, np.uint16)
    factor = float(depth_scale_m) * 1000.0
    if arr.dtype == np.uint16 and factor == 1.0:
        np.copyto(out, arr)
        return out
    mm = arr.astype(np.float64) * factor
    mm = np.rint(mm, out=mm)
    bad = ~np.isfinite(mm) | (mm < 0) | (mm > 65535)
    mm[bad] = 0
    np.copyto(out, mm, casting="unsafe")
    return out


class RealSensePublisher(SourceThread):
    """Publish a RealSense camera's colour and aligned depth.

    Args:
        session: an open Zenoh session.
        keys: the vehicle namespace.
        clock: stamps (when the camera has no global time) and retry pauses.
        width_px, height_px, rate_hz: the colour and depth profile to ask for.
        depth: also publish aligned depth.
        serial: pick one camera by serial number (None: the first one).
        jpeg_quality: also publish the colour stream as JPEG (0 = off).
        retry_s: after the camera vanished, how often to try restarting the pipeline.
        readout_s: the colour sensor's rolling-shutter readout, first row to last, s, when known
            (the SDK does not give it); 0 = not known or a global shutter.

    Raises:
        CaptureError: pyrealsense2 is missing (see :func:`import_realsense`), or a bad ``readout_s``.
    """

    thread_name = "realsense"
    what = "framesets"

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        clock: Clock,
        *,
        width_px: int = 848,
        height_px: int = 480,
        rate_hz: int = 30,
        depth: bool = True,
        serial: str | None = None,
        jpeg_quality: int = 0,
        retry_s: float = 1.0,
        frame_timeout_s: float = 2.0,
        readout_s: float = 0.0,
    ) -> None:
        super().__init__(clock)
        self._rs = import_realsense()
        self._session = session
        self._keys = keys
        self.width_px, self.height_px, self.rate_hz = width_px, height_px, rate_hz
        self.depth_enabled = depth
        self.serial = serial
        self.jpeg_quality = jpeg_quality
        self.retry_s = retry_s
        self.frame_timeout_s = frame_timeout_s
        try:
            self.readout_s = check_readout_s(readout_s)
        except BusError as exc:
            raise CaptureError(f"RealSense: {exc}") from exc
        self.color: CameraStream | None = None
        self._stamp_source = ""  # device or host, once the first frameset said
        self.depth: CameraStream | None = None
        self.model: CameraModel | None = None
        self.depth_scale_m = 0.001
        self._depth_mm: npt.NDArray[np.uint16] | None = None

    @property
    def keys(self) -> list[str]:
        """The image and camera-info keys of the colour (and, when enabled, depth) streams."""
        names = ("color", "depth") if self.depth_enabled else ("color",)
        return [k for n in names for k in (self._keys.camera_image(n), self._keys.camera_info(n))]

    def _start_pipeline(self) -> tuple[Any, Any]:
        rs = self._rs
        pipe = rs.pipeline()
        cfg = rs.config()
        if self.serial:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.color, self.width_px, self.height_px, rs.format.rgb8, self.rate_hz)
        if self.depth_enabled:
            cfg.enable_stream(rs.stream.depth, self.width_px, self.height_px, rs.format.z16, self.rate_hz)
        profile = pipe.start(cfg)
        if self.depth_enabled:
            self.depth_scale_m = float(profile.get_device().first_depth_sensor().get_depth_scale())
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        model = camera_model_from_intrinsics(intr)
        if self.model is None:  # publishers are declared once, with the first profile's calibration
            self.model = model
            color_model = dataclasses.replace(model, readout_s=self.readout_s)
            self.color = CameraStream(
                self._session, self._keys, "color", color_model, "rgb8", jpeg_quality=self.jpeg_quality,
                clock=self.clock,
            )
            if self.depth_enabled:
                self.depth = CameraStream(
                    self._session,
                    self._keys,
                    "depth",
                    model,
                    "16UC1",
                    frame_id=optical_frame_id(self._keys, "color"),
                    clock=self.clock,
                )
        align = rs.align(rs.stream.color) if self.depth_enabled else None
        logger.info(
            "RealSense %s streaming %dx%d at %d Hz (depth scale %g m)",
            self.serial or "camera",
            model.width_px,
            model.height_px,
            self.rate_hz,
            self.depth_scale_m,
        )
        return pipe, align

    def _stamp_ns(self, frames: Any) -> int:
        rs = self._rs
        device = frames.get_frame_timestamp_domain() == rs.timestamp_domain.global_time
        source = STAMP_DEVICE if device else STAMP_HOST
        if source != self._stamp_source:  # the first frameset, or the domain changed
            self._stamp_source = source
            for stream in (self.color, self.depth):
                if stream is not None:
                    stream.stamp_source = source
            if not device:
                logger.warning("RealSense %s gives no global-time frame stamps (domain %s); stamping frames "
                               "on arrival", self.serial or "camera", frames.get_frame_timestamp_domain())
        if device:
            return int(round(frames.get_timestamp() * 1e6))  # ms since the epoch
        return self.clock.time_ns()

    def _run_loop(self) -> None:
        pipe = None
        align = None
        lost = False
        while not self.stopping:
            if pipe is None:
                try:
                    pipe, align = self._start_pipeline()
                except RuntimeError as exc:
                    if not lost:
                        logger.warning("RealSense not available (%s); retrying every %g s", exc, self.retry_s)
                        lost = True
                    self._pause(self.retry_s)
                    continue
                if lost:
                    logger.info("RealSense is back")
                    lost = False
            try:
                frames = pipe.wait_for_frames(int(self.frame_timeout_s * 1000))
            except RuntimeError as exc:  # timeout or the device went away
                logger.warning("RealSense delivered no frames (%s); restarting the pipeline", exc)
                lost = True
                try:
                    pipe.stop()
                except RuntimeError:
                    pass
                pipe = None
                continue
            stamp_ns = self._stamp_ns(frames)
            if align is not None:
                frames = align.process(frames)
            color = frames.get_color_frame()
            if not color:
                continue
            assert self.color is not None
            self.color.publish(stamp_ns, np.asanyarray(color.get_data()))
            if self.depth is not None:
                d = frames.get_depth_frame()
                if d:
                    self._depth_mm = depth_to_mm(
                        np.asanyarray(d.get_data()), self.depth_scale_m, self._depth_mm
                    )
                    self.depth.publish(stamp_ns, self._depth_mm)
            self._count()
        if pipe is not None:
            try:
                pipe.stop()
            except RuntimeError:
                pass

    def _close_outputs(self) -> None:
        for s in (self.color, self.depth):
            if s is not None:
                s.close()
