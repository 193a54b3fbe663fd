"""The simulator as a motion-capture system: a :class:`~flightkit.mocap.base.MocapSource` in-process.

:class:`SimMocapSource` samples the ground truth of a :class:`~flightkit.sim.lab.SimLab` at
``rate_hz`` on the lab's clock (so it runs as fast as the simulation), the way a Vicon or
OptiTrack system samples the real vehicle, and hands out :class:`MocapPose` values in the
world frame. It needs no bus: flight code in the same process (tests, examples,
``flightkit fly --connect sim``) uses it exactly like any other source.

Faults can be injected on demand, like a lab's real trouble:

* :meth:`SimMocapSource.drop_for`: the stream goes silent for a while (network hiccup);
  frame numbers keep counting, so ``seq`` shows the gap.

Frame numbers follow the lab clock, as a real camera system's do (frame n is exposed at
``n / rate_hz`` after the start): when the sampling thread is starved (a loaded machine),
the frames it could not take show as a gap in ``seq``, not as a slower rate.
* :meth:`SimMocapSource.hide_body` / :meth:`~SimMocapSource.show_body`: the body is occluded;
  frames keep coming, flagged ``valid=False`` with the last tracked pose.

Example::

    with SimLab(autopilot="px4", clock=SimClock(speed=5)) as lab:
        async with SimMocapSource(lab, body="uav1", rate_hz=120) as mocap:
            pose = await mocap.wait_for_body("uav1", timeout_s=2.0)

The sampling runs on its own thread (a real mocap driver does too), so a busy event loop
does not delay the samples; each pose's ``received_s`` is the lab clock's ``monotonic_s``
when it was produced, the same clock the flight runner measures staleness with.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
from collections.abc import AsyncIterator, Callable, Mapping
from types import TracebackType
from typing import TYPE_CHECKING, Self

import numpy as np

from flightkit.errors import MocapBodyMissing
from flightkit.frames import Transform
from flightkit.mocap.base import MocapPose

if TYPE_CHECKING:
    from flightkit.sim.lab import SimLab

__all__ = ["SimMocapSource"]

logger = logging.getLogger(__name__)

_QUEUE_SIZE = 64


class _Subscriber:
    __slots__ = ("body", "loop", "queue")

    def __init__(self, body: str | None, loop: asyncio.AbstractEventLoop) -> None:
        self.body = body
        self.loop = loop
        self.queue: asyncio.Queue[MocapPose] = asyncio.Queue(_QUEUE_SIZE)


def _put_drop_oldest(queue: asyncio.Queue[MocapPose], pose: MocapPose) -> None:
    if queue.full():
        try:
            queue.get_nowait()
        except asyncio.QueueEmpty:  # pragma: no cover - raced with the consumer
            pass
    queue.put_nowait(pose)


class SimMocapSource:
    """Mocap poses of a simulated vehicle (and optional static bodies).

    Args:
        lab: the simulated lab; its clock drives the sampling and stamps.
        body: rigid-body name of the vehicle.
        rate_hz: frames per second of (lab clock) time.
        noise_m: standard deviation of white position noise, metres (per axis).
        seed: seed of the noise generator (reproducible runs).
        T_world_mocap: the calibration the source applies to map the mocap system's frame into
            the world (what ``mocap.T_world_mocap`` in config holds).
        true_T_world_mocap: where the mocap frame really is (default: ``T_world_mocap``);
            give a different one to simulate a calibration error.
        static_bodies: other rigid bodies in the room, name -> fixed ``T_world_body``.

    Use as ``async with source:`` (or ``with source:`` / :meth:`start` and :meth:`stop`).
    """

    def __init__(
        self,
        lab: SimLab,
        body: str = "uav1",
        rate_hz: float = 120.0,
        noise_m: float = 0.0,
        seed: int = 0,
        T_world_mocap: Transform | None = None,
        *,
        true_T_world_mocap: Transform | None = None,
        static_bodies: Mapping[str, Transform] | None = None,
    ) -> None:
        if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 2000.0):
            raise ValueError(f"simulated mocap rate {rate_hz!r} Hz is outside 1-2000 Hz; pick e.g. 120")
        if not (math.isfinite(noise_m) and noise_m >= 0.0):
            raise ValueError(f"simulated mocap noise {noise_m!r} m must be >= 0")
        self.lab = lab
        self.clock = lab.clock
        self.body = body
        self.rate_hz = float(rate_hz)
        self.noise_m = float(noise_m)
        self.T_world_mocap = T_world_mocap or Transform.identity()
        true = true_T_world_mocap or self.T_world_mocap
        # truth (world) -> what the mocap system measures (its frame) -> what we report (world)
        self._T_report_truth = self.T_world_mocap @ true.inverse()
        self._identity = self._T_report_truth.almost_equal(Transform.identity(), 1e-12, 1e-12)
        self._static = dict(static_bodies or {})
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._latest: dict[str, MocapPose] = {}
        self._seen: list[str] = []
        self._subs: list[_Subscriber] = []
        self._frame = 0
        self._t0_s = 0.0
        self._hidden = False
        self._drop_until_s = -math.inf
        self._last_tracked: Transform | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._changed = threading.Condition(self._lock)
        self.hooks: list[Callable[[MocapPose], None]] = []
        """Called with every pose of the vehicle on the sampling thread just before consumers can
        see it (benchmarks time the path from sample to setpoint with it); keep them quick."""
        self.frames_published = 0
        self.frames_dropped = 0

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> SimMocapSource:
        """Start sampling on a background thread; returns immediately (idempotent)."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"sim-mocap-{self.body}", daemon=True)
            self._thread.start()
            logger.info("simulated mocap: %r at %.0f Hz, noise %.4f m", self.body, self.rate_hz, self.noise_m)
        return self

    def stop(self) -> None:
        """Stop sampling; idempotent. Blocks until the thread has ended (at most ~1 frame)."""
        thread = self._thread
        if thread is None:
            return
        self._stop.set()
        thread.join(5.0)
        self._thread = None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    async def __aenter__(self) -> Self:
        self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await asyncio.to_thread(self.stop)

    # ------------------------------------------------------------------ faults

    def drop_for(self, duration_s: float) -> None:
        """Publish nothing for ``duration_s`` of lab clock time from now; returns immediately."""
        if not duration_s >= 0.0:
            raise ValueError(f"dropout duration {duration_s!r} s must be >= 0")
        with self._lock:
            self._drop_until_s = self.clock.monotonic_s() + duration_s
        logger.info("simulated mocap: dropping frames for %.2f s", duration_s)

    def hide_body(self) -> None:
        """The vehicle's markers are occluded: frames say ``valid=False`` until :meth:`show_body`."""
        with self._lock:
            self._hidden = True

    def show_body(self) -> None:
        """The vehicle is tracked again."""
        with self._lock:
            self._hidden = False

    @property
    def dropping(self) -> bool:
        """True while a :meth:`drop_for` dropout lasts."""
        return self.clock.monotonic_s() < self._drop_until_s

    # ------------------------------------------------------------------ MocapSource

    def bodies(self) -> tuple[str, ...]:
        """Names of the bodies seen so far; returns immediately."""
        with self._lock:
            return tuple(self._seen)

    def latest(self, body: str) -> MocapPose | None:
        """Newest pose of ``body`` (None if never seen); returns immediately."""
        return self._latest.get(body)

    async def wait_for_body(self, body: str, timeout_s: float) -> MocapPose:
        """Wait until ``body`` has a valid pose newer than the call, for up to ``timeout_s`` of clock time.

        Raises:
            MocapBodyMissing: not seen (or never valid) in time; names the bodies that are visible.
        """
        clock = self.clock
        deadline = clock.monotonic_s() + timeout_s
        period = 1.0 / self.rate_hz
        while True:
            pose = self._latest.get(body)
            if (
                pose is not None
                and pose.valid
                and clock.monotonic_s() - pose.received_s <= 2.0 * period + 0.05
            ):
                return pose
            if clock.monotonic_s() >= deadline:
                raise MocapBodyMissing(body, self.bodies())
            await clock.sleep(min(period, max(0.0, deadline - clock.monotonic_s())))

    async def poses(self, body: str | None = None) -> AsyncIterator[MocapPose]:
        """New poses of ``body`` (or of every body), as they are produced.

        A slow consumer loses the oldest poses (the queue holds 64); the iterator never ends
        on its own: break out of it or cancel the task.
        """
        sub = _Subscriber(body, asyncio.get_running_loop())
        with self._lock:
            self._subs.append(sub)
        try:
            while True:
                yield await sub.queue.get()
        finally:
            with self._lock:
                if sub in self._subs:
                    self._subs.remove(sub)

    # ------------------------------------------------------------------ sampling

    def _run(self) -> None:
        clock = self.clock
        period = 1.0 / self.rate_hz
        next_s = self._t0_s = clock.monotonic_s()
        while not self._stop.is_set():
            now = clock.monotonic_s()
            try:
                self._sample(now)
            except Exception:  # the sampler must survive anything (e.g. the lab stopping)
                logger.exception("simulated mocap sample failed")
            next_s += period
            now = clock.monotonic_s()
            if next_s < now - 5 * period:  # fell far behind (machine busy): skip, keep the rate
                next_s = now
            clock.sleep_blocking(max(0.0, next_s - now))

    def _measure(self, now_s: float) -> Transform:
        T = self.lab.T_world_body(now_s)
        if not self._identity:
            T = self._T_report_truth @ T
        if self.noise_m > 0.0:
            T = Transform(T.rotation, T.translation + self._rng.normal(0.0, self.noise_m, 3))
        return T

    def _sample(self, now_s: float) -> None:
        stamp_ns = self.clock.time_ns()
        with self._lock:
            # the frame the mocap system exposes now (1 at the start); never repeat one
            frame = max(self._frame + 1, 1 + int((now_s - self._t0_s) * self.rate_hz + 1e-6))
            skipped, self._frame = frame - self._frame, frame
            seq = frame
            if now_s < self._drop_until_s:
                self.frames_dropped += skipped
                return
            hidden = self._hidden
        if hidden:
            last = self._last_tracked
            if last is None:
                return  # never tracked: the system does not know the body yet
            poses = [MocapPose(stamp_ns, self.body, last, False, seq, now_s)]
        else:
            T = self._measure(now_s)
            self._last_tracked = T
            poses = [MocapPose(stamp_ns, self.body, T, True, seq, now_s)]
        for name, T_static in self._static.items():
            poses.append(MocapPose(stamp_ns, name, T_static, True, seq, now_s))
        self._publish(poses)

    def _publish(self, poses: list[MocapPose]) -> None:
        for hook in self.hooks:
            for p in poses:
                if p.body == self.body:
                    try:
                        hook(p)
                    except Exception:
                        logger.exception("simulated mocap hook %r failed", hook)
        with self._lock:
            for p in poses:
                if p.body not in self._latest:
                    self._seen.append(p.body)
                self._latest[p.body] = p
            subs = list(self._subs)
            self.frames_published += 1
        for p in poses:
            for sub in subs:
                if sub.body is not None and sub.body != p.body:
                    continue
                try:
                    sub.loop.call_soon_threadsafe(_put_drop_oldest, sub.queue, p)
                except RuntimeError:  # the consumer's loop is closed
                    with self._lock:
                        if sub in self._subs:
                            self._subs.remove(sub)

    def __repr__(self) -> str:
        state = "running" if self._thread is not None else "stopped"
        return f"SimMocapSource({self.body!r}, {self.rate_hz:g} Hz, {state})"
