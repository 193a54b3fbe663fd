"""The MAVSDK instance under the MAVSDK backend: opening it, its plugins, closing it.

:class:`MavsdkConnection` creates MAVSDK with our system/component ids, adds the connection
(``link.url`` in MAVSDK's URL form), waits for the first autopilot and builds the plugins the
link uses (action, offboard, telemetry, mocap, mavlink_direct, param). :meth:`MavsdkConnection.close`
destroys MAVSDK off the event loop (it joins MAVSDK's threads).

MAVSDK's own log lines (printed to stdout by default) are folded into the
``flightkit.link.mavsdk.core`` logger once per process (:func:`install_core_logging`).

One of them is expected and harmless: MAVSDK sends its first HEARTBEAT as soon as a connection
is added, and on a TCP link (ArduPilot SITL's ``tcp:5760``) its asynchronous connect has not
completed yet, so that send fails and MAVSDK logs "Sending message failed" as an error; the
next heartbeat, a second later, goes out. While a connection is still looking for its
autopilot that line is logged at DEBUG, with that reason (``docs/hardware.md``, MAVSDK backend).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Iterator
from typing import Any

from flightkit.config import LinkConfig
from flightkit.errors import EndpointError, LinkTimeout

__all__ = ["MavsdkConnection", "install_core_logging"]

logger = logging.getLogger(__name__)
_core_logger = logging.getLogger("flightkit.link.mavsdk.core")

_log_lock = threading.Lock()
_log_installed = False
_opening = 0  # MAVSDK connections added but without their autopilot yet (under _log_lock)
_SEND_FAILED = "Sending message failed"
_SEND_FAILED_AT_CONNECT = (
    "Sending message failed (MAVSDK's first heartbeat, sent before its connection was up; harmless)"
)


def install_core_logging() -> None:
    """Route MAVSDK's own log lines (stdout by default) to ``flightkit.link.mavsdk.core``."""
    global _log_installed
    with _log_lock:
        if _log_installed:
            return
        from mavsdk.logging import LogLevel, log_subscribe

        levels = {
            LogLevel.DEBUG: logging.DEBUG,
            LogLevel.INFO: logging.DEBUG,  # MAVSDK's INFO is chatty (version banners, discoveries)
            LogLevel.WARN: logging.WARNING,
            LogLevel.ERROR: logging.ERROR,
        }

        def on_log(level: Any, message: str, file: str | None, line: int) -> bool:
            try:
                if message == _SEND_FAILED and _opening > 0:
                    _core_logger.debug("%s", _SEND_FAILED_AT_CONNECT)
                    return True
                _core_logger.log(levels.get(level, logging.INFO), "%s", message)
            except Exception:  # never let an exception cross into C
                pass
            return True  # suppress MAVSDK's stdout printing

        log_subscribe(on_log)
        _log_installed = True


@contextlib.contextmanager
def _connecting() -> Iterator[None]:
    """While inside, MAVSDK's failed first heartbeat is expected (see the module docstring)."""
    global _opening
    with _log_lock:
        _opening += 1
    try:
        yield
    finally:
        with _log_lock:
            _opening -= 1


class MavsdkConnection:
    """One MAVSDK instance, the autopilot system it found and that system's plugins.

    Args:
        cfg: link settings (our system/component ids, heartbeat timeout, the url for messages).
        url: ``cfg.url`` in MAVSDK's form (:func:`~flightkit.link.mavsdk.encoding.mavsdk_url`).

    The plugin attributes are None until :meth:`open` has found an autopilot, and after
    :meth:`close`.
    """

    def __init__(self, cfg: LinkConfig, url: str) -> None:
        self._cfg = cfg
        self.url = url
        self.mavsdk: Any = None
        self.system: Any = None
        self.action: Any = None
        self.offboard: Any = None
        self.telemetry: Any = None
        self.mocap: Any = None
        self.direct: Any = None
        self.param: Any = None

    @property
    def is_open(self) -> bool:
        """True from :meth:`open` until :meth:`close`."""
        return self.mavsdk is not None

    async def open(self) -> int:
        """Create MAVSDK, add the connection, wait for an autopilot and build its plugins.

        Returns the autopilot's system id. On an error MAVSDK may stay created; call
        :meth:`close` to release it.

        Raises:
            EndpointError: MAVSDK cannot open the connection (bad URL, port in use, no device).
            LinkTimeout: MAVSDK found no autopilot within ``link.heartbeat_timeout_s`` (wall).
        """
        install_core_logging()
        from mavsdk.asyncio import Configuration, Mavsdk, MavsdkConnectionError
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.asyncio.plugins.mocap import MocapAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.param import ParamAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        conf = Configuration.create_manual(self._cfg.source_system, self._cfg.source_component, True)
        self.mavsdk = Mavsdk(conf)
        timeout_s = self._cfg.heartbeat_timeout_s
        with _connecting():
            try:
                await self.mavsdk.add_any_connection(self.url)
            except MavsdkConnectionError as exc:
                raise EndpointError(
                    f"MAVSDK cannot open {self.url} (from link.url {self._cfg.url!r}): {exc}; "
                    "check the address, that the port is free, or the serial device exists"
                ) from exc
            system = await self.mavsdk.first_autopilot(timeout_s=timeout_s)
        if system is None:
            raise LinkTimeout(
                f"no autopilot HEARTBEAT on {self.url} after {timeout_s:.1f} s; "
                "is the autopilot or simulator running and link.url right?",
                what="HEARTBEAT",
                timeout_s=timeout_s,
            )
        self.system = system
        self.action = ActionAsync(system)
        self.offboard = OffboardAsync(system)
        self.telemetry = TelemetryAsync(system)
        self.mocap = MocapAsync(system)
        self.direct = MavlinkDirectAsync(system)
        self.param = ParamAsync(system)
        return int(await system.get_system_id())

    async def close(self) -> None:
        """Drop the plugins and destroy MAVSDK; idempotent."""
        if self.mavsdk is None:
            return
        mav, self.mavsdk = self.mavsdk, None
        self.action = self.offboard = self.telemetry = self.mocap = self.direct = self.param = None
        self.system = None
        # destroy() joins MAVSDK's threads; keep the loop responsive meanwhile.
        await asyncio.get_running_loop().run_in_executor(None, mav.destroy)
