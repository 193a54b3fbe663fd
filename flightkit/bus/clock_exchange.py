"""Clock exchange between hosts on the bus: the stamps an NTP-style offset estimate needs.

Each host that stamps data (a vehicle computer, a ground station) runs a :class:`ClockServer`
on ``<ns>/clock/<host>``: a Zenoh queryable that answers every query with the time it received
it (``t1``) and the time it answered (``t2``), on its injected :class:`~flightkit.clock.Clock`.
A :class:`ClockProbe` on another host queries it, stamping the query as it leaves (``t0``) and
the reply as it arrives (``t3``) on its own clock, and feeds the
:class:`~flightkit.calibration.clock_sync.ClockSync`, which keeps the offset of the remote clock
(min-RTT filter, drift fit).

:class:`ClockWatch` is what a host runs to put every host on one time base: it serves its own
clock and probes every other server in the namespace (``<ns>/clock/*``) continuously, one
:class:`ClockSync` per host. ``flightkit record`` runs one and stores the offsets in the
recording (metadata record :data:`~flightkit.calibration.clock_sync.CLOCK_OFFSETS_RECORD`, read back with
:meth:`flightkit.datasets.mcap_reader.RecordingReader.clock_offsets`); the simulated lab serves
its clock as host ``sim``.

Payloads: the reply is 16 bytes, ``t1`` and ``t2`` as little-endian int64 nanoseconds.
"""

from __future__ import annotations

import logging
import re
import socket
import struct
import threading
import time
from collections.abc import Iterator
from typing import Self

import zenoh

from flightkit.bus.keys import Keys, check_name
from flightkit.calibration.clock_sync import ClockOffsetEstimate, ClockSync, Exchange, offsets_to_metadata
from flightkit.clock import Clock, sleep_until
from flightkit.errors import BusError
from flightkit.lifetime import Running

__all__ = ["ClockProbe", "ClockServer", "ClockWatch", "bus_host_name", "clock_key"]

logger = logging.getLogger(__name__)

_REPLY = struct.Struct("<qq")


def clock_key(keys: Keys, host: str) -> str:
    """``<ns>/clock/<host>``."""
    return f"{keys.namespace}/clock/{check_name(host, 'host')}"


def bus_host_name() -> str:
    """This machine's host name as a bus name (characters a key chunk refuses become ``_``)."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname()) or "host"


def _exchanges(session: zenoh.Session, key: str, clock: Clock, timeout_s: float) -> Iterator[tuple[str, Exchange]]:
    """Query ``key`` (one host's or ``<ns>/clock/*``) and yield (host, exchange) per reply as it arrives.

    Raises:
        BusError: a malformed reply.
    """
    t0 = clock.time_ns()
    for reply in session.get(key, timeout=timeout_s):
        t3 = clock.time_ns()
        if reply.ok is None:
            continue
        data = reply.ok.payload.to_bytes()
        if len(data) != _REPLY.size:
            raise BusError(f"a clock reply on {reply.ok.key_expr} has {len(data)} bytes, not {_REPLY.size}")
        t1, t2 = _REPLY.unpack(data)
        yield str(reply.ok.key_expr).rsplit("/", 1)[-1], Exchange(t0, t1, t2, t3)


class ClockServer:
    """Answer clock queries on ``<ns>/clock/<host>`` with this host's receive and reply stamps.

    Args:
        session: an open Zenoh session.
        keys: the namespace.
        host: this host's name on the bus.
        clock: the clock whose stamps this host records.

    Close with :meth:`close` (or ``with``).
    """

    def __init__(self, session: zenoh.Session, keys: Keys, host: str, clock: Clock) -> None:
        self.key = clock_key(keys, host)
        self._clock = clock
        self.answered = 0
        self._q: zenoh.Queryable[None] | None = session.declare_queryable(self.key, self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        t1 = self._clock.time_ns()
        try:
            query.reply(self.key, _REPLY.pack(t1, self._clock.time_ns()))
            self.answered += 1
        except Exception:  # a query whose asker went away
            logger.debug("clock query on %s could not be answered", self.key, exc_info=True)

    def close(self) -> None:
        """Undeclare the queryable; idempotent."""
        q, self._q = self._q, None
        if q is not None:
            q.undeclare()

    def __enter__(self) -> ClockServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ClockProbe:
    """Exchange stamps with a remote :class:`ClockServer` and keep the remote clock's offset.

    Args:
        session: an open Zenoh session.
        keys: the namespace.
        host: the remote host's name.
        clock: this host's clock.
        sync: where the exchanges go (default: a 60 s :class:`ClockSync`).
    """

    def __init__(self, session: zenoh.Session, keys: Keys, host: str, clock: Clock,
                 sync: ClockSync | None = None) -> None:
        self.key = clock_key(keys, host)
        self._session = session
        self._clock = clock
        self.sync = sync or ClockSync()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def exchange(self, timeout_s: float = 1.0) -> Exchange:
        """One exchange; blocks until the reply arrives (at most ``timeout_s`` of wall time).

        Raises:
            BusError: no reply within ``timeout_s`` (no server on the key), or a malformed reply.
        """
        for _, ex in _exchanges(self._session, self.key, self._clock, timeout_s):
            self.sync.add(ex)
            return ex
        raise BusError(f"no clock reply on {self.key} within {timeout_s:g} s; is a ClockServer running there?")

    def wait_for_server(self, timeout_s: float = 5.0) -> Exchange:
        """Exchange until the server answers (a queryable takes a moment to be routed after it is
        declared); returns the first exchange. Blocks for at most ``timeout_s`` of wall time.

        Raises:
            BusError: no answer within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                return self.exchange(timeout_s=max(0.05, min(0.5, left)))
            except BusError:
                if time.monotonic() >= deadline:
                    raise BusError(
                        f"no clock server answered on {self.key} within {timeout_s:g} s; is a ClockServer running "
                        "there, and are the hosts on one bus?"
                    ) from None

    def estimate(self) -> ClockOffsetEstimate:
        """The remote clock's offset over the history (see :class:`ClockSync`).

        Raises:
            CalibrationError: no exchange yet.
        """
        return self.sync.estimate()

    def start(self, interval_s: float = 0.5) -> ClockProbe:
        """Exchange every ``interval_s`` (this clock's time) on a thread; returns immediately."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, args=(interval_s,), name="clock-probe", daemon=True)
            self._thread.start()
        return self

    def _run(self, interval_s: float) -> None:
        while not self._stop.is_set():
            try:
                self.exchange()
            except BusError as exc:
                logger.debug("clock exchange failed: %s", exc)
            self._clock.sleep_blocking(interval_s)

    def stop(self) -> None:
        """Stop the thread (blocks for at most one interval); idempotent."""
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None:
            t.join(5.0)


class ClockWatch(Running):
    """Serve this host's clock and keep the offset of every other host's clock in the namespace.

    Args:
        session: an open Zenoh session.
        keys: the namespace the clocks are served in.
        host: this host's name on the bus (its own server is not probed).
        clock: this host's clock (the time base the offsets are relative to).
        interval_s: time between exchange rounds (this clock's time).

    Use ``with`` or :meth:`start` / :meth:`stop`; :meth:`estimates` any time.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, host: str, clock: Clock, interval_s: float = 0.5) -> None:
        self.host = check_name(host, "host")
        self._session = session
        self._keys = keys
        self._clock = clock
        self.interval_s = interval_s
        self._pattern = f"{keys.namespace}/clock/*"
        self._syncs: dict[str, ClockSync] = {}
        self._lock = threading.Lock()
        self._server: ClockServer | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def exchange_round(self, timeout_s: float = 1.0) -> int:
        """One round with every server that answers within ``timeout_s``; returns how many did."""
        n = 0
        for host, ex in _exchanges(self._session, self._pattern, self._clock, timeout_s):
            if host == self.host:
                continue
            with self._lock:
                self._syncs.setdefault(host, ClockSync()).add(ex)
            n += 1
        return n

    def estimates(self) -> dict[str, ClockOffsetEstimate]:
        """Every other host's clock against this one (hosts that answered at least once)."""
        with self._lock:
            syncs = dict(self._syncs)
        return {host: sync.estimate() for host, sync in sorted(syncs.items())}

    def to_metadata(self) -> dict[str, str]:
        """The estimates as the recording metadata record :data:`CLOCK_OFFSETS_RECORD`."""
        return offsets_to_metadata(self.host, self.estimates())

    def start(self) -> Self:
        """Serve this clock and probe the others on a thread; returns immediately."""
        if self._thread is None:
            self._server = ClockServer(self._session, self._keys, self.host, self._clock)
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="clock-watch", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.exchange_round(timeout_s=min(0.25, self.interval_s))  # a stop waits at most this
            except BusError as exc:
                logger.debug("clock exchange round failed: %s", exc)
            except Exception:  # the session closed under us
                if not self._stop.is_set():
                    logger.exception("clock watch stopped")
                return
            sleep_until(self._clock, self._clock.monotonic_s() + self.interval_s, self._stop)

    def stop(self) -> None:
        """Stop probing and serving (blocks for at most one round); idempotent."""
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None:
            t.join(5.0)
        server, self._server = self._server, None
        if server is not None:
            server.close()
