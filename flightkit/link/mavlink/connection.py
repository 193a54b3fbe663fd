"""The wire under the pymavlink backend: one endpoint, its codec and its reader thread.

:class:`MavlinkConnection` opens the transport (:mod:`flightkit.link.endpoints`), builds
pymavlink's MAVLink 2 codec (ArduPilot dialect, a superset of common) for each direction,
applies message signing when a key is configured, and runs the **reader thread**: it owns
the transport's receive side, parses packets, hands each message to the
:class:`~flightkit.link.mavlink.telemetry.VehicleState` and wakes its waiters, and sends our
HEARTBEAT at 1 Hz. :meth:`MavlinkConnection.send` may be called from any thread.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.clock import Clock
from flightkit.link.endpoints import Endpoint, Transport, open_transport
from flightkit.link.mavlink.encoding import MAV_AUTOPILOT_INVALID, MAV_STATE_ACTIVE
from flightkit.link.mavlink.telemetry import VehicleState
from flightkit.link.signing import SigningSettings, apply_signing, signing_timestamp

__all__ = ["MavlinkConnection"]

logger = logging.getLogger(__name__)

_READER_POLL_S = 0.01  # wall seconds per transport poll (bounds heartbeat jitter and close latency)


class _TransportWriter:
    """The file-like object pymavlink's MAVLink.send writes to."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport

    def write(self, data: bytes | bytearray) -> None:
        self.transport.send(bytes(data))


class MavlinkConnection:
    """One MAVLink endpoint with its reader thread.

    Args:
        endpoint: where to listen or connect.
        clock: time source of the heartbeat period, message stamps and signing timestamps.
        source_system, source_component: our MAVLink identity.
        heartbeat_type: the MAV_TYPE our HEARTBEAT announces.
        signing: MAVLink 2 signing key and link id, or None for unsigned.
        state: receives every parsed message (``handle``) and a ``wake`` after each batch.
    """

    def __init__(
        self,
        endpoint: Endpoint,
        clock: Clock,
        source_system: int,
        source_component: int,
        heartbeat_type: int,
        signing: SigningSettings | None,
        state: VehicleState,
    ) -> None:
        self.endpoint = endpoint
        self._clock = clock
        self._source = (source_system, source_component)
        self._hb_type = heartbeat_type
        self._signing = signing
        self._state = state
        self._transport: Transport | None = None
        self._tx: Any = None  # pymavlink MAVLink used for sending (under _tx_lock)
        self._rx: Any = None  # pymavlink MAVLink used for parsing (reader thread only)
        self._tx_lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self.packets_sent = 0
        self.local_port = 0  # our local UDP/TCP port (0 before open and for serial)

    @property
    def opened(self) -> bool:
        """True once :meth:`open` succeeded (and still after :meth:`close`)."""
        return self._transport is not None

    async def open(self, timeout_s: float) -> None:
        """Open the endpoint and start the reader thread; returns once it runs.

        Raises:
            EndpointError: the endpoint cannot be opened (port in use, no such device).
        """
        self._transport = await asyncio.to_thread(open_transport, self.endpoint, timeout_s)
        self.local_port = self._transport.local_port
        writer = _TransportWriter(self._transport)
        self._tx = mavlink2.MAVLink(writer, *self._source)
        self._rx = mavlink2.MAVLink(None, *self._source)
        self._rx.robust_parsing = True
        if self._signing is not None:
            now_ns = self._clock.time_ns()
            apply_signing(self._tx, self._signing, now_ns)
            apply_signing(self._rx, self._signing, now_ns)
        self._stop_reader.clear()
        self._reader = threading.Thread(
            target=self._read_loop, name=f"mavlink-reader {self.endpoint.url}", daemon=True
        )
        self._reader.start()
        logger.debug("listening on %s (local port %d)", self.endpoint.url, self.local_port)

    async def close(self) -> None:
        """Stop the reader thread and close the endpoint; returns when both are done."""
        self._stop_reader.set()
        if self._reader is not None:
            await asyncio.to_thread(self._reader.join, 2.0)
            self._reader = None
        with self._tx_lock:
            self._tx = None
            if self._transport is not None:
                self._transport.close()

    def pin_last_sender(self) -> None:
        """Reply only to the address the last packet came from (the autopilot's)."""
        sender = self._transport.last_sender if self._transport is not None else None
        if sender is not None and self._transport is not None:
            self._transport.pin_peer(sender)

    def send(self, msg: Any) -> None:
        """Send one message (any thread); dropped silently once closed."""
        with self._tx_lock:
            if self._tx is None:
                return
            if self._signing is not None:
                # pymavlink counts the timestamp up by one per packet; keep it at least at "now"
                # so an autopilot that restarts still accepts us as a fresh stream.
                self._tx.signing.timestamp = max(
                    self._tx.signing.timestamp, signing_timestamp(self._clock.time_ns())
                )
            self._tx.send(msg)
            self.packets_sent += 1

    def _read_loop(self) -> None:
        transport = self._transport
        assert transport is not None
        next_hb_s = self._clock.monotonic_s()
        while not self._stop_reader.is_set():
            data = transport.recv(_READER_POLL_S)
            if data:
                try:
                    msgs = self._rx.parse_buffer(data) or []
                except Exception as exc:  # noqa: BLE001 - a bad packet must not kill the reader
                    logger.debug("MAVLink parse error: %s", exc)
                    msgs = []
                if msgs:
                    now = self._clock.monotonic_s()
                    for msg in msgs:
                        self._state.handle(msg, now)
                    self._state.wake()
            now = self._clock.monotonic_s()
            if now >= next_hb_s:
                self._send_heartbeat()
                next_hb_s = max(next_hb_s + 1.0, now + 0.5)

    def _send_heartbeat(self) -> None:
        self.send(
            mavlink2.MAVLink_heartbeat_message(self._hb_type, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE, 3)
        )
