"""A serial port driven by one thread, carrying one protocol endpoint.

The port is anything :func:`serial.serial_for_url` opens: ``/dev/ttyUSB0`` or
``/dev/ttyACM0`` (a BLE UART dongle), ``/dev/serial/by-id/...``, ``rfc2217://host:port``,
``socket://host:port`` (a TCP serial bridge) or ``loop://``.

The thread reads whatever arrived, hands it to the endpoint, and asks the endpoint for the
next frame only when the line is free. "Free" is computed from the baud rate: after writing
``n`` bytes the line is busy for ``n * bits_per_byte / baud`` seconds (10 bits per byte for
8N1). Pacing matters twice: on a pseudo-terminal or TCP bridge (no baud limit) it gives
honest throughput figures, and on a real port it keeps the OS transmit buffer empty, so a
pose is chosen at the moment it can actually leave and an old pose never waits in a kernel
buffer behind... itself. ``link_rate_bps`` lets a slower radio (BLE UART throughput is often
below the dongle's serial baud) be paced at its real rate.

If the port vanishes (USB dongle unplugged, pty closed, TCP bridge gone) the thread logs one
clear warning, keeps the endpoint (and its undelivered reliable messages), retries opening
the port every ``reopen_interval_s`` and resumes when it is back; the session's heartbeats
then detect the gap and re-handshake.
"""
from __future__ import annotations

import logging
import math
import os
import queue
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, Self, TypeVar

import serial

from flightkit.clock import Clock, WallClock
from flightkit.errors import ProtocolError
from flightkit.lifetime import Running

from .events import Event

__all__ = ["Endpoint", "PortLost", "PortOpened", "SerialTransport", "TransportEvent", "TransportStats"]

logger = logging.getLogger(__name__)

R = TypeVar("R")


class Endpoint(Protocol):
    """What a transport drives (:class:`~.endpoints.RobotEndpoint`, :class:`~.endpoints.ServerEndpoint`)."""

    def receive_bytes(self, data: bytes, now_s: float) -> None: ...
    def next_bytes(self, now_s: float) -> bytes | None: ...
    def poll(self, now_s: float) -> None: ...
    def next_deadline_s(self) -> float: ...
    def take_events(self) -> list[Event]: ...
    def on_port_reset(self) -> None: ...
    def close(self) -> None: ...


@dataclass(frozen=True, slots=True)
class PortOpened:
    url: str


@dataclass(frozen=True, slots=True)
class PortLost:
    url: str
    message: str


TransportEvent = Event | PortOpened | PortLost


@dataclass(slots=True)
class TransportStats:
    bytes_tx: int = 0
    bytes_rx: int = 0
    writes: int = 0
    opens: int = 0
    losses: int = 0


class SerialTransport(Running):
    """Run ``endpoint`` over the serial port ``url`` on a background thread.

    Use as a context manager (or call :meth:`start` / :meth:`stop`). Talk to the endpoint
    only through :meth:`call`, which runs a function under the transport's lock and wakes
    the thread so a new pose or message leaves without waiting for a timer. Events (the
    endpoint's and :class:`PortOpened` / :class:`PortLost`) go to ``on_event`` (called on
    the transport thread; keep it short) and to the :attr:`events` queue.

    Args:
        url: port name or URL for :func:`serial.serial_for_url`.
        endpoint: the protocol end to drive.
        baud: serial baud rate.
        clock: time for the protocol's timers (pacing always uses real time).
        pace: throttle writes to the line rate (keep True except on purpose).
        link_rate_bps: pace at this bit rate instead of ``baud`` (e.g. a BLE link's real rate).
        bits_per_byte: 10 for 8N1.
        reopen_interval_s: how often to retry a vanished port.
        on_event: optional callback for every event.
        queue_events: also put events on :attr:`events` (turn off if nobody drains it).
    """

    def __init__(
        self,
        url: str,
        endpoint: Endpoint,
        *,
        baud: int = 115200,
        clock: Clock | None = None,
        pace: bool = True,
        link_rate_bps: float | None = None,
        bits_per_byte: int = 10,
        reopen_interval_s: float = 0.5,
        on_event: Callable[[TransportEvent], None] | None = None,
        queue_events: bool = True,
    ) -> None:
        if baud <= 0:
            raise ProtocolError(f"baud {baud} must be positive; use e.g. 115200")
        self.url = url
        self.endpoint = endpoint
        self.baud = baud
        self.clock: Clock = clock or WallClock()
        self.pace = pace
        self.byte_time_s = bits_per_byte / float(link_rate_bps or baud)
        self.reopen_interval_s = reopen_interval_s
        self.on_event = on_event
        self.queue_events = queue_events
        self.events: queue.Queue[TransportEvent] = queue.Queue()
        self.stats = TransportStats()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._port: Any = None
        self._port_ok = threading.Event()
        self._line_free_at = 0.0
        self._lost_reported = False
        self._closing = False
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)

    # ------------------------------------------------------------------ lifetime

    def start(self) -> Self:
        """Start the thread; returns immediately (the port opens in the background)."""
        if self._thread is not None:
            return self
        now = self.clock.monotonic_s()
        with self._lock:
            start = getattr(self.endpoint, "start", None)
            if callable(start):
                start(now)
        self._thread = threading.Thread(target=self._run, name=f"serial:{self.url}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0, *, goodbye: bool = True) -> None:
        """Say goodbye (flushing it if the port is open), stop the thread and close the port."""
        if self._thread is None:
            return
        if goodbye and self._port_ok.is_set():
            with self._lock:
                self.endpoint.close()
            self._closing = True
            self._wake()
            deadline = time.monotonic() + min(timeout_s, 0.5)
            while self._closing and time.monotonic() < deadline and self._thread.is_alive():
                time.sleep(0.005)
        self._stop.set()
        self._wake()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            logger.warning("serial thread for %s did not stop within %.1f s", self.url, timeout_s)
        self._thread = None
        self._close_port()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    @property
    def port_open(self) -> bool:
        return self._port_ok.is_set()

    def wait_port_open(self, timeout_s: float) -> None:
        """Block until the port is open.

        Raises:
            ProtocolError: when it did not open within ``timeout_s``.
        """
        if not self._port_ok.wait(timeout_s):
            raise ProtocolError(
                f"serial port {self.url} did not open within {timeout_s:.1f} s; "
                "check the device path/URL, that the dongle is plugged in and that you may open it"
            )

    def call(self, fn: Callable[[Any], R]) -> R:
        """Run ``fn(endpoint)`` under the lock and wake the thread; returns its result."""
        with self._lock:
            result = fn(self.endpoint)
        self._wake()
        return result

    # ------------------------------------------------------------------ thread

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass  # already awake (pipe full) or shutting down

    def _open(self) -> bool:
        try:
            port = serial.serial_for_url(self.url, baudrate=self.baud, timeout=0.005, write_timeout=2.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._report_lost(f"cannot open serial port {self.url}: {exc}")
            return False
        if self._fileno(port) is not None:
            port.timeout = 0  # we select() ourselves; reads only take what is there
        self._port = port
        self._line_free_at = time.monotonic()
        self.stats.opens += 1
        self._lost_reported = False
        with self._lock:
            self.endpoint.on_port_reset()
        self._port_ok.set()
        logger.info("serial port %s open at %d baud", self.url, self.baud)
        self._emit([PortOpened(self.url)])
        return True

    def _report_lost(self, message: str) -> None:
        if self._lost_reported:
            return
        self._lost_reported = True
        full = f"{message}; retrying every {self.reopen_interval_s:g} s until it returns"
        logger.warning("%s", full)
        self._emit([PortLost(self.url, full)])

    def _close_port(self) -> None:
        port, self._port = self._port, None
        self._port_ok.clear()
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    def _emit(self, events: list[Any]) -> None:
        for ev in events:
            if self.queue_events:
                self.events.put(ev)
            if self.on_event is not None:
                try:
                    self.on_event(ev)
                except Exception:  # a broken callback must not kill the port thread
                    logger.exception("event callback failed on %r", ev)

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._port is None:
                if not self._open():
                    self._stop.wait(self.reopen_interval_s)
                    continue
            try:
                self._serve_once()
            except (serial.SerialException, OSError) as exc:
                self.stats.losses += 1
                self._close_port()
                self._closing = False
                self._report_lost(f"serial port {self.url} vanished ({exc}); is the dongle unplugged?")
                self._stop.wait(self.reopen_interval_s)
        self._closing = False

    def _serve_once(self) -> None:
        port = self._port
        assert port is not None
        # 1. write while the line is free
        while True:
            wall = time.monotonic()
            if self.pace and wall < self._line_free_at:
                break
            with self._lock:
                data = self.endpoint.next_bytes(self.clock.monotonic_s())
            if data is None:
                self._closing = False
                break
            port.write(data)
            self.stats.bytes_tx += len(data)
            self.stats.writes += 1
            if self.pace:
                self._line_free_at = max(self._line_free_at, wall) + len(data) * self.byte_time_s
        # 2. wait for input, a wake-up, the line to free up or the next protocol timer
        wall = time.monotonic()
        with self._lock:
            deadline = self.endpoint.next_deadline_s()
        line_wait_s = self._line_free_at - wall if self.pace else 0.0
        if deadline == -math.inf:
            wait_s = line_wait_s  # something is ready to go as soon as the line is free
        elif deadline == math.inf:
            wait_s = 0.05
        else:
            speed = self.clock.speed if math.isfinite(self.clock.speed) else 1.0
            wait_s = (deadline - self.clock.monotonic_s()) / speed
        wait_s = min(max(wait_s, 0.0), 0.05)
        data = self._read(port, wait_s)
        with self._lock:
            now = self.clock.monotonic_s()
            if data:
                self.endpoint.receive_bytes(data, now)
            self.endpoint.poll(now)
            events = self.endpoint.take_events()
        if events:
            self._emit(events)

    def _read(self, port: Any, wait_s: float) -> bytes:
        fd = self._fileno(port)
        if fd is None:
            # No file descriptor (loop://): a short blocking read is the best we can do.
            data: bytes = port.read(max(1, port.in_waiting))
        else:
            ready, _, _ = select.select([fd, self._wake_r], [], [], wait_s)
            if self._wake_r in ready:
                try:
                    os.read(self._wake_r, 4096)
                except BlockingIOError:
                    pass
            if fd not in ready:
                return b""
            data = port.read(max(1, port.in_waiting))
        if data:
            self.stats.bytes_rx += len(data)
        return data

    @staticmethod
    def _fileno(port: Any) -> int | None:
        try:
            fd = port.fileno()
        except (AttributeError, OSError, serial.SerialException, NotImplementedError):
            return None
        return fd if isinstance(fd, int) and fd >= 0 else None
