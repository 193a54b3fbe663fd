"""The simulated mocap system: ground-truth poses on the bus, like a real mocap bridge.

:class:`SimMocapPublisher` samples ``truth()`` (``(stamp_ns, T_world_body)``, e.g. from
``SimLab``) at ``rate_hz`` on the clock and publishes ``geometry_msgs/PoseStamped`` on
``<ns>/mocap/<body>/pose`` **in the mocap system's own frame** (``T_mocap_body =
T_world_mocap^-1 @ T_world_body``; frame_id ``"mocap"``), exactly as a Vicon/OptiTrack
bridge would, so consumers must apply ``T_world_mocap`` -- and a wrong calibration shows.

Faults on demand: :meth:`drop_for` stops publishing for a while (a stalled mocap stream),
:meth:`hide_body` publishes the body as lost (NaN pose, like an occluded rigid body) until
:meth:`show_body`. Optional Gaussian noise on position (``noise_m``) and attitude
(``noise_rad``), reproducible with ``seed``.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from types import TracebackType
from typing import Any, Self

import numpy as np
from scipy.spatial.transform import Rotation

from flightkit.bus.keys import Keys
from flightkit.bus.msgs import Header, PoseStamped
from flightkit.bus.pubsub import BusPublisher
from flightkit.clock import Clock
from flightkit.frames import Transform

__all__ = ["MOCAP_FRAME_ID", "SimMocapPublisher"]

logger = logging.getLogger(__name__)

MOCAP_FRAME_ID = "mocap"
_NAN = float("nan")


class SimMocapPublisher:
    """Publish one rigid body's simulated mocap pose.

    Args:
        session: an open Zenoh session.
        keys: the vehicle namespace's keys.
        body: the rigid-body name.
        truth: returns ``(stamp_ns, T_world_body)``; called from the publisher thread.
        clock: paces the publisher (``rate_hz`` of clock time) and times dropouts.
        T_world_mocap: where the mocap frame sits in the world.
        rate_hz: publication rate.
        noise_m: standard deviation of position noise, metres (per axis).
        seed: random seed for the noise.
        noise_rad: standard deviation of attitude noise, radians (per axis).

    Start with :meth:`start` (a thread) or ``with``/``async with``; or call
    :meth:`publish_once` yourself.
    """

    def __init__(
        self,
        session: Any,
        keys: Keys,
        body: str,
        truth: Callable[[], tuple[int, Transform]],
        clock: Clock,
        T_world_mocap: Transform | None = None,
        rate_hz: float = 120.0,
        noise_m: float = 0.0,
        seed: int | None = None,
        *,
        noise_rad: float = 0.0,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.body = body
        self.truth = truth
        self.clock = clock
        self.T_world_mocap = T_world_mocap or Transform.identity()
        self._T_mocap_world = self.T_world_mocap.inverse()
        self.rate_hz = float(rate_hz)
        self.noise_m = float(noise_m)
        self.noise_rad = float(noise_rad)
        self._rng = np.random.default_rng(seed)
        self._pub = BusPublisher(
            session, keys.mocap_pose(body), PoseStamped, reliable=True, drop_when_congested=False, express=True
        )
        self._lock = threading.Lock()
        self._drop_until_s = -math.inf
        self._hidden = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.published = 0
        self.dropped = 0

    @property
    def key(self) -> str:
        return self._pub.key

    # -- faults
    def drop_for(self, duration_s: float) -> None:
        """Publish nothing for ``duration_s`` of clock time from now."""
        with self._lock:
            self._drop_until_s = self.clock.monotonic_s() + duration_s

    def hide_body(self) -> None:
        """Report the body as lost (NaN pose) until :meth:`show_body`."""
        with self._lock:
            self._hidden = True

    def show_body(self) -> None:
        with self._lock:
            self._hidden = False

    # -- publishing
    def mocap_pose(self, T_world_body: Transform) -> Transform:
        """``T_mocap_body`` for a world pose, with the configured noise."""
        T = self._T_mocap_world @ T_world_body
        if self.noise_m > 0.0 or self.noise_rad > 0.0:
            dt = self._rng.normal(0.0, self.noise_m, 3) if self.noise_m > 0 else np.zeros(3)
            dr = self._rng.normal(0.0, self.noise_rad, 3) if self.noise_rad > 0 else np.zeros(3)
            T = Transform(Rotation.from_rotvec(dr) * T.rotation, T.translation + dt)
        return T

    def publish_once(self) -> bool:
        """Sample the truth and publish one pose now; False while a dropout is on."""
        with self._lock:
            dropping = self.clock.monotonic_s() < self._drop_until_s
            hidden = self._hidden
        if dropping:
            self.dropped += 1
            return False
        stamp_ns, T_world_body = self.truth()
        if hidden:
            msg = PoseStamped(Header(stamp_ns, MOCAP_FRAME_ID), (_NAN, _NAN, _NAN), (_NAN, _NAN, _NAN, _NAN))
        else:
            msg = PoseStamped.from_transform(stamp_ns, MOCAP_FRAME_ID, self.mocap_pose(T_world_body))
        self._pub.publish(msg)
        self.published += 1
        return True

    def _run(self) -> None:
        period_s = 1.0 / self.rate_hz
        next_s = self.clock.monotonic_s()
        while not self._stop.is_set():
            try:
                self.publish_once()
            except Exception:
                logger.exception("simulated mocap for %r failed; stopping it", self.body)
                return
            next_s += period_s
            now_s = self.clock.monotonic_s()
            if next_s < now_s - period_s:  # behind by more than a period: skip ahead, no burst
                next_s = now_s
            self.clock.sleep_blocking(max(0.0, next_s - now_s))

    def start(self) -> Self:
        """Publish at ``rate_hz`` on a daemon thread; returns immediately."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"sim-mocap-{self.body}", daemon=True)
            self._thread.start()
            logger.info("simulated mocap publishes %s at %g Hz", self.key, self.rate_hz)
        return self

    def stop(self) -> None:
        """Stop the thread and undeclare the publisher; idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=max(0.5, 2.0 / self.rate_hz))
            self._thread = None
        self._pub.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    async def __aenter__(self) -> Self:
        return self.start()

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
