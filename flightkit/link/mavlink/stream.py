"""The background velocity-setpoint stream of the pymavlink backend.

:class:`SetpointStream` runs one **setpoint thread** while a stream is on: it sends the
current velocity setpoint at absolute deadlines of the injected
:class:`~flightkit.clock.Clock` (no drift, low jitter), and replaces it by an explicit
zero-velocity stop when the caller has been silent for ``link.setpoint_timeout_s``.
:meth:`SetpointStream.set` replaces the streamed setpoint from any thread, and can push it
on the wire at once (``send_now``) for a control loop driven by mocap.

The stream knows nothing about MAVLink messages: it hands
:class:`~flightkit.link.mavlink.encoding.SetpointFields` to the ``send`` callable the link
gives it (which addresses and encodes SET_POSITION_TARGET_LOCAL_NED).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

from flightkit.clock import Clock
from flightkit.errors import LinkError
from flightkit.link.base import SetpointFrame, VelocitySetpoint
from flightkit.link.mavlink.encoding import SetpointFields, check_hard_limits, encode_velocity_setpoint

__all__ = ["SetpointStream"]

logger = logging.getLogger(__name__)


@dataclass(slots=True)
class _Run:
    """One run of the stream, from start() to stop()."""

    rate_hz: float
    setpoint: VelocitySetpoint
    fields: SetpointFields
    set_at_s: float
    started_s: float
    thread: threading.Thread
    stop: threading.Event
    loop: asyncio.AbstractEventLoop | None
    sent_at_s: float = -math.inf  # last setpoint on the wire (stream thread or send_now)
    pushed_at_s: float = -math.inf  # last setpoint sent by set(send_now=True)


class SetpointStream:
    """Streams velocity setpoints on a thread of its own; counters live as long as the link.

    Args:
        clock: time source of the deadlines and of the silence timeout.
        timeout_s: after this long without :meth:`set`, send zero velocity instead.
        send: puts one setpoint on the wire (called from the stream thread, from the thread
            calling :meth:`set` with ``send_now``, and from :meth:`stop`).
    """

    def __init__(self, clock: Clock, timeout_s: float, send: Callable[[SetpointFields], None]) -> None:
        self._clock = clock
        self._timeout_s = timeout_s
        self._send = send
        self._run: _Run | None = None
        self._lock = threading.Lock()
        self.setpoints_sent = 0
        self.stops_sent = 0  # explicit zero-velocity setpoints sent because the caller was silent

    @property
    def running(self) -> bool:
        """True while the stream runs."""
        return self._run is not None

    @property
    def started_s(self) -> float | None:
        """Clock time the running stream started at; None when it is not running."""
        run = self._run
        return None if run is None else run.started_s

    def start(self, rate_hz: float, loop: asyncio.AbstractEventLoop | None) -> None:
        """Start streaming zero velocity (world frame) at ``rate_hz``; returns immediately.

        Does nothing if the stream already runs. The thread stops by itself when ``loop``
        (the event loop that owns the link) is closed.
        """
        with self._lock:
            if self._run is not None:
                return
            zero = VelocitySetpoint.zero()
            now = self._clock.monotonic_s()
            stop = threading.Event()
            thread = threading.Thread(target=self._thread_main, name="mavlink-setpoints", daemon=True)
            self._run = _Run(rate_hz, zero, encode_velocity_setpoint(zero), now, now, thread, stop, loop)
            thread.start()
        logger.info("setpoint stream started at %.0f Hz", rate_hz)

    async def stop(self) -> None:
        """Stop the thread and send one zero-velocity setpoint; idempotent."""
        with self._lock:
            run = self._run
            self._run = None
        if run is None:
            return
        run.stop.set()
        if run.thread is not threading.current_thread():
            await asyncio.to_thread(run.thread.join, 2.0)
        self._send(encode_velocity_setpoint(VelocitySetpoint.zero(run.setpoint.frame)))
        logger.info("setpoint stream stopped")

    def set(self, setpoint: VelocitySetpoint, *, send_now: bool = False) -> None:
        """Replace the streamed setpoint; returns immediately (see ``MavlinkLink.set_velocity``).

        Raises:
            SetpointError: beyond the hard safety limits (see HARD_MAX_*).
            LinkError: the stream is not running.
        """
        check_hard_limits(setpoint)
        run = self._run
        if run is None:
            raise LinkError("the setpoint stream is not running; call start_setpoint_stream() first")
        fields = encode_velocity_setpoint(setpoint)
        # One attribute write each; the stream thread reads them without a lock (fields first).
        run.fields = fields
        run.setpoint = setpoint
        now = self._clock.monotonic_s()
        run.set_at_s = now
        if send_now and now - run.sent_at_s >= 0.25 / run.rate_hz:
            run.sent_at_s = run.pushed_at_s = now
            self._send(fields)
            self.setpoints_sent += 1

    def _thread_main(self) -> None:
        run = self._run
        assert run is not None
        clock = self._clock
        period = 1.0 / run.rate_hz
        timeout_s = self._timeout_s
        next_s = clock.monotonic_s()
        stale_logged = False
        stops: dict[SetpointFrame, SetpointFields] = {
            f: encode_velocity_setpoint(VelocitySetpoint.zero(f)) for f in SetpointFrame
        }
        loop = run.loop
        while not run.stop.is_set():
            if loop is not None and loop.is_closed():
                logger.warning("the event loop that owns the link is gone; stopping the setpoint stream")
                break
            now = clock.monotonic_s()
            if now - run.set_at_s > timeout_s:
                if not stale_logged:
                    logger.warning(
                        "no set_velocity() for %.2f s (link.setpoint_timeout_s); sending zero velocity until the "
                        "next setpoint",
                        now - run.set_at_s,
                    )
                    stale_logged = True
                self._send(stops[run.setpoint.frame])
                self.stops_sent += 1
                run.sent_at_s = now
                self.setpoints_sent += 1
            elif now - run.pushed_at_s >= period * 0.9:  # no send_now within the last period
                stale_logged = False
                run.sent_at_s = now
                self._send(run.fields)
                self.setpoints_sent += 1
            else:
                stale_logged = False
            next_s += period
            now = clock.monotonic_s()
            if next_s < now - period:  # fell behind by more than a period (e.g. suspended): resync
                next_s = now
            clock.sleep_blocking(next_s - now)
