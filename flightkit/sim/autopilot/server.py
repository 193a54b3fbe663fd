"""SimAutopilot: the simulated autopilot's UDP socket, its two threads and the control tick.

:class:`SimAutopilot` binds a real UDP socket (``udpin`` answers every sender, ``udpout``
sends to a listening client as PX4 SITL does), runs one thread that receives datagrams and
handles each message at once (so COMMAND_ACKs go out without waiting for a tick), and one
that runs the control loop (modes, physics, estimator, streams) on the injected clock (or
none: a fleet's :class:`~flightkit.sim.stepper.SimStepper` ticks every autopilot from one
thread through :meth:`SimAutopilot.step`). Both take one lock. The behaviour itself comes from the layers it inherits
(:mod:`.core`, :mod:`.flight`, :mod:`.telemetry`, :mod:`.commands`).
"""

from __future__ import annotations

import logging
import math
import socket
import threading

from flightkit.errors import EndpointError, SimError
from flightkit.sim.autopilot.commands import _AutopilotInbound
from flightkit.sim.autopilot.core import _Client

__all__ = ['MAX_TICK_S', 'SimAutopilot']

logger = logging.getLogger(__name__)

MAX_TICK_S = 0.25
"""The longest physics step (clock seconds) one tick takes; a longer stall of the loop thread
loses the rest, so the vehicle pauses rather than jumps."""


class SimAutopilot(_AutopilotInbound):
    """A simulated autopilot on a real UDP socket.

    Args:
        personality: PX4 or ArduPilot behaviour (:mod:`flightkit.sim.personality`).
        dynamics: the vehicle it flies; its start position becomes the local origin.
        clock: time source for everything (physics, streams, timeouts).
        options: endpoint and non-firmware knobs.
        on_event: called as ``on_event(kind, detail)`` on state changes (armed, disarmed,
            mode, takeoff, landed, failsafe, ...), from the simulator's threads.

    ``start()`` binds the socket and starts the threads; ``stop()`` ends them.
    """

    @property
    def bound_address(self) -> tuple[str, int]:
        """(host, port) of our socket; with ``udpin:...:0`` this is the port to connect to."""
        if self._bound is None:
            raise SimError("SimAutopilot is not started, so it has no bound address; call start() (or enter it) first")
        return self._bound

    @property
    def url(self) -> str:
        """The endpoint as started (port 0 resolved)."""
        if self._kind == "udpin":
            return f"udpin:{self._host}:{self.bound_address[1]}"
        return f"udpout:{self._host}:{self._port}"

    @property
    def client_url(self) -> str:
        """What a client passes to connect to us (pymavlink style): ``udpout:HOST:PORT`` or ``udpin:...``."""
        if self._kind == "udpin":
            return f"udpout:{self._host}:{self.bound_address[1]}"
        return f"udpin:{self._host}:{self._port}"

    def start(self, *, own_loop: bool = True) -> None:
        """Bind the socket and start the receive and control threads; returns immediately.

        With ``own_loop=False`` there is no control thread: whoever started it calls :meth:`step`
        every tick (a :class:`~flightkit.sim.stepper.SimStepper` ticking a fleet's autopilots).

        Raises:
            EndpointError: the address is in use or cannot be bound.
        """
        if self._running.is_set():
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if self._kind == "udpin":
                sock.bind((self._host, self._port))
            else:
                sock.bind(("0.0.0.0", self.options.local_port))
        except OSError as exc:
            sock.close()
            where = (
                f"{self._host}:{self._port}"
                if self._kind == "udpin"
                else f"local port {self.options.local_port}"
            )
            raise EndpointError(
                f"cannot bind the simulated autopilot to {where}: {exc.strerror or exc}; "
                "stop whatever uses that port (another sim or SITL?) or pick another port"
            ) from exc
        sock.settimeout(0.05)
        self._sock = sock
        self._bound = sock.getsockname()[:2]
        now = self.clock.monotonic_s()
        with self._lock:
            self._t0 = now
            self._last_tick_s = now
            if self._kind == "udpout":
                addr = (self._host, self._port)
                self._clients[addr] = _Client(addr, self._new_parser(), now, fixed=True)
            self._next_due = {m: now for m in self._intervals}
        self._running.set()
        self._threads = [threading.Thread(target=self._rx_loop, name="sim-autopilot-rx", daemon=True)]
        if own_loop:
            self._threads.append(threading.Thread(target=self._control_loop, name="sim-autopilot-loop", daemon=True))
        for t in self._threads:
            t.start()
        logger.info(
            "simulated %s autopilot on %s (bound %s:%d)",
            self.personality.autopilot.value,
            self.options.url,
            *self._bound,
        )

    def stop(self) -> None:
        """Stop the threads and close the socket; idempotent."""
        if not self._running.is_set():
            return
        self._running.clear()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        logger.info("simulated autopilot stopped")

    def __enter__(self) -> SimAutopilot:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _rx_loop(self) -> None:
        while self._running.is_set():
            sock = self._sock
            if sock is None:
                break
            try:
                data, addr = sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                if not self._running.is_set():
                    break
                continue
            now = self.clock.monotonic_s()
            if now < self._link_dead_until:
                continue
            with self._lock:
                client = self._clients.get(addr)
                if client is None:
                    if self._kind == "udpout":
                        # replies from the client's socket may come from another port
                        client = _Client(addr, self._new_parser(), now)
                    else:
                        client = _Client(addr, self._new_parser(), now)
                    self._clients[addr] = client
                    logger.info("new MAVLink client %s:%d", *addr)
                client.last_heard_s = now
                try:
                    msgs = client.parser.parse_buffer(data) or []
                except Exception as exc:  # corrupt input must never stop the simulator
                    logger.debug("unparsable datagram from %s: %s", addr, exc)
                    self.rejected_messages += 1
                    continue
                for msg in msgs:
                    if msg.get_type() == "BAD_DATA":
                        self.rejected_messages += 1
                        continue
                    try:
                        self._handle(msg, now)
                    except Exception:
                        logger.exception("handling %s failed", msg.get_type())

    def _control_loop(self) -> None:
        speed = self.clock.speed
        tick_sim_s = self.options.tick_wall_s * speed if math.isfinite(speed) else 0.01
        while self._running.is_set():
            self.step(self.clock.monotonic_s())
            self.clock.sleep_blocking(tick_sim_s)

    def step(self, now: float) -> None:
        """One control tick at clock time ``now``: modes, physics since the last tick (at most
        :data:`MAX_TICK_S`), estimator, streams. The control thread calls it, or a stepper."""
        if not self._running.is_set():
            return
        with self._lock:
            try:
                self._tick(now)
            except Exception:
                logger.exception("simulator tick failed")

    def _tick(self, now: float) -> None:
        dt = min(max(0.0, now - self._last_tick_s), MAX_TICK_S)
        self._last_tick_s = now
        self._update_modes(now)
        self._command_dynamics(now)
        self.dynamics.step(dt)
        if self._armed:
            self._battery_used_s += dt
        self._update_estimator(now)
        self._update_ground_state(now)
        self._forget_clients(now)
        self._send_streams(now)

    def _forget_clients(self, now: float) -> None:
        stale = [
            a
            for a, c in self._clients.items()
            if not c.fixed and now - c.last_heard_s > self.options.client_timeout_s
        ]
        for addr in stale:
            del self._clients[addr]
            logger.info("MAVLink client %s:%d silent, forgotten", *addr)
