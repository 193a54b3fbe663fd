"""The control loop of one vehicle: each :meth:`ControlLoop.tick` is one cycle.

1. read the newest mocap pose of the body (age since the newest *valid* pose);
2. compute the reference at pattern time t (pattern time stands still while holding);
3. ask the supervisor (:func:`trajectories.supervisor.supervise`);
4. on CONTINUE run the controller and replace the streamed setpoint; on HOLD send zero
   velocity; anything else raises :class:`FaultExit` for the fault reactor;
5. return the cycle as a typed :class:`~trajectories.flightlog.LogRow` (and append it to the flight log).

:meth:`ControlLoop.track` repeats ticks until a phase is done. It is driven by mocap: it
wakes when a new pose arrives (so the setpoint follows the sample by microseconds), and at the
latest ``1 / rate_hz`` seconds of clock time after the previous cycle began (not after it ended:
the cycle's own time does not slow the rate), so stale mocap is still noticed.

The loop knows nothing of phases' meaning nor of the firmware: the phase sequencer
(:mod:`trajectories.runner`) gives it patterns, the fault reactor
(:mod:`trajectories.fault_reactor`) acts on its :class:`FaultExit`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from flightkit.calibration.latency import DEFAULT_STAGES, latency_stats, predict_pose, velocity_from_poses
from flightkit.clock import Clock
from flightkit.errors import LinkTimeout, MocapBodyMissing
from flightkit.frames import Transform, Vec3Tuple
from flightkit.link.base import FlightMode, VehicleLink, VelocitySetpoint
from flightkit.mocap.base import MocapPose, MocapSource
from trajectories.base import Pattern, with_acceleration
from trajectories.controller import SetpointKind, VelocityController
from trajectories.flightlog import FlightLog, FlightSummary, LogRow, PhaseStats
from trajectories.status import Status
from trajectories.supervisor import (
    ACTION_OF,
    Action,
    Decision,
    Fault,
    FaultKind,
    SafetyConfig,
    SupervisorInput,
    supervise,
)
from trajectories.takeoff import LiftOff

__all__ = ["ControlLoop", "FaultExit"]

logger = logging.getLogger(__name__)


class FaultExit(Exception):
    """The supervisor decided more than the phase tolerates; the fault reactor takes over."""

    def __init__(self, decision: Decision) -> None:
        self.decision = decision
        super().__init__(decision.action.name)


@dataclass(slots=True)
class _Phase:
    """What one :meth:`ControlLoop.track` call carries from tick to tick."""

    pattern: Pattern
    name: str
    controller: VelocityController
    stats: PhaseStats
    tolerate: Action
    floor_m: float | None
    send: bool
    laps: int
    lookahead_s: float
    last_s: float
    t_pattern_s: float = 0.0
    epoch_s: float | None = None  # clock time at which pattern time is 0 (a fleet's common start)
    started: bool = False  # the pattern clock has run (a CONTINUE cycle happened)


class ControlLoop:
    """The per-vehicle loop: pose, reference, supervision, control, send, log.

    Args:
        link: connected vehicle link. mocap: running mocap source (same clock as the link).
        body: the vehicle's mocap rigid body. clock: the clock every wait uses.
        control_mode: the mode in which the autopilot follows our setpoints.
        controller: the tracking controller. lift_controller: the one used for :class:`LiftOff`.
        safety: the supervisor's configuration. rate_hz: the least control rate.
        log: flight log (None: none). on_status: live status callback. summary: where
        phases, faults and timing figures go.
        predict_latency_s: a known mocap latency: the controller tracks the pose predicted this
            far (plus the pose's age, at most 50 ms) ahead with the measured velocity; the
            supervisor keeps the measured pose. 0 (the default) predicts nothing.
    """

    def __init__(
        self,
        link: VehicleLink,
        mocap: MocapSource,
        *,
        body: str,
        clock: Clock,
        control_mode: FlightMode,
        controller: VelocityController,
        lift_controller: VelocityController,
        safety: SafetyConfig,
        rate_hz: float,
        summary: FlightSummary,
        log: FlightLog | None = None,
        on_status: Callable[[Status], None] | None = None,
        predict_latency_s: float = 0.0,
    ) -> None:
        self.link = link
        self.mocap = mocap
        self.predict_latency_s = predict_latency_s
        self.body = body
        self.clock = clock
        self.control_mode = control_mode
        self.controller = controller
        self.lift_controller = lift_controller
        self.safety = safety
        self.rate_hz = rate_hz
        self.summary = summary
        self.log = log
        self.on_status = on_status
        self.interrupted = asyncio.Event()
        self.in_control = False  # we command the vehicle (armed, in the offboard mode)
        self.airborne = False  # it may be off the ground (from take-off until touchdown)
        self.external_faults: tuple[Fault, ...] = ()  # raised by an outer (fleet) supervisor; latched
        self.phase_started_s = math.nan  # clock time of the last phase's first cycle that ran its pattern clock
        self.cycle_s: list[float] = []  # wall time per control cycle
        self.cycle_cpu_s: list[float] = []  # this thread's CPU time per cycle (no waits, no steal)
        self.latency_s: list[float] = []  # mocap sample received -> setpoint computed from it sent
        self._chain_ns: dict[str, list[float]] = {name: [] for name in DEFAULT_STAGES}  # per sample flown on
        self._t0 = clock.monotonic_s()
        self._active: set[FaultKind] = set()
        self._last_phase = ""
        self._last_status_s = -math.inf
        self._last_valid: MocapPose | None = None
        self._yaw_cache: tuple[int, float] = (-1, 0.0)
        self._prev_for_speed: tuple[float, Vec3Tuple, Transform] | None = None
        self._speed_m_s = math.nan
        self._motion: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None = None  # (v world, w body)
        self._new_pose = asyncio.Event()
        self._pose_task: asyncio.Task[None] | None = None
        self._last_err = math.nan

    # ------------------------------------------------------------------ mocap

    @property
    def t_s(self) -> float:
        """Flight time, seconds since the loop was created."""
        return self.clock.monotonic_s() - self._t0

    def start_pose_watch(self) -> None:
        """Wake the loop on every new pose of the body (idempotent; needs a running event loop)."""
        if self._pose_task is None:
            self._pose_task = asyncio.get_running_loop().create_task(self._watch_poses(), name="runner-mocap-watch")

    async def _watch_poses(self) -> None:
        try:
            async for _ in self.mocap.poses(self.body):
                self._new_pose.set()
        except asyncio.CancelledError:
            raise
        except Exception:  # the control loop notices staleness on its own
            logger.exception("mocap pose stream ended")

    def pose(self, now_s: float) -> tuple[MocapPose | None, float]:
        """Newest valid pose and its age at ``now_s`` (inf when none)."""
        p = self.mocap.latest(self.body)
        if p is not None and p.valid:
            if self._last_valid is None or p.stamp_ns != self._last_valid.stamp_ns:
                self._update_speed(p)
            self._last_valid = p
        lv = self._last_valid
        if lv is None:
            return None, math.inf
        return lv, max(0.0, now_s - lv.received_s)

    def _predicted(self, pose: MocapPose | None, age_s: float) -> tuple[Vec3Tuple, float] | None:
        """The pose moved ``predict_latency_s`` (plus its age, at most 50 ms) ahead at the measured
        linear and angular velocity: (position, yaw); None when not predicting."""
        if pose is None or self.predict_latency_s <= 0.0 or self._motion is None or not math.isfinite(age_s):
            return None
        T = predict_pose(pose.T_world_body, *self._motion, self.predict_latency_s + min(age_s, 0.05))  # noqa: N806
        t = T.translation
        return (float(t[0]), float(t[1]), float(t[2])), T.yaw_rad

    def _stages(self, p: MocapPose) -> tuple[float, float, float]:
        """Record the pose's stamps along the chain (setpoint: now) and return its stage latencies
        (s, :data:`~trajectories.flightlog.LATENCY_STAGES`; NaN where the source does not say).
        A source in this process has no bus: its hand-over counts as the bus stamp."""
        nan = math.nan
        bus = float(p.bus_ns or p.received_ns or nan)
        runner = float(p.received_ns or nan)
        stamps = (float(p.stamp_ns), bus, runner, float(self.clock.time_ns()))
        for name, value in zip(DEFAULT_STAGES, stamps, strict=True):
            self._chain_ns[name].append(value)
        return (bus - stamps[0]) * 1e-9, (runner - bus) * 1e-9, (stamps[3] - runner) * 1e-9

    def _update_speed(self, p: MocapPose) -> None:
        t = p.stamp_ns * 1e-9
        pos = _position(p)
        prev = self._prev_for_speed
        if prev is None or t - prev[0] >= 0.05:  # 20 Hz finite difference: robust to mocap jitter
            if prev is not None and t > prev[0]:
                self._speed_m_s = math.dist(pos, prev[1]) / (t - prev[0])
                if self.predict_latency_s > 0.0:
                    self._motion = velocity_from_poses(prev[2], p.T_world_body, t - prev[0])
            self._prev_for_speed = (t, pos, p.T_world_body)

    def _yaw(self, p: MocapPose) -> float:
        if self._yaw_cache[0] != p.stamp_ns:
            self._yaw_cache = (p.stamp_ns, p.T_world_body.yaw_rad)
        return self._yaw_cache[1]

    def current_pose(self) -> tuple[Vec3Tuple, float]:
        """Newest valid mocap position (world ENU) and yaw; MocapBodyMissing when there is none."""
        p, _ = self.pose(self.clock.monotonic_s())
        if p is None:
            raise MocapBodyMissing(self.body, tuple(self.mocap.bodies()))
        return _position(p), self._yaw(p)

    def current_position(self) -> Vec3Tuple | None:
        """Newest valid mocap position (world ENU), None when there is none."""
        p, _ = self.pose(self.clock.monotonic_s())
        return None if p is None else _position(p)

    async def wait_tick(self, timeout_s: float) -> None:
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

    # ------------------------------------------------------------------ faults

    def record(self, decision: Decision) -> None:
        """Add the decision's new faults to the summary and the log (each once while it lasts)."""
        kinds = {f.kind for f in decision.faults}
        for f in decision.faults:
            if f.kind not in self._active:
                self.summary.faults.append(f)
                if self.log is not None:
                    self.log.fault(f)
                logger.warning("fault at t=%.2f s: %s: %s", f.time_s, f.kind.value, f.message)
        self._active = kinds

    def raise_fault(self, kind: FaultKind, message: str) -> None:
        """Latch a fault detected outside this vehicle (the fleet supervisor's); from the event
        loop. The next tick reacts to it like to its own supervisor's faults."""
        if all(f.kind is not kind for f in self.external_faults):
            self.external_faults += (Fault(self.t_s, kind, message, ACTION_OF[kind]),)

    def fault(self, kind: FaultKind, message: str, action: Action) -> Decision:
        """A decision for a fault the loop's owner detected (not the supervisor)."""
        return Decision(action, (Fault(self.t_s, kind, message, action),))

    # ------------------------------------------------------------------ the loop

    def _begin(
        self,
        pattern: Pattern,
        phase: str,
        tolerate: Action,
        floor_m: float | None,
        send: bool,
        epoch_s: float | None = None,
    ) -> _Phase:
        ctl = self.lift_controller if isinstance(pattern, LiftOff) else self.controller
        ctl.reset()
        return _Phase(
            pattern=pattern,
            name=phase,
            controller=ctl,
            stats=self._stats_for(phase),
            tolerate=tolerate,
            floor_m=floor_m,
            send=send,
            laps=pattern.laps if pattern.laps > 1 or phase == "pattern" else 0,
            lookahead_s=self.safety.fence_lookahead_s if self.safety.geofence.enabled else 0.0,
            last_s=self.clock.monotonic_s(),
            epoch_s=epoch_s,
        )

    def _bounded_position(self, sp: VelocitySetpoint, floor_m: float | None) -> VelocitySetpoint:
        """``sp`` with its position target (if any) inside the geofence and not below ``floor_m``
        (a landing reference that reaches below the floor keeps pressing down through the
        velocity alone)."""
        if sp.pos_m is None:
            return sp
        fence = self.safety.geofence
        lo = list(fence.min_m) if fence.enabled else [-math.inf] * 3
        hi = list(fence.max_m) if fence.enabled else [math.inf] * 3
        if floor_m is not None:
            lo[2] = max(lo[2], floor_m)
        p = sp.pos_m
        bounded = (min(max(p[0], lo[0]), hi[0]), min(max(p[1], lo[1]), hi[1]), min(max(p[2], lo[2]), hi[2]))
        return sp if bounded == p else dataclasses.replace(sp, pos_m=bounded)

    def tick(self, ph: _Phase) -> LogRow:
        """One cycle of phase ``ph``: pose, reference, supervision, control, send; returns the row.

        Raises:
            FaultExit: the supervisor's action is beyond what the phase tolerates.
        """
        now = self.clock.monotonic_s()
        dt = now - ph.last_s
        ph.last_s = now
        c0 = time.perf_counter()
        c0_cpu = time.thread_time()
        pose, age = self.pose(now)
        pos: Vec3Tuple | None = None
        yaw = math.nan
        if pose is not None:
            pos = _position(pose)
            yaw = self._yaw(pose)
        pattern = ph.pattern
        ref = pattern.reference(ph.t_pattern_s)
        ahead = pattern.reference(ph.t_pattern_s + ph.lookahead_s) if ph.lookahead_s > 0.0 else ref
        decision = supervise(
            self.safety,
            SupervisorInput(
                now - self._t0,
                age,
                self.link.telemetry,
                self.control_mode if self.in_control else None,
                pos,
                ahead.pos_m,
                self._speed_m_s,
                self.interrupted.is_set(),
                self.external_faults,
            ),
        )
        if decision.faults or self._active:
            self.record(decision)
        action = decision.action
        if action > Action.HOLD and action <= ph.tolerate:
            action = Action.HOLD if any(f.action is Action.HOLD for f in decision.faults) else Action.CONTINUE
        err = math.nan
        ctl_pos, ctl_yaw = self._predicted(pose, age) or (pos, yaw)
        if action is Action.CONTINUE and ctl_pos is not None:
            if not ph.started:
                ph.started = True
                self.phase_started_s = now
                if ph.epoch_s is not None:  # on the common clock, however late this first cycle is
                    ph.t_pattern_s = max(0.0, now - ph.epoch_s)
                    dt = 0.0
            ph.t_pattern_s += dt
            ref = pattern.reference(ph.t_pattern_s)
            if ph.controller.config.setpoint is SetpointKind.PVA:
                ref = with_acceleration(pattern, ref)
            out = ph.controller.step(ref, ctl_pos, ctl_yaw, dt)
            sp = self._bounded_position(out.setpoint, ph.floor_m)
            err = out.error_norm_m
            if ph.floor_m is not None and ref.pos_m[2] < ph.floor_m:
                err = math.dist((ref.pos_m[0], ref.pos_m[1], ph.floor_m), ctl_pos)
        elif action is Action.HOLD or (action is Action.CONTINUE and pos is None):
            sp = self.controller.hold()
            if pos is not None:
                rz = ref.pos_m[2] if ph.floor_m is None else max(ref.pos_m[2], ph.floor_m)
                err = math.dist((ref.pos_m[0], ref.pos_m[1], rz), pos)
        else:
            raise FaultExit(decision)
        if ph.send:
            self.link.set_velocity(sp, send_now=True)
        cycle_cpu = time.thread_time() - c0_cpu  # (inside the wall window, so never larger)
        cycle = time.perf_counter() - c0
        self.cycle_cpu_s.append(cycle_cpu)
        self.cycle_s.append(cycle)
        stages = (math.nan, math.nan, math.nan)
        if ph.send and pose is not None and math.isfinite(age):
            self.latency_s.append(age + cycle)
            stages = self._stages(pose)
        if not math.isnan(err) and ph.send:
            ph.stats.add(err)
            self._last_err = err
        row = LogRow(
            now - self._t0,
            self.clock.time_ns(),
            ph.name,
            ref.lap,
            action,
            ref,
            pos,
            yaw,
            age if math.isfinite(age) else -1.0,
            sp,
            err,
            cycle,
            cycle_cpu,
            stages,
        )
        if self.log is not None:
            self.log.row(row.values())
        if now - self._last_status_s >= 0.2:
            self._last_status_s = now
            self.status(ph.name, ref.lap + 1 if ph.laps else 0, ph.laps, pos, action.name)
        if ph.stats.samples > 1:
            ph.stats.duration_s += dt
        return row

    async def track(
        self,
        pattern: Pattern,
        phase: str,
        *,
        tolerate: Action = Action.CONTINUE,
        until: Callable[[float, Vec3Tuple], bool] | None = None,
        end_when: Callable[[float, Vec3Tuple], bool] | None = None,
        floor_m: float | None = None,
        timeout_s: float = math.inf,
        send: bool = True,
        epoch_s: float | None = None,
    ) -> None:
        """Tick ``pattern`` until it is done (and ``until(t, pos)`` holds, if given), or as soon
        as ``end_when(t, pos)`` holds.

        Faults whose action is at most ``tolerate`` are recorded but do not end the phase; HOLD
        faults pause the pattern. With ``send=False`` nothing is sent (the autopilot flies on its
        own; the loop only supervises and logs). With ``floor_m`` the tracking error is measured
        against the reference clamped to the floor (a landing reference reaches below it). With
        ``epoch_s`` pattern time runs from that clock time (vehicles sharing it fly one timeline).

        Raises:
            FaultExit: a fault beyond ``tolerate``. LinkTimeout: not finished within ``timeout_s``.
        """
        self.start_pose_watch()
        ph = self._begin(pattern, phase, tolerate, floor_m, send, epoch_s)
        period_s = 1.0 / self.rate_hz
        start = ph.last_s
        while True:
            row = self.tick(ph)
            now = ph.last_s
            pos = row.pos_m
            finished = row.ref.done or (until is not None and math.isinf(pattern.duration_s))
            if (finished and (until is None or (pos is not None and until(now - start, pos)))) or (
                end_when is not None and pos is not None and end_when(now - start, pos)
            ):
                if phase == "pattern":
                    self.summary.laps_completed += pattern.laps
                return
            if now - start > timeout_s:
                raise LinkTimeout(f"{phase} did not finish within {timeout_s:.0f} s", phase, timeout_s)
            # the next cycle is due one period after this one began, whatever the cycle took; after
            # a stall it runs at once and the period counts from there (no burst of catch-up cycles)
            await self.wait_tick(now + period_s - self.clock.monotonic_s())

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

    # ------------------------------------------------------------------ status and figures

    def status(self, phase: str, lap: int, laps: int, pos: Vec3Tuple | None, action: str, message: str = "") -> None:
        """Tell ``on_status`` where the flight is (no-op without a callback)."""
        if self.on_status is None:
            return
        rate = self.rate_estimate() if len(self.cycle_s) > 10 else math.nan
        self.on_status(Status(self.t_s, phase, lap, laps, pos, self._last_err, rate, action, message))

    def rate_estimate(self) -> float:
        """Control cycles per second of controlled time so far: the time inside the phases, not
        the waits between them (connecting, arming, the autopilot's own lift-off)."""
        phases = self.summary.phases
        controlled_s = sum(p.duration_s for p in phases)
        if controlled_s <= 0:
            return math.nan
        # a phase's duration spans its cycles' intervals: one interval fewer than its cycles
        return max(0, len(self.cycle_s) - len(phases)) / controlled_s

    def fill_timing(self, summary: FlightSummary) -> None:
        """Cycle-time percentiles and the loop rate into ``summary``."""
        summary.duration_s = self.t_s
        if self.cycle_s:
            summary.cycle_p50_ms, summary.cycle_p99_ms = _p50_p99_ms(self.cycle_s)
            summary.cycle_cpu_p50_ms, summary.cycle_cpu_p99_ms = _p50_p99_ms(self.cycle_cpu_s)
            summary.loop_rate_hz = self.rate_estimate()
        if self.latency_s:
            summary.latency_p50_ms, summary.latency_p99_ms = _p50_p99_ms(self.latency_s)
        if self._chain_ns["capture"]:
            chain = latency_stats(self._chain_ns)
            summary.stage_latency_ms = {st.name: (st.p50_ms, st.p99_ms) for st in chain.stages if st.count}

    async def close(self) -> None:
        """Stop watching the mocap stream; idempotent."""
        if self._pose_task is not None:
            self._pose_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._pose_task
            self._pose_task = None


def _position(p: MocapPose) -> Vec3Tuple:
    t = p.T_world_body.translation
    return (float(t[0]), float(t[1]), float(t[2]))


def _p50_p99_ms(values_s: list[float]) -> tuple[float, float]:
    v = sorted(values_s)
    return v[len(v) // 2] * 1e3, v[min(len(v) - 1, int(len(v) * 0.99))] * 1e3
