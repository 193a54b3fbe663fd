"""The simulated motion-capture system: one sampler, served in-process or on the bus.

:class:`SimMocapSystem` samples the true poses of the tracked bodies at ``rate_hz`` of clock
time on its own thread, the way a Vicon or OptiTrack system samples the real vehicles, and
measures them **in the mocap system's own frame** (``T_mocap_body = T_world_mocap^-1 @
T_world_body`` with the *true* ``T_world_mocap``), with optional noise. Every frame goes to
its sinks:

* :class:`SimMocapSource` -- an in-process :class:`~flightkit.mocap.base.MocapSource`; it
  places the samples in the world with the *configured* ``T_world_mocap`` (so a calibration
  error shows, as in a lab). Flight code in the same process (tests, examples,
  ``flightkit fly --connect sim``) uses it like any other source.
* :class:`SimMocapPublisher` -- ``geometry_msgs/PoseStamped`` on ``<ns>/mocap/<body>/pose``
  (``frame_id "mocap"``), exactly as a mocap bridge publishes.

Faults, like a lab's real trouble: :meth:`SimMocapSystem.drop_for` silences the stream for a
while (frame numbers keep counting, so ``seq`` shows the gap); :meth:`SimMocapSystem.hide_body`
reports a body as lost (NaN / ``valid=False``) until :meth:`~SimMocapSystem.show_body`.

Frame numbers follow the clock, as a real camera system's do (frame n is exposed at
``n / rate_hz`` after the start): when the sampling thread is starved (a loaded machine), the
frames it could not take show as a gap in ``seq``, not as a slower rate.

Example::

    with SimLab(autopilot="px4", clock=SimClock(speed=5)) as lab:
        async with SimMocapSource(lab, body="uav1", rate_hz=120) as mocap:
            pose = await mocap.wait_for_body("uav1", timeout_s=2.0)
"""
from __future__ import annotations

import asyncio
import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Self

import numpy as np
import zenoh
from scipy.spatial.transform import Rotation

from flightkit.bus.keys import Keys
from flightkit.bus.pubsub import STAMP_DEVICE
from flightkit.bus.streams import PosePublisher
from flightkit.clock import Clock, sleep_until
from flightkit.errors import MocapError
from flightkit.frames import MOCAP_FRAME_ID, Transform, WorldFrames
from flightkit.lifetime import Running
from flightkit.mocap.base import MocapSample
from flightkit.mocap.source import WorldFrameSource
from flightkit.sim.timing_errors import PoseDelay

if TYPE_CHECKING:
    from flightkit.sim.lab import SimLab

__all__ = ["SimMocapPublisher", "SimMocapSource", "SimMocapSystem", "TruthFn"]

logger = logging.getLogger(__name__)

TruthFn = Callable[[float], Transform]
"""Clock time (``Clock.monotonic_s``) -> the body's true ``T_world_body`` then."""

FrameSink = Callable[[Sequence[MocapSample]], None]
"""Called on the sampling thread with every frame's samples (one per body)."""


class SimMocapSystem(Running):
    """The simulated mocap system (see the module docstring).

    Args:
        clock: paces the sampling and stamps the frames.
        bodies: tracked moving bodies, name -> true pose as a function of clock time.
        T_world_mocap: where the mocap frame truly sits in the world.
        rate_hz: frames per second of clock time.
        noise_m: standard deviation of white position noise per axis, metres.
        noise_rad: standard deviation of attitude noise per axis, radians.
        seed: seed of the noise generator (reproducible runs).
        static_bodies: other rigid bodies in the room, name -> fixed ``T_world_body``.
        latency_s: each frame reaches the host this long after its capture: the pose handed out
            now is the one of ``latency_s`` ago, stamped with its capture time (the system's own
            frame time, as Vicon and Qualisys report it); the bus time is now.

    Raises:
        MocapError: a rate, noise or latency out of range, or no body.
    """

    def __init__(
        self,
        clock: Clock,
        bodies: Mapping[str, TruthFn],
        *,
        T_world_mocap: Transform | None = None,  # noqa: N803
        rate_hz: float = 120.0,
        noise_m: float = 0.0,
        noise_rad: float = 0.0,
        seed: int | None = 0,
        static_bodies: Mapping[str, Transform] | None = None,
        latency_s: float = 0.0,
    ) -> None:
        if not (math.isfinite(latency_s) and 0.0 <= latency_s <= 1.0):
            raise MocapError(f"simulated mocap latency {latency_s!r} s is outside 0-1 s")
        if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 2000.0):
            raise MocapError(f"simulated mocap rate {rate_hz!r} Hz is outside 1-2000 Hz; pick e.g. 120")
        if not (math.isfinite(noise_m) and noise_m >= 0.0 and math.isfinite(noise_rad) and noise_rad >= 0.0):
            raise MocapError(f"simulated mocap noise ({noise_m!r} m, {noise_rad!r} rad) must be >= 0")
        if not bodies and not static_bodies:
            raise MocapError("a simulated mocap system needs at least one body to track")
        self.clock = clock
        self.bodies = dict(bodies)
        self.T_world_mocap = T_world_mocap or Transform.identity()
        self._T_mocap_world = self.T_world_mocap.inverse()
        # a mocap frame on the world frame (the simulated lab's default) measures the truth as it is:
        # composing with the identity costs two scipy rotation operations per body and frame
        self._mocap_is_world = self.T_world_mocap.is_identity
        self.rate_hz = float(rate_hz)
        self.noise_m = float(noise_m)
        self.noise_rad = float(noise_rad)
        self._rng = np.random.default_rng(seed)
        self.latency_s = float(latency_s)
        self._delays = {name: PoseDelay(self.latency_s) for name in self.bodies}
        self._static = {name: self._T_mocap_world @ T for name, T in (static_bodies or {}).items()}
        self.sinks: list[FrameSink] = []
        self._lock = threading.Lock()
        self._frame = 0
        self._t0_s: float | None = None
        self._hidden: set[str] = set()
        self._drop_until_s = -math.inf
        self._tracked: set[str] = set()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._users = 0
        self.frames_published = 0
        self.frames_dropped = 0

    # ------------------------------------------------------------------ faults

    def drop_for(self, duration_s: float) -> None:
        """Publish nothing for ``duration_s`` of clock time from now; returns immediately."""
        if not duration_s >= 0.0:
            raise MocapError(f"dropout duration {duration_s!r} s must be >= 0")
        with self._lock:
            self._drop_until_s = self.clock.monotonic_s() + duration_s
        logger.info("simulated mocap: dropping frames for %.2f s", duration_s)

    def hide_body(self, body: str | None = None) -> None:
        """``body``'s markers are occluded (None: every moving body): its samples say lost until
        :meth:`show_body`."""
        with self._lock:
            self._hidden |= {body} if body is not None else set(self.bodies)

    def show_body(self, body: str | None = None) -> None:
        """``body`` (None: every body) is tracked again."""
        with self._lock:
            self._hidden -= {body} if body is not None else set(self._hidden)

    @property
    def dropping(self) -> bool:
        """True while a :meth:`drop_for` dropout lasts."""
        return self.clock.monotonic_s() < self._drop_until_s

    @property
    def body_names(self) -> tuple[str, ...]:
        """Every body the system reports: the moving ones, then the static ones."""
        return (*self.bodies, *self._static)

    # ------------------------------------------------------------------ sampling

    def measure(self, T_world_body: Transform) -> Transform:  # noqa: N803
        """``T_mocap_body`` of a true world pose, with the configured noise."""
        T = T_world_body if self._mocap_is_world else self._T_mocap_world @ T_world_body  # noqa: N806
        if self.noise_m > 0.0 or self.noise_rad > 0.0:
            dt = self._rng.normal(0.0, self.noise_m, 3) if self.noise_m > 0 else np.zeros(3)
            dr = self._rng.normal(0.0, self.noise_rad, 3) if self.noise_rad > 0 else np.zeros(3)
            T = Transform(Rotation.from_rotvec(dr) * T.rotation, T.translation + dt)  # noqa: N806
        return T

    def sample(self, now_s: float | None = None) -> list[MocapSample]:
        """Take one frame now (the sampling thread calls this); returns its samples, empty during a
        dropout. Hands the frame to every sink."""
        now = self.clock.monotonic_s() if now_s is None else now_s
        arrival_ns = self.clock.time_ns()
        stamp_ns = arrival_ns - round(self.latency_s * 1e9)  # the frame's capture time
        with self._lock:
            if self._t0_s is None:
                self._t0_s = now
            # the frame the system exposes now (1 at the start); never repeat one
            frame = max(self._frame + 1, 1 + int((now - self._t0_s) * self.rate_hz + 1e-6))
            skipped, self._frame = frame - self._frame, frame
            if now < self._drop_until_s:
                self.frames_dropped += skipped
                return []
            hidden = set(self._hidden)
            sinks = list(self.sinks)
        samples: list[MocapSample] = []
        for name, truth in self.bodies.items():
            if name in hidden:
                if name in self._tracked:  # a body never tracked is not known to the system yet
                    samples.append(MocapSample(stamp_ns, name, MOCAP_FRAME_ID, None, False, frame, now, 0, arrival_ns))
                continue
            self._tracked.add(name)
            T_true = self._delays[name](now, truth(now))  # noqa: N806
            samples.append(MocapSample(stamp_ns, name, MOCAP_FRAME_ID, self.measure(T_true), True, frame, now, 0,
                                       arrival_ns))
        for name, T in self._static.items():
            samples.append(MocapSample(stamp_ns, name, MOCAP_FRAME_ID, T, True, frame, now, 0, arrival_ns))
        with self._lock:
            self.frames_published += 1
        for sink in sinks:
            try:
                sink(samples)
            except Exception:
                logger.exception("simulated mocap sink %r failed", sink)
        return samples

    def _run(self) -> None:
        clock = self.clock
        period = 1.0 / self.rate_hz
        next_s = clock.monotonic_s()
        while not self._stop.is_set():
            now = clock.monotonic_s()
            try:
                self.sample(now)
            except Exception:  # the sampler must survive anything (e.g. the lab stopping)
                logger.exception("simulated mocap sample failed")
            next_s += period
            now = clock.monotonic_s()
            if next_s < now - 5 * period:  # fell far behind (machine busy): skip, keep the rate
                next_s = now
            # Until the frame's absolute time: a duration from ``now`` would overshoot by a tick when
            # a lock-step clock advances between that read and the sleep (the frame never comes).
            sleep_until(clock, next_s, self._stop)

    # ------------------------------------------------------------------ lifetime

    def start(self) -> Self:
        """Start sampling on a daemon thread (counted: every :meth:`start` needs a :meth:`stop`);
        returns immediately."""
        with self._lock:
            self._users += 1
            if self._thread is not None:
                return self
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="sim-mocap", daemon=True)
        self._thread.start()
        logger.info(
            "simulated mocap: %s at %.0f Hz, noise %.4f m", ", ".join(self.bodies) or "static bodies", self.rate_hz,
            self.noise_m,
        )
        return self

    def stop(self) -> None:
        """Undo one :meth:`start`; the last one stops the thread (blocks for at most ~1 frame)."""
        with self._lock:
            self._users = max(0, self._users - 1)
            if self._users or self._thread is None:
                return
            thread, self._thread = self._thread, None
        self._stop.set()
        thread.join(5.0)

    def __repr__(self) -> str:
        return f"SimMocapSystem({sorted(self.bodies)}, {self.rate_hz:g} Hz)"


class SimMocapSource(WorldFrameSource):
    """Mocap poses of a simulated vehicle, in-process (a :class:`~flightkit.mocap.base.MocapSource`).

    Either samples one lab's vehicle itself (``lab``, ``body``, ``rate_hz``, noise, true frame,
    static bodies) or serves a shared :class:`SimMocapSystem` (``system``, e.g. a fleet's).

    Args:
        lab: the simulated lab whose vehicle is tracked (its clock drives the sampling).
        body: rigid-body name of the vehicle.
        rate_hz, noise_m, seed, latency_s: see :class:`SimMocapSystem`.
        T_world_mocap: the calibration the source applies (what ``mocap.T_world_mocap`` in
            config holds).
        true_T_world_mocap: where the mocap frame really is (default: ``T_world_mocap``); give a
            different one to simulate a calibration error.
        static_bodies: other rigid bodies in the room, name -> fixed ``T_world_body``.
        system: serve this system's frames instead of sampling ``lab`` (the other sampling
            arguments are then ignored).
        clock: the clock when ``lab`` is None (a shared ``system``'s clock by default).

    Use as ``async with source:``; fault injection goes through :attr:`system`.
    """

    stamp_source = STAMP_DEVICE  # the simulated system stamps each frame with its capture time

    def __init__(
        self,
        lab: SimLab | None = None,
        body: str = "uav1",
        rate_hz: float = 120.0,
        noise_m: float = 0.0,
        seed: int = 0,
        T_world_mocap: Transform | None = None,  # noqa: N803
        *,
        true_T_world_mocap: Transform | None = None,  # noqa: N803
        static_bodies: Mapping[str, Transform] | None = None,
        system: SimMocapSystem | None = None,
        clock: Clock | None = None,
        latency_s: float = 0.0,
    ) -> None:
        if system is None:
            if lab is None:
                raise MocapError("SimMocapSource needs a lab to track or a SimMocapSystem to serve")
            system = SimMocapSystem(
                lab.clock,
                {body: lab.T_world_body},
                T_world_mocap=true_T_world_mocap or T_world_mocap,
                rate_hz=rate_hz,
                noise_m=noise_m,
                seed=seed,
                static_bodies=static_bodies,
                latency_s=latency_s,
            )
        clk = clock or (lab.clock if lab is not None else system.clock)
        super().__init__(
            clk,
            WorldFrames(T_world_mocap or Transform.identity()),
            name=f"simulated mocap {sorted(system.bodies)}",
            fresh_within_s=max(0.1, 5.0 / system.rate_hz),
        )
        self.system = system
        self.body = body

    @property
    def rate_hz(self) -> float:
        return self.system.rate_hz

    def drop_for(self, duration_s: float) -> None:
        """Silence the system for ``duration_s`` of clock time (see :meth:`SimMocapSystem.drop_for`)."""
        self.system.drop_for(duration_s)

    def hide_body(self, body: str | None = None) -> None:
        """Occlude ``body`` (default: this source's vehicle) until :meth:`show_body`."""
        self.system.hide_body(body or self.body)

    def show_body(self, body: str | None = None) -> None:
        """Track ``body`` (default: this source's vehicle) again."""
        self.system.show_body(body or self.body)

    @property
    def dropping(self) -> bool:
        return self.system.dropping

    @property
    def frames_dropped(self) -> int:
        return self.system.frames_dropped

    @property
    def frames_published(self) -> int:
        return self.system.frames_published

    def _on_frame(self, samples: Sequence[MocapSample]) -> None:
        for s in samples:
            self._ingest(s)

    async def _open(self) -> None:
        self.system.sinks.append(self._on_frame)
        self.system.start()

    async def _close(self) -> None:
        if self._on_frame in self.system.sinks:
            self.system.sinks.remove(self._on_frame)
        await asyncio.to_thread(self.system.stop)


class SimMocapPublisher(Running):
    """Publish a :class:`SimMocapSystem`'s frames on the bus, one topic per body.

    Args:
        session: an open Zenoh session.
        keys: the namespace the poses go under (``<ns>/mocap/<body>/pose``), or body -> namespace
            (a fleet: each body under its own vehicle's namespace).
        system: the simulated mocap system (started and stopped with this publisher).

    Use ``with``/``async with`` or :meth:`start` / :meth:`stop`.
    """

    def __init__(self, session: zenoh.Session, keys: Keys | Mapping[str, Keys], system: SimMocapSystem) -> None:
        self.system = system
        keys_of = keys if isinstance(keys, Mapping) else dict.fromkeys(system.body_names, keys)
        self._pubs = {name: PosePublisher(session, keys_of[name], name, clock=system.clock, stamp_source=STAMP_DEVICE)
                      for name in system.body_names}
        self.published = 0

    @property
    def keys(self) -> list[str]:
        """The keys published on."""
        return [p.key for p in self._pubs.values()]

    @property
    def key(self) -> str:
        """The first body's key (one-vehicle labs)."""
        return self.keys[0]

    @property
    def has_subscribers(self) -> bool:
        """Whether every body's key has a subscriber (e.g. a recorder) right now."""
        return all(p.has_subscribers for p in self._pubs.values())

    def _on_frame(self, samples: Sequence[MocapSample]) -> None:
        for s in samples:
            self._pubs[s.body].publish(s.stamp_ns, s.T_frame_body)
        self.published += 1

    def start(self) -> Self:
        """Start the system and publish its frames; returns immediately."""
        self.system.sinks.append(self._on_frame)
        self.system.start()
        logger.info("simulated mocap publishes %s at %g Hz", ", ".join(self.keys), self.system.rate_hz)
        return self

    def stop(self) -> None:
        """Stop publishing, undeclare the publishers; idempotent."""
        if self._on_frame in self.system.sinks:
            self.system.sinks.remove(self._on_frame)
            self.system.stop()
        for p in self._pubs.values():
            p.close()

