"""The phase sequencer of one flight: take-off, hold, goto, pattern, landing.

:class:`FlightRunner` owns one flight on an already connected :class:`VehicleLink` and a
running :class:`MocapSource`. Each blocking method (:meth:`~FlightRunner.takeoff`,
:meth:`~FlightRunner.hold`, :meth:`~FlightRunner.fly`, :meth:`~FlightRunner.goto`,
:meth:`~FlightRunner.land`) builds a reference and has the vehicle's
:class:`~trajectories.control_loop.ControlLoop` track it until it is done; a fault ends the
phase and the :class:`~trajectories.fault_reactor.FaultReactor` reacts (hold then land, land,
hand over to the autopilot's LAND, release to the pilot, or stop) and raises
:class:`~flightkit.errors.SafetyAbort`.

The runner does not know which firmware it flies: it asks the link's
:class:`~flightkit.link.base.FirmwareTraits` (control mode, setpoint pre-stream, lift-off by
the autopilot).

:func:`trajectories.fly.fly_plan` flies a whole plan in one call.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import signal
from collections.abc import Callable, Iterator
from typing import Any

from flightkit.clock import Clock
from flightkit.errors import CommandRejected, LinkError, LinkTimeout, MocapError, PlanError, SafetyAbort
from flightkit.frames import Vec3Tuple
from flightkit.link.base import LandedState, VehicleLink, read_companion_loss
from flightkit.mocap.base import MocapSource
from trajectories.base import Pattern, PiecewisePattern, Reference, Turn
from trajectories.circle import Circle
from trajectories.control_loop import ControlLoop
from trajectories.controller import ControllerConfig, SetpointKind, VelocityController
from trajectories.fault_reactor import FaultReactor
from trajectories.flightlog import FlightLog, FlightSummary
from trajectories.hold import Hold
from trajectories.plan import PlanSettings
from trajectories.status import Status
from trajectories.supervisor import Action, SafetyConfig, preflight_problems
from trajectories.takeoff import Land, LiftOff, Takeoff
from trajectories.waypoints import Waypoints

__all__ = ["FlightRunner", "pattern_in_fence", "with_laps"]

logger = logging.getLogger(__name__)

LIFT_SETTLED_M_S = 0.1
"""With position targets, the autopilot's own lift counts as over below this climb rate (m/s)."""


def with_laps(pattern: Pattern, laps: int) -> Pattern:
    """The same pattern flown ``laps`` times (PlanError if its laps do not close)."""
    if laps == pattern.laps:
        return pattern
    if isinstance(pattern, Circle):
        return dataclasses.replace(pattern, laps=laps)
    if isinstance(pattern, PiecewisePattern):
        return PiecewisePattern(pattern.name, pattern.segments, laps)
    raise PlanError(
        f"cannot change the lap count of a {type(pattern).__name__}; build it with laps={laps} instead"
    )


def pattern_in_fence(pattern: Pattern, safety: SafetyConfig, step_s: float = 0.05) -> Reference | None:
    """The first reference of ``pattern`` outside the geofence, or None when it stays inside."""
    if not safety.geofence.enabled:
        return None
    n = max(2, int(pattern.duration_s / step_s) + 1)
    for i in range(n + 1):
        ref = pattern.reference(pattern.duration_s * i / n)
        if not safety.geofence.contains(ref.pos_m):
            return ref
    return None


class FlightRunner:
    """One flight on a connected link and a running mocap source.

    Args:
        link: connected vehicle link. mocap: running mocap source (same clock as the link).
        body: mocap rigid-body name of the vehicle.
        clock: the clock every wait uses. settings / controller / safety: plan sections.
        log: flight log to write each cycle to (None: no log).
        on_status: called with a :class:`Status` about 5 times a second (from the event loop).
        name: plan name for the summary.
        predict_latency_s: see :class:`~trajectories.control_loop.ControlLoop`.
    """

    def __init__(
        self,
        link: VehicleLink,
        mocap: MocapSource,
        *,
        body: str,
        clock: Clock,
        settings: PlanSettings | None = None,
        controller: ControllerConfig | None = None,
        safety: SafetyConfig | None = None,
        log: FlightLog | None = None,
        on_status: Callable[[Status], None] | None = None,
        name: str = "flight",
        predict_latency_s: float = 0.0,
    ) -> None:
        self.link = link
        self.clock = clock
        self.settings = settings or PlanSettings()
        self.safety = safety or SafetyConfig()
        self.traits = link.info.traits
        self.summary = FlightSummary(plan=name, log_path=str(log.path) if log else None)
        ctl = VelocityController(controller or ControllerConfig())
        self.loop = ControlLoop(
            link,
            mocap,
            body=body,
            clock=clock,
            control_mode=self.traits.control_mode,
            controller=ctl,
            # lift-off is pure feed-forward (see LiftOff): it uses it even under the P-only law
            lift_controller=VelocityController(dataclasses.replace(ctl.config, feedforward=True)),
            safety=self.safety,
            rate_hz=self.settings.rate_hz,
            summary=self.summary,
            log=log,
            on_status=on_status,
            predict_latency_s=predict_latency_s,
        )
        self.reactor = FaultReactor(
            self.loop, safety=self.safety, landed_timeout_s=self.settings.landed_timeout_s, land=self._controlled_land
        )
        self._headroom_warned: set[str] = set()
        self._last_target: Vec3Tuple | None = None
        self._last_yaw: float | None = None
        self.pattern_started_s = math.nan
        """Clock time of the last pattern's first cycle (a fleet's start skew is measured on it)."""

    # ------------------------------------------------------------------ state

    @property
    def t_s(self) -> float:
        """Flight time, seconds since the runner was created."""
        return self.loop.t_s

    @property
    def airborne(self) -> bool:
        """The vehicle may be off the ground (from take-off until touchdown)."""
        return self.loop.airborne

    @property
    def ended(self) -> bool:
        """A fault ended the flight (landed, released or stopped)."""
        return self.reactor.ended

    def current_pose(self) -> tuple[Vec3Tuple, float]:
        """Newest valid mocap position (world ENU) and yaw; MocapBodyMissing when there is none."""
        return self.loop.current_pose()

    def interrupt(self) -> None:
        """Ask the flight to land (what Ctrl-C and SIGTERM do); returns immediately."""
        self.loop.interrupted.set()

    @contextlib.contextmanager
    def signals_land(self) -> Iterator[None]:
        """While inside, SIGINT and SIGTERM make the flight land instead of killing the process.

        Only in the main thread (elsewhere this does nothing).
        """
        loop = asyncio.get_running_loop()
        installed: list[tuple[signal.Signals, Any]] = []
        try:
            for sig in (signal.SIGINT, signal.SIGTERM):
                try:
                    old = signal.getsignal(sig)
                    loop.add_signal_handler(sig, self._on_signal, sig)
                    installed.append((sig, old))
                except (ValueError, RuntimeError, NotImplementedError):
                    pass  # not the main thread
            yield
        finally:
            for sig, old in installed:
                loop.remove_signal_handler(sig)
                signal.signal(sig, old)

    def _on_signal(self, sig: int) -> None:
        logger.warning("%s received: landing", signal.Signals(sig).name)
        self.interrupt()

    # ------------------------------------------------------------------ phases

    async def preflight(self) -> None:
        """Wait for the mocap body and check the vehicle can fly; blocks up to ``preflight_timeout_s``.

        Raises:
            MocapBodyMissing: the body is not visible (the error names the visible bodies).
            SafetyAbort: another preflight check failed (reason ``"preflight"``).
        """
        loop = self.loop
        await loop.mocap.wait_for_body(loop.body, self.settings.preflight_timeout_s)
        stream = await self._watch_mocap_stream()
        pos = loop.current_position()
        problems = preflight_problems(
            self.safety, loop.body, tuple(loop.mocap.bodies()), pos is not None, self.link.telemetry, pos
        )
        problems += stream
        problems += await self._companion_loss_problems()
        if problems:
            raise SafetyAbort("preflight", "preflight failed: " + "; ".join(problems))
        logger.info("preflight ok: body %r at %s", loop.body, pos)

    async def _companion_loss_problems(self) -> list[str]:
        """Read the parameters that decide what the autopilot does if flightkit stops (the
        firmware's traits name them), log that in one line and keep it in the summary; a reason
        not to arm when it would hover armed until the battery runs out, unless
        ``allow_hover_on_companion_loss``."""
        verdict = await read_companion_loss(self.link)
        self.summary.companion_loss = verdict.summary
        if not verdict.hovers:
            logger.info("%s", verdict.summary)
            return []
        if self.safety.allow_hover_on_companion_loss:
            logger.warning("%s; arming anyway ([safety] allow_hover_on_companion_loss)", verdict.summary)
            return []
        logger.warning("%s", verdict.summary)
        return [
            f"{verdict.reason}; or accept it with [safety] allow_hover_on_companion_loss = true "
            "(flightkit fly --allow-hover-on-companion-loss)"
        ]

    async def _watch_mocap_stream(self) -> list[str]:
        """Watch the body's poses for ``preflight_mocap_window_s``: what breaks the rate, age and
        jitter bounds of ``[safety]`` (one sentence each; empty: the stream is fit to fly on)."""
        from flightkit.calibration.latency import stream_health

        cfg, loop = self.safety, self.loop
        window_s = cfg.preflight_mocap_window_s
        received_ns: list[int] = []

        async def collect() -> None:  # every pose in arrival order: none is missed between wake-ups
            async for p in loop.mocap.poses(loop.body):
                if p.valid:
                    received_ns.append(round(p.received_s * 1e9))

        collector = asyncio.ensure_future(collect())
        try:
            await self.clock.sleep(window_s)
        finally:
            collector.cancel()
            with contextlib.suppress(asyncio.CancelledError, MocapError):
                await collector
        now_ns = round(self.clock.monotonic_s() * 1e9)
        if len(received_ns) < 2:
            return [
                f"mocap body {loop.body!r} gave {len(received_ns)} pose(s) in {window_s:g} s; check the mocap stream"
            ]
        health = stream_health(received_ns, now_ns, window_s=window_s + 1.0)
        return health.problems(
            cfg.preflight_mocap_min_rate_hz or 0.0,
            cfg.preflight_mocap_max_age_s or math.inf,
            cfg.preflight_mocap_max_jitter_ms or math.inf,
        )

    async def start(self, arm: bool) -> None:
        """Start the setpoint stream and get control: arm and switch mode ourselves (``arm=True``),
        or wait for the pilot to arm and switch to OFFBOARD/GUIDED (countdown via ``on_status``).

        Blocks until armed in the offboard mode. Raises CommandRejected / LinkTimeout.
        """
        link = self.link
        self.loop.start_pose_watch()
        await link.start_setpoint_stream(max(self.settings.rate_hz, 20.0))
        link.set_velocity(self.loop.controller.hold())
        mode = self.traits.control_mode
        if arm:
            await self._keep_streaming(self.traits.setpoint_prestream_s)
            await link.set_mode(mode)
            deadline = self.clock.monotonic_s() + 15.0
            while True:
                try:
                    await link.arm()
                    break
                except CommandRejected:
                    if self.clock.monotonic_s() > deadline:
                        raise
                    await self._keep_streaming(0.5)
        else:
            deadline = self.clock.monotonic_s() + self.settings.arm_timeout_s
            logger.info("waiting for the pilot to arm and switch to %s", mode.value)
            while True:
                tel = link.telemetry
                if tel.armed and tel.mode is mode:
                    break
                left = deadline - self.clock.monotonic_s()
                if left <= 0:
                    raise LinkTimeout(
                        f"the pilot did not arm and switch to {mode.value} "
                        f"within {self.settings.arm_timeout_s:.0f} s; "
                        "arm from the transmitter or run with --arm",
                        "armed",
                        self.settings.arm_timeout_s,
                    )
                self.loop.status(
                    "wait_pilot",
                    0,
                    0,
                    self.loop.current_position(),
                    "CONTINUE",
                    f"arm and switch to {mode.value}: {left:4.0f} s left",
                )
                await self._keep_streaming(0.2)
        self.loop.in_control = True
        logger.info("armed in %s", mode.value)

    async def _keep_streaming(self, duration_s: float) -> None:
        end = self.clock.monotonic_s() + duration_s
        while self.clock.monotonic_s() < end:
            self.link.set_velocity(self.loop.controller.hold())
            await self.clock.sleep(min(0.05, duration_s))

    async def takeoff(self, height_m: float, climb_m_s: float | None = None) -> None:
        """Take off to ``height_m`` (world z); blocks until there (SafetyAbort on a fault)."""
        await self.reactor.run(lambda: self._takeoff(height_m, climb_m_s))

    async def _takeoff(self, height_m: float, climb_m_s: float | None) -> None:
        climb = self._vertical_rate(climb_m_s or self.settings.climb_m_s, "climb_m_s")
        pos, yaw = self.current_pose()
        self.loop.airborne = True
        if self.traits.liftoff_m > 0.0:
            await self._autopilot_liftoff(pos, yaw, max(0.2, min(height_m - pos[2], self.traits.liftoff_m)))
            pos = self.current_pose()[0]
        else:
            # our setpoints lift it off: climb (feed-forward) until 8 cm up
            lifted_z_m = pos[2] + 0.08
            await self.loop.track(
                self._liftoff_reference(pos, yaw, climb),
                "takeoff",
                until=lambda _t, p: p[2] >= lifted_z_m,
                timeout_s=30.0,
            )
        pos2, _ = self.current_pose()
        if height_m - pos2[2] > 0.02:
            pat = Takeoff((pos[0], pos[1], pos2[2]), height_m, climb, self.settings.accel_m_s2, yaw)
            await self.loop.track(pat, "takeoff")
            self._remember(pat)
        else:
            self._last_target, self._last_yaw = (pos[0], pos[1], height_m), yaw

    async def _autopilot_liftoff(self, pos: Vec3Tuple, yaw: float, lift_m: float) -> None:
        """The firmware leaves the ground only on its own take-off command: pause the setpoint
        stream (a velocity setpoint would cancel its climb), command the lift-off and watch it,
        supervising, without sending, until near ``lift_m`` up."""
        lifted_z_m = pos[2] + lift_m - 0.05
        rate_hz = max(self.settings.rate_hz, 20.0)
        # With position targets our climb starts from rest, so let the firmware's lift finish
        # (it overshoots its own height: ArduCopter's 0.3 m lift tops out at 0.41 m) first.
        settle = self.loop.controller.config.setpoint is SetpointKind.PVA

        def lifted(_t: float, p: Vec3Tuple) -> bool:
            if p[2] < lifted_z_m:
                return False
            vz = self.link.telemetry.vel_local_enu_m_s[2]
            return not settle or (math.isfinite(vz) and abs(vz) < LIFT_SETTLED_M_S)

        await self.link.stop_setpoint_stream()
        try:
            await self.link.takeoff(lift_m)
            await self.loop.track(
                self._liftoff_reference(pos, yaw, 0.0),
                "takeoff",
                send=False,
                timeout_s=60.0,
                until=lifted,
            )
        except BaseException:
            # whatever reacts (a fault's hold and land, a cancelled flight's landing) streams
            # setpoints: the stream must run again first
            with contextlib.suppress(LinkError):
                await self.link.start_setpoint_stream(rate_hz)
            raise
        await self.link.start_setpoint_stream(rate_hz)

    def _liftoff_reference(self, pos: Vec3Tuple, yaw: float, climb_m_s: float) -> LiftOff:
        def height() -> float | None:
            p = self.loop.current_position()
            return None if p is None else p[2]

        return LiftOff(pos, yaw, climb_m_s, height)

    async def hold(self, duration_s: float, pos_m: Vec3Tuple | None = None, yaw_rad: float | None = None) -> None:
        """Hold ``pos_m`` (default: the current reference end / position) for ``duration_s``; blocks."""
        if duration_s <= 0:
            return
        p, y = self._here(pos_m, yaw_rad)
        await self.reactor.run(lambda: self.loop.track(Hold(p, y, duration_s), "hold"))

    def _here(self, pos_m: Vec3Tuple | None, yaw_rad: float | None) -> tuple[Vec3Tuple, float]:
        cur, cyaw = self.current_pose()
        return (pos_m or self._last_target or cur), (
            yaw_rad if yaw_rad is not None else (self._last_yaw if self._last_yaw is not None else cyaw)
        )

    async def goto(self, pos_m: Vec3Tuple, yaw_rad: float | None = None, speed_m_s: float | None = None) -> None:
        """Fly a straight line to ``pos_m`` (world ENU), then turn in place to ``yaw_rad``.

        Blocks until there."""
        start, syaw = self._here(None, None)
        end_yaw = None if yaw_rad is None else syaw + math.remainder(yaw_rad - syaw, 2 * math.pi)
        dist = math.dist(start, pos_m)
        turn = end_yaw is not None and abs(end_yaw - syaw) > 0.01
        if dist < 0.01 and not turn:
            return
        pat: Pattern
        if dist < 0.01:
            assert end_yaw is not None
            pat = PiecewisePattern("goto", [Turn(start, syaw, end_yaw, 3.0)])
        else:
            pat = Waypoints(
                [start, pos_m],
                self._transit_speed(start, pos_m, speed_m_s or self.settings.transit_speed_m_s),
                self.settings.accel_m_s2,
                syaw,
                end_yaw_rad=end_yaw,
                turn_s=3.0,
                name="goto",
            )
        await self.reactor.run(lambda: self.loop.track(pat, "goto"))
        self._remember(pat)

    def _vertical_rate(self, rate_m_s: float, name: str) -> float:
        """``rate_m_s`` capped at ``[plan] reference_headroom`` of the vertical speed limit (warned once)."""
        limit = self.loop.controller.config.max_vertical_m_s
        cap = self.settings.reference_headroom * limit
        if rate_m_s <= cap:
            return rate_m_s
        if name not in self._headroom_warned:
            self._headroom_warned.add(name)
            logger.warning(
                "plan %s %.2f m/s leaves the controller no room to correct below max_vertical_m_s %.2f m/s; "
                "flying %.2f m/s (raise [controller] max_vertical_m_s or lower %s)",
                name, rate_m_s, limit, cap, name,
            )
        return cap

    def _transit_speed(self, start: Vec3Tuple, end: Vec3Tuple, speed_m_s: float) -> float:
        """The speed along a straight transit that keeps both its horizontal and vertical parts
        within ``[plan] reference_headroom`` of the controller's limits."""
        c = self.loop.controller.config
        dist = math.dist(start, end)
        horizontal = math.hypot(end[0] - start[0], end[1] - start[1]) / dist
        vertical = abs(end[2] - start[2]) / dist
        cap = math.inf
        if horizontal > 0.0:
            cap = self.settings.reference_headroom * c.max_horizontal_m_s / horizontal
        if vertical > 0.0:
            cap = min(cap, self.settings.reference_headroom * c.max_vertical_m_s / vertical)
        return min(speed_m_s, cap)

    def _remember(self, pattern: Pattern) -> None:
        end = pattern.reference(pattern.duration_s)
        self._last_target = end.pos_m
        self._last_yaw = end.yaw_rad

    async def fly(self, pattern: Pattern, laps: int | None = None, *, start_at_s: float | None = None) -> None:
        """Fly ``pattern`` (``laps`` times if given); first moves to its start. Blocks until done.

        With ``start_at_s`` (clock time) it holds at the start until then and runs the pattern on
        that epoch: vehicles given the same one fly one timeline (a fleet's synchronised start).

        Raises:
            SafetyAbort: a fault ended the pattern (the runner has already reacted: landed, etc.).
            PlanError: the pattern leaves the geofence (with ``check_plan_in_fence``).
        """
        if laps is not None:
            pattern = with_laps(pattern, laps)
        if self.safety.check_plan_in_fence:
            bad = pattern_in_fence(pattern, self.safety)
            if bad is not None:
                raise PlanError(
                    f"{pattern.name} leaves the geofence {self.safety.geofence.describe()} "
                    f"at t={bad.t_s:.1f} s, position ({bad.pos_m[0]:.2f}, {bad.pos_m[1]:.2f}, "
                    f"{bad.pos_m[2]:.2f}); shrink the pattern or move the fence"
                )
        first = pattern.reference(0.0)
        await self.goto(first.pos_m, first.yaw_rad)
        self._last_yaw = first.yaw_rad
        if start_at_s is not None:
            # hold until a cycle before the epoch, then wake at the epoch itself: every vehicle's first
            # pattern cycle runs then, not at its next mocap sample after it (up to a period late)
            lead_s = 1.0 / self.loop.rate_hz
            await self.hold_until(lambda: self.clock.monotonic_s() >= start_at_s - lead_s, phase="sync")
            await self.clock.sleep(max(0.0, start_at_s - self.clock.monotonic_s()))
        await self.reactor.run(lambda: self.loop.track(pattern, "pattern", epoch_s=start_at_s))
        self.pattern_started_s = self.loop.phase_started_s
        self._remember(pattern)

    async def hold_until(self, done: Callable[[], bool], timeout_s: float = 120.0, phase: str = "sync") -> None:
        """Hold the current target (or position) until ``done()`` is true; blocks.

        Raises:
            SafetyAbort: a fault ended the hold. LinkTimeout: still not done after ``timeout_s``.
        """
        if done():
            return
        p, y = self._here(None, None)
        await self.reactor.run(
            lambda: self.loop.track(
                Hold(p, y, 1e6), phase, end_when=lambda _t, _p: done(), timeout_s=timeout_s
            )
        )

    async def land(self) -> None:
        """Descend under control, let the autopilot finish the touchdown, wait for disarm; blocks."""
        await self.reactor.run(lambda: self._controlled_land(Action.CONTINUE))

    async def _controlled_land(self, tolerate: Action) -> None:
        pos, yaw = self.current_pose()
        floor = self.settings.floor_m
        if self.link.telemetry.armed and pos[2] > floor + 0.12:
            descent = self._vertical_rate(self.settings.descent_m_s, "descent_m_s")
            pat = Land(pos, descent, floor, 0.3, self.settings.accel_m_s2, yaw)
            # the reference reaches below the floor to keep pressing down; the phase ends near
            # the floor (or on touchdown) and the autopilot's LAND finishes the touchdown
            await self.loop.track(
                pat,
                "land",
                tolerate=tolerate,
                floor_m=floor,
                end_when=lambda _t, p: p[2] < floor + 0.12 or self._landed(),
            )
        if self.link.telemetry.armed:
            self.loop.in_control = False
            if not self._landed():
                await self.link.land()
            await self.reactor.wait_landed(disarm_on_ground=True)
        self.loop.airborne = False
        self.loop.in_control = False
        with contextlib.suppress(LinkError):
            await self.link.stop_setpoint_stream()

    def _landed(self) -> bool:
        tel = self.link.telemetry
        return (not tel.armed) or tel.landed_state is LandedState.ON_GROUND

    # ------------------------------------------------------------------ summary

    def finish(self) -> FlightSummary:
        """Fill in timing figures; returns the summary (call once at the end)."""
        self.loop.fill_timing(self.summary)
        return self.summary

    async def close(self) -> None:
        """Stop watching the mocap stream; idempotent."""
        await self.loop.close()
