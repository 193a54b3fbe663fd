"""Mocap poses from the bus: ``<ns>/mocap/<body>/pose`` (geometry_msgs/PoseStamped).

Publishers (the simulator, mocap bridges) send poses in the mocap system's own frame; this
source maps them into the world through ``T_world_mocap``. A pose whose position or
orientation is not finite (NaN) is the publisher's way of saying "body lost": it becomes a
:class:`~flightkit.mocap.base.MocapPose` with ``valid=False`` carrying the last known pose.
Silence is not flagged here; consumers judge staleness from ``received_s``.
"""

from __future__ import annotations

import logging
import math
from types import TracebackType
from typing import Any, Self

from flightkit.bus.keys import Keys
from flightkit.bus.msgs import PoseStamped
from flightkit.bus.pubsub import BusSample, BusSubscriber
from flightkit.clock import Clock
from flightkit.errors import BusError
from flightkit.frames import Transform
from flightkit.mocap.base import MocapPose
from flightkit.mocap.store import PoseStore, StoreBackedSource

__all__ = ["BusMocapSource", "pose_is_valid"]

logger = logging.getLogger(__name__)


def pose_is_valid(msg: PoseStamped) -> bool:
    """True when position and orientation are finite and the quaternion is not degenerate."""
    vals = msg.position_m + msg.quat_xyzw
    if not all(math.isfinite(v) for v in vals):
        return False
    n2 = sum(q * q for q in msg.quat_xyzw)
    return 0.25 < n2 < 4.0


class BusMocapSource(StoreBackedSource):
    """A :class:`~flightkit.mocap.base.MocapSource` reading ``<ns>/mocap/*/pose`` from Zenoh.

    Args:
        session: an open Zenoh session (owned by the caller).
        keys: the vehicle namespace's keys.
        clock: gives ``received_s`` and runs timeouts.
        T_world_mocap: the mocap frame in the world (from ``MocapConfig.T_world_mocap``).
        owns_session: close ``session`` when the source closes (set by :func:`open_mocap`).

    Use as ``async with BusMocapSource(...) as src:``; subscribing happens on entry.
    """

    def __init__(
        self,
        session: Any,
        keys: Keys,
        clock: Clock,
        T_world_mocap: Transform | None = None,
        *,
        owns_session: bool = False,
    ) -> None:
        self._session = session
        self._owns_session = owns_session
        self.keys = keys
        self.clock = clock
        self.T_world_mocap = T_world_mocap or Transform.identity()
        self._prefix = f"{keys.namespace}/mocap/"
        self._store = PoseStore(clock, name=f"bus mocap {keys.mocap_all()!r}")
        self._sub: BusSubscriber | None = None

    def start(self) -> Self:
        """Subscribe; returns immediately (poses arrive on Zenoh threads)."""
        if self._sub is None:
            self._sub = BusSubscriber(self._session, self.keys.mocap_all(), callback=self._on_sample)
        return self

    def close(self) -> None:
        """Unsubscribe and end every iterator; idempotent."""
        if self._sub is not None:
            self._sub.close()
            self._sub = None
        self._store.close()
        if self._owns_session:
            self._owns_session = False
            self._session.close()

    def _on_sample(self, s: BusSample) -> None:
        if not (s.key.startswith(self._prefix) and s.key.endswith("/pose")):
            return
        body = s.key[len(self._prefix) : -len("/pose")]
        try:
            msg = PoseStamped.decode(s.payload)
        except BusError as exc:
            logger.warning("dropping a malformed pose on %s: %s", s.key, exc)
            return
        received_s = self.clock.monotonic_s()
        if pose_is_valid(msg):
            T_world_body = self.T_world_mocap @ msg.to_transform()
            valid = True
        else:
            prev = self._store.latest(body)
            T_world_body = prev.T_world_body if prev is not None else Transform.identity()
            valid = False
        self._store.update(MocapPose(msg.header.stamp_ns, body, T_world_body, valid, max(s.seq, 0), received_s))

    def missed(self, body: str | None = None) -> int:
        """Poses lost on the way (sequence gaps) for ``body`` or all bodies."""
        if self._sub is None:
            return 0
        return self._sub.missed(self.keys.mocap_pose(body) if body else None)

    async def __aenter__(self) -> Self:
        return self.start()

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"BusMocapSource({self.keys.mocap_all()!r}, bodies={list(self.bodies())})"
