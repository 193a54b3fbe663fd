"""Several simulated autopilots behind one endpoint: one UDP port, or one pseudo-terminal "radio".

A lab that reaches its vehicles through a telemetry radio, or through a router such as
mavlink-router forwarding several system ids to one port, gives the ground one endpoint for the
whole fleet. :class:`SimRouter` plays that part for the simulated lab: each
:class:`~flightkit.sim.autopilot.SimAutopilot` keeps its own loopback UDP port; the router is
their one client and serves them all on

* ``udpin:HOST:PORT``: one UDP port (port 0 picks a free one); replies go to whoever last sent to it;
* ``pty``: a pseudo-terminal whose device (``/dev/pts/N``) the ground opens as a serial port.

Towards the autopilots a message goes to the one its ``target_system`` names, or to all when it
names none (heartbeats, external poses), as a router does; every autopilot's packets go out on
the shared endpoint as they are (their system ids tell them apart). Stopping the router closes
the endpoint: a ground station on the pty then sees its serial device die.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import threading
import tty
from collections.abc import Mapping
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.errors import SimError
from flightkit.lifetime import Running
from flightkit.sim.autopilot.options import parse_endpoint

__all__ = ["PTY", "SimRouter"]

logger = logging.getLogger(__name__)

PTY = "pty"
"""The shared endpoint kind of a simulated serial radio (a pseudo-terminal)."""

_POLL_S = 0.05  # wall seconds per select (bounds the stop latency)
_MAX_DATAGRAM = 65535
_DRAIN_DATAGRAMS = 32
_RCVBUF_BYTES = 1 << 20


class SimRouter(Running):
    """One shared endpoint in front of several simulated autopilots.

    Args:
        autopilots: system id -> the (host, port) its autopilot listens on.
        shared: ``udpin:HOST:PORT`` (one UDP port) or ``pty`` (a pseudo-terminal radio).
        baud: the baud rate written into :attr:`client_url` for a pty (a pty ignores it).

    ``start()`` opens the endpoint and the forwarding thread; ``stop()`` closes both.
    """

    def __init__(self, autopilots: Mapping[int, tuple[str, int]], shared: str, *, baud: int = 57600) -> None:
        if not autopilots:
            raise SimError("a shared link needs at least one simulated autopilot behind it; add vehicles")
        self._autopilots = dict(autopilots)
        self._shared = shared.strip()
        if self._shared != PTY:
            kind, self._host, self._port = parse_endpoint(self._shared)
            if kind != "udpin":
                raise SimError(
                    f"a shared simulated link listens; give udpin:HOST:PORT or {PTY!r}, not {shared!r}"
                )
        self._baud = baud
        self._parser: Any = None
        self._inward: socket.socket | None = None
        self._outward: socket.socket | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._peer: tuple[str, int] | None = None
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self.device = ""  # the pty's device path ("" for UDP)
        self.dropped = 0  # packets the radio could not take (the ground was not reading)

    @property
    def client_url(self) -> str:
        """What every vehicle's link.url names (after :meth:`start`)."""
        if self._shared == PTY:
            if not self.device:
                raise SimError("the shared radio is not started, so it has no device; call start() first")
            return f"serial:{self.device}:{self._baud}"
        if self._outward is None:
            raise SimError("the shared port is not started, so it has no port; call start() first")
        return f"udpout:{self._host}:{self._outward.getsockname()[1]}"

    def start(self) -> SimRouter:
        """Open the shared endpoint and start forwarding; returns immediately."""
        if self._running.is_set():
            return self
        self._parser = mavlink2.MAVLink(None, 0, 0)
        self._parser.robust_parsing = True
        self._inward = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._inward.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF_BYTES)
        self._inward.bind(("127.0.0.1", 0))
        if self._shared == PTY:
            self._master, self._slave = os.openpty()
            tty.setraw(self._slave)  # no echo or line editing before the ground configures the port
            os.set_blocking(self._master, False)
            self.device = os.ttyname(self._slave)
        else:
            self._outward = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                self._outward.bind((self._host, self._port))
            except OSError as exc:
                self.stop()
                raise SimError(
                    f"cannot bind the shared simulated link to {self._host}:{self._port}: {exc.strerror or exc}; "
                    "stop whatever uses that port or pick another"
                ) from exc
        self._running.set()
        self._thread = threading.Thread(target=self._forward_loop, name="sim-router", daemon=True)
        self._thread.start()
        logger.info("%d simulated autopilots behind %s", len(self._autopilots), self.client_url)
        return self

    def stop(self) -> None:
        """Stop forwarding and close the shared endpoint; idempotent."""
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for sock in (self._inward, self._outward):
            if sock is not None:
                sock.close()
        self._inward = self._outward = None
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None

    # ------------------------------------------------------------------ forwarding thread

    def _forward_loop(self) -> None:
        inward = self._inward
        assert inward is not None
        outward: Any = self._outward if self._outward is not None else self._master
        while self._running.is_set():
            try:
                ready, _, _ = select.select([inward, outward], [], [], _POLL_S)
            except (OSError, ValueError):
                return
            if inward in ready:
                self._from_autopilots(inward)
            if outward in ready:
                self._from_ground()

    def _from_autopilots(self, inward: socket.socket) -> None:
        chunks: list[bytes] = []
        for _ in range(_DRAIN_DATAGRAMS):  # everything queued, sent on as one write
            try:
                chunks.append(inward.recv(_MAX_DATAGRAM, socket.MSG_DONTWAIT))
            except OSError:
                break
        if not chunks:
            return
        data = b"".join(chunks)
        if self._master is not None:
            try:
                os.write(self._master, data)
            except OSError:  # the ground is not reading: the radio's buffer is full
                self.dropped += 1
        elif self._outward is not None and self._peer is not None:
            try:
                self._outward.sendto(data, self._peer)
            except OSError as exc:
                logger.debug("shared link send to %s failed: %s", self._peer, exc)

    def _from_ground(self) -> None:
        try:
            if self._master is not None:
                data = os.read(self._master, _MAX_DATAGRAM)
            else:
                assert self._outward is not None
                data, addr = self._outward.recvfrom(_MAX_DATAGRAM)
                self._peer = (str(addr[0]), int(addr[1]))
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # the pty has no reader yet
            return
        try:
            msgs = self._parser.parse_buffer(data) or []
        except Exception as exc:  # noqa: BLE001 - corrupt input must never stop the router
            logger.debug("unparsable bytes on the shared link: %s", exc)
            return
        inward = self._inward
        assert inward is not None
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                continue
            buf = bytes(msg.get_msgbuf())
            target = getattr(msg, "target_system", 0)
            addrs = [self._autopilots[target]] if target in self._autopilots else self._autopilots.values()
            for addr in addrs:
                try:
                    inward.sendto(buf, addr)
                except OSError as exc:
                    logger.debug("forward to %s failed: %s", addr, exc)
