"""A mocap bridge: any :class:`~flightkit.mocap.base.MocapSource` published on the bus.

Every pose becomes ``geometry_msgs/PoseStamped`` on ``<ns>/mocap/<body>/pose`` **in the
mocap system's own frame** (``frame_id "mocap"``), exactly as the simulator publishes it and
as :class:`~flightkit.mocap.bus_source.BusMocapSource` expects: consumers apply
``T_world_mocap`` from their config, so a bus consumer and an in-process consumer of the
same system see the same ``T_world_body``. The bridge publishes each pose as the system
measured it (``MocapPose.T_mocap_body``), never a world pose turned back.

A lost body (occluded; ``valid=False``) is published as a NaN pose, the bus's way of saying
"lost" (BusMocapSource turns it back into ``valid=False``). Stamps are the source's.

::

    async with open_bridge_source(lab_cfg, clock) as source:
        bridge = MocapBridge(session, Keys("uav1"), source)
        await bridge.run(duration_s=60)
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from typing import Any

import zenoh

from flightkit.bus.keys import Keys
from flightkit.bus.streams import PosePublisher
from flightkit.clock import STAMP_DEVICE, STAMP_HOST, Clock
from flightkit.errors import BusError, CaptureError
from flightkit.frames import WorldFrames
from flightkit.mocap.base import MocapPose, MocapSource

__all__ = ["MocapBridge", "open_bridge_source"]

logger = logging.getLogger(__name__)


def open_bridge_source(lab_cfg: Any, clock: Clock, *, connect_timeout_s: float = 5.0) -> MocapSource:
    """The mocap system named by ``lab_cfg.mocap`` as a source for the bridge.

    Only ``mocap.source = "motioncapture"`` makes sense here: a ``bus`` source already is on the bus.

    Raises:
        CaptureError: the config names the bus as the mocap source.
    """
    from flightkit.config import MocapSourceKind
    from flightkit.mocap.motioncapture_source import MotionCaptureSource

    cfg = lab_cfg.mocap
    if cfg.source is not MocapSourceKind.MOTIONCAPTURE:
        raise CaptureError(
            f"mocap.source is {cfg.source.value!r} in {lab_cfg.source_path}: those poses are already on the bus; "
            'set mocap.source = "motioncapture" (with system_type and hostname) to bridge a mocap system'
        )
    return MotionCaptureSource(
        cfg.system_type,
        clock,
        hostname=cfg.hostname,
        options=cfg.options,
        frames=WorldFrames(cfg.T_world_mocap.to_transform()),
        connect_timeout_s=connect_timeout_s,
    )


class MocapBridge:
    """Publish a mocap source's poses on ``<ns>/mocap/<body>/pose``.

    Args:
        session: an open Zenoh session.
        keys: the vehicle namespace (all bodies go under it).
        source: an entered MocapSource of a mocap system (its poses carry ``T_mocap_body``).
        bodies: only these bodies (None: every body the source reports).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        source: MocapSource,
        *,
        bodies: Sequence[str] | None = None,
    ) -> None:
        self._session = session
        self.keys = keys
        self.source = source
        self._only = set(bodies) if bodies else None
        self._pubs: dict[str, PosePublisher | None] = {}
        self._said_host_stamps = False
        self.published = 0
        self.per_body: dict[str, int] = {}
        self.lost_published = 0

    @property
    def body_keys(self) -> list[str]:
        return [p.key for p in self._pubs.values() if p is not None]

    def _publisher(self, body: str) -> PosePublisher | None:
        if body in self._pubs:
            return self._pubs[body]
        pub: PosePublisher | None = None
        stamp_source = getattr(self.source, "stamp_source", STAMP_HOST)
        try:
            pub = PosePublisher(self._session, self.keys, body, clock=getattr(self.source, "clock", None),
                                stamp_source=stamp_source)
            logger.info("bridging mocap body %r to %s", body, pub.key)
            if stamp_source != STAMP_DEVICE and not self._said_host_stamps:
                self._said_host_stamps = True
                logger.warning("mocap source %s gives no frame time: poses are stamped on arrival here "
                               "(recorded as capture_stamp=host)", type(self.source).__name__)
        except BusError as exc:
            logger.warning("not bridging mocap body %r: %s", body, exc)
        self._pubs[body] = pub
        return pub

    def publish(self, pose: MocapPose) -> bool:
        """Publish one pose (NaN when not valid); returns False for a skipped body. Blocks only
        while Zenoh's reliable queue is full."""
        if self._only is not None and pose.body not in self._only:
            return False
        pub = self._publisher(pose.body)
        if pub is None:
            return False
        if pose.valid and pose.T_mocap_body is None:
            raise CaptureError(
                f"the bridge's source gave body {pose.body!r} without its mocap-frame pose; bridge a mocap "
                "system's source (open_bridge_source), not a world-frame one"
            )
        pub.publish(pose.stamp_ns, pose.T_mocap_body if pose.valid else None)
        if not pose.valid:
            self.lost_published += 1
        self.published += 1
        self.per_body[pose.body] = self.per_body.get(pose.body, 0) + 1
        return True

    async def run(self, duration_s: float | None = None, clock: Clock | None = None) -> int:
        """Publish every new pose until the source ends, ``duration_s`` of ``clock`` time passed,
        or the task is cancelled; returns the number published.

        Raises:
            MocapError: the source failed.
        """
        if duration_s is None:
            await self._pump()
            return self.published
        if clock is None:
            raise CaptureError("MocapBridge.run(duration_s=...) needs the clock the duration is measured on")
        task = asyncio.ensure_future(self._pump())
        timer = asyncio.ensure_future(clock.sleep(duration_s))
        try:
            await asyncio.wait((task, timer), return_when=asyncio.FIRST_COMPLETED)
        finally:
            timer.cancel()
            if not task.done():
                task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                pass
        return self.published

    async def _pump(self) -> None:
        try:
            async for pose in self.source.poses():
                self.publish(pose)
        finally:
            if self.published:
                logger.info("mocap bridge published %d poses (%s)", self.published, self._summary())

    def _summary(self) -> str:
        return ", ".join(f"{b}: {n}" for b, n in sorted(self.per_body.items()))

    def close(self) -> None:
        """Undeclare the publishers; idempotent."""
        for pub in self._pubs.values():
            if pub is not None:
                pub.close()
        self._pubs.clear()
