"""The fault reactor: what a flight does when the supervisor ends a phase.

The control loop raises :class:`~trajectories.control_loop.FaultExit` with the supervisor's
decision; :meth:`FaultReactor.react` carries the decision out (hold then land, land under our
control, hand over to the autopilot's LAND, release to the pilot, or stop streaming), escalating
when a further fault happens meanwhile, and then raises :class:`~flightkit.errors.SafetyAbort`.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Awaitable, Callable
from typing import NoReturn

from flightkit.errors import CommandRejected, LinkError, LinkTimeout, SafetyAbort
from flightkit.link.base import FlightMode, LandedState
from trajectories.control_loop import ControlLoop, FaultExit
from trajectories.hold import Hold
from trajectories.supervisor import Action, Decision, FaultKind, SafetyConfig

__all__ = ["FaultReactor"]

logger = logging.getLogger(__name__)

_OUTCOME = {
    Action.ABORT: "landed_early",
    Action.LAND: "landed_early",
    Action.LAND_AUTOPILOT: "autopilot_landing",
    Action.RELEASE: "released",
    Action.STOP: "stopped",
}


class FaultReactor:
    """Carries out the supervisor's decisions for one vehicle.

    Args:
        loop: the vehicle's control loop. safety: the supervisor's configuration.
        landed_timeout_s: how long a landing may take.
        land: the controlled landing, tolerating faults up to the given action.
    """

    def __init__(
        self,
        loop: ControlLoop,
        *,
        safety: SafetyConfig,
        landed_timeout_s: float,
        land: Callable[[Action], Awaitable[None]],
    ) -> None:
        self.loop = loop
        self.safety = safety
        self.landed_timeout_s = landed_timeout_s
        self._land = land
        self.ended = False  # a fault ended the flight (landed, released or stopped)

    async def run(self, phase: Callable[[], Awaitable[None]]) -> None:
        """Run one phase; on a fault, react and raise SafetyAbort."""
        if self.ended:
            raise SafetyAbort("ended", "the flight has already ended after a fault; start a new one")
        try:
            await phase()
        except FaultExit as exc:
            await self.react(exc.decision)

    async def react(self, decision: Decision) -> NoReturn:
        """Carry out ``decision`` (escalating on further faults); always raises SafetyAbort."""
        loop = self.loop
        top = max(decision.faults, key=lambda f: f.action) if decision.faults else None
        action = decision.action
        while True:
            try:
                if action is Action.ABORT:
                    pos, yaw = loop.current_pose()
                    if self.safety.abort_hold_s > 0:
                        await loop.track(Hold(pos, yaw, self.safety.abort_hold_s), "abort_hold", tolerate=Action.ABORT)
                    action = Action.LAND
                    continue
                if action is Action.LAND:
                    await self._land(Action.LAND)
                elif action is Action.LAND_AUTOPILOT:
                    await self.autopilot_land()
                elif action in (Action.RELEASE, Action.STOP):
                    loop.in_control = False
                    with contextlib.suppress(LinkError):
                        await loop.link.stop_setpoint_stream()
                break
            except FaultExit as exc:
                if exc.decision.action <= action:  # cannot happen with tolerate; be safe
                    raise
                action = exc.decision.action
                top = max(exc.decision.faults, key=lambda f: f.action)
        self.ended = True
        loop.summary.outcome = _OUTCOME.get(action, "landed_early")
        kind = top.kind.value if top else "unknown"
        msg = top.message if top else "flight ended by the supervisor"
        raise SafetyAbort(kind, msg)

    async def autopilot_land(self) -> None:
        """Hand over to the autopilot's LAND mode and wait for touchdown (watching heartbeat and pilot)."""
        logger.warning("switching to the autopilot's LAND mode")
        self.loop.in_control = False
        await self.loop.link.land()
        await self.wait_landed(watch_mode=FlightMode.LAND)

    async def wait_landed(self, *, watch_mode: FlightMode | None = None, disarm_on_ground: bool = False) -> None:
        """Until the vehicle is disarmed, watching the heartbeat (and, with ``watch_mode``, that
        the pilot leaves the autopilot in that mode); with ``disarm_on_ground`` it disarms the
        vehicle once the autopilot reports it on the ground.

        Raises:
            FaultExit: heartbeat lost (STOP), pilot took over (RELEASE). LinkTimeout: not disarmed
            within ``landed_timeout_s``.
        """
        loop = self.loop
        deadline = loop.clock.monotonic_s() + self.landed_timeout_s
        disarm_sent = False
        while True:
            tel = loop.link.telemetry
            if tel.heartbeat_age_s > self.safety.heartbeat_period_s + self.safety.heartbeat_timeout_s:
                raise FaultExit(
                    loop.fault(
                        FaultKind.HEARTBEAT_LOST,
                        f"no autopilot heartbeat for {tel.heartbeat_age_s:.2f} s while landing",
                        Action.STOP,
                    )
                )
            if not tel.armed:
                loop.airborne = False
                return
            if disarm_on_ground and tel.landed_state is LandedState.ON_GROUND and not disarm_sent:
                disarm_sent = True
                with contextlib.suppress(CommandRejected, LinkTimeout):
                    await loop.link.disarm()
            if watch_mode is not None and tel.mode is not watch_mode:
                raise FaultExit(
                    loop.fault(
                        FaultKind.PILOT_TAKEOVER,
                        f"mode changed from {watch_mode.value} to {tel.mode.value} while landing",
                        Action.RELEASE,
                    )
                )
            if loop.clock.monotonic_s() > deadline:
                raise LinkTimeout(
                    f"the vehicle did not land and disarm within {self.landed_timeout_s:.0f} s",
                    "disarmed",
                    self.landed_timeout_s,
                )
            await loop.clock.sleep(0.05)
