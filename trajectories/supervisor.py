"""The safety supervisor: a pure function from what we know this cycle to what to do.

Checked every control cycle (see ``docs/safety.md``):

==========================  =====================================  ====================
fault                       condition                              action
==========================  =====================================  ====================
``heartbeat_lost``          HEARTBEAT 1 s overdue (2 s at 1 Hz)    STOP (stop, report)
``pilot_takeover``          mode left OFFBOARD / GUIDED            RELEASE (end script)
``disarmed``                vehicle disarmed while we fly it       RELEASE
``mocap_lost``              no valid mocap pose for 1 s            LAND_AUTOPILOT
``battery_low``             battery below the threshold            LAND
``interrupted``             Ctrl-C or SIGTERM                      LAND
``geofence_position``       measured position outside the box      ABORT (hold, land)
``geofence_reference``      reference outside the box              ABORT (hold, land)
``overspeed``               measured speed above the limit         ABORT (hold, land)
``separation``              (fleet) two vehicles too close, now    ABORT (hold, land)
                            or predicted a look-ahead ahead
``fleet``                   (fleet) another vehicle's fault, with  ABORT (hold, land)
                            ``on_vehicle_fault = "land"``
``mocap_stale``             no valid mocap pose for 0.2 s          HOLD (zero velocity)
==========================  =====================================  ====================

When several faults are active the most severe action wins (the order of :class:`Action`),
and every active fault is reported. The supervisor itself keeps no state: the runner latches
actions (once landing, it keeps landing) and records each fault once, when it first appears.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

from flightkit.errors import ConfigError
from flightkit.frames import Vec3Tuple
from flightkit.link.base import FlightMode, Telemetry
from flightkit.settings import setting

__all__ = [
    "ACTION_OF",
    "Action",
    "Decision",
    "Fault",
    "FaultKind",
    "Geofence",
    "SafetyConfig",
    "SupervisorInput",
    "preflight_problems",
    "supervise",
]


class Action(enum.IntEnum):
    """What the runner must do, in increasing severity."""

    CONTINUE = 0
    HOLD = 1  # zero velocity, keep yaw, until the fault clears
    ABORT = 2  # leave the pattern: hold for SafetyConfig.abort_hold_s, then land
    LAND = 3  # controlled descent on mocap, then disarm
    LAND_AUTOPILOT = 4  # cannot control (no mocap): hand over to the autopilot's LAND mode
    RELEASE = 5  # the pilot has the vehicle: stop sending setpoints, end the script
    STOP = 6  # the link is gone: stop and report


class FaultKind(enum.Enum):
    """Short machine-readable names of faults (also ``SafetyAbort.reason``)."""

    MOCAP_STALE = "mocap_stale"
    MOCAP_LOST = "mocap_lost"
    HEARTBEAT_LOST = "heartbeat_lost"
    PILOT_TAKEOVER = "pilot_takeover"
    DISARMED = "disarmed"
    GEOFENCE_POSITION = "geofence_position"
    GEOFENCE_REFERENCE = "geofence_reference"
    OVERSPEED = "overspeed"
    BATTERY_LOW = "battery_low"
    INTERRUPTED = "interrupted"
    SEPARATION = "separation"
    FLEET = "fleet"


ACTION_OF: dict[FaultKind, Action] = {
    FaultKind.MOCAP_STALE: Action.HOLD,
    FaultKind.GEOFENCE_POSITION: Action.ABORT,
    FaultKind.GEOFENCE_REFERENCE: Action.ABORT,
    FaultKind.OVERSPEED: Action.ABORT,
    FaultKind.SEPARATION: Action.ABORT,
    FaultKind.FLEET: Action.ABORT,
    FaultKind.BATTERY_LOW: Action.LAND,
    FaultKind.INTERRUPTED: Action.LAND,
    FaultKind.MOCAP_LOST: Action.LAND_AUTOPILOT,
    FaultKind.PILOT_TAKEOVER: Action.RELEASE,
    FaultKind.DISARMED: Action.RELEASE,
    FaultKind.HEARTBEAT_LOST: Action.STOP,
}


@dataclass(frozen=True, slots=True)
class Fault:
    """One fault: when, what, why, and the action it asked for.

    Attributes:
        time_s: flight time (seconds since the flight started) when it was detected.
        kind: which fault.
        message: one sentence with the values involved.
        action: the action this fault asks for.
    """

    time_s: float
    kind: FaultKind
    message: str
    action: Action

    def to_dict(self) -> dict[str, object]:
        return {
            "time_s": round(self.time_s, 3),
            "kind": self.kind.value,
            "message": self.message,
            "action": self.action.name,
        }


@dataclass(frozen=True, slots=True)
class Geofence:
    """An axis-aligned box in the world frame (ENU, metres)."""

    min_m: tuple[float, ...] = setting((-3.0, -3.0, -0.5), length=3, help="x, y, z lower corner, metres")
    max_m: tuple[float, ...] = setting((3.0, 3.0, 3.0), length=3, help="x, y, z upper corner, metres")
    enabled: bool = setting(True, help="check the box")

    @staticmethod
    def _check(obj: Geofence, path: str, key: str) -> None:
        for i, axis in enumerate("xyz"):
            if obj.min_m[i] >= obj.max_m[i]:
                raise ConfigError(
                    path,
                    f"{key}.min_m" if key else "min_m",
                    f"{axis} min {obj.min_m[i]} is not below max {obj.max_m[i]}",
                    "give min_m below max_m on every axis",
                    obj.min_m,
                )

    def contains(self, p: Sequence[float], margin_m: float = 0.0) -> bool:
        """True when ``p`` lies inside the box shrunk by ``margin_m`` on every side."""
        if not self.enabled:
            return True
        return all(self.min_m[i] + margin_m <= p[i] <= self.max_m[i] - margin_m for i in range(3))

    def describe(self) -> str:
        lo = ", ".join(f"{x:g}" for x in self.min_m)
        hi = ", ".join(f"{x:g}" for x in self.max_m)
        return f"[{lo}] .. [{hi}] m"


@dataclass(frozen=True, slots=True)
class SafetyConfig:
    """Supervisor thresholds; a ``[safety]`` table in a plan."""

    mocap_hold_after_s: float = setting(0.2, min=0.005, max=10.0, help="mocap age that triggers a hold")
    mocap_land_after_s: float = setting(1.0, min=0.01, max=30.0, help="mocap age that triggers a landing")
    heartbeat_timeout_s: float = setting(
        1.0, min=0.1, max=30.0, help="heartbeats missing this long stop the flight"
    )
    heartbeat_period_s: float = setting(
        1.0, min=0.0, max=10.0, help="the autopilot's heartbeat interval (1 Hz)"
    )
    battery_min_pct: float = setting(20.0, min=0.0, max=100.0, help="land below this charge (0 = off)")
    battery_min_v: float = setting(0.0, min=0.0, max=100.0, help="land below this voltage (0 = off)")
    max_speed_m_s: float = setting(2.0, min=0.1, max=50.0, help="measured speed that aborts the flight")
    abort_hold_s: float = setting(2.0, min=0.0, max=60.0, help="hold this long after an abort, then land")
    geofence: Geofence = setting(default_factory=Geofence, help="the box the vehicle must stay in")
    fence_lookahead_s: float = setting(
        0.5,
        min=0.0,
        max=10.0,
        help="check the reference this far ahead, so a breach stops the vehicle inside",
    )
    check_plan_in_fence: bool = setting(True, help="refuse plans whose references leave the geofence")
    preflight_mocap_window_s: float = setting(
        1.0, min=0.1, max=30.0, help="how long the mocap stream is watched before arming"
    )
    preflight_mocap_min_rate_hz: float = setting(
        20.0, min=0.0, max=2000.0, help="refuse to arm below this mocap rate (0 = off)"
    )
    preflight_mocap_max_age_s: float = setting(
        0.5, min=0.0, max=10.0, help="refuse to arm when the newest pose is older (0 = off)"
    )
    preflight_mocap_max_jitter_ms: float = setting(
        200.0, min=0.0, max=10_000.0, help="refuse to arm when the p99 interval jitter is larger (0 = off)"
    )
    allow_hover_on_companion_loss: bool = setting(
        False,
        help="arm even though the autopilot's settings make it hover armed until the battery runs out "
        "if flightkit stops (docs/safety.md)",
    )

    @staticmethod
    def _check(obj: SafetyConfig, path: str, key: str) -> None:
        if obj.mocap_land_after_s <= obj.mocap_hold_after_s:
            raise ConfigError(
                path,
                f"{key}.mocap_land_after_s" if key else "mocap_land_after_s",
                f"{obj.mocap_land_after_s} s is not longer than "
                f"mocap_hold_after_s = {obj.mocap_hold_after_s} s",
                "land only after holding: make mocap_land_after_s the larger",
                obj.mocap_land_after_s,
            )


@dataclass(frozen=True, slots=True)
class SupervisorInput:
    """Everything the supervisor looks at in one cycle.

    Attributes:
        now_s: flight time, seconds (for fault stamps).
        mocap_age_s: seconds since the newest *valid* mocap pose of our body (inf: none yet).
        telemetry: the link's latest snapshot.
        control_mode: the mode we expect while we fly the vehicle (OFFBOARD or GUIDED), or None
            before we have control (takeover and disarm are not checked then).
        pos_m: measured position (world ENU), None when unknown.
        ref_pos_m: reference position (world ENU), None when not flying a reference; the runner
            gives the reference ``fence_lookahead_s`` ahead, so a breach is seen before it is flown.
        speed_m_s: measured speed (from mocap), NaN when unknown.
        interrupted: Ctrl-C / SIGTERM received.
        external: faults raised outside this vehicle (the fleet supervisor's), passed on as active.
    """

    now_s: float
    mocap_age_s: float
    telemetry: Telemetry
    control_mode: FlightMode | None = None
    pos_m: Vec3Tuple | None = None
    ref_pos_m: Vec3Tuple | None = None
    speed_m_s: float = math.nan
    interrupted: bool = False
    external: tuple[Fault, ...] = ()


@dataclass(frozen=True, slots=True)
class Decision:
    """The supervisor's verdict: the action to take and every fault active now."""

    action: Action
    faults: tuple[Fault, ...] = ()

    @property
    def ok(self) -> bool:
        return self.action is Action.CONTINUE


_OK = Decision(Action.CONTINUE)


def _fmt(p: Sequence[float]) -> str:
    return "(" + ", ".join(f"{x:.2f}" for x in p) + ")"


def supervise(cfg: SafetyConfig, inp: SupervisorInput) -> Decision:
    """Check one cycle; pure and allocation-light (about 3 us when all is well)."""
    faults: list[Fault] = []
    t = inp.now_s
    tel = inp.telemetry

    def add(kind: FaultKind, msg: str) -> None:
        faults.append(Fault(t, kind, msg, ACTION_OF[kind]))

    if tel.heartbeat_age_s > cfg.heartbeat_period_s + cfg.heartbeat_timeout_s:
        add(
            FaultKind.HEARTBEAT_LOST,
            f"no autopilot heartbeat for {tel.heartbeat_age_s:.2f} s "
            f"(expected every {cfg.heartbeat_period_s:g} s, lost after {cfg.heartbeat_timeout_s:g} s more); "
            "stopped, the autopilot's own failsafe is in charge",
        )
    elif inp.control_mode is not None:
        if not tel.armed:
            add(FaultKind.DISARMED, "the vehicle was disarmed during the flight; script ended")
        elif tel.mode is not inp.control_mode:
            add(
                FaultKind.PILOT_TAKEOVER,
                f"mode changed from {inp.control_mode.value} to {tel.mode.value}; "
                "the pilot has the vehicle, script ended without fighting the pilot",
            )
    if inp.mocap_age_s > cfg.mocap_land_after_s:
        add(
            FaultKind.MOCAP_LOST,
            f"no valid mocap pose for {inp.mocap_age_s:.2f} s (limit {cfg.mocap_land_after_s:g} s); "
            "landing with the autopilot",
        )
    elif inp.mocap_age_s > cfg.mocap_hold_after_s:
        add(
            FaultKind.MOCAP_STALE,
            f"mocap pose is {inp.mocap_age_s:.2f} s old (limit {cfg.mocap_hold_after_s:g} s); holding",
        )
    pct = tel.battery.remaining_pct
    volts = tel.battery.voltage_v
    if cfg.battery_min_pct > 0.0 and not math.isnan(pct) and pct < cfg.battery_min_pct:
        add(FaultKind.BATTERY_LOW, f"battery at {pct:.0f} % (limit {cfg.battery_min_pct:g} %); landing")
    elif cfg.battery_min_v > 0.0 and not math.isnan(volts) and volts < cfg.battery_min_v:
        add(FaultKind.BATTERY_LOW, f"battery at {volts:.2f} V (limit {cfg.battery_min_v:g} V); landing")
    if inp.interrupted:
        add(FaultKind.INTERRUPTED, "interrupted (Ctrl-C or SIGTERM); landing")
    fence = cfg.geofence
    if inp.pos_m is not None and not fence.contains(inp.pos_m):
        add(
            FaultKind.GEOFENCE_POSITION,
            f"position {_fmt(inp.pos_m)} is outside the geofence {fence.describe()}; holding, then landing",
        )
    if inp.ref_pos_m is not None and not fence.contains(inp.ref_pos_m):
        add(
            FaultKind.GEOFENCE_REFERENCE,
            f"reference {_fmt(inp.ref_pos_m)} is outside the geofence {fence.describe()}; "
            "holding, then landing",
        )
    if not math.isnan(inp.speed_m_s) and inp.speed_m_s > cfg.max_speed_m_s:
        add(
            FaultKind.OVERSPEED,
            f"measured speed {inp.speed_m_s:.2f} m/s is above {cfg.max_speed_m_s:g} m/s; "
            "holding, then landing",
        )
    faults.extend(inp.external)
    if not faults:
        return _OK
    return Decision(max(f.action for f in faults), tuple(faults))


def preflight_problems(
    cfg: SafetyConfig,
    body: str,
    visible_bodies: Sequence[str],
    body_valid: bool,
    telemetry: Telemetry,
    pos_m: Vec3Tuple | None,
) -> list[str]:
    """Reasons not to arm, each one sentence; an empty list means go.

    Checks: the mocap body is visible and tracked, the heartbeat is fresh, the battery is above
    the threshold, and the vehicle stands inside the geofence.
    """
    problems: list[str] = []
    if body not in visible_bodies:
        seen = ", ".join(sorted(visible_bodies)) or "none"
        problems.append(f"mocap body {body!r} is not visible (visible bodies: {seen}); check mocap.body")
    elif not body_valid:
        problems.append(f"mocap body {body!r} is visible but not tracked; check its markers")
    if telemetry.heartbeat_age_s > cfg.heartbeat_period_s + cfg.heartbeat_timeout_s:
        problems.append(f"autopilot heartbeat is {telemetry.heartbeat_age_s:.2f} s old; check the link")
    pct = telemetry.battery.remaining_pct
    if cfg.battery_min_pct > 0.0 and not math.isnan(pct) and pct < cfg.battery_min_pct:
        problems.append(f"battery at {pct:.0f} % is below {cfg.battery_min_pct:g} %; charge or swap it")
    volts = telemetry.battery.voltage_v
    if cfg.battery_min_v > 0.0 and not math.isnan(volts) and volts < cfg.battery_min_v:
        problems.append(f"battery at {volts:.2f} V is below {cfg.battery_min_v:g} V; charge or swap it")
    if pos_m is not None and not cfg.geofence.contains(pos_m):
        problems.append(f"vehicle at {_fmt(pos_m)} is outside the geofence {cfg.geofence.describe()}")
    return problems
