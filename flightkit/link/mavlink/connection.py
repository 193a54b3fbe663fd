"""The wire under the pymavlink backend: one endpoint shared by every vehicle on it.

Several vehicles can sit behind one endpoint: a telemetry radio on a serial port, or a router
(mavlink-router, MAVProxy, the simulator's ``--shared-link``) forwarding several system ids
to one UDP port. The process opens each endpoint once: :class:`MavlinkConnection` owns the
transport (:mod:`flightkit.link.transports`), pymavlink's MAVLink 2 codec (ArduPilot dialect, a
superset of common) for each direction, signing when a key is configured, the **writer thread**
(once several vehicles share the link, senders only queue messages; it packs them, with
sequence numbers and signatures, and sends what queued together, so no control loop waits for a
lock shared by the fleet's senders, in a system call, or for the GIL after one; a vehicle alone
on its link sends from the caller's thread) and the **reader thread**. The reader parses
every packet once and hands it to the
:class:`~flightkit.link.mavlink.telemetry.VehicleState` of the vehicle whose system id sent it
(heartbeats of autopilots nobody claimed go to every vehicle, so a vehicle that waits for
another id can name what answered), wakes that vehicle's waiters, and sends our HEARTBEAT at
1 Hz, once for the whole link.

Each link holds a :class:`VehicleChannel`: it attaches its state to the endpoint's connection
(opening it on first use), sends on its behalf (messages carry their own ``target_system``),
counts its packets, and detaches on close; the connection closes with its last vehicle. When
the transport dies (a radio unplugged, a pseudo-terminal closed) every vehicle on it fails with
the same message. A listening endpoint on port 0 is never shared (each asks for a fresh port).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import logging
import threading
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.clock import Clock
from flightkit.errors import EndpointError, LinkError
from flightkit.link.endpoints import Endpoint
from flightkit.link.mavlink.encoding import MAV_AUTOPILOT_INVALID, MAV_STATE_ACTIVE
from flightkit.link.mavlink.telemetry import VehicleState
from flightkit.link.signing import SigningSettings, apply_signing, signing_timestamp
from flightkit.link.transports import Transport, open_transport

__all__ = ["LinkIdentity", "MavlinkConnection", "VehicleChannel"]

logger = logging.getLogger(__name__)

_READER_POLL_S = 0.01  # wall seconds per transport poll (bounds heartbeat jitter and close latency)
_WRITE_MAX_BYTES = 1200  # packets sent together stay in one unfragmented datagram


@dataclass(frozen=True, slots=True)
class LinkIdentity:
    """Who we are on a link; the vehicles that share an endpoint's connection share it.

    Attributes:
        source_system, source_component: our MAVLink ids.
        heartbeat_type: the MAV_TYPE our HEARTBEAT announces.
        signing: MAVLink 2 signing key and link id, or None for unsigned.
    """

    source_system: int
    source_component: int
    heartbeat_type: int
    signing: SigningSettings | None


class _Outbox:
    """Messages waiting for the writer thread (a link shared by several vehicles). Senders (control
    loops, setpoint streams) only append here: packing, sequence numbers, signing and the system
    call are the writer's, so a sender never waits for a lock held by a thread that lost the GIL,
    nor for the GIL after sendto."""

    def __init__(self) -> None:
        self.msgs: collections.deque[Any] = collections.deque()
        self.ready = threading.Event()

    def put(self, msg: Any) -> None:
        self.msgs.append(msg)
        self.ready.set()


class _Packets:
    """The file-like object pymavlink's MAVLink.send writes to (under the send lock)."""

    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, data: bytes | bytearray) -> None:
        self.packets.append(bytes(data))

    def take(self) -> list[bytes]:
        """Everything packed, in order, as writes of at most _WRITE_MAX_BYTES (several packets each)."""
        writes: list[bytes] = []
        chunk: list[bytes] = []
        size = 0
        for packet in self.packets:
            if chunk and size + len(packet) > _WRITE_MAX_BYTES:
                writes.append(b"".join(chunk))
                chunk, size = [], 0
            chunk.append(packet)
            size += len(packet)
        if chunk:
            writes.append(b"".join(chunk))
        self.packets = []
        return writes


class MavlinkConnection:
    """One MAVLink endpoint, its reader thread and the vehicles on it.

    Args:
        endpoint: where to listen or connect.
        clock: time source of the heartbeat period, message stamps and signing timestamps.
        identity: our ids, heartbeat type and signing.

    Get one through :meth:`VehicleChannel.open`, which shares it by endpoint URL.
    """

    def __init__(self, endpoint: Endpoint, clock: Clock, identity: LinkIdentity) -> None:
        self.endpoint = endpoint
        self.identity = identity
        self._clock = clock
        self._transport: Transport | None = None
        self._tx: Any = None  # pymavlink MAVLink used for sending (under _tx_lock)
        self._rx: Any = None  # pymavlink MAVLink used for parsing (reader thread only)
        self._sending = False  # True from open until close or failure
        self._queued = False  # True once a second vehicle shares the link: senders queue for the writer
        self._tx_lock = threading.Lock()  # packing and writing, in order
        self._reader: threading.Thread | None = None
        self._writer: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._outbox = _Outbox()
        self._packets = _Packets()
        self._opening: concurrent.futures.Future[None] | None = None
        self._routes_lock = threading.Lock()
        self._by_system: dict[int, VehicleState] = {}
        self._any: VehicleState | None = None  # a lone vehicle that takes the first autopilot heard
        self.failure: str | None = None  # why the transport died (every vehicle on it fails)
        self.local_port = 0  # our local UDP/TCP port (0 before open and for serial)

    # ------------------------------------------------------------------ vehicles

    @property
    def vehicles(self) -> int:
        """How many vehicles are attached."""
        with self._routes_lock:
            return len(self._by_system) + (self._any is not None)

    def attach(self, state: VehicleState, system_id: int | None) -> None:
        """Route the messages of ``system_id`` (None: of the first autopilot heard) to ``state``.

        Raises:
            LinkError: the endpoint already serves that system id, or a vehicle without a system id
                would share it.
        """
        url = self.endpoint.url
        with self._routes_lock:
            if self._any is not None or (system_id is None and self._by_system):
                raise LinkError(
                    f"several vehicles share {url} but one has no link.system_id; give each vehicle on a shared "
                    "link its autopilot's system id (SYSID_THISMAV / MAV_SYS_ID)"
                )
            if system_id is None:
                self._any = state
                return
            if system_id in self._by_system:
                raise LinkError(
                    f"two vehicles on {url} name system id {system_id}; give each vehicle its own autopilot's "
                    "system id"
                )
            self._by_system[system_id] = state
            self._queued = self._queued or len(self._by_system) > 1

    def detach(self, state: VehicleState) -> int:
        """Stop routing to ``state``; returns how many vehicles remain."""
        with self._routes_lock:
            if self._any is state:
                self._any = None
            for sysid in [s for s, st in self._by_system.items() if st is state]:
                del self._by_system[sysid]
            return len(self._by_system) + (self._any is not None)

    def _states(self) -> list[VehicleState]:
        with self._routes_lock:
            return [*self._by_system.values(), *([self._any] if self._any is not None else [])]

    # ------------------------------------------------------------------ lifetime

    async def open(self, timeout_s: float) -> None:
        """Open the endpoint and start the reader thread, once; later callers wait for the first.

        Raises:
            EndpointError: the endpoint cannot be opened (port in use, no such device).
        """
        with self._routes_lock:
            first = self._opening is None
            if first:
                self._opening = concurrent.futures.Future()
            opening = self._opening
        assert opening is not None
        if not first:
            await asyncio.wrap_future(opening)
            return
        try:
            transport = await asyncio.to_thread(open_transport, self.endpoint, timeout_s)
        except BaseException as exc:
            opening.set_exception(exc)
            raise
        self._start(transport)
        opening.set_result(None)

    def _start(self, transport: Transport) -> None:
        self._transport = transport
        self.local_port = transport.local_port
        ident = self.identity
        self._tx = mavlink2.MAVLink(self._packets, ident.source_system, ident.source_component)
        self._rx = mavlink2.MAVLink(None, ident.source_system, ident.source_component)
        self._rx.robust_parsing = True
        if ident.signing is not None:
            now_ns = self._clock.time_ns()
            apply_signing(self._tx, ident.signing, now_ns)
            apply_signing(self._rx, ident.signing, now_ns)
        self._stop_reader.clear()
        self._sending = True
        self._reader = threading.Thread(
            target=self._read_loop, name=f"mavlink-reader {self.endpoint.url}", daemon=True
        )
        self._reader.start()
        self._writer = threading.Thread(
            target=self._write_loop, name=f"mavlink-writer {self.endpoint.url}", daemon=True
        )
        self._writer.start()
        logger.debug("listening on %s (local port %d)", self.endpoint.url, self.local_port)

    async def close(self) -> None:
        """Stop the reader, send what is queued, stop the writer and close the endpoint; returns
        when all are done."""
        self._stop_reader.set()
        self._outbox.ready.set()
        for attr in ("_reader", "_writer"):
            thread = getattr(self, attr)
            if thread is not None:
                await asyncio.to_thread(thread.join, 2.0)
                setattr(self, attr, None)
        with self._tx_lock:
            self._sending = False
            if self._transport is not None:
                self._transport.close()

    def pin_last_sender(self) -> None:
        """Reply only to the address the last packet came from (the autopilot's, or its router's)."""
        transport = self._transport
        sender = transport.last_sender if transport is not None else None
        if sender is not None and transport is not None:
            transport.pin_peer(sender)

    def send(self, msg: Any) -> bool:
        """Send one message (any thread); False (dropped) once closed or dead. Alone on the link it
        goes out at once from the caller's thread; with vehicles sharing it, it is queued for the
        writer thread."""
        if not self._sending:
            return False
        if self._queued:
            self._outbox.put(msg)
            return True
        with self._tx_lock:
            if not self._sending:
                return False
            self._pack(msg)
            self._flush()
        return True

    def _pack(self, msg: Any) -> None:
        """Pack one message into ``_packets`` (under ``_tx_lock``)."""
        signing = self.identity.signing
        if signing is not None:
            # pymavlink counts the timestamp up by one per packet; keep it at least at "now"
            # so an autopilot that restarts still accepts us as a fresh stream.
            self._tx.signing.timestamp = max(self._tx.signing.timestamp, signing_timestamp(self._clock.time_ns()))
        self._tx.send(msg)

    def _flush(self) -> None:
        """Write what is packed (under ``_tx_lock``)."""
        transport = self._transport
        for data in self._packets.take():
            if transport is not None:
                transport.send(data)

    # ------------------------------------------------------------------ reader thread

    def _read_loop(self) -> None:
        transport = self._transport
        assert transport is not None
        next_hb_s = self._clock.monotonic_s()
        while not self._stop_reader.is_set():
            try:
                data = transport.recv(_READER_POLL_S)
            except EndpointError as exc:
                self._fail(str(exc))
                return
            if data:
                try:
                    msgs = self._rx.parse_buffer(data) or []
                except Exception as exc:  # noqa: BLE001 - a bad packet must not kill the reader
                    logger.debug("MAVLink parse error: %s", exc)
                    msgs = []
                if msgs:
                    self._route(msgs)
            now = self._clock.monotonic_s()
            if now >= next_hb_s:
                self._send_heartbeat()
                next_hb_s = max(next_hb_s + 1.0, now + 0.5)

    def _write_loop(self) -> None:
        outbox = self._outbox
        while True:
            outbox.ready.wait()
            outbox.ready.clear()
            with self._tx_lock:
                while outbox.msgs:
                    msg = outbox.msgs.popleft()
                    try:
                        self._pack(msg)
                    except Exception:  # noqa: BLE001 - one bad message must not stop the link's sending
                        logger.exception("cannot pack %s for %s; dropped", msg.get_type(), self.endpoint.url)
                self._flush()
            if self._stop_reader.is_set() and not outbox.msgs:
                return

    def _route(self, msgs: list[Any]) -> None:
        now = self._clock.monotonic_s()
        with self._routes_lock:
            by_system, lone = self._by_system, self._any
            woken: set[int] = set()
            for msg in msgs:
                state = lone if lone is not None else by_system.get(msg.get_srcSystem())
                if state is not None:
                    state.handle(msg, now)
                    woken.add(id(state))
                elif msg.get_type() in ("HEARTBEAT", "BAD_DATA"):
                    # nobody's autopilot: every vehicle hears it (and can name it when it waits for another id)
                    for other in by_system.values():
                        other.handle(msg, now)
            states = [s for s in by_system.values() if id(s) in woken]
            if lone is not None and id(lone) in woken:
                states.append(lone)
        for state in states:
            state.wake()

    def _fail(self, why: str) -> None:
        states = self._states()
        with self._routes_lock:
            ids = sorted(self._by_system)
        who = f"system{'s' if len(ids) > 1 else ''} {', '.join(map(str, ids))}" if ids else "its vehicle"
        self.failure = (
            f"the link {self.endpoint.url} failed ({why}); every vehicle on it ({who}) lost its connection: "
            "check the radio or cable, then reconnect"
        )
        logger.error("%s", self.failure)
        self._sending = False
        for state in states:
            state.fail(self.failure)

    def _send_heartbeat(self) -> None:
        self.send(
            mavlink2.MAVLink_heartbeat_message(
                self.identity.heartbeat_type, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE, 3
            )
        )


# ---------------------------------------------------------------------- sharing by URL

_shared_lock = threading.Lock()
_shared: dict[tuple[str, LinkIdentity], MavlinkConnection] = {}


def _share_key(endpoint: Endpoint, identity: LinkIdentity) -> tuple[str, LinkIdentity] | None:
    """The key vehicles on one endpoint share, or None when each must open its own. A client with
    another identity (a second ground station in this process) opens its own connection."""
    if endpoint.listens and endpoint.port == 0:
        return None
    return endpoint.url, identity


class VehicleChannel:
    """One vehicle's use of an endpoint: its state attached to the (shared) connection.

    Args:
        endpoint: where its autopilot is reached.
        clock: time source (the connection takes the first vehicle's).
        identity: our ids, heartbeat type and signing on this link.
        state: receives this vehicle's messages.
        system_id: the vehicle's autopilot system id (None: the first autopilot heard; the
            endpoint is then not shared).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        clock: Clock,
        identity: LinkIdentity,
        state: VehicleState,
        system_id: int | None,
    ) -> None:
        self.endpoint = endpoint
        self._clock = clock
        self._identity = identity
        self._state = state
        self._system_id = system_id
        self._conn: MavlinkConnection | None = None
        self._attached = False
        self.packets_sent = 0

    @property
    def opened(self) -> bool:
        """True once :meth:`open` succeeded (and still after :meth:`close`)."""
        return self._conn is not None

    @property
    def local_port(self) -> int:
        """Our local UDP/TCP port (0 before open and for serial)."""
        return self._conn.local_port if self._conn is not None else 0

    @property
    def shared_with(self) -> int:
        """How many vehicles use this endpoint (this one included; 0 before open)."""
        return self._conn.vehicles if self._conn is not None else 0

    async def open(self, timeout_s: float) -> None:
        """Attach to the endpoint's connection, opening it if this is its first vehicle.

        Raises:
            EndpointError: the endpoint cannot be opened. LinkError: the vehicle cannot share it
                (see :meth:`MavlinkConnection.attach`).
        """
        key = _share_key(self.endpoint, self._identity)
        with _shared_lock:
            conn = _shared.get(key) if key is not None else None
            if conn is None or conn.failure is not None:
                conn = MavlinkConnection(self.endpoint, self._clock, self._identity)
                if key is not None:
                    _shared[key] = conn
            conn.attach(self._state, self._system_id)
        try:
            await conn.open(timeout_s)
        except BaseException:
            await self._release(conn)
            raise
        self._conn = conn
        self._attached = True

    async def close(self) -> None:
        """Detach; the connection closes with its last vehicle. Idempotent."""
        if self._attached and self._conn is not None:
            self._attached = False
            await self._release(self._conn)

    async def _release(self, conn: MavlinkConnection) -> None:
        with _shared_lock:
            left = conn.detach(self._state)
            if left == 0:
                key = _share_key(self.endpoint, self._identity)
                if key is not None and _shared.get(key) is conn:
                    del _shared[key]
        if left == 0:
            await conn.close()

    def pin_last_sender(self) -> None:
        """Reply only to the address the autopilot's packets come from (reader thread)."""
        if self._conn is not None:
            self._conn.pin_last_sender()

    def send(self, msg: Any) -> None:
        """Send one message on this vehicle's behalf (any thread); dropped once closed."""
        conn = self._conn
        if conn is not None and self._attached and conn.send(msg):
            self.packets_sent += 1
