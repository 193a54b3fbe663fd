"""The flight runner: sequences phases, runs the control loop, applies the supervisor's decisions.

:class:`FlightRunner` owns one flight on an already connected :class:`VehicleLink` and a
running :class:`MocapSource`. Each blocking method (:meth:`~FlightRunner.takeoff`,
:meth:`~FlightRunner.hold`, :meth:`~FlightRunner.fly`, :meth:`~FlightRunner.goto`,
:meth:`~FlightRunner.land`) tracks a pattern until it is done. Every cycle:

1. read the newest mocap pose of the body (age since the newest *valid* pose);
2. compute the reference at pattern time t (pattern time stands still while holding);
3. ask the supervisor (:func:`trajectories.supervisor.supervise`);
4. on CONTINUE run the controller and replace the streamed setpoint; on HOLD send zero
   velocity; anything else ends the phase: the runner reacts (hold then land, land, hand
   over to the autopilot's LAND, release to the pilot, or stop) and raises
   :class:`~flightkit.errors.SafetyAbort`;
5. log the cycle.

The loop is driven by mocap: it wakes when a new pose arrives (so the setpoint follows the
sample by microseconds), and at least every ``1 / rate_hz`` seconds of clock time so stale
mocap is still noticed.

:func:`fly_plan` is the one-call entry point (the CLI and ``make demo`` use it).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import inspect
import logging
import math
import signal
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from flightkit.clock import Clock, WallClock
from flightkit.config import Autopilot, LabConfig
from flightkit.errors import (
    CommandRejected,
    LinkError,
    LinkTimeout,
    MocapBodyMissing,
    MocapError,
    SafetyAbort,
)
from flightkit.link.base import FlightMode, LandedState, VehicleLink, VelocitySetpoint, offboard_mode_for
from flightkit.mocap.base import MocapPose, MocapSource
from trajectories.base import Pattern, PiecewisePattern, Reference, Turn, Vec3
from trajectories.circle import Circle
from trajectories.controller import ControllerConfig, VelocityController
from trajectories.flightlog import FlightLog, FlightSummary, PhaseStats
from trajectories.hold import Hold
from trajectories.plan import Plan, PlanSettings
from trajectories.supervisor import (
    Action,
    Decision,
    Fault,
    FaultKind,
    SafetyConfig,
    SupervisorInput,
    preflight_problems,
    supervise,
)
from trajectories.takeoff import Land, Takeoff
from trajectories.waypoints import Waypoints

__all__ = ["FlightRunner", "Status", "fly_plan", "open_lab_mocap", "pattern_in_fence", "with_laps"]

logger = logging.getLogger(__name__)

# ArduCopter leaves the ground only on its own take-off command, and climbs at its own rate
# (WPNAV_SPEED_UP, 2.5 m/s by default: above the supervisor's 2 m/s limit on a tall take-off).
# So it lifts the vehicle this high above its start, and our controller climbs the rest at the
# plan's rate, as on PX4.
_ARDUPILOT_LIFTOFF_M = 0.3

_OUTCOME = {
    Action.ABORT: "landed_early",
    Action.LAND: "landed_early",
    Action.LAND_AUTOPILOT: "autopilot_landing",
    Action.RELEASE: "released",
    Action.STOP: "stopped",
}


@dataclass(frozen=True, slots=True)
class Status:
    """A snapshot for the live status line (given to ``on_status`` a few times a second).

    Attributes:
        t_s: flight time. phase: current phase. lap / laps: 1-based lap of the pattern.
        pos_m: measured position (world ENU). err_m: tracking error. rate_hz: control rate.
        action: supervisor action name. message: extra text (e.g. a countdown).
    """

    t_s: float
    phase: str
    lap: int = 0
    laps: int = 0
    pos_m: Vec3 | None = None
    err_m: float = math.nan
    rate_hz: float = math.nan
    action: str = "CONTINUE"
    message: str = ""

    def line(self) -> str:
        p = (
            "(  ---,   ---,   ---)"
            if self.pos_m is None
            else "({:5.2f}, {:5.2f}, {:5.2f})".format(*self.pos_m)
        )
        lap = f"lap {self.lap}/{self.laps}" if self.laps else "       "
        extra = f"  {self.message}" if self.message else ""
        act = "" if self.action == "CONTINUE" else f"  [{self.action}]"
        return (
            f"t={self.t_s:7.2f}s  {self.phase:<10} {lap}  pos {p}  err {self.err_m:6.3f} m  "
            f"{self.rate_hz:5.0f} Hz{act}{extra}"
        )


def with_laps(pattern: Pattern, laps: int) -> Pattern:
    """The same pattern flown ``laps`` times (raises ValueError if its laps do not close)."""
    if laps == pattern.laps:
        return pattern
    if isinstance(pattern, Circle):
        return dataclasses.replace(pattern, laps=laps)
    if isinstance(pattern, PiecewisePattern):
        return PiecewisePattern(pattern.name, pattern.segments, laps)
    raise ValueError(f"cannot change the lap count of a {type(pattern).__name__}; build it with laps={laps}")


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


class _FaultExit(Exception):
    def __init__(self, decision: Decision) -> None:
        self.decision = decision
        super().__init__(decision.action.name)


class FlightRunner:
    """One flight on a connected link and a running mocap source.

    Args:
        link: connected vehicle link. mocap: running mocap source (same clock as the link).
        body: mocap rigid-body name of the vehicle. autopilot: its firmware.
        clock: the clock every wait uses. settings / controller / safety: plan sections.
        log: flight log to write each cycle to (None: no log).
        on_status: called with a :class:`Status` about 5 times a second (from the event loop).
        name: plan name for the summary.
    """

    def __init__(
        self,
        link: VehicleLink,
        mocap: MocapSource,
        *,
        body: str,
        autopilot: Autopilot,
        clock: Clock,
        settings: PlanSettings | None = None,
        controller: ControllerConfig | None = None,
        safety: SafetyConfig | None = None,
        log: FlightLog | None = None,
        on_status: Callable[[Status], None] | None = None,
        name: str = "flight",
    ) -> None:
        self.link = link
        self.mocap = mocap
        self.body = body
        self.autopilot = autopilot
        self.clock = clock
        self.settings = settings or PlanSettings()
        self.controller = VelocityController(controller or ControllerConfig())
        # lift-off is pure feed-forward (see _Climb): it uses it even under the P-only law
        self._lift_controller = VelocityController(
            dataclasses.replace(self.controller.config, feedforward=True)
        )
        self.safety = safety or SafetyConfig()
        self.log = log
        self.on_status = on_status
        self.control_mode = offboard_mode_for(autopilot)
        self._push = _immediate_setter(link)
        self.summary = FlightSummary(plan=name, log_path=str(log.path) if log else None)
        self.interrupted = asyncio.Event()
        self.in_control = False  # we command the vehicle (armed, in the offboard mode)
        self.airborne = False
        self.ended = False  # a fault ended the flight (landed, released or stopped)
        self._t0 = clock.monotonic_s()
        self._active: set[FaultKind] = set()
        self._last_phase = ""
        self._cycle_s: list[float] = []  # wall time per control cycle
        self._cycle_cpu_s: list[float] = []  # this thread's CPU time per cycle (no waits, no steal)
        self._ticks = 0
        self._last_status_s = -math.inf
        self._last_valid: MocapPose | None = None
        self._yaw_cache: tuple[int, float] = (-1, 0.0)
        self._prev_for_speed: tuple[float, Vec3] | None = None
        self._speed_m_s = math.nan
        self._new_pose = asyncio.Event()
        self._pose_task: asyncio.Task[None] | None = None
        self._last_err = math.nan

    # ------------------------------------------------------------------ mocap

    @property
    def t_s(self) -> float:
        """Flight time, seconds since the runner was created."""
        return self.clock.monotonic_s() - self._t0

    def _start_pose_watch(self) -> None:
        if self._pose_task is None:
            self._pose_task = asyncio.get_running_loop().create_task(
                self._watch_poses(), name="runner-mocap-watch"
            )

    async def _watch_poses(self) -> None:
        try:
            async for _ in self.mocap.poses(self.body):
                self._new_pose.set()
        except asyncio.CancelledError:
            raise
        except Exception:  # the control loop notices staleness on its own
            logger.exception("mocap pose stream ended")

    def _pose(self, now: float) -> tuple[MocapPose | None, float]:
        """Newest valid pose and its age (inf when none)."""
        p = self.mocap.latest(self.body)
        if p is not None and p.valid:
            if self._last_valid is None or p.stamp_ns != self._last_valid.stamp_ns:
                self._update_speed(p)
            self._last_valid = p
        lv = self._last_valid
        if lv is None:
            return None, math.inf
        return lv, max(0.0, now - lv.received_s)

    def _update_speed(self, p: MocapPose) -> None:
        t = p.stamp_ns * 1e-9
        pos = (
            float(p.T_world_body.translation[0]),
            float(p.T_world_body.translation[1]),
            float(p.T_world_body.translation[2]),
        )
        prev = self._prev_for_speed
        if prev is None or t - prev[0] >= 0.05:  # 20 Hz finite difference: robust to mocap jitter
            if prev is not None and t > prev[0]:
                self._speed_m_s = math.dist(pos, prev[1]) / (t - prev[0])
            self._prev_for_speed = (t, pos)

    def _yaw(self, p: MocapPose) -> float:
        if self._yaw_cache[0] != p.stamp_ns:
            self._yaw_cache = (p.stamp_ns, p.T_world_body.yaw_rad)
        return self._yaw_cache[1]

    def current_pose(self) -> tuple[Vec3, float]:
        """Newest valid mocap position (world ENU) and yaw; MocapBodyMissing when there is none."""
        p, _ = self._pose(self.clock.monotonic_s())
        if p is None:
            raise MocapBodyMissing(self.body, tuple(self.mocap.bodies()))
        t = p.T_world_body.translation
        return (float(t[0]), float(t[1]), float(t[2])), self._yaw(p)

    # ------------------------------------------------------------------ faults

    def _record(self, decision: Decision) -> None:
        kinds = {f.kind for f in decision.faults}
        for f in decision.faults:
            if f.kind not in self._active:
                self.summary.faults.append(f)
                if self.log is not None:
                    self.log.fault(f)
                logger.warning("fault at t=%.2f s: %s: %s", f.time_s, f.kind.value, f.message)
        self._active = kinds

    def _fault(self, kind: FaultKind, message: str, action: Action) -> Decision:
        return Decision(action, (Fault(self.t_s, kind, message, action),))

    def interrupt(self) -> None:
        """Ask the flight to land (what Ctrl-C and SIGTERM do); returns immediately."""
        self.interrupted.set()

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

    # ------------------------------------------------------------------ the loop

    async def _wait_tick(self, timeout_s: float) -> None:
        """Until a new mocap pose arrives or ``timeout_s`` of clock time passes."""
        if self._new_pose.is_set():
            self._new_pose.clear()
            return
        if self._pose_task is None:
            await self.clock.sleep(timeout_s)
            return
        sleeper = asyncio.ensure_future(self.clock.sleep(timeout_s))
        waiter = asyncio.ensure_future(self._new_pose.wait())
        try:
            await asyncio.wait((sleeper, waiter), return_when=asyncio.FIRST_COMPLETED)
        finally:
            sleeper.cancel()
            waiter.cancel()
        self._new_pose.clear()

    async def _track(
        self,
        pattern: Pattern,
        phase: str,
        *,
        tolerate: Action = Action.CONTINUE,
        until: Callable[[float, Vec3], bool] | None = None,
        end_when: Callable[[float, Vec3], bool] | None = None,
        floor_m: float | None = None,
        timeout_s: float = math.inf,
        send: bool = True,
    ) -> None:
        """Track ``pattern`` until it is done (and ``until(t, pos)`` holds, if given), or
        as soon as ``end_when(t, pos)`` holds.

        Faults whose action is at most ``tolerate`` are recorded but do not end the phase;
        HOLD faults pause the pattern. Raises _FaultExit for the others. With ``send=False``
        nothing is sent (the autopilot flies on its own; we only supervise and log). With
        ``floor_m`` the tracking error is measured against the reference clamped to the floor
        (a landing reference reaches below it to keep pressing down).
        """
        self._start_pose_watch()
        ctl = self._lift_controller if isinstance(pattern, _Climb) else self.controller
        ctl.reset()
        stats = self._stats_for(phase)
        period = 1.0 / self.settings.rate_hz
        clock = self.clock
        start = last = clock.monotonic_s()
        t_pat = 0.0
        frame = self.controller.config.output_frame.setpoint_frame.value
        laps = pattern.laps if pattern.laps > 1 or phase == "pattern" else 0
        lookahead = self.safety.fence_lookahead_s if self.safety.geofence.enabled else 0.0
        while True:
            now = clock.monotonic_s()
            dt = now - last
            last = now
            c0 = time.perf_counter()
            c0_cpu = time.thread_time()
            pose, age = self._pose(now)
            pos: Vec3 | None = None
            yaw = math.nan
            if pose is not None:
                t = pose.T_world_body.translation
                pos = (float(t[0]), float(t[1]), float(t[2]))
                yaw = self._yaw(pose)
            ref = pattern.reference(t_pat)
            ahead = pattern.reference(t_pat + lookahead) if lookahead > 0.0 else ref
            tel = self.link.telemetry
            decision = supervise(
                self.safety,
                SupervisorInput(
                    now - self._t0,
                    age,
                    tel,
                    self.control_mode if self.in_control else None,
                    pos,
                    ahead.pos_m,
                    self._speed_m_s,
                    self.interrupted.is_set(),
                ),
            )
            if decision.faults or self._active:
                self._record(decision)
            action = decision.action
            if action > Action.HOLD and action <= tolerate:
                action = (
                    Action.HOLD if any(f.action is Action.HOLD for f in decision.faults) else Action.CONTINUE
                )
            err = math.nan
            if action is Action.CONTINUE and pos is not None:
                t_pat += dt
                ref = pattern.reference(t_pat)
                out = ctl.step(ref, pos, yaw, dt)
                sp = out.setpoint
                err = out.error_norm_m
                if floor_m is not None and ref.pos_m[2] < floor_m:
                    err = math.dist((ref.pos_m[0], ref.pos_m[1], floor_m), pos)
                if send:
                    self._push(sp)
            elif action is Action.HOLD or (action is Action.CONTINUE and pos is None):
                sp = self.controller.hold()
                if send:
                    self._push(sp)
                if pos is not None:
                    rz = ref.pos_m[2] if floor_m is None else max(ref.pos_m[2], floor_m)
                    err = math.dist((ref.pos_m[0], ref.pos_m[1], rz), pos)
            else:
                raise _FaultExit(decision)
            cycle_cpu = time.thread_time() - c0_cpu  # (inside the wall window, so never larger)
            cycle = time.perf_counter() - c0
            self._cycle_cpu_s.append(cycle_cpu)
            self._cycle_s.append(cycle)
            self._ticks += 1
            if not math.isnan(err) and send:
                stats.add(err)
                self._last_err = err
            if self.log is not None:
                p = pos or (math.nan, math.nan, math.nan)
                self.log.row(
                    (
                        round(now - self._t0, 6),
                        clock.time_ns(),
                        phase,
                        ref.lap,
                        action.name,
                        *ref.pos_m,
                        ref.yaw_rad,
                        *ref.vel_m_s,
                        *p,
                        yaw,
                        age if math.isfinite(age) else -1.0,
                        frame,
                        *sp.vel_m_s,
                        sp.yaw_rad if sp.yaw_rad is not None else math.nan,
                        sp.yaw_rate_rad_s if sp.yaw_rate_rad_s is not None else math.nan,
                        err,
                        cycle,
                    )
                )
            if now - self._last_status_s >= 0.2:
                self._last_status_s = now
                self._status(phase, ref.lap + 1 if laps else 0, laps, pos, action.name)
            stats.duration_s = stats.duration_s + dt if stats.samples > 1 else stats.duration_s
            finished = ref.done or (until is not None and math.isinf(pattern.duration_s))
            if (finished and (until is None or (pos is not None and until(now - start, pos)))) or (
                end_when is not None and pos is not None and end_when(now - start, pos)
            ):
                if phase == "pattern":
                    self.summary.laps_completed += pattern.laps
                return
            if now - start > timeout_s:
                raise LinkTimeout(f"{phase} did not finish within {timeout_s:.0f} s", phase, timeout_s)
            await self._wait_tick(period)

    def _stats_for(self, phase: str) -> PhaseStats:
        """The statistics entry of ``phase``: the current one if the previous phase had the same
        name (a take-off in two steps), else a new entry (a second hold becomes ``hold_2``)."""
        phases = self.summary.phases
        if phases and self._last_phase == phase:
            return phases[-1]
        self._last_phase = phase
        n = sum(1 for p in phases if p.name == phase or p.name.startswith(phase + "_"))
        stats = PhaseStats(phase if n == 0 else f"{phase}_{n + 1}")
        phases.append(stats)
        return stats

    def _status(
        self, phase: str, lap: int, laps: int, pos: Vec3 | None, action: str, message: str = ""
    ) -> None:
        if self.on_status is None:
            return
        n = len(self._cycle_s)
        rate = math.nan
        if n > 10 and self._ticks > 10:
            rate = self._rate_estimate()
        self.on_status(Status(self.t_s, phase, lap, laps, pos, self._last_err, rate, action, message))

    def _rate_estimate(self) -> float:
        elapsed = self.t_s
        return self._ticks / elapsed if elapsed > 0 else math.nan

    # ------------------------------------------------------------------ reactions

    async def _run(self, coro_fn: Callable[[], Any]) -> None:
        """Run one phase; on a fault, react and raise SafetyAbort."""
        if self.ended:
            raise SafetyAbort("ended", "the flight has already ended after a fault; start a new one")
        try:
            await coro_fn()
        except _FaultExit as exc:
            await self._react(exc.decision)

    async def _react(self, decision: Decision) -> None:
        first = decision.faults[0] if decision.faults else None
        top = max(decision.faults, key=lambda f: f.action) if decision.faults else first
        action = decision.action
        while True:
            try:
                if action is Action.ABORT:
                    pos, yaw = self.current_pose()
                    if self.safety.abort_hold_s > 0:
                        await self._track(
                            Hold(pos, yaw, self.safety.abort_hold_s), "abort_hold", tolerate=Action.ABORT
                        )
                    action = Action.LAND
                    continue
                if action is Action.LAND:
                    await self._controlled_land(tolerate=Action.LAND)
                elif action is Action.LAND_AUTOPILOT:
                    await self._autopilot_land()
                elif action in (Action.RELEASE, Action.STOP):
                    self.in_control = False
                    with contextlib.suppress(LinkError):
                        await self.link.stop_setpoint_stream()
                break
            except _FaultExit as exc:
                if exc.decision.action <= action:  # cannot happen with tolerate; be safe
                    raise
                action = exc.decision.action
                top = max(exc.decision.faults, key=lambda f: f.action)
        self.ended = True
        self.summary.outcome = _OUTCOME.get(action, "landed_early")
        kind = top.kind.value if top else "unknown"
        msg = top.message if top else "flight ended by the supervisor"
        raise SafetyAbort(kind, msg)

    async def _autopilot_land(self) -> None:
        """Hand over to the autopilot's LAND mode and wait for touchdown (watching heartbeat and pilot)."""
        logger.warning("switching to the autopilot's LAND mode")
        self.in_control = False
        await self.link.land()
        await self._wait_landed(watch_mode=FlightMode.LAND)

    async def _wait_landed(self, watch_mode: FlightMode | None) -> None:
        deadline = self.clock.monotonic_s() + self.settings.landed_timeout_s
        while True:
            tel = self.link.telemetry
            if tel.heartbeat_age_s > self.safety.heartbeat_period_s + self.safety.heartbeat_timeout_s:
                raise _FaultExit(
                    self._fault(
                        FaultKind.HEARTBEAT_LOST,
                        f"no autopilot heartbeat for {tel.heartbeat_age_s:.2f} s while landing",
                        Action.STOP,
                    )
                )
            if not tel.armed:
                self.airborne = False
                return
            if watch_mode is not None and tel.mode is not watch_mode:
                raise _FaultExit(
                    self._fault(
                        FaultKind.PILOT_TAKEOVER,
                        f"mode changed from {watch_mode.value} to {tel.mode.value} while landing",
                        Action.RELEASE,
                    )
                )
            if self.clock.monotonic_s() > deadline:
                raise LinkTimeout(
                    f"the vehicle did not land and disarm within {self.settings.landed_timeout_s:.0f} s",
                    "landed",
                    self.settings.landed_timeout_s,
                )
            await self.clock.sleep(0.05)

    # ------------------------------------------------------------------ phases

    async def preflight(self) -> None:
        """Wait for the mocap body and check the vehicle can fly; blocks up to ``preflight_timeout_s``.

        Raises:
            MocapBodyMissing: the body is not visible (the error names the visible bodies).
            SafetyAbort: another preflight check failed (reason ``"preflight"``).
        """
        try:
            await self.mocap.wait_for_body(self.body, self.settings.preflight_timeout_s)
        except MocapBodyMissing:
            raise
        pose, _ = self._pose(self.clock.monotonic_s())
        pos = None
        if pose is not None:
            t = pose.T_world_body.translation
            pos = (float(t[0]), float(t[1]), float(t[2]))
        problems = preflight_problems(
            self.safety, self.body, tuple(self.mocap.bodies()), pose is not None, self.link.telemetry, pos
        )
        if problems:
            raise SafetyAbort("preflight", "preflight failed: " + "; ".join(problems))
        logger.info("preflight ok: body %r at %s", self.body, pos)

    async def start(self, arm: bool) -> None:
        """Start the setpoint stream and get control: arm and switch mode ourselves (``arm=True``),
        or wait for the pilot to arm and switch to OFFBOARD/GUIDED (countdown via ``on_status``).

        Blocks until armed in the offboard mode. Raises CommandRejected / LinkTimeout.
        """
        link = self.link
        self._start_pose_watch()
        await link.start_setpoint_stream(max(self.settings.rate_hz, 20.0))
        link.set_velocity(self.controller.hold())
        mode = self.control_mode
        if arm:
            # PX4 wants a second of setpoints before OFFBOARD / arming; keep them fresh meanwhile.
            await self._keep_streaming(1.2 if self.autopilot is Autopilot.PX4 else 0.1)
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
                pose, _ = self._pose(self.clock.monotonic_s())
                pos: Vec3 | None = None
                if pose is not None:
                    t = pose.T_world_body.translation
                    pos = (float(t[0]), float(t[1]), float(t[2]))
                self._status(
                    "wait_pilot",
                    0,
                    0,
                    pos,
                    "CONTINUE",
                    f"arm and switch to {mode.value}: {left:4.0f} s left",
                )
                await self._keep_streaming(0.2)
        self.in_control = True
        logger.info("armed in %s", mode.value)

    async def _keep_streaming(self, duration_s: float) -> None:
        end = self.clock.monotonic_s() + duration_s
        while self.clock.monotonic_s() < end:
            self.link.set_velocity(self.controller.hold())
            await self.clock.sleep(min(0.05, duration_s))

    async def takeoff(self, height_m: float, climb_m_s: float | None = None) -> None:
        """Take off to ``height_m`` (world z); blocks until there (SafetyAbort on a fault)."""
        await self._run(lambda: self._takeoff(height_m, climb_m_s))

    async def _takeoff(self, height_m: float, climb_m_s: float | None) -> None:
        climb = climb_m_s or self.settings.climb_m_s
        pos, yaw = self.current_pose()
        self.airborne = True
        if self.autopilot is Autopilot.ARDUPILOT:
            # A velocity setpoint would cancel ArduCopter's own climb: pause the stream, command the
            # lift-off, watch (no setpoints) until near its height, then climb the rest ourselves.
            lift_m = max(0.2, min(height_m - pos[2], _ARDUPILOT_LIFTOFF_M))
            lifted_z_m = pos[2] + lift_m - 0.05
            rate_hz = max(self.settings.rate_hz, 20.0)
            await self.link.stop_setpoint_stream()
            try:
                await self.link.takeoff(lift_m)
                await self._track(
                    _Climb(pos, yaw, 0.0),
                    "takeoff",
                    send=False,
                    timeout_s=60.0,
                    until=lambda _t, p: p[2] >= lifted_z_m,
                )
            except BaseException:
                # whatever reacts (a fault's hold and land, a cancelled flight's landing) streams
                # setpoints: the stream must run again first
                with contextlib.suppress(LinkError):
                    await self.link.start_setpoint_stream(rate_hz)
                raise
            await self.link.start_setpoint_stream(rate_hz)
            pos = self.current_pose()[0]
        else:
            await self._climb_until(pos, yaw, pos[2] + 0.08, climb)
        pos2, _ = self.current_pose()
        if height_m - pos2[2] > 0.02:
            pat = Takeoff((pos[0], pos[1], pos2[2]), height_m, climb, self.settings.accel_m_s2, yaw)
            await self._track(pat, "takeoff")
            self._remember(pat)
        else:
            self._last_target, self._last_yaw = (pos[0], pos[1], height_m), yaw

    async def _climb_until(self, start: Vec3, yaw: float, z_m: float, climb: float) -> None:
        """Lift-off: command a climb (feed-forward, position held horizontally) until z >= z_m.

        The motors spin up for a few seconds after arming; the climb reference waits for them
        (it starts from the measured height while the vehicle is still on the ground).
        """
        await self._track(
            _Climb(start, yaw, climb, self), "takeoff", until=lambda _t, p: p[2] >= z_m, timeout_s=30.0
        )

    async def hold(self, duration_s: float, pos_m: Vec3 | None = None, yaw_rad: float | None = None) -> None:
        """Hold ``pos_m`` (default: the current reference end / position) for ``duration_s``; blocks."""
        if duration_s <= 0:
            return
        p, y = self._here(pos_m, yaw_rad)
        await self._run(lambda: self._track(Hold(p, y, duration_s), "hold"))

    def _here(self, pos_m: Vec3 | None, yaw_rad: float | None) -> tuple[Vec3, float]:
        cur, cyaw = self.current_pose()
        return (pos_m or self._last_target or cur), (
            yaw_rad if yaw_rad is not None else (self._last_yaw if self._last_yaw is not None else cyaw)
        )

    _last_target: Vec3 | None = None
    _last_yaw: float | None = None

    async def goto(self, pos_m: Vec3, yaw_rad: float | None = None, speed_m_s: float | None = None) -> None:
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
                speed_m_s or self.settings.transit_speed_m_s,
                self.settings.accel_m_s2,
                syaw,
                end_yaw_rad=end_yaw,
                turn_s=3.0,
                name="goto",
            )
        await self._run(lambda: self._track(pat, "goto"))
        self._remember(pat)

    def _remember(self, pattern: Pattern) -> None:
        end = pattern.reference(pattern.duration_s)
        self._last_target = end.pos_m
        self._last_yaw = end.yaw_rad

    async def fly(self, pattern: Pattern, laps: int | None = None) -> None:
        """Fly ``pattern`` (``laps`` times if given); first moves to its start. Blocks until done.

        Raises:
            SafetyAbort: a fault ended the pattern (the runner has already reacted: landed, etc.).
            ValueError: the pattern leaves the geofence (with ``check_plan_in_fence``).
        """
        if laps is not None:
            pattern = with_laps(pattern, laps)
        if self.safety.check_plan_in_fence:
            bad = pattern_in_fence(pattern, self.safety)
            if bad is not None:
                raise ValueError(
                    f"{pattern.name} leaves the geofence {self.safety.geofence.describe()} "
                    f"at t={bad.t_s:.1f} s, position ({bad.pos_m[0]:.2f}, {bad.pos_m[1]:.2f}, "
                    f"{bad.pos_m[2]:.2f}); shrink the pattern"
                )
        first = pattern.reference(0.0)
        await self.goto(first.pos_m, first.yaw_rad)
        self._last_yaw = first.yaw_rad
        await self._run(lambda: self._track(pattern, "pattern"))
        self._remember(pattern)

    async def land(self) -> None:
        """Descend under control, let the autopilot finish the touchdown, wait for disarm; blocks."""
        await self._run(lambda: self._controlled_land(tolerate=Action.CONTINUE))

    async def _controlled_land(self, tolerate: Action) -> None:
        pos, yaw = self.current_pose()
        floor = self.settings.floor_m
        if self.link.telemetry.armed and pos[2] > floor + 0.12:
            pat = Land(pos, self.settings.descent_m_s, floor, 0.3, self.settings.accel_m_s2, yaw)
            # the reference reaches below the floor to keep pressing down; the phase ends near
            # the floor (or on touchdown) and the autopilot's LAND finishes the touchdown
            await self._track(
                pat,
                "land",
                tolerate=tolerate,
                floor_m=floor,
                end_when=lambda _t, p: p[2] < floor + 0.12 or self._landed(),
            )
        if self.link.telemetry.armed:
            self.in_control = False
            if not self._landed():
                await self.link.land()
            await self._wait_landed_or_disarm()
        self.airborne = False
        self.in_control = False
        with contextlib.suppress(LinkError):
            await self.link.stop_setpoint_stream()

    def _landed(self) -> bool:
        tel = self.link.telemetry
        return (not tel.armed) or tel.landed_state is LandedState.ON_GROUND

    async def _wait_landed_or_disarm(self) -> None:
        deadline = self.clock.monotonic_s() + self.settings.landed_timeout_s
        disarm_sent = False
        while self.link.telemetry.armed:
            tel = self.link.telemetry
            if tel.heartbeat_age_s > self.safety.heartbeat_period_s + self.safety.heartbeat_timeout_s:
                raise _FaultExit(
                    self._fault(
                        FaultKind.HEARTBEAT_LOST,
                        f"no autopilot heartbeat for {tel.heartbeat_age_s:.2f} s while landing",
                        Action.STOP,
                    )
                )
            if tel.landed_state is LandedState.ON_GROUND and not disarm_sent:
                disarm_sent = True
                with contextlib.suppress(CommandRejected, LinkTimeout):
                    await self.link.disarm()
            if self.clock.monotonic_s() > deadline:
                raise LinkTimeout(
                    f"the vehicle did not land and disarm within {self.settings.landed_timeout_s:.0f} s",
                    "disarmed",
                    self.settings.landed_timeout_s,
                )
            await self.clock.sleep(0.05)

    # ------------------------------------------------------------------ summary

    def finish(self) -> FlightSummary:
        """Fill in timing figures; returns the summary (call once at the end)."""
        s = self.summary
        s.duration_s = self.t_s
        if self._cycle_s:
            s.cycle_p50_ms, s.cycle_p99_ms = _p50_p99_ms(self._cycle_s)
            s.cycle_cpu_p50_ms, s.cycle_cpu_p99_ms = _p50_p99_ms(self._cycle_cpu_s)
            s.loop_rate_hz = self._rate_estimate()
        return s

    async def close(self) -> None:
        if self._pose_task is not None:
            self._pose_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._pose_task
            self._pose_task = None


def _immediate_setter(link: VehicleLink) -> Callable[[VelocitySetpoint], None]:
    """``link.set_velocity`` that puts the setpoint on the wire at once when the backend can
    (``send_now``, pymavlink), so the setpoint follows the mocap sample without waiting for the
    stream's next tick; the plain replace-the-streamed-setpoint call otherwise."""
    try:
        params = inspect.signature(link.set_velocity).parameters
    except (TypeError, ValueError):  # pragma: no cover - builtins
        return link.set_velocity
    if "send_now" in params:
        return functools.partial(link.set_velocity, send_now=True)  # type: ignore[call-arg]
    return link.set_velocity


class _Climb:
    """Lift-off reference: stay over ``start`` and climb at ``climb_m_s`` open-ended."""

    name = "climb"
    laps = 1
    lap_duration_s = math.inf
    duration_s = math.inf

    def __init__(self, start: Vec3, yaw: float, climb_m_s: float, runner: FlightRunner | None = None) -> None:
        self.start, self.yaw, self.climb, self.runner = start, yaw, climb_m_s, runner

    def reference(self, t_s: float) -> Reference:
        # The height reference is the measured height (no vertical P term): the climb is pure
        # feed-forward, so spin-up time does not build a position error that would overshoot later.
        z = self.start[2]
        if self.runner is not None:
            with contextlib.suppress(MocapBodyMissing):
                z = self.runner.current_pose()[0][2]
        return Reference(
            t_s, (self.start[0], self.start[1], z), (0.0, 0.0, self.climb), self.yaw, 0.0, 0, False
        )


# ---------------------------------------------------------------------- one-call entry point


async def fly_plan(
    plan: Plan,
    lab: LabConfig,
    *,
    link: VehicleLink | None = None,
    mocap: MocapSource | None = None,
    clock: Clock | None = None,
    arm: bool = False,
    log_path: str | Path | None = None,
    on_status: Callable[[Status], None] | None = None,
    handle_signals: bool = False,
) -> FlightSummary:
    """Fly a whole plan: preflight, arm (or wait for the pilot), take off, hold, pattern, hold, land.

    Opens the link (``lab.link``) and mocap source (``lab.mocap``) unless given. Blocks until
    the flight ends; a fault does not raise but ends the flight (after the safety reaction)
    and shows in the summary's ``outcome`` and ``faults``.

    Args:
        log_path: flight log file; None writes ``<log_dir>/<plan>-<time>.csv``; "" disables it.
        handle_signals: make SIGINT/SIGTERM land the vehicle (CLI use).

    Raises:
        MocapBodyMissing: the body is not visible at start (names the visible ones).
        SafetyAbort: a preflight check failed (reason "preflight").
        LinkError, ConfigError: as raised by the link and the plan.
    """
    clock = clock or WallClock()
    plan = plan.with_lab_defaults(lab)
    pattern = plan.build_pattern()
    async with contextlib.AsyncExitStack() as stack:
        if link is None:
            from flightkit.link import open_link

            link = await stack.enter_async_context(open_link(lab.link, lab.vehicle.autopilot, clock))
        if mocap is None:
            mocap = await stack.enter_async_context(open_lab_mocap(lab, clock))
        assert link is not None and mocap is not None
        log = None
        if log_path != "":
            path = Path(log_path) if log_path else _default_log_path(plan)
            log = FlightLog(
                path,
                {
                    "plan": plan.name,
                    "source": plan.source_path,
                    "pattern": plan.pattern.__class__.__name__,
                    "controller": _jsonable(plan.controller),
                    "autopilot": lab.vehicle.autopilot.value,
                    "body": lab.mocap.body,
                },
            )
        runner = FlightRunner(
            link,
            mocap,
            body=lab.mocap.body,
            autopilot=lab.vehicle.autopilot,
            clock=clock,
            settings=plan.settings,
            controller=plan.controller,
            safety=plan.safety,
            log=log,
            on_status=on_status,
            name=plan.name,
        )
        sig_ctx = runner.signals_land() if handle_signals else contextlib.nullcontext()
        try:
            with sig_ctx:
                await _fly_sequence(runner, plan, pattern, arm)
        except SafetyAbort as exc:
            if exc.reason == "preflight":
                raise
            logger.warning("flight ended early: %s", exc)
        finally:
            summary = runner.finish()
            await runner.close()
            if log is not None:
                log.close(summary)
        return summary
    raise AssertionError("unreachable")  # pragma: no cover


async def _fly_sequence(runner: FlightRunner, plan: Plan, pattern: Pattern, arm: bool) -> None:
    s = plan.settings
    if plan.safety.check_plan_in_fence:
        bad = pattern_in_fence(pattern, plan.safety)
        if bad is not None:
            raise SafetyAbort(
                "preflight",
                f"preflight failed: the {pattern.name} leaves the geofence "
                f"{plan.safety.geofence.describe()} at t={bad.t_s:.1f} s; shrink it or move the fence",
            )
    await runner.preflight()
    await runner.start(arm)
    try:
        await runner.takeoff(s.takeoff_height_m)
        await runner.hold(s.hold_before_s)
        await runner.fly(pattern)
        await runner.hold(s.hold_after_s)
        await runner.land()
    except (asyncio.CancelledError, KeyboardInterrupt):
        if runner.airborne and not runner.ended:
            runner.interrupt()
            with contextlib.suppress(SafetyAbort):  # the landing reports "interrupted"; the caller cancelled
                await asyncio.shield(runner.land())
        raise


def open_lab_mocap(lab: LabConfig, clock: Clock) -> MocapSource:
    """The mocap source ``lab.mocap`` names, not yet started (enter it with ``async with``).

    Uses :func:`flightkit.mocap.open_mocap` (bus or motioncapture, per ``lab.mocap.source``)
    with the vehicle's bus namespace (``lab.vehicle.namespace``).

    Raises:
        MocapError: no mocap backend is available; pass a source (e.g. a
            :class:`~flightkit.sim.mocap.SimMocapSource`) instead.
    """
    import flightkit.mocap as mocap_pkg

    opener = getattr(mocap_pkg, "open_mocap", None)
    if opener is None:
        raise MocapError(
            f"no mocap backend for mocap.source = {lab.mocap.source.value!r} is available in this install; "
            "pass a MocapSource (mocap=...) or fly the simulator with --connect sim"
        )
    from flightkit.bus.keys import Keys

    return cast(MocapSource, opener(lab.mocap, lab.bus, Keys(lab.vehicle.namespace), clock))


def _default_log_path(plan: Plan) -> Path:
    folder = Path(plan.settings.log_dir or "flightlogs")
    return folder / f"{plan.name}-{time.strftime('%Y%m%d-%H%M%S')}.csv"


def _jsonable(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        out[f.name] = v.value if hasattr(v, "value") else v
    return out


def _p50_p99_ms(values_s: list[float]) -> tuple[float, float]:
    v = sorted(values_s)
    return v[len(v) // 2] * 1e3, v[min(len(v) - 1, int(len(v) * 0.99))] * 1e3
