"""Clock exchange between hosts on the bus: the stamps an NTP-style offset estimate needs.

Each host that stamps data (a vehicle computer, a ground station) runs a :class:`ClockServer`
on ``<ns>/clock/<host>``: a Zenoh queryable that answers every query with the time it received
it (``t1``) and the time it answered (``t2``), on its injected :class:`~flightkit.clock.Clock`.
A :class:`ClockProbe` on another host queries it, stamping the query as it leaves (``t0``) and
the reply as it arrives (``t3``) on its own clock, and feeds the
:class:`~flightkit.calibration.clock_sync.ClockSync`, which keeps the offset of the remote clock
(min-RTT filter, drift fit).

Payloads: the reply is 16 bytes, ``t1`` and ``t2`` as little-endian int64 nanoseconds.
"""

from __future__ import annotations

import logging
import struct
import threading
import time

import zenoh

from flightkit.bus.keys import Keys, check_name
from flightkit.calibration.clock_sync import ClockOffsetEstimate, ClockSync, Exchange
from flightkit.clock import Clock
from flightkit.errors import BusError

__all__ = ["ClockProbe", "ClockServer", "clock_key"]

logger = logging.getLogger(__name__)

_REPLY = struct.Struct("<qq")


def clock_key(keys: Keys, host: str) -> str:
    """``<ns>/clock/<host>``."""
    return f"{keys.namespace}/clock/{check_name(host, 'host')}"


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
        t0 = self._clock.time_ns()
        replies = self._session.get(self.key, timeout=timeout_s)
        for reply in replies:
            t3 = self._clock.time_ns()
            if reply.ok is None:
                continue
            data = reply.ok.payload.to_bytes()
            if len(data) != _REPLY.size:
                raise BusError(f"a clock reply on {self.key} has {len(data)} bytes, not {_REPLY.size}")
            t1, t2 = _REPLY.unpack(data)
            ex = Exchange(t0, t1, t2, t3)
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
