"""The Python API for custom flight scripts.

::

    import asyncio
    from flightkit.config import load_config
    from trajectories.script import Flight
    from trajectories.patterns import Circle

    async def main() -> None:
        async with Flight(load_config("lab.toml"), arm=True) as flight:   # connects, preflight, arms
            await flight.takeoff(1.5)                                       # blocks until at 1.5 m
            await flight.hold(5.0)                                          # blocks 5 s
            await flight.fly(Circle(radius_m=1.0, period_s=40.0), laps=2)   # blocks until both laps are flown
            await flight.goto((0.0, 0.0, 1.5), yaw_rad=0.0)                 # blocks until there
            await flight.land()                                             # blocks until disarmed
        print(flight.summary.format_table())

    asyncio.run(main())

Leaving the ``async with`` block always lands the vehicle if it is still flying: after an
exception in the script, on Ctrl-C or SIGTERM, or when the script simply forgot
:meth:`Flight.land`. A safety fault raises :class:`~flightkit.errors.SafetyAbort` out of the
blocking call *after* the supervisor's reaction (hold then land, land, hand-over to the pilot).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Self

from flightkit.clock import Clock, WallClock
from flightkit.config import LabConfig
from flightkit.errors import FlightkitError
from flightkit.frames import Vec3Tuple
from flightkit.link.base import VehicleLink
from flightkit.mocap.base import MocapSource
from trajectories.base import Pattern
from trajectories.controller import ControllerConfig
from trajectories.flightlog import FlightLog, FlightSummary
from trajectories.fly import open_lab_mocap
from trajectories.plan import PlanSettings
from trajectories.runner import FlightRunner
from trajectories.status import Status
from trajectories.supervisor import SafetyConfig

__all__ = ["Flight"]

logger = logging.getLogger(__name__)


class Flight:
    """A supervised flight: ``async with Flight(lab_cfg, arm=...) as flight: ...``.

    Args:
        lab: lab config (link, mocap body, autopilot).
        arm: arm and switch to OFFBOARD/GUIDED from the script; False (default) waits for the
            pilot to do both from the transmitter (``settings.arm_timeout_s``).
        link / mocap: already opened ones (otherwise opened from ``lab`` and closed on exit).
        clock: time source (``SimClock`` to run a simulated flight faster than real time).
        settings / controller / safety: plan sections (defaults: the lab's own).
        log_path: flight log file (None: no log).
        on_status: live status callback.
        handle_signals: SIGINT / SIGTERM land the vehicle instead of ending the process.
    """

    def __init__(
        self,
        lab: LabConfig,
        *,
        arm: bool = False,
        link: VehicleLink | None = None,
        mocap: MocapSource | None = None,
        clock: Clock | None = None,
        settings: PlanSettings | None = None,
        controller: ControllerConfig | None = None,
        safety: SafetyConfig | None = None,
        log_path: str | Path | None = None,
        on_status: Callable[[Status], None] | None = None,
        handle_signals: bool = True,
        name: str = "script",
    ) -> None:
        self.lab = lab
        self._arm = arm
        self._link = link
        self._mocap = mocap
        self.clock = clock or WallClock()
        self._settings = settings or PlanSettings(name=name)
        self._controller = controller
        self._safety = safety
        self._log_path = log_path
        self._on_status = on_status
        self._handle_signals = handle_signals
        self._name = name
        self._stack = contextlib.AsyncExitStack()
        self._runner: FlightRunner | None = None
        self._log: FlightLog | None = None

    @property
    def runner(self) -> FlightRunner:
        if self._runner is None:
            raise FlightkitError("the flight is not started; use 'async with Flight(...) as flight:'")
        return self._runner

    @property
    def summary(self) -> FlightSummary:
        return self.runner.summary

    async def __aenter__(self) -> Self:
        """Connect, check preflight, and arm (or wait for the pilot).

        Blocks until armed in OFFBOARD/GUIDED."""
        stack = self._stack
        try:
            link = self._link
            if link is None:
                from flightkit.link import open_link

                link = await stack.enter_async_context(
                    open_link(self.lab.link, self.lab.vehicle.autopilot, self.clock)
                )
            mocap = self._mocap
            if mocap is None:
                mocap = await stack.enter_async_context(open_lab_mocap(self.lab, self.clock))
            if self._log_path is not None:
                self._log = FlightLog(
                    self._log_path,
                    {
                        "plan": self._name,
                        "autopilot": self.lab.vehicle.autopilot.value,
                        "body": self.lab.mocap.body,
                    },
                )
            self._runner = FlightRunner(
                link,
                mocap,
                body=self.lab.mocap.body,
                clock=self.clock,
                settings=self._settings,
                controller=self._controller,
                safety=self._safety,
                log=self._log,
                on_status=self._on_status,
                name=self._name,
            )
            if self._handle_signals:
                stack.enter_context(self._runner.signals_land())
            await self._runner.preflight()
            await self._runner.start(self._arm)
        except BaseException:
            await self._cleanup()
            raise
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Land if still flying (whatever happened in the block), then disconnect. Blocks until landed."""
        runner = self._runner
        try:
            if runner is not None and runner.airborne and not runner.ended:
                if exc is not None:
                    logger.warning("script ended with %s while flying: landing", type(exc).__name__)
                else:
                    logger.warning("script ended without land(): landing")
                with contextlib.suppress(FlightkitError):
                    await runner.land()
        finally:
            await self._cleanup()

    async def _cleanup(self) -> None:
        summary = None
        if self._runner is not None:
            summary = self._runner.finish()
            await self._runner.close()
        if self._log is not None:
            self._log.close(summary)
        await self._stack.aclose()

    # the blocking commands -------------------------------------------------

    async def takeoff(self, height_m: float, climb_m_s: float | None = None) -> None:
        """Take off to ``height_m`` (world z, metres). Blocks until there; SafetyAbort on a fault."""
        await self.runner.takeoff(height_m, climb_m_s)

    async def hold(self, duration_s: float, pos_m: Vec3Tuple | None = None, yaw_rad: float | None = None) -> None:
        """Hold the last target (or ``pos_m``/``yaw_rad``) for ``duration_s``. Blocks for that long."""
        await self.runner.hold(duration_s, pos_m, yaw_rad)

    async def fly(self, pattern: Pattern, laps: int | None = None) -> None:
        """Move to the pattern's start, then fly it (``laps`` times). Blocks until the last lap ends."""
        await self.runner.fly(pattern, laps)

    async def goto(self, pos_m: Vec3Tuple, yaw_rad: float | None = None, speed_m_s: float | None = None) -> None:
        """Fly straight to ``pos_m`` (world ENU), then turn to ``yaw_rad``. Blocks until there."""
        await self.runner.goto(pos_m, yaw_rad, speed_m_s)

    async def land(self) -> None:
        """Descend, touch down and disarm. Blocks until disarmed."""
        await self.runner.land()

    def interrupt(self) -> None:
        """Make the current blocking call land the vehicle (as Ctrl-C does); returns immediately."""
        self.runner.interrupt()
