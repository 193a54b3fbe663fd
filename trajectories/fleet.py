"""Several vehicles flown together under one mocap system.

``async with Fleet(lab, arm=True) as fleet:`` connects every vehicle of the lab config
(``[[vehicles]]``), checks them all before flight, arms them, and gives the blocking verbs of
:class:`~trajectories.script.Flight` acting on all vehicles or a named subset::

    async with Fleet(lab, arm=True) as fleet:
        await fleet.takeoff(1.2)                 # all take off; each holds until all are up
        skew_s = await fleet.fly(patterns)       # each to its start, all start at one time
        await fleet.land()

Supervision is on two levels. Each vehicle keeps its own supervisor (stale mocap, geofence,
link, pilot, battery: :mod:`trajectories.supervisor`). The fleet supervisor watches the
separation of every pair (measured, and predicted ``lookahead_s`` ahead at constant velocity,
:func:`~trajectories.separation.closest_approach`) and what one vehicle's fault does to the
others (``on_vehicle_fault``: ``land``, the others hold then land; or ``continue``); a vehicle
its pilot takes over leaves the fleet and the others go on. A lost separation makes every
airborne vehicle hold, then land. Leaving the block on an exception,
Ctrl-C or SIGTERM lands every vehicle still flying. :meth:`Fleet.fly` refuses patterns whose
references come closer than the minimum separation before any vehicle moves.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import signal
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Self

from flightkit.bus.keys import Keys
from flightkit.clock import Clock, WallClock
from flightkit.config import LabConfig, MocapSourceKind
from flightkit.errors import PlanError, SafetyAbort
from flightkit.frames import Vec3Tuple
from flightkit.link.base import VehicleLink
from flightkit.mocap.base import MocapSource
from trajectories.base import Pattern
from trajectories.controller import ControllerConfig
from trajectories.flightlog import FlightLog, FlightSummary
from trajectories.plan import PlanSettings
from trajectories.runner import FlightRunner
from trajectories.separation import Approach, FleetSafety, closest_approach, plan_separation
from trajectories.status import Status
from trajectories.supervisor import FaultKind, Geofence, SafetyConfig

__all__ = ["Fleet", "FleetReport", "FleetVehicle"]

logger = logging.getLogger(__name__)

_LEAVES_ALONE = frozenset({FaultKind.PILOT_TAKEOVER.value})
"""Faults that take one vehicle out of the fleet without a reaction in the others: its pilot
took it over on purpose, and the others stay clear of it as they were."""

Verb = Callable[[FlightRunner, str], Awaitable[None]]
"""What a fleet verb does to one vehicle: ``verb(runner, vehicle_name)``."""

_START_LEAD_S = 0.25
"""How far ahead of the moment every vehicle holds at its start the common pattern epoch is set."""

_VELOCITY_BASELINE_S = 0.1
"""Least time between the two mocap poses a vehicle's velocity is differenced from."""


@dataclass
class FleetVehicle:
    """One vehicle of a running fleet."""

    name: str
    config: LabConfig
    link: VehicleLink
    mocap: MocapSource
    runner: FlightRunner
    fault: str = ""  # why it stopped flying with the fleet ("" while it flies)


@dataclass
class FleetReport:
    """What the fleet supervisor measured.

    Attributes:
        min_separation_m: least distance measured between two airborne vehicles (inf: never two).
        closest_pair: the pair it was measured between.
        start_skew_s: the last :meth:`Fleet.fly`'s spread of pattern start times.
        faults: ``(time_s, vehicle or pair, message)`` of the fleet-level faults.
    """

    min_separation_m: float = math.inf
    closest_pair: tuple[str, str] = ("", "")
    start_skew_s: float = math.nan
    faults: list[tuple[float, str, str]] = field(default_factory=list)


class Fleet:
    """The vehicles of ``lab`` (its ``[[vehicles]]``), flown together.

    Args:
        lab: the lab config; :meth:`LabConfig.fleet` gives each vehicle's link and mocap body.
        arm: arm and switch mode from the script (False: each vehicle's pilot does).
        clock: the clock every wait uses (the simulator's in tests).
        mocap: one source serving every body (None: each vehicle's ``lab.mocap`` source).
        settings, controller, safety: the plan's sections, shared by every vehicle (a vehicle's
            ``geofence_min_m``/``geofence_max_m`` replace the geofence for it).
        fleet_safety: the fleet supervisor's limits and policy.
        log_dir: one flight log per vehicle goes here (None: no logs).
        on_status: called with (vehicle name, :class:`Status`) a few times a second.
    """

    def __init__(
        self,
        lab: LabConfig,
        *,
        arm: bool = False,
        clock: Clock | None = None,
        mocap: MocapSource | None = None,
        settings: PlanSettings | None = None,
        controller: ControllerConfig | None = None,
        safety: SafetyConfig | None = None,
        fleet_safety: FleetSafety | None = None,
        log_dir: str | Path | None = None,
        on_status: Callable[[str, Status], None] | None = None,
        name: str = "fleet",
    ) -> None:
        self.lab = lab
        self.arm = arm
        self.clock: Clock = clock or WallClock()
        self.settings = settings or PlanSettings()
        self.controller = controller or ControllerConfig()
        self.safety = safety or SafetyConfig()
        self.fleet_safety = fleet_safety or FleetSafety()
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.on_status = on_status
        self.name = name
        self.vehicles: dict[str, FleetVehicle] = {}
        self.report = FleetReport()
        self._shared_mocap = mocap
        self._logs: list[FlightLog] = []
        self._stack = contextlib.AsyncExitStack()
        self._watch: asyncio.Task[None] | None = None
        self._signals: list[int] = []

    # ------------------------------------------------------------------ lifetime

    async def __aenter__(self) -> Self:
        try:
            await self._open()
        except BaseException:
            await self._close()
            raise
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            flying = [v for v in self.vehicles.values() if v.runner.airborne and not v.runner.ended]
            if flying:
                why = "leaving the fleet block" if exc is None else f"{type(exc).__name__} in the script"
                logger.warning("%s with %d vehicle(s) flying: landing them", why, len(flying))
                for v in flying:
                    v.runner.interrupt()
                with contextlib.suppress(SafetyAbort):
                    await asyncio.shield(self._each([v.name for v in flying], lambda r, _n: r.land(), react=False))
        finally:
            await self._close()

    async def _open(self) -> None:
        from flightkit.link import open_link

        self.lab.check_shared_links()
        configs = self.lab.fleet()
        session = None
        if self._shared_mocap is None and self.lab.mocap.source is MocapSourceKind.BUS:
            # one bus session serves every vehicle's mocap subscription
            from flightkit.bus.session import open_session

            session = open_session(self.lab.bus)
            self._stack.callback(session.close)
        for vcfg in configs:
            name = vcfg.vehicle.namespace
            # the runner flies on mocap: unless asked for, the autopilot's own pose would only load the link
            link_cfg = vcfg.link
            if link_cfg.pose_telemetry_hz < 0:
                link_cfg = dataclasses.replace(link_cfg, pose_telemetry_hz=0.0)
            link = await self._stack.enter_async_context(open_link(link_cfg, vcfg.vehicle.autopilot, self.clock))
            mocap = self._shared_mocap
            if mocap is None:
                from flightkit.mocap import open_mocap

                mocap = await self._stack.enter_async_context(
                    open_mocap(vcfg.mocap, vcfg.bus, Keys(name), self.clock, session=session)
                )
            log = None
            if self.log_dir is not None:
                log = FlightLog(self.log_dir / f"{self.name}-{name}.csv", {"plan": self.name, "vehicle": name})
                self._logs.append(log)
            runner = FlightRunner(
                link,
                mocap,
                body=vcfg.mocap.body,
                clock=self.clock,
                settings=self.settings,
                controller=self.controller,
                safety=self._safety_for(name),
                log=log,
                on_status=self._status_for(name),
                name=f"{self.name}/{name}",
            )
            self.vehicles[name] = FleetVehicle(name, vcfg, link, mocap, runner)
        await self._each(self.names, lambda r, _n: r.preflight(), react=False)
        self._install_signals()
        await self._each(self.names, lambda r, _n: r.start(self.arm), react=False)
        self._watch = asyncio.get_running_loop().create_task(self._watch_separation(), name="fleet-separation")

    async def _close(self) -> None:
        self._remove_signals()
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
            self._watch = None
        for v in self.vehicles.values():
            summary = v.runner.finish()
            await v.runner.close()
            if v.runner.loop.log is not None:
                v.runner.loop.log.close(summary)
        await self._stack.aclose()

    def _status_for(self, name: str) -> Callable[[Status], None] | None:
        cb = self.on_status
        if cb is None:
            return None
        return lambda status: cb(name, status)

    def _safety_for(self, name: str) -> SafetyConfig:
        entry = self.lab.vehicle_entry(name)
        if entry is None or not entry.geofence_min_m:
            return self.safety
        fence = Geofence(min_m=entry.geofence_min_m, max_m=entry.geofence_max_m, enabled=True)
        return dataclasses.replace(self.safety, geofence=fence)

    def _install_signals(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                loop.add_signal_handler(sig, self.interrupt)
                self._signals.append(sig)
            except (ValueError, RuntimeError, NotImplementedError):
                pass  # not the main thread: the caller handles signals

    def _remove_signals(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in self._signals:
            loop.remove_signal_handler(sig)
        self._signals.clear()

    # ------------------------------------------------------------------ state

    @property
    def names(self) -> tuple[str, ...]:
        """The vehicles' names, in config order."""
        return tuple(self.vehicles)

    def runner(self, name: str) -> FlightRunner:
        """The runner of vehicle ``name``."""
        return self.vehicles[name].runner

    def summaries(self) -> dict[str, FlightSummary]:
        """Each vehicle's flight summary so far."""
        return {n: v.runner.summary for n, v in self.vehicles.items()}

    def interrupt(self) -> None:
        """Land every vehicle (what Ctrl-C and SIGTERM do); returns immediately."""
        logger.warning("fleet interrupted: landing every vehicle")
        for v in self.vehicles.values():
            v.runner.interrupt()

    # ------------------------------------------------------------------ verbs

    async def takeoff(self, height_m: float, names: Iterable[str] | None = None) -> None:
        """Take the vehicles off to ``height_m``; each holds until all are up. Blocks."""
        await self._each_then_sync(names, lambda r, _n: r.takeoff(height_m))

    async def hold(self, duration_s: float, names: Iterable[str] | None = None) -> None:
        """Hold where they are for ``duration_s``; blocks."""
        await self._each(self._select(names), lambda r, _n: r.hold(duration_s))

    async def goto(self, positions_m: Mapping[str, Vec3Tuple], yaw_rad: Mapping[str, float] | None = None) -> None:
        """Fly each named vehicle to its position (world ENU); each holds until all are there."""
        yaws = yaw_rad or {}
        await self._each_then_sync(positions_m, lambda r, n: r.goto(positions_m[n], yaws.get(n)))

    async def fly(self, patterns: Mapping[str, Pattern]) -> float:
        """Fly each named vehicle's pattern, started together; returns the start skew (s).

        Every vehicle first flies to its pattern's start and holds there until all are at theirs;
        then every pattern runs on one clock epoch (a vehicle whose first cycle comes late joins the
        common timeline). The skew returned is the spread of the vehicles' first pattern cycles.

        Raises:
            PlanError: the references come closer than ``min_separation_m`` (nothing moves).
            SafetyAbort: a fault ended the flight of a vehicle (after the fleet reacted).
        """
        unknown = sorted(set(patterns) - set(self.vehicles))
        if unknown:
            raise PlanError(f"no vehicle named {', '.join(unknown)} in this fleet; it has {', '.join(self.names)}")
        d, t, pair = plan_separation(patterns)
        if d < self.fleet_safety.min_separation_m:
            raise PlanError(
                f"the patterns of {pair[0]} and {pair[1]} come {d:.2f} m close at t={t:.1f} s, below the "
                f"fleet's min_separation_m {self.fleet_safety.min_separation_m:g} m; spread them apart"
            )
        starts = {n: p.reference(0.0) for n, p in patterns.items()}
        await self.goto({n: r.pos_m for n, r in starts.items()}, {n: r.yaw_rad for n, r in starts.items()})
        # one epoch for every pattern, a few cycles ahead so every loop is waiting for it
        start_at_s = self.clock.monotonic_s() + _START_LEAD_S
        await self._each(list(patterns), lambda r, n: r.fly(patterns[n], start_at_s=start_at_s))
        started = [self.vehicles[n].runner.pattern_started_s for n in patterns]
        self.report.start_skew_s = max(started) - min(started) if started else math.nan
        return self.report.start_skew_s

    async def land(self, names: Iterable[str] | None = None) -> None:
        """Land the vehicles (each descends under control, then disarms); blocks."""
        await self._each(self._select(names), lambda r, _n: r.land())

    # ------------------------------------------------------------------ running verbs

    def _select(self, names: Iterable[str] | None) -> list[str]:
        chosen = list(self.names if names is None else names)
        unknown = [n for n in chosen if n not in self.vehicles]
        if unknown:
            raise PlanError(f"no vehicle named {', '.join(unknown)} in this fleet; it has {', '.join(self.names)}")
        return [n for n in chosen if not self.vehicles[n].fault]

    async def _each_then_sync(
        self, names: Iterable[str] | None, verb: Verb
    ) -> None:
        chosen = self._select(names)
        arrived: set[str] = set()

        async def one(runner: FlightRunner, name: str) -> None:
            await verb(runner, name)
            arrived.add(name)
            # hold there until every vehicle still flying with the fleet has arrived
            await runner.hold_until(lambda: all(n in arrived or self.vehicles[n].fault for n in chosen))

        await self._each(chosen, one)

    async def _each(
        self, names: Iterable[str], verb: Verb, *, react: bool = True
    ) -> None:
        """Run ``verb`` on each vehicle concurrently; apply the fault policy; raise the first fault."""
        chosen = list(names)

        async def one(name: str) -> None:
            v = self.vehicles[name]
            try:
                await verb(v.runner, name)
            except SafetyAbort as exc:
                if react and not v.fault:
                    self._vehicle_faulted(name, exc)
                raise

        results = await asyncio.gather(*(one(n) for n in chosen), return_exceptions=True)
        errors = [r for r in results if isinstance(r, BaseException)]
        others = [e for e in errors if not isinstance(e, SafetyAbort)]
        if others:
            raise others[0]
        aborts = [e for e in errors if isinstance(e, SafetyAbort)]
        # the fleet's flight ends when its own supervisor or policy ended it, or no vehicle is left;
        # a vehicle its pilot took over (or that faulted under "continue") just leaves the fleet
        fleet_wide = {FaultKind.FLEET.value, FaultKind.SEPARATION.value, FaultKind.INTERRUPTED.value}
        ends = [
            a
            for a in aborts
            if a.reason in fleet_wide
            or (a.reason not in _LEAVES_ALONE and self.fleet_safety.on_vehicle_fault == "land")
        ]
        if ends or (aborts and len(aborts) == len(chosen)) or (aborts and not react):
            raise next((a for a in ends if a.reason != FaultKind.FLEET.value), (ends or aborts)[0])

    def _vehicle_faulted(self, name: str, exc: SafetyAbort) -> None:
        v = self.vehicles[name]
        v.fault = f"{exc.reason}: {exc}"
        t = v.runner.t_s
        self.report.faults.append((t, name, v.fault))
        if exc.reason == FaultKind.FLEET.value:
            return
        if exc.reason in _LEAVES_ALONE:
            logger.warning("%s: %s; the pilot has it, the other vehicles go on", name, exc)
        elif self.fleet_safety.on_vehicle_fault == "land":
            logger.warning("%s: %s; the other vehicles hold, then land", name, exc)
            for other in self.vehicles.values():
                if other.name != name and not other.runner.ended:
                    other.runner.loop.raise_fault(FaultKind.FLEET, f"{name} ended its flight ({exc.reason}); landing")
        else:
            logger.warning("%s: %s; the other vehicles continue", name, exc)

    # ------------------------------------------------------------------ separation

    async def _watch_separation(self) -> None:
        fs = self.fleet_safety
        period_s = 1.0 / fs.check_rate_hz
        # per vehicle: (stamp s, position) of the pose the velocity is differenced from; velocities
        # come from the poses' own capture stamps over at least _VELOCITY_BASELINE_S, so a late
        # wake-up of this task or mocap jitter does not turn into a phantom closing speed
        ref: dict[str, tuple[float, Vec3Tuple]] = {}
        vel: dict[str, Vec3Tuple] = {}
        while True:
            await self.clock.sleep(period_s)
            now = self.clock.monotonic_s()
            pos: dict[str, Vec3Tuple] = {}
            for n, v in self.vehicles.items():
                pose, _age = v.runner.loop.pose(now)
                if pose is None or not v.runner.airborne:
                    ref.pop(n, None)
                    vel.pop(n, None)
                    continue
                t = pose.T_world_body.translation
                p = (float(t[0]), float(t[1]), float(t[2]))
                stamp_s = pose.stamp_ns * 1e-9
                pos[n] = p
                if n not in ref:
                    ref[n] = (stamp_s, p)
                elif stamp_s - ref[n][0] >= _VELOCITY_BASELINE_S:
                    dt = stamp_s - ref[n][0]
                    q = ref[n][1]
                    vel[n] = ((p[0] - q[0]) / dt, (p[1] - q[1]) / dt, (p[2] - q[2]) / dt)
                    ref[n] = (stamp_s, p)
            approach = closest_approach(pos, vel, fs.lookahead_s)
            if approach is None:
                continue
            if approach.distance_m < self.report.min_separation_m:
                self.report.min_separation_m = approach.distance_m
                self.report.closest_pair = approach.pair
            if approach.closest_m < fs.min_separation_m:
                self._separation_lost(approach)

    def _separation_lost(self, a: Approach) -> None:
        fs = self.fleet_safety
        when = "now" if a.distance_m < fs.min_separation_m else f"within {fs.lookahead_s:g} s"
        msg = (
            f"{a.pair[0]} and {a.pair[1]} are {a.distance_m:.2f} m apart ({a.predicted_m:.2f} m predicted), "
            f"below {fs.min_separation_m:g} m {when}; every vehicle holds, then lands"
        )
        if not any(k == f"{a.pair[0]}/{a.pair[1]}" for _, k, _ in self.report.faults):
            logger.warning("fleet: %s", msg)
            self.report.faults.append((min(v.runner.t_s for v in self.vehicles.values()), "/".join(a.pair), msg))
        for v in self.vehicles.values():
            if v.runner.airborne and not v.runner.ended:
                v.runner.loop.raise_fault(FaultKind.SEPARATION, msg)
