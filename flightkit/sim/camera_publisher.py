"""The simulated camera as a bus publisher, like a real camera driver.

:class:`SimCameraPublisher` renders the simulated lab (:mod:`flightkit.sim.camera`) from the
vehicle's ground-truth pose at the configured rate on the injected clock and publishes::

    <ns>/camera/color/image        sensor_msgs/Image rgb8          + <ns>/camera/color/camera_info
    <ns>/camera/depth/image        sensor_msgs/Image 16UC1 (mm)    + <ns>/camera/depth/camera_info
    <ns>/camera/left|right/image   sensor_msgs/Image mono8 (rectified pair; ``streams.stereo``)
    <ns>/tf                        tf2_msgs/TFMessage: base_link -> camera (extrinsics) and
                                   world -> camera_gt (the exact pose each frame was rendered from)

Depth is aligned to colour (same camera). The camera pose is ``T_world_body @ T_body_camera``
with the extrinsics from ``[camera] T_body_camera``; the image stamp is the truth stamp, so
the ground truth is exact. For calibration tests, ``timing`` makes the camera's clock late and
fast (:class:`~flightkit.sim.timing_errors.SimTimingErrors`: every stamp, images and tf alike,
is ``camera_stamp_ns`` of the capture time) and ``true_T_body_camera`` renders from a mount other
than the configured one, which is still what tf announces.

Timing: frames are due every ``1 / rate_hz`` of clock time. Rendering costs real time
(about 25 ms at 320x240 and 200 ms at 640x480 on a laptop core), so when the clock runs
faster than the renderer the publisher skips the frames it could not render (counted in
:attr:`SimCameraPublisher.frames_skipped`) rather than fall behind; with ``render_budget_s`` a
stall-limited :class:`~flightkit.clock.SimClock` waits for each frame instead (a camera that
never drops a frame, as a closed loop on live VO wants, at the cost of wall time). Under a
:class:`~flightkit.clock.LockstepClock` time stands still while rendering, so every due
frame is published exactly.
"""
from __future__ import annotations

import logging
import math
import threading
from typing import Any, Self

import cv2
import numpy as np
import zenoh

from flightkit.bus.keys import Keys
from flightkit.bus.pubsub import STAMP_DEVICE
from flightkit.bus.streams import CameraModel, CameraStream, CameraStreamSelection, TfPublisher, optical_frame_id
from flightkit.clock import Clock, sleep_until
from flightkit.config import CameraConfig
from flightkit.errors import BusError
from flightkit.frames import WORLD_FRAME_ID, Transform
from flightkit.lifetime import Running
from flightkit.sim.camera import PinholeModel, Scene, SimCamera
from flightkit.sim.mocap import TruthFn
from flightkit.sim.timing_errors import SimTimingErrors

__all__ = ["SimCameraPublisher"]

logger = logging.getLogger(__name__)


class SimCameraPublisher(Running):
    """Publish simulated camera streams on the bus.

    Args:
        session: an open Zenoh session.
        keys: the vehicle's namespace.
        truth: clock time -> the vehicle's true ``T_world_body``, e.g. ``lab.T_world_body``.
        camera_cfg: resolution (320x240 to 848x480 in practice), rate, intrinsics, extrinsics.
        clock: the simulation's clock (the rate is in its time; frames are stamped with it).
        streams: which streams (colour, depth, stereo, tf, JPEG); defaults when None.
        scene: what to render (default: the lab with textured boxes).
        timing: the camera clock's offset and drift (default: none).
        true_T_body_camera: the mount rendered from (default: the configured one).
        render_budget_s: simulated time a frame's rendering may take; the clock waits for a
            slower host (see :meth:`flightkit.clock.SimClock.busy`). None: skip late frames.

    Use :meth:`start`/:meth:`stop` (or ``with``); :meth:`publish_at` renders and publishes
    one frame synchronously (for scripted tests).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        truth: TruthFn,
        camera_cfg: CameraConfig,
        clock: Clock,
        *,
        streams: CameraStreamSelection | None = None,
        scene: Scene | None = None,
        timing: SimTimingErrors | None = None,
        true_T_body_camera: Transform | None = None,  # noqa: N803
        render_budget_s: float | None = None,
    ) -> None:
        cap = streams or CameraStreamSelection()
        if not (cap.color or cap.depth or cap.stereo):
            raise BusError("no camera stream enabled; set capture.color, capture.depth or capture.stereo to true")
        self._truth = truth
        self._clock = clock
        self.render_budget_s = render_budget_s
        self._keys = keys
        self.rate_hz = camera_cfg.rate_hz
        self.T_body_camera = camera_cfg.T_body_camera.to_transform()
        self.true_T_body_camera = true_T_body_camera or self.T_body_camera
        self.timing = timing or SimTimingErrors()
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
        # the camera's own capture stamps (true exposure time on its late, drifting clock); bus time from the clock
        stamping: dict[str, Any] = {"clock": clock, "stamp_source": STAMP_DEVICE}
        if cap.color:
            self.color = CameraStream(session, keys, "color", self.model, "rgb8", jpeg_quality=cap.jpeg_quality,
                                      **stamping)
        if cap.depth:  # aligned to colour: same optical frame
            self.depth = CameraStream(session, keys, "depth", self.model, "16UC1", frame_id=color_frame, **stamping)
        if cap.stereo:
            self.left = CameraStream(session, keys, "left", self.model, "mono8", frame_id=color_frame, **stamping)
            right_model = CameraModel(w, h, fx, fy, cx, cy, (0.0,) * 5, -fx * camera_cfg.stereo_baseline_m)
            self.right = CameraStream(session, keys, "right", right_model, "mono8", **stamping)
        self._streams = [s for s in (self.color, self.depth, self.left, self.right) if s is not None]
        self._tf = TfPublisher(session, keys, clock, STAMP_DEVICE) if cap.tf else None
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
        T_world_camera = T_world_body @ self.true_T_body_camera  # noqa: N806
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
                    (WORLD_FRAME_ID, f"{ns}/camera_gt", T_world_camera),
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
            BusError: not reached within ``timeout_s``, or the publisher thread failed.
        """
        with self._cond:
            ok = self._cond.wait_for(lambda: self.frames_published >= count or self.error is not None, timeout_s)
            if self.error is not None:
                raise BusError(f"the simulated camera stopped: {self.error}") from self.error
            if not ok:
                raise BusError(
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
        start_ns = self._clock.time_ns()  # the camera clock's own start (its drift counts from here)
        n = 0  # index of the next due frame; due times are t0 + n * period (no drift from sums)
        try:
            while not self._stop.is_set():
                sleep_until(self._clock, t0 + n * period, self._stop)
                if self._stop.is_set():
                    break
                now_s = self._clock.monotonic_s()
                stamp_ns = self.timing.camera_stamp_ns(self._clock.time_ns(), start_ns)
                if self.render_budget_s is None:
                    self.publish_at(stamp_ns, self._truth(now_s))
                else:
                    with self._clock.busy(self.render_budget_s):
                        self.publish_at(stamp_ns, self._truth(now_s))
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
