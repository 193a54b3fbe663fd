"""The one adapter every mocap source is built on: measured poses in, world poses out.

A backend subclasses :class:`WorldFrameSource`, starts its producer in :meth:`_open` (a
thread, a bus subscription, a polling task), and hands every measured
:class:`~flightkit.mocap.base.MocapSample` to :meth:`_ingest` from whatever thread it runs on.
:meth:`_ingest` is the only place a measured pose is placed in the world
(``T_world_body = frames.to_world(frame_id, T_frame_body)``); it also keeps the pose as the
mocap system measured it (``T_mocap_body``) for bridges and recorders, carries a lost
body's last known pose forward (``valid=False``), and stores the result in a
:class:`~flightkit.mocap.store.PoseStore`, which serves ``latest``, ``wait_for_body`` (one
freshness rule) and ``poses``.

A sample in a frame the source's :class:`~flightkit.frames.WorldFrames` cannot place fails
the source: every waiter and stream raises a MocapError naming the frame.

Lifetime: ``async with source:`` starts the backend and stops it on exit; a source can be
entered again after it was left.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from types import TracebackType
from typing import Self

from flightkit.clock import STAMP_HOST, Clock
from flightkit.errors import FrameError, MocapError
from flightkit.frames import MOCAP_FRAME_ID, Transform, WorldFrames
from flightkit.mocap.base import MocapPose, MocapSample
from flightkit.mocap.store import PoseStore

__all__ = ["WorldFrameSource"]

logger = logging.getLogger(__name__)


class WorldFrameSource:
    """Base class of every :class:`~flightkit.mocap.base.MocapSource` (see the module docstring).

    Args:
        clock: stamps, timeouts and freshness.
        frames: where the backend's frames sit in the world (``T_world_mocap`` from config).
        name: the source's name, for messages.
        fresh_within_s: :meth:`wait_for_body` wants a pose received at most this long ago.

    Attributes:
        hooks: called with every stored pose on the backend's thread before consumers see it
            (benchmarks time the path from sample to setpoint with it); keep them quick.
        stamp_source: ``device`` when the backend's stamps are the mocap system's own frame
            times, ``host`` (the default) when they are the arrival time here (a bridge says so
            in the bus attachment and the recording's channel metadata).
    """

    stamp_source: str = STAMP_HOST

    def __init__(self, clock: Clock, frames: WorldFrames, *, name: str, fresh_within_s: float = 0.5) -> None:
        self.clock = clock
        self.world_frames = frames
        self.name = name
        self._store = PoseStore(clock, name=name, fresh_within_s=fresh_within_s)
        self._T_mocap_world = frames.T_world_mocap.inverse()
        self._mocap_is_world = frames.T_world_mocap.is_identity  # then a mocap pose is a world pose as it is
        self.hooks: list[Callable[[MocapPose], None]] = []
        self._entered = False

    @property
    def T_world_mocap(self) -> Transform:  # noqa: N802
        """The mocap system's frame in the world, as this source applies it."""
        return self.world_frames.T_world_mocap

    # ------------------------------------------------------------------ for backends

    async def _open(self) -> None:
        """Start producing samples (subclasses); may raise MocapError."""

    async def _close(self) -> None:
        """Stop producing samples (subclasses); must not raise."""

    def _ingest(self, sample: MocapSample) -> MocapPose | None:
        """Place ``sample`` in the world and store it; thread-safe. Returns the stored pose,
        or None when the sample's frame is unknown (the source then fails with a FrameError)."""
        if sample.T_frame_body is None:  # lost: carry the last known pose, flagged invalid
            prev = self._store.latest(sample.body)
            T_world = prev.T_world_body if prev is not None else Transform.identity()
            T_mocap = prev.T_mocap_body if prev is not None else None
        else:
            try:
                T_world, T_mocap = self._place(sample)
            except FrameError as exc:
                logger.error("%s: %s", self.name, exc)
                self._store.fail(exc)
                return None
        valid = sample.valid and sample.T_frame_body is not None
        pose = MocapPose(sample.stamp_ns, sample.body, T_world, valid, sample.seq, sample.received_s, T_mocap,
                         sample.bus_ns, sample.received_ns)
        for hook in self.hooks:
            try:
                hook(pose)
            except Exception:
                logger.exception("%s: mocap hook %r failed", self.name, hook)
        self._store.update(pose)
        return pose

    def _place(self, sample: MocapSample) -> tuple[Transform, Transform]:
        assert sample.T_frame_body is not None
        if sample.frame_id == MOCAP_FRAME_ID:
            if self._mocap_is_world:  # two scipy rotation operations saved per pose (about 0.1 ms)
                return sample.T_frame_body, sample.T_frame_body
            return self.world_frames.T_world_mocap @ sample.T_frame_body, sample.T_frame_body
        T_world = self.world_frames.to_world(sample.frame_id, sample.T_frame_body)
        return T_world, self._T_mocap_world @ T_world

    def _fail(self, error: MocapError) -> None:
        """The backend died: waiters and streams raise ``error``; thread-safe."""
        self._store.fail(error)

    # ------------------------------------------------------------------ MocapSource

    def bodies(self) -> tuple[str, ...]:
        """Names of the bodies seen so far; returns immediately."""
        return self._store.bodies()

    def visible(self) -> tuple[str, ...]:
        """Bodies whose newest pose is valid; returns immediately."""
        return self._store.visible()

    def latest(self, body: str) -> MocapPose | None:
        """Newest pose of ``body`` (None if never seen); returns immediately."""
        return self._store.latest(body)

    async def wait_for_body(self, body: str, timeout_s: float) -> MocapPose:
        """Wait (``timeout_s`` of clock time) for a valid pose of ``body`` received at most
        ``fresh_within_s`` ago.

        Raises:
            MocapBodyMissing: none in time; names the bodies that are visible.
            MocapError: the backend failed (or sent a pose in an unknown frame).
        """
        return await self._store.wait_for_body(body, timeout_s)

    def poses(self, body: str | None = None) -> AsyncIterator[MocapPose]:
        """New poses of ``body`` (or of every body) from now on, in arrival order; ends when
        the source closes, raises MocapError when the backend fails."""
        return self._store.poses(body)

    # ------------------------------------------------------------------ lifetime

    async def __aenter__(self) -> Self:
        if not self._entered:
            self._store.reopen()
            await self._open()
            self._entered = True
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Stop the backend and end every stream; idempotent."""
        if self._entered:
            self._entered = False
            await self._close()
        self._store.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, bodies={list(self.bodies())})"
