"""One thread ticking several simulated autopilots: a fleet's physics and control on one clock.

A :class:`~flightkit.sim.autopilot.SimAutopilot` alone runs its control loop on its own thread
(a tick every ``tick_wall_s``). Ten of them would be ten threads waking 200 times a second each,
and on a small machine the wake-ups cost about as much as the ticks. :class:`SimStepper` ticks
them all, one after the other at one clock reading, from one thread; each autopilot keeps its
own lock, state, dynamics and receive thread, so nothing a vehicle does reaches another.
A fleet (:class:`~flightkit.sim.fleet.SimFleet`) starts its autopilots without their own loop
(``start(own_loop=False)``) and one stepper for them.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Sequence
from typing import Self

from flightkit.clock import Clock
from flightkit.errors import SimError
from flightkit.lifetime import Running
from flightkit.sim.autopilot import SimAutopilot

__all__ = ["SimStepper"]

logger = logging.getLogger(__name__)


class SimStepper(Running):
    """Ticks ``autopilots`` (started with ``own_loop=False``) every ``tick_wall_s`` of wall time.

    Args:
        clock: the autopilots' shared clock.
        autopilots: the autopilots to tick, in this order.
        tick_wall_s: wall seconds from one round's start to the next's (default: the first
            autopilot's ``options.tick_wall_s``); a round that takes longer starts the next at once.

    Raises:
        SimError: no autopilot, or one on another clock.
    """

    def __init__(self, clock: Clock, autopilots: Sequence[SimAutopilot], tick_wall_s: float | None = None) -> None:
        if not autopilots:
            raise SimError("a simulation stepper needs at least one autopilot to tick; pass the fleet's autopilots")
        if any(ap.clock is not clock for ap in autopilots):
            raise SimError("every autopilot a stepper ticks must run on the stepper's clock; build them on one clock")
        self.clock = clock
        self.autopilots = tuple(autopilots)
        self.tick_wall_s = autopilots[0].options.tick_wall_s if tick_wall_s is None else float(tick_wall_s)
        self.rounds = 0
        """Ticking rounds done (every autopilot once per round)."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> Self:
        """Start ticking on a daemon thread; returns immediately."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="sim-stepper", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop ticking (after the current round); idempotent."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(2.0)

    def _run(self) -> None:
        clock = self.clock
        speed = clock.speed
        tick_s = self.tick_wall_s * speed if math.isfinite(speed) else 0.01  # clock seconds per round
        while not self._stop.is_set():
            start = clock.monotonic_s()
            for ap in self.autopilots:
                ap.step(start)
            self.rounds += 1
            # the next round is due one tick after this one began (ten ticks take a while)
            clock.sleep_blocking(max(0.0, start + tick_s - clock.monotonic_s()))
