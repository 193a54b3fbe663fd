"""Vehicle links: the :class:`~flightkit.link.base.VehicleLink` interface and its backends.

Pick a backend from config with :func:`open_link`::

    link = open_link(cfg.link, cfg.vehicle.autopilot, clock)
    async with link:
        await link.arm()

``link.backend = "pymavlink"`` gives :class:`~flightkit.link.mavlink.MavlinkLink`,
``"mavsdk"`` gives :class:`~flightkit.link.mavsdk.MavsdkLink`. Both are imported only
when chosen, so importing :mod:`flightkit.link` stays cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from flightkit.clock import Clock, WallClock
from flightkit.config import Autopilot, LinkBackend, LinkConfig

if TYPE_CHECKING:
    from flightkit.link.base import VehicleLink

__all__ = ["open_link"]


def open_link(cfg: LinkConfig, autopilot: Autopilot, clock: Clock | None = None) -> VehicleLink:
    """Create (not yet connect) the link that ``cfg.backend`` names.

    Connect with ``async with link:`` or ``await link.connect()``.

    Raises:
        EndpointError: ``cfg.url`` is malformed.
        ConfigError: ``cfg.signing_key_hex`` is not 64 hex digits.
    """
    clock = clock if clock is not None else WallClock()
    if cfg.backend is LinkBackend.MAVSDK:
        from flightkit.link.mavsdk import MavsdkLink

        return MavsdkLink(cfg, autopilot, clock)
    from flightkit.link.mavlink import MavlinkLink

    return MavlinkLink(cfg, autopilot, clock)
