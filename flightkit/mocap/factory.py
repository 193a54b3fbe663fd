"""Pick and build the mocap source that config names."""

from __future__ import annotations

from typing import Any

from flightkit.bus.keys import Keys
from flightkit.clock import Clock
from flightkit.config import BusConfig, MocapConfig, MocapSourceKind
from flightkit.frames import WorldFrames
from flightkit.mocap.base import MocapSource

__all__ = ["open_mocap"]


def open_mocap(
    cfg: MocapConfig, bus_cfg: BusConfig, keys: Keys, clock: Clock, *, session: Any = None
) -> MocapSource:
    """Create (not yet start) the mocap source ``cfg.source`` names; enter it with ``async with``.

    ``bus``: a :class:`~flightkit.mocap.bus_source.BusMocapSource` on ``session``, or on a
    session opened from ``bus_cfg`` now and closed with the source.
    ``motioncapture``: a :class:`~flightkit.mocap.motioncapture_source.MotionCaptureSource`
    for ``cfg.system_type`` at ``cfg.hostname`` with ``cfg.options``.
    Both map poses into the world through ``cfg.T_world_mocap``.

    Raises:
        BusError: the bus session cannot be opened.
    """
    frames = WorldFrames(cfg.T_world_mocap.to_transform())
    if cfg.source is MocapSourceKind.MOTIONCAPTURE:
        from flightkit.mocap.motioncapture_source import MotionCaptureSource

        return MotionCaptureSource(cfg.system_type, clock, hostname=cfg.hostname, options=cfg.options, frames=frames)
    from flightkit.bus.session import open_session
    from flightkit.mocap.bus_source import BusMocapSource

    owns = session is None
    if session is None:
        session = open_session(bus_cfg)
    return BusMocapSource(session, keys, clock, frames, owns_session=owns)
