"""Motion-capture sources: timestamped rigid-body poses in the world frame.

Every backend maps the mocap system's own frame into the world frame through
``T_world_mocap`` (from config) before a pose leaves it, so consumers only ever see
``T_world_body``.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

from flightkit.frames import Transform

__all__ = ["MocapPose", "MocapSource"]


@dataclass(frozen=True, slots=True)
class MocapPose:
    """One rigid-body pose.

    Attributes:
        stamp_ns: capture time, ns since the Unix epoch (the source clock's ``time_ns``).
        body: rigid-body name.
        T_world_body: body pose in the world frame (ENU, z up).
        valid: False when the system reports the body as occluded/untracked (the pose is
            then the last known one and must not be flown on).
        seq: per-body sequence number from the source (gaps mean missed frames).
        received_s: ``Clock.monotonic_s`` when we received it (for staleness checks).
    """

    stamp_ns: int
    body: str
    T_world_body: Transform
    valid: bool = True
    seq: int = 0
    received_s: float = 0.0


@runtime_checkable
class MocapSource(Protocol):
    """A stream of rigid-body poses. Use as ``async with source:``."""

    def bodies(self) -> tuple[str, ...]:
        """Names of the bodies seen so far; returns immediately."""
        ...

    def latest(self, body: str) -> MocapPose | None:
        """Newest pose of ``body`` (None if never seen); returns immediately."""
        ...

    async def wait_for_body(self, body: str, timeout_s: float) -> MocapPose:
        """Wait until ``body`` has a valid pose; MocapBodyMissing (naming visible bodies) otherwise."""
        ...

    def poses(self, body: str | None = None) -> AsyncIterator[MocapPose]:
        """Async iterator over new poses (of one body, or all)."""
        ...

    async def __aenter__(self) -> Self: ...

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...
