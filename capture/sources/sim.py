"""The simulated camera as a bus publisher, like a real camera driver.

:class:`SimCameraPublisher` renders the simulated lab (:mod:`flightkit.sim.camera`) from the
vehicle's ground-truth pose at the configured rate on the injected clock and publishes::

    <ns>/camera/color/image        sensor_msgs/Image rgb8          + <ns>/camera/color/camera_info
    <ns>/camera/depth/image        sensor_msgs/Image 16UC1 (mm)    + <ns>/camera/depth/camera_info
    <ns>/camera/left|right/image   sensor_msgs/Image mono8 (rectified pair; [capture] stereo = true)
    <ns>/tf                        tf2_msgs/TFMessage: base_link -> camera (extrinsics) and
                                   world -> camera_gt (the exact pose each frame was rendered from)

Depth is aligned to colour (same camera). The camera pose is ``T_world_body @ T_body_camera``
with the extrinsics from ``[camera] T_body_camera``; the image stamp is the truth stamp, so
the ground truth is exact.

Timing: frames are due every ``1 / rate_hz`` of clock time. Rendering costs real time
(about 25 ms at 320x240 and 200 ms at 640x480 on a laptop core), so when the clock runs
faster than the renderer the publisher skips the frames it could not render (counted in
:attr:`SimCameraPublisher.frames_skipped`) rather than fall behind. Under a
:class:`~flightkit.clock.LockstepClock` time stands still while rendering, so every due
frame is published exactly.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from types import TracebackType
from typing import Self

import cv2
import numpy as np
import zenoh

from capture.config import CaptureConfig
from capture.streams import CameraModel, CameraStream, TfPublisher, optical_frame_id
from flightkit.bus.keys import Keys
from flightkit.clock import Clock, sleep_until
from flightkit.config import CameraConfig
from flightkit.errors import CaptureError
from flightkit.frames import Transform
from flightkit.sim.camera import PinholeModel, Scene, SimCamera

__all__ = ["SimCameraPublisher", "SimCameraService", "TruthFn", "start_sim_camera"]

logger = logging.getLogger(__name__)

TruthFn = Callable[[], tuple[int, Transform]]
"""Returns ``(stamp_ns, T_world_body)``: the vehicle's true pose now (same as the mocap publisher's)."""


class SimCameraPublisher:
    """Publish simulated camera streams on the bus.

    Args:
        session: an open Zenoh session.
        keys: the vehicle's namespace.
        lab_truth_fn: ``() -> (stamp_ns, T_world_body)``, e.g.
            ``lambda: (clock.time_ns(), lab.T_world_body())``.
        camera_cfg: resolution (320x240 to 848x480 in practice), rate, intrinsics, extrinsics.
        clock: the simulation's clock (the rate is in its time).
        capture_cfg: which streams (colour, depth, stereo, tf, JPEG); defaults when None.
        scene: what to render (default: the lab with textured boxes).

    Use :meth:`start`/:meth:`stop` (or ``with``); :meth:`publish_at` renders and publishes
    one frame synchronously (for scripted tests).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        lab_truth_fn: TruthFn,
        camera_cfg: CameraConfig,
        clock: Clock,
        *,
        capture_cfg: CaptureConfig | None = None,
        scene: Scene | None = None,
    ) -> None:
        cap = capture_cfg or CaptureConfig()
        if not (cap.color or cap.depth or cap.stereo):
            raise CaptureError("no camera stream enabled; set capture.color, capture.depth or capture.stereo to true")
        self._truth = lab_truth_fn
        self._clock = clock
        self._keys = keys
        self.rate_hz = camera_cfg.rate_hz
        self.T_body_camera = camera_cfg.T_body_camera.to_transform()
        fx, fy, cx, cy = camera_cfg.intrinsics()
        w, h = camera_cfg.width_px, camera_cfg.height_px
        self.renderer = SimCamera(
            scene or Scene.default_lab(), PinholeModel(w, h, fx, fy, cx, cy),
            camera_cfg.stereo_baseline_m, camera_cfg.depth_max_m,
        )
        self.model = CameraModel(w, h, fx, fy, cx, cy, (0.0,) * 5)
        self.T_left_right = Transform(translation=np.array([camera_cfg.stereo_baseline_m, 0.0, 0.0]))
        color_frame = optical_frame_id(keys, "color")
        self._streams: list[CameraStream] = []
        self.color = self.depth = self.left = self.right = None
        if cap.color:
            self.color = CameraStream(session, keys, "color", self.model, "rgb8", jpeg_quality=cap.jpeg_quality)
        if cap.depth:  # aligned to colour: same optical frame
            self.depth = CameraStream(session, keys, "depth", self.model, "16UC1", frame_id=color_frame)
        if cap.stereo:
            self.left = CameraStream(session, keys, "left", self.model, "mono8", frame_id=color_frame)
            right_model = CameraModel(w, h, fx, fy, cx, cy, (0.0,) * 5, -fx * camera_cfg.stereo_baseline_m)
            self.right = CameraStream(session, keys, "right", right_model, "mono8")
        self._streams = [s for s in (self.color, self.depth, self.left, self.right) if s is not None]
        self._tf = TfPublisher(session, keys) if cap.tf else None
        self.frames_published = 0
        self.frames_skipped = 0
        self.last_T_world_camera: Transform | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ publishing

    @property
    def keys(self) -> list[str]:
        """Every key this publisher sends on."""
        out = [k for s in self._streams for k in (s.image_key, s.info_key)]
        if self._tf is not None:
            out.append(self._tf.key)
        return out

    def publish_at(self, stamp_ns: int, T_world_body: Transform) -> Transform:  # noqa: N803
        """Render from ``T_world_body`` and publish every enabled stream stamped ``stamp_ns``.

        Returns the exact camera pose ``T_world_camera`` rendered from.
        """
        T_world_camera = T_world_body @ self.T_body_camera  # noqa: N806
        frame = self.renderer.render(T_world_camera)
        if self.color is not None:
            self.color.publish(stamp_ns, frame.color_rgb)
        if self.depth is not None:
            self.depth.publish(stamp_ns, frame.depth_mm)
        if self.left is not None and self.right is not None:
            self.left.publish(stamp_ns, cv2.cvtColor(frame.color_rgb, cv2.COLOR_RGB2GRAY))
            right = self.renderer.render(T_world_camera @ self.T_left_right).color_rgb
            self.right.publish(stamp_ns, cv2.cvtColor(right, cv2.COLOR_RGB2GRAY))
        if self._tf is not None:
            ns = self._keys.namespace
            self._tf.publish(
                stamp_ns,
                [
                    (f"{ns}/base_link", optical_frame_id(self._keys, "color"), self.T_body_camera),
                    ("world", f"{ns}/camera_gt", T_world_camera),
                ],
            )
        with self._cond:
            self.frames_published += 1
            self.last_T_world_camera = T_world_camera
            self._cond.notify_all()
        return T_world_camera

    @property
    def has_subscribers(self) -> bool:
        """Whether every image stream has a subscriber (e.g. a recorder) right now."""
        return all(s.has_subscribers for s in self._streams)

    def wait_frames(self, count: int, timeout_s: float) -> int:
        """Block until at least ``count`` frames were published (wall-clock timeout); returns the count.

        Raises:
            CaptureError: not reached within ``timeout_s``, or the publisher thread failed.
        """
        with self._cond:
            ok = self._cond.wait_for(lambda: self.frames_published >= count or self.error is not None, timeout_s)
            if self.error is not None:
                raise CaptureError(f"the simulated camera stopped: {self.error}") from self.error
            if not ok:
                raise CaptureError(
                    f"the simulated camera published {self.frames_published} of {count} frames within "
                    f"{timeout_s:g} s; is the clock running?"
                )
            return self.frames_published

    # ------------------------------------------------------------------ thread

    def start(self) -> Self:
        """Start publishing on a thread; returns immediately."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="sim-camera", daemon=True)
            self._thread.start()
            logger.info(
                "simulated camera publishing %dx%d at %g Hz on %s",
                self.model.width_px, self.model.height_px, self.rate_hz, ", ".join(self.keys),
            )
        return self

    def stop(self) -> None:
        """Stop the thread and undeclare the publishers; idempotent."""
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None:
            t.join(timeout=5.0)  # its waits end within 50 ms of the stop flag (clock.sleep_until)
        for s in self._streams:
            s.close()
        if self._tf is not None:
            self._tf.close()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        lockstep = not math.isfinite(self._clock.speed)  # lock-step time waits for us: never skip
        t0 = self._clock.monotonic_s()
        n = 0  # index of the next due frame; due times are t0 + n * period (no drift from sums)
        try:
            while not self._stop.is_set():
                sleep_until(self._clock, t0 + n * period, self._stop)
                if self._stop.is_set():
                    break
                stamp_ns, T_world_body = self._truth()  # noqa: N806
                self.publish_at(stamp_ns, T_world_body)
                n += 1
                behind = self._clock.monotonic_s() - (t0 + n * period)
                if behind > period and not lockstep:
                    skip = int(behind / period)
                    if self.frames_skipped == 0:
                        logger.warning(
                            "simulated camera cannot render %g frames/s at this clock speed; skipping frames "
                            "(lower the resolution, the rate or the sim speed)", self.rate_hz * self._clock.speed,
                        )
                    self.frames_skipped += skip
                    n += skip
        except Exception as exc:  # publishing on a closed session, renderer failure
            if not self._stop.is_set():
                logger.exception("simulated camera stopped")
                with self._cond:
                    self.error = exc
                    self._cond.notify_all()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


class SimCameraService:
    """A :class:`SimCameraPublisher` with the Zenoh session it opened; :meth:`stop` closes both."""

    def __init__(self, session: zenoh.Session, publisher: SimCameraPublisher) -> None:
        self.session = session
        self.publisher = publisher

    def stop(self) -> None:
        self.publisher.stop()
        self.session.close()


def start_sim_camera(lab: object, lab_cfg: object) -> SimCameraService:
    """Start publishing the camera of a running :class:`~flightkit.sim.lab.SimLab` on the bus
    (session from ``lab_cfg.bus``, streams from ``[camera]`` and ``[capture]``); returns immediately.

    Raises:
        BusError: the session cannot be opened. CaptureError: no stream is enabled.
    """
    from flightkit.bus.session import open_session
    from flightkit.config import LabConfig
    from flightkit.sim.lab import SimLab

    assert isinstance(lab, SimLab) and isinstance(lab_cfg, LabConfig)
    clock = lab.clock
    session = open_session(lab_cfg.bus)
    try:
        pub = SimCameraPublisher(
            session, Keys(lab_cfg.vehicle.namespace), lambda: (clock.time_ns(), lab.T_world_body()),
            lab_cfg.camera, clock, capture_cfg=lab_cfg.section("capture", CaptureConfig),
        ).start()
    except BaseException:
        session.close()
        raise
    return SimCameraService(session, pub)
