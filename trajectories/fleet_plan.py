"""Fleet plans: one TOML file flying several vehicles, and the function that flies it.

A fleet plan is a plan (``[plan]``, ``[pattern]``, ``[controller]``, ``[safety]``: see
:mod:`trajectories.plan`) plus a ``[fleet]`` table (:class:`~trajectories.separation.FleetSafety`
and how the shared pattern is shared out) and one ``[vehicles.<name>]`` table per vehicle::

    [pattern]                      # the shared pattern
    kind = "circle"
    radius_m = 1.0
    period_s = 30.0
    height_m = 1.2

    [fleet]
    min_separation_m = 0.6
    on_vehicle_fault = "land"      # the others hold, then land ("continue": they go on)

    [vehicles.uav1]                # on the circle, 120 degrees apart
    phase_deg = 0.0
    [vehicles.uav2]
    phase_deg = 120.0
    [vehicles.uav3]
    phase_deg = 240.0

A vehicle's table takes ``phase_deg`` (a circle: start that far further around), ``offset_m``
(a formation: the shared pattern moved by [dx, dy, dz], e.g. behind a leader flying it with
``[0, 0, 0]``), or its own ``[vehicles.<name>.pattern]``. With ``[fleet] split = "strips"`` a
lawnmower's area is cut across its lanes into one strip per vehicle (in the order listed).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flightkit.clock import Clock
from flightkit.config import LabConfig
from flightkit.errors import ConfigError, PlanError, SafetyAbort
from flightkit.frames import Vec3Tuple
from flightkit.mocap.base import MocapSource
from flightkit.settings import load_section, load_toml, setting
from trajectories.base import Pattern, Reference
from trajectories.flightlog import FlightSummary
from trajectories.plan import CircleSpec, LawnmowerSpec, PatternSpec, Plan, parse_plan
from trajectories.separation import FleetSafety, plan_separation
from trajectories.status import Status

__all__ = [
    "FleetPlan",
    "FleetResult",
    "VehicleAssignment",
    "fly_fleet_plan",
    "is_fleet_plan",
    "load_fleet_plan",
    "parse_fleet_plan",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class VehicleAssignment:
    """A ``[vehicles.<name>]`` table: how this vehicle flies the shared pattern (or its own)."""

    phase_deg: float = setting(0.0, min=-360.0, max=360.0, help="circle: start this far further around")
    offset_m: tuple[float, ...] = setting((0.0, 0.0, 0.0), length=3, help="formation offset from the pattern")
    pattern: PatternSpec | None = field(default=None, metadata={"init_only_loader": True})


class _Shifted:
    """A pattern moved by a constant offset (a formation member following the leader's pattern)."""

    def __init__(self, base: Pattern, offset_m: Vec3Tuple) -> None:
        self.base, self.offset_m = base, offset_m
        self.name, self.laps = base.name, base.laps
        self.lap_duration_s, self.duration_s = base.lap_duration_s, base.duration_s

    def reference(self, t_s: float) -> Reference:
        r = self.base.reference(t_s)
        o = self.offset_m
        return dataclasses.replace(r, pos_m=(r.pos_m[0] + o[0], r.pos_m[1] + o[1], r.pos_m[2] + o[2]))


@dataclass(frozen=True, slots=True)
class FleetPlan:
    """A parsed fleet plan: the shared plan, the fleet's safety, and every vehicle's assignment."""

    plan: Plan
    fleet: FleetSafety
    vehicles: Mapping[str, VehicleAssignment]
    split: str = ""

    @property
    def name(self) -> str:
        return self.plan.name

    def build_patterns(self) -> dict[str, Pattern]:
        """Each vehicle's pattern (pure).

        Raises:
            PlanError: an assignment that does not fit the shared pattern.
        """
        spec = self.plan.pattern
        names = list(self.vehicles)
        out: dict[str, Pattern] = {}
        for i, (name, a) in enumerate(self.vehicles.items()):
            if a.pattern is not None:
                out[name] = a.pattern.build()
                continue
            own = spec
            if self.split == "strips":
                if not isinstance(spec, LawnmowerSpec):
                    raise PlanError(f"split = 'strips' needs a lawnmower pattern, not {type(spec).__name__}")
                own = _strip(spec, i, len(names))
            if a.phase_deg:
                if not isinstance(own, CircleSpec):
                    raise PlanError(f"vehicles.{name}.phase_deg needs a circle pattern; use offset_m for others")
                own = dataclasses.replace(own, start_angle_deg=own.start_angle_deg + a.phase_deg)
            pattern = own.build()
            if any(a.offset_m):
                pattern = _Shifted(pattern, (a.offset_m[0], a.offset_m[1], a.offset_m[2]))
            out[name] = pattern
        return out

    def check_separation(self) -> None:
        """Refuse references that come closer than ``min_separation_m`` (PlanError naming the pair)."""
        d, t, pair = plan_separation(self.build_patterns())
        if d < self.fleet.min_separation_m:
            raise PlanError(
                f"{self.plan.source_path}: the references of {pair[0]} and {pair[1]} come {d:.2f} m close at "
                f"t={t:.1f} s of the pattern, below [fleet] min_separation_m {self.fleet.min_separation_m:g} m; "
                "spread the vehicles apart (phase_deg, offset_m) or lower the limit"
            )


def _strip(spec: LawnmowerSpec, i: int, n: int) -> LawnmowerSpec:
    """Strip ``i`` of ``n`` of the lawnmower's area, cut across its lanes."""
    a = math.radians(spec.lane_dir_deg)
    across = spec.size_m[1] / n
    # centre of the strip: the area's centre moved across the lanes (the +90 degree direction)
    if spec.origin_m:
        hx, hy = spec.size_m[0] / 2.0, spec.size_m[1] / 2.0
        cx = spec.origin_m[0] + math.cos(a) * hx - math.sin(a) * hy
        cy = spec.origin_m[1] + math.sin(a) * hx + math.cos(a) * hy
    else:
        cx, cy = spec.centre_m[0], spec.centre_m[1]
    shift = -spec.size_m[1] / 2.0 + across * (i + 0.5)
    centre = (cx - math.sin(a) * shift, cy + math.cos(a) * shift)
    return dataclasses.replace(spec, centre_m=centre, origin_m=(), size_m=(spec.size_m[0], across))


def parse_fleet_plan(table: Mapping[str, Any], path: str = "<dict>") -> FleetPlan:
    """Validate a fleet plan given as a TOML-shaped mapping (ConfigError naming file and key)."""
    shared = {k: v for k, v in table.items() if k not in ("fleet", "vehicles")}
    plan = parse_plan(shared, path)
    fleet_table = dict(table.get("fleet", {}))
    split = fleet_table.pop("split", "")
    if split not in ("", "strips"):
        raise ConfigError(path, "fleet.split", f"unknown split {split!r}", "use 'strips' or leave it out", split)
    fleet = load_section(FleetSafety, fleet_table, path=path, prefix="fleet")
    raw = table.get("vehicles")
    if not isinstance(raw, Mapping) or len(raw) < 1:
        raise ConfigError(
            path, "vehicles", "a fleet plan names its vehicles", "add a [vehicles.uav1] table per vehicle", raw
        )
    vehicles: dict[str, VehicleAssignment] = {}
    for name, vt in raw.items():
        if not isinstance(vt, Mapping):
            raise ConfigError(path, f"vehicles.{name}", "expected a table", f"write it as [vehicles.{name}]", vt)
        vt = dict(vt)
        own = vt.pop("pattern", None)
        a = load_section(VehicleAssignment, vt, path=path, prefix=f"vehicles.{name}")
        if own is not None:
            sub = parse_plan({"pattern": own}, path)
            a = dataclasses.replace(a, pattern=sub.pattern)
        vehicles[str(name)] = a
    fp = FleetPlan(plan, fleet, vehicles, split)
    try:
        fp.build_patterns()
    except (PlanError, ValueError) as exc:
        raise ConfigError(path, "vehicles", str(exc), "fix the vehicles' assignments") from exc
    return fp


def load_fleet_plan(path: str | Path) -> FleetPlan:
    """Read and validate a fleet plan TOML file."""
    return parse_fleet_plan(load_toml(path), str(path))


def is_fleet_plan(table: Mapping[str, Any]) -> bool:
    """True when a plan table describes a fleet (it has ``[fleet]`` or ``[vehicles]``)."""
    return "fleet" in table or "vehicles" in table


@dataclass
class FleetResult:
    """How a fleet plan's flight went.

    Attributes:
        name: the plan's name. summaries: each vehicle's flight summary.
        min_separation_m / start_skew_s / faults: the fleet supervisor's figures
            (:class:`~trajectories.fleet.FleetReport`).
    """

    name: str
    summaries: dict[str, FlightSummary]
    min_separation_m: float
    start_skew_s: float
    faults: list[tuple[float, str, str]]

    @property
    def outcome(self) -> str:
        """``completed`` when every vehicle completed, else how many did."""
        done = sum(1 for s in self.summaries.values() if s.outcome == "completed")
        return "completed" if done == len(self.summaries) else f"{done} of {len(self.summaries)} vehicles completed"

    @property
    def ok(self) -> bool:
        return self.outcome == "completed" and not self.faults

    def format_table(self) -> str:
        skew = "-" if math.isnan(self.start_skew_s) else f"{self.start_skew_s * 1e3:.0f} ms"
        lines = [
            f"fleet {self.name!r}: {self.outcome}; min separation {self.min_separation_m:.2f} m; "
            f"pattern start skew {skew}"
        ]
        for t, who, msg in self.faults:
            lines.append(f"  fleet fault t={t:6.2f} s {who}: {msg}")
        for name, s in self.summaries.items():
            lines.append(f"-- {name}")
            lines.append(s.format_table())
        return "\n".join(lines)


async def fly_fleet_plan(
    fplan: FleetPlan,
    lab: LabConfig,
    *,
    clock: Clock | None = None,
    mocap: MocapSource | None = None,
    arm: bool = False,
    log_dir: str | Path | None = None,
    on_status: Callable[[str, Status], None] | None = None,
) -> FleetResult:
    """Fly a fleet plan on the lab's vehicles: take off together, hold, fly the patterns started
    together, hold, land. Blocks until every vehicle has landed (or the fleet reacted to a fault).

    Raises:
        PlanError: the references come too close, or a vehicle of the plan is not in the lab
            (before anything is armed).
    """
    from trajectories.fleet import Fleet

    fplan.check_separation()
    patterns = fplan.build_patterns()
    lab_names = [c.vehicle.namespace for c in lab.fleet()]
    missing = [n for n in patterns if n not in lab_names]
    if missing:
        raise PlanError(
            f"the plan flies {', '.join(missing)}, which the lab config does not list; "
            f"its vehicles are {', '.join(lab_names)} ([[vehicles]] in the lab config)"
        )
    only = dataclasses.replace(lab, vehicles=tuple(v for v in lab.vehicles if v.name in patterns))
    s = fplan.plan.settings
    fleet = Fleet(
        only,
        arm=arm,
        clock=clock,
        mocap=mocap,
        settings=s,
        controller=fplan.plan.controller,
        safety=fplan.plan.safety,
        fleet_safety=fplan.fleet,
        log_dir=log_dir,
        on_status=on_status,
        name=fplan.name,
    )
    try:
        async with fleet:
            await fleet.takeoff(s.takeoff_height_m)
            await fleet.hold(s.hold_before_s)
            await fleet.fly(patterns)
            await fleet.hold(s.hold_after_s)
            await fleet.land()
    except SafetyAbort as exc:
        logger.warning("fleet flight ended early: %s", exc)
    r = fleet.report
    return FleetResult(fplan.name, fleet.summaries(), r.min_separation_m, r.start_skew_s, r.faults)
