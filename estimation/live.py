"""Live visual odometry: camera frames from the bus in, odometry and vision poses out.

:class:`LiveVo` subscribes to a vehicle's colour and depth images and the colour
``camera_info`` (``<ns>/camera/color/image``, ``<ns>/camera/depth/image``,
``<ns>/camera/color/camera_info``; the camera's rolling-shutter readout is asked for on its
``calibration`` key, :mod:`flightkit.bus.camera_calibration`), pairs colour and depth by stamp, and runs
:class:`~estimation.pipeline.VisualOdometry` on its own thread, one frame at a time. When the
estimator falls behind, it works on the newest pair and drops the older ones (counted in
:attr:`LiveVoStats.frames_dropped`), so its output never lags by more than one frame.

Each estimate is

* published on the bus as ``geometry_msgs/PoseStamped`` on ``<ns>/odometry/<method>``
  (``T_world_body``, frame_id ``"world"``, stamped with the frame's capture time), and
* when a :class:`~flightkit.link.base.VehicleLink` is given, sent to the autopilot with
  :meth:`~flightkit.link.base.VehicleLink.send_vision_pose` (VISION_POSITION_ESTIMATE or
  ODOMETRY), at most ``vision_rate_hz`` times a second, stamped with the frame's capture time
  and with a covariance from the estimate's quality and inlier count
  (:func:`~estimation.live_config.vision_uncertainty`).

Frames: the estimate lives in the world frame because the VO starts at a known pose of the
body (:meth:`LiveVo.start`, normally the mocap pose at that moment):
``T_world_camera0 = T_world_body0 @ T_body_camera``, and every later body pose is
``T_world_body = T_world_camera @ T_body_camera^-1``.

Threads: Zenoh delivers samples on its threads (they only store the payload); the VO runs
on one worker thread; the vision sender runs as a task on the asyncio loop that entered
``async with LiveVo(...)`` (so the link is only touched from its own loop).

Example::

    async with LiveVo(session, Keys("uav1"), clock, T_body_camera=T_bc, link=link) as vo:
        vo.start(mocap.latest("uav1").T_world_body)
        ...
        print(vo.stats().format())
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Self

import cv2
import numpy as np
import numpy.typing as npt

from estimation.live_config import LiveVoConfig, external_pose_from_frame
from estimation.live_inputs import FramePairer, intrinsics_from_camera_info
from estimation.pipeline import FramePose, Method, VisualOdometry, VoOptions, warm_up
from flightkit.bus.camera_calibration import ask_calibration, calibration_key
from flightkit.bus.image_msgs import CameraInfo, Image
from flightkit.bus.keys import Keys
from flightkit.bus.pose_msgs import PoseStamped
from flightkit.bus.streams import check_readout_s
from flightkit.clock import Clock
from flightkit.datasets.base import CameraIntrinsics
from flightkit.errors import BusError, EstimationError
from flightkit.frames import Transform
from flightkit.link.base import ExternalPose, VehicleLink

__all__ = [
    "LiveVo",
    "LiveVoStats",
]

logger = logging.getLogger(__name__)

WORLD_FRAME_ID = "world"


# ---------------------------------------------------------------------------------- pure parts


class _Throttle:
    """At most one event per ``1 / rate_hz`` of clock time."""

    __slots__ = ("_last_s", "period_s")

    def __init__(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz
        self._last_s = -math.inf

    def wait_s(self, now_s: float) -> float:
        """Seconds until the next event is allowed (0 when it is now)."""
        return max(0.0, self._last_s + 0.98 * self.period_s - now_s)

    def mark(self, now_s: float) -> None:
        self._last_s = now_s


# ---------------------------------------------------------------------------------- stats


@dataclass(frozen=True, slots=True)
class LiveVoStats:
    """Counters of a :class:`LiveVo` run.

    Attributes:
        pairs_received: colour+depth pairs complete while estimating.
        frames_processed: pairs the VO processed.
        frames_dropped: pairs skipped because the VO was busy (it always takes the newest).
        unmatched: colour or depth frames that never found their partner.
        vision_sent: poses sent to the autopilot; vision_rate_hz: their rate over the run.
        mean_ms, p95_ms: VO wall time per frame.
        latency_ms: mean clock time from capture stamp to the estimate being ready.
        quality: frames per :class:`~estimation.pipeline.Quality` name.
    """

    pairs_received: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0
    unmatched: int = 0
    vision_sent: int = 0
    vision_rate_hz: float = 0.0
    mean_ms: float = math.nan
    p95_ms: float = math.nan
    latency_ms: float = math.nan
    quality: dict[str, int] = field(default_factory=dict)

    def format(self) -> str:
        q = ", ".join(f"{k.lower()} {v}" for k, v in sorted(self.quality.items()))
        return (
            f"VO frames {self.frames_processed} processed, {self.frames_dropped} dropped "
            f"({self.pairs_received} pairs, {self.unmatched} unmatched); "
            f"{self.mean_ms:.1f} ms/frame (p95 {self.p95_ms:.1f}), latency {self.latency_ms:.0f} ms; "
            f"vision {self.vision_sent} sent, {self.vision_rate_hz:.1f}/s; quality: {q or '-'}"
        )


# ---------------------------------------------------------------------------------- LiveVo


class LiveVo:
    """Visual odometry on live bus frames, feeding the bus and (optionally) the autopilot.

    Args:
        session: an open Zenoh session (the camera's bus).
        keys: the vehicle's namespace.
        clock: the clock of the flight (vision timing, latency).
        T_body_camera: camera mounting (OpenCV camera in the FLU body).
        link: a connected vehicle link to feed with vision poses (None: bus output only).
        config: :class:`LiveVoConfig`.
        options: VO tuning (:class:`~estimation.pipeline.VoOptions`).

    Use ``async with`` (subscribes, starts the worker and the sender); nothing is estimated
    until :meth:`start` gives the start pose.

    Raises:
        EstimationError: a bad configuration.
    """

    def __init__(
        self,
        session: Any,
        keys: Keys,
        clock: Clock,
        *,
        T_body_camera: Transform,  # noqa: N803
        link: VehicleLink | None = None,
        config: LiveVoConfig | None = None,
        options: VoOptions | None = None,
    ) -> None:
        self.config = config or LiveVoConfig()
        self.session = session
        self.keys = keys
        self.clock = clock
        self.T_body_camera = T_body_camera
        self.link = link
        self.options = options
        self.method = Method(self.config.method)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._pairer = FramePairer(self.config.pair_tolerance_ns)
        self._pending: tuple[int, bytes, bytes] | None = None
        self._intrinsics: CameraIntrinsics | None = None
        self._asking_camera = False  # the camera's calibration (its readout) was asked for
        self._initial: Callable[[int], Transform | None] | None = None
        self._vo: VisualOdometry | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._subs: list[Any] = []
        self._pub: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._sender: asyncio.Task[None] | None = None
        self._new_estimate: asyncio.Event | None = None
        self._to_send: ExternalPose | None = None
        self._depth_buf: npt.NDArray[np.float32] | None = None
        # results
        self._estimates: list[tuple[int, npt.NDArray[np.float64]]] = []
        self._latest: FramePose | None = None
        self._pairs = 0
        self._dropped = 0
        self._processed = 0
        self._ms: list[float] = []
        self._latency_s: list[float] = []
        self._quality: collections.Counter[str] = collections.Counter()
        self._sent = 0
        self._first_sent_s = math.nan
        self._last_sent_s = math.nan
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> Self:
        from flightkit.bus.pubsub import BusPublisher, BusSubscriber

        cfg = self.config
        self._loop = asyncio.get_running_loop()
        self._new_estimate = asyncio.Event()
        # Load (or, once after an install, compile) the VO's kernels now, off the event loop,
        # rather than on the first live frame while the camera streams on.
        t0 = time.perf_counter()
        await asyncio.to_thread(warm_up, self.method)
        logger.debug("live VO %s: kernels ready in %.2f s", self.method.value, time.perf_counter() - t0)
        try:
            self._subs = [
                BusSubscriber(self.session, self.keys.camera_info(cfg.color_camera), callback=self._on_info),
                BusSubscriber(
                    self.session, self.keys.camera_image(cfg.color_camera), callback=self._on_color
                ),
                BusSubscriber(
                    self.session, self.keys.camera_image(cfg.depth_camera), callback=self._on_depth
                ),
            ]
            if cfg.publish_odometry:
                self._pub = BusPublisher(
                    self.session,
                    self.keys.odometry(self.method.value),
                    PoseStamped,
                    reliable=True,
                    express=True,
                )
        except BaseException:
            self._close_bus()
            raise
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"live-vo-{self.method.value}", daemon=True)
        self._thread.start()
        if self.link is not None:
            self._sender = self._loop.create_task(self._send_loop(), name="live-vo-vision")
        logger.info(
            "live VO %s on %s + %s%s",
            self.method.value,
            self.keys.camera_image(cfg.color_camera),
            self.keys.camera_image(cfg.depth_camera),
            f", feeding the autopilot at <= {cfg.vision_rate_hz:g} Hz" if self.link is not None else "",
        )
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Stop estimating and sending, unsubscribe; idempotent."""
        if self._sender is not None:
            self._sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._sender
            self._sender = None
        self._close_bus()
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        thread, self._thread = self._thread, None
        if thread is not None:
            await asyncio.to_thread(thread.join, 5.0)

    def _close_bus(self) -> None:
        for sub in self._subs:
            sub.close()
        self._subs = []
        if self._pub is not None:
            self._pub.close()
            self._pub = None

    def start(self, initial_pose: Transform | Callable[[int], Transform | None]) -> None:
        """Start estimating from the next frame pair; returns immediately.

        Args:
            initial_pose: ``T_world_body`` of the first frame: a fixed pose (the body must be
                still), or a function of the first frame's stamp (ns) returning the body pose
                then (e.g. looked up in the mocap history), or None to wait for a later frame.
        """
        fn: Callable[[int], Transform | None]
        fn = (lambda _stamp: initial_pose) if isinstance(initial_pose, Transform) else initial_pose
        with self._cond:
            self._initial = fn
            self._cond.notify_all()

    @property
    def camera(self) -> CameraIntrinsics | None:
        """The camera's intrinsics (with its rolling-shutter readout) once its camera_info and
        calibration are in; None before."""
        with self._lock:
            return self._intrinsics

    @property
    def started(self) -> bool:
        """True once the VO has produced its first estimate."""
        return self._vo is not None

    # ------------------------------------------------------------------ results

    @property
    def latest(self) -> FramePose | None:
        """The newest estimate (None before the first)."""
        return self._latest

    def estimates(self) -> list[tuple[int, Transform]]:
        """Every estimate so far as ``(capture stamp_ns, T_world_body)``, oldest first."""
        with self._lock:
            items = list(self._estimates)
        return [(s, Transform.from_matrix(m)) for s, m in items]

    def stats(self) -> LiveVoStats:
        """Counters so far; returns immediately."""
        with self._lock:
            ms = sorted(self._ms)
            lat = list(self._latency_s)
            rate = 0.0
            if self._sent > 1 and self._last_sent_s > self._first_sent_s:
                rate = (self._sent - 1) / (self._last_sent_s - self._first_sent_s)
            return LiveVoStats(
                pairs_received=self._pairs,
                frames_processed=self._processed,
                frames_dropped=self._dropped,
                unmatched=self._pairer.unmatched,
                vision_sent=self._sent,
                vision_rate_hz=rate,
                mean_ms=float(np.mean(ms)) if ms else math.nan,
                p95_ms=ms[min(len(ms) - 1, int(0.95 * len(ms)))] if ms else math.nan,
                latency_ms=float(np.mean(lat)) * 1e3 if lat else math.nan,
                quality=dict(self._quality),
            )

    # ------------------------------------------------------------------ Zenoh threads

    def _on_info(self, s: Any) -> None:
        with self._lock:
            if self._intrinsics is not None or self._asking_camera:
                return
        try:
            intr = intrinsics_from_camera_info(CameraInfo.decode(s.payload))
        except Exception:
            logger.exception("live VO: cannot use the camera_info on %s", s.key)
            return
        with self._lock:
            if self._asking_camera:
                return
            self._asking_camera = True
        # CameraInfo has no rolling-shutter readout: the camera serves it on its calibration key.
        try:
            key = calibration_key(str(s.key))
        except BusError:
            self._use_camera(intr, {})
            return
        ask_calibration(self.session, key, lambda fields: self._use_camera(intr, fields))

    def _use_camera(self, intr: CameraIntrinsics, fields: dict[str, str]) -> None:
        """Zenoh thread: the camera's calibration answer is in (``{}``: none): its ``readout_s``
        joins the camera_info's intrinsics (``VoOptions.readout_s`` still overrides it)."""
        if "readout_s" in fields:
            try:
                intr = dataclasses.replace(intr, readout_s=check_readout_s(fields["readout_s"]))
            except BusError as exc:
                logger.warning("live VO: ignoring the camera's readout: %s", exc)
        with self._cond:
            self._intrinsics = intr
            self._cond.notify_all()
        logger.info(
            "live VO: camera %dx%d, fx %.1f px, %s",
            intr.width,
            intr.height,
            intr.fx,
            f"rolling shutter {intr.readout_s * 1e3:.3g} ms" if intr.readout_s > 0 else "global shutter",
        )

    def _on_color(self, s: Any) -> None:
        self._add(True, s)

    def _on_depth(self, s: Any) -> None:
        self._add(False, s)

    def _add(self, color: bool, s: Any) -> None:
        stamp = int(s.stamp_ns) or Image.decode(s.payload).header.stamp_ns
        with self._cond:
            if self._initial is None:
                return  # not estimating yet
            pair = (self._pairer.add_color if color else self._pairer.add_depth)(stamp, s.payload)
            if pair is None:
                return
            self._pairs += 1
            if self._pending is not None:
                self._dropped += 1
            self._pending = pair
            self._cond.notify_all()

    # ------------------------------------------------------------------ worker thread

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                while not self._stop.is_set() and (self._pending is None or self._intrinsics is None):
                    self._cond.wait(0.5)
                if self._stop.is_set():
                    return
                assert self._pending is not None
                stamp_ns, color_payload, depth_payload = self._pending
                self._pending = None
            budget_s = self.config.compute_budget_s
            try:
                with contextlib.nullcontext() if budget_s is None else self.clock.busy(budget_s):
                    self._process(stamp_ns, color_payload, depth_payload)
            except Exception as exc:  # keep estimating; a bad frame must not end the flight's VO
                logger.exception("live VO: frame %d failed", stamp_ns)
                self.error = exc

    def _decode(self, color_payload: bytes, depth_payload: bytes) -> tuple[Any, npt.NDArray[np.float32]]:
        color = Image.decode(color_payload)
        arr = color.array()
        if color.encoding in ("rgb8", "rgba8"):
            gray = cv2.cvtColor(arr, cv2.COLOR_RGB2GRAY if color.encoding == "rgb8" else cv2.COLOR_RGBA2GRAY)
        elif color.encoding in ("bgr8", "bgra8"):
            gray = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY if color.encoding == "bgr8" else cv2.COLOR_BGRA2GRAY)
        elif color.encoding == "mono8":
            gray = arr
        else:
            raise EstimationError(
                f"live VO cannot use {color.encoding!r} colour images; publish rgb8, bgr8 or mono8"
            )
        depth = Image.decode(depth_payload)
        darr = depth.array()
        if depth.encoding in ("16UC1", "mono16"):
            buf = self._depth_buf
            if buf is None or buf.shape != darr.shape:
                buf = self._depth_buf = np.empty(darr.shape, np.float32)
            np.multiply(darr, np.float32(0.001), out=buf, casting="unsafe")
            depth_m = buf
        elif depth.encoding == "32FC1":
            depth_m = np.nan_to_num(darr.astype(np.float32), nan=0.0)
        else:
            raise EstimationError(
                f"live VO cannot use {depth.encoding!r} depth; publish 16UC1 (mm) or 32FC1 (m)"
            )
        return gray, depth_m

    def _process(self, stamp_ns: int, color_payload: bytes, depth_payload: bytes) -> None:
        gray, depth_m = self._decode(color_payload, depth_payload)
        if self._vo is None:
            init = self._initial
            T0 = init(stamp_ns) if init is not None else None  # noqa: N806
            if T0 is None:
                return  # no start pose for this frame yet
            intr = self._intrinsics
            assert intr is not None
            self._vo = VisualOdometry(
                self.method,
                intr,
                depth_intrinsics=intr,
                T_body_camera=self.T_body_camera,
                T_world_camera0=T0 @ self.T_body_camera,
                options=self.options,
            )
            logger.info("live VO started at %s", T0)
        t0 = time.perf_counter()
        pose = self._vo.process(stamp_ns, gray, depth_m=depth_m)
        wall_ms = (time.perf_counter() - t0) * 1e3
        latency_s = max(0.0, (self.clock.time_ns() - stamp_ns) * 1e-9)
        with self._lock:
            self._processed += 1
            self._ms.append(wall_ms)
            self._latency_s.append(latency_s)
            self._quality[pose.quality.name] += 1
            self._estimates.append((stamp_ns, pose.T_world_body.copy()))
            self._latest = pose
        if self._pub is not None:
            self._pub.publish(
                PoseStamped.from_transform(stamp_ns, WORLD_FRAME_ID, Transform.from_matrix(pose.T_world_body))
            )
        loop = self._loop
        if self.link is not None and loop is not None and not loop.is_closed():
            ext = external_pose_from_frame(pose, self.config)
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(self._offer, ext)

    # ------------------------------------------------------------------ vision sender (event loop)

    def _offer(self, pose: ExternalPose) -> None:
        self._to_send = pose
        if self._new_estimate is not None:
            self._new_estimate.set()

    async def _send_loop(self) -> None:
        assert self.link is not None and self._new_estimate is not None
        throttle = _Throttle(self.config.vision_rate_hz)
        event = self._new_estimate
        while True:
            await event.wait()
            wait = throttle.wait_s(self.clock.monotonic_s())
            if wait > 0:
                await self.clock.sleep(wait)
            event.clear()
            pose, self._to_send = self._to_send, None
            if pose is None:
                continue
            now = self.clock.monotonic_s()
            try:
                await self.link.send_vision_pose(pose, self.config.kind)
            except Exception:  # a link hiccup must not end the feed
                logger.exception("live VO: sending the vision pose failed")
                continue
            throttle.mark(now)
            with self._lock:
                self._sent += 1
                if self._sent == 1:
                    self._first_sent_s = now
                self._last_sent_s = now
