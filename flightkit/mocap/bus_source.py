"""Mocap poses from the bus: ``<ns>/mocap/<body>/pose`` (geometry_msgs/PoseStamped).

Publishers (the simulator, mocap bridges) send poses in the frame their header names,
``"mocap"`` for a mocap system's own frame; :class:`BusMocapSource` places them in the world
through its :class:`~flightkit.frames.WorldFrames` (``T_world_mocap`` from config) and fails
with a message naming the frame when a pose comes in a frame it cannot place. A pose whose
position or orientation is not finite (NaN) is the publisher's way of saying "body lost": it
becomes a :class:`~flightkit.mocap.base.MocapPose` with ``valid=False`` carrying the last
known pose. Silence is not flagged here; consumers judge staleness from ``received_s``.
"""

from __future__ import annotations

import logging
import math

import zenoh

from flightkit.bus.keys import Keys
from flightkit.bus.pose_msgs import PoseStamped
from flightkit.bus.pubsub import BusSample, BusSubscriber
from flightkit.clock import Clock
from flightkit.errors import BusError
from flightkit.frames import WorldFrames
from flightkit.mocap.base import MocapSample
from flightkit.mocap.source import WorldFrameSource

__all__ = ["BusMocapSource", "pose_is_valid"]

logger = logging.getLogger(__name__)


def pose_is_valid(msg: PoseStamped) -> bool:
    """True when position and orientation are finite and the quaternion is not degenerate."""
    vals = msg.position_m + msg.quat_xyzw
    if not all(math.isfinite(v) for v in vals):
        return False
    n2 = sum(q * q for q in msg.quat_xyzw)
    return 0.25 < n2 < 4.0


class BusMocapSource(WorldFrameSource):
    """A :class:`~flightkit.mocap.base.MocapSource` reading ``<ns>/mocap/*/pose`` from Zenoh.

    Args:
        session: an open Zenoh session (owned by the caller unless ``owns_session``).
        keys: the namespace whose mocap poses are read.
        clock: gives ``received_s`` and runs timeouts.
        frames: where the publishers' frames sit in the world (``T_world_mocap`` from config).
        owns_session: close ``session`` when the source closes (set by :func:`open_mocap`).

    Use as ``async with BusMocapSource(...) as src:``; subscribing happens on entry.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        clock: Clock,
        frames: WorldFrames | None = None,
        *,
        owns_session: bool = False,
    ) -> None:
        super().__init__(clock, frames or WorldFrames(), name=f"bus mocap {keys.mocap_all()!r}")
        self._session = session
        self._owns_session = owns_session
        self.keys = keys
        self._prefix = f"{keys.namespace}/mocap/"
        self._sub: BusSubscriber | None = None

    async def _open(self) -> None:
        self._sub = BusSubscriber(self._session, self.keys.mocap_all(), callback=self._on_sample)

    async def _close(self) -> None:
        if self._sub is not None:
            self._sub.close()
            self._sub = None
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
        T = msg.to_transform() if pose_is_valid(msg) else None  # noqa: N806
        self._ingest(
            MocapSample(msg.header.stamp_ns, body, msg.header.frame_id, T, T is not None, max(s.seq, 0),
                        self.clock.monotonic_s(), s.bus_ns, self.clock.time_ns())
        )

    def missed(self, body: str | None = None) -> int:
        """Poses lost on the way (sequence gaps) for ``body`` or all bodies."""
        if self._sub is None:
            return 0
        return self._sub.missed(self.keys.mocap_pose(body) if body else None)
