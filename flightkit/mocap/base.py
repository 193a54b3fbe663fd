"""Motion capture: timestamped rigid-body poses, measured in a named frame and served in the world frame.

A backend (a mocap system, the bus, the simulator, the autopilot's own estimate) measures
:class:`MocapSample` values in the frame it names (``frame_id``, usually ``"mocap"``); the one
adapter, :class:`~flightkit.mocap.source.WorldFrameSource`, places them in the world through
:class:`~flightkit.frames.WorldFrames` and hands out :class:`MocapPose` values, so consumers only
ever see ``T_world_body``.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

from flightkit.frames import Transform

__all__ = ["MocapPose", "MocapSample", "MocapSource"]


@dataclass(frozen=True, slots=True)
class MocapSample:
    """One rigid-body pose as a backend measured it.

    Attributes:
        stamp_ns: capture time, ns since the Unix epoch (the source clock's ``time_ns``).
        body: rigid-body name.
        frame_id: the frame ``T_frame_body`` is in (``"mocap"``, ``"world"``, or another frame
            the source's :class:`~flightkit.frames.WorldFrames` knows).
        T_frame_body: the pose in ``frame_id``; None when the system lost the body.
        valid: False when the body is occluded or untracked (the pose must not be flown on).
        seq: per-body sequence number from the system (gaps mean missed frames).
        received_s: ``Clock.monotonic_s`` when it arrived (for staleness checks).
        bus_ns: when its publisher put it on the bus (publisher's clock, ns since the epoch; 0
            when it did not come over the bus).
        received_ns: ``Clock.time_ns`` when it arrived here (0 when not known).
    """

    stamp_ns: int
    body: str
    frame_id: str
    T_frame_body: Transform | None
    valid: bool = True
    seq: int = 0
    received_s: float = 0.0
    bus_ns: int = 0
    received_ns: int = 0


@dataclass(frozen=True, slots=True)
class MocapPose:
    """One rigid-body pose in the world frame.

    Attributes:
        stamp_ns: capture time, ns since the Unix epoch (the source clock's ``time_ns``).
        body: rigid-body name.
        T_world_body: body pose in the world frame (ENU, z up).
        valid: False when the system reports the body as occluded/untracked (the pose is
            then the last known one and must not be flown on).
        seq: per-body sequence number from the source (gaps mean missed frames).
        received_s: ``Clock.monotonic_s`` when we received it (for staleness checks).
        T_mocap_body: the same pose in the mocap system's own frame, as measured (what a
            bridge or a recorder publishes with ``frame_id "mocap"``).
        bus_ns, received_ns: see :class:`MocapSample` (the latency stages of the flight log).
    """

    stamp_ns: int
    body: str
    T_world_body: Transform
    valid: bool = True
    seq: int = 0
    received_s: float = 0.0
    T_mocap_body: Transform | None = None
    bus_ns: int = 0
    received_ns: int = 0


@runtime_checkable
class MocapSource(Protocol):
    """A stream of rigid-body poses in the world frame. Use as ``async with source:``."""

    def bodies(self) -> tuple[str, ...]:
        """Names of the bodies seen so far; returns immediately."""
        ...

    def latest(self, body: str) -> MocapPose | None:
        """Newest pose of ``body`` (None if never seen); returns immediately."""
        ...

    async def wait_for_body(self, body: str, timeout_s: float) -> MocapPose:
        """Wait until ``body`` has a valid, fresh pose; MocapBodyMissing (naming visible bodies) otherwise."""
        ...

    def poses(self, body: str | None = None) -> AsyncIterator[MocapPose]:
        """Async iterator over new poses (of one body, or all)."""
        ...

    async def __aenter__(self) -> Self: ...

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...
