"""Flight plans: TOML files describing one flight, validated into frozen dataclasses.

A plan flies a fixed sequence: preflight checks, arm (or wait for the pilot to), take off,
hold, the pattern for its laps, hold, land, disarm. Example (``examples/circle.toml``)::

    [plan]
    name = "circle"
    takeoff_height_m = 1.5
    hold_before_s = 5.0
    hold_after_s = 5.0

    [pattern]
    kind = "circle"
    centre_m = [0.0, 0.0]
    radius_m = 1.0
    period_s = 40.0
    laps = 2
    height_m = 1.5
    yaw = "inward"
    start_angle_deg = 180.0

    [controller]          # optional: gains, limits, output frame (see ControllerConfig)
    [safety]              # optional: thresholds and [safety.geofence] (see SafetyConfig)

Every error names the file and the key (``circle.toml: pattern.radius_m: ...``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flightkit.config import LabConfig
from flightkit.errors import ConfigError, PlanError
from flightkit.settings import load_section, load_toml, setting
from trajectories.base import Pattern, YawMode
from trajectories.circle import Circle
from trajectories.controller import ControllerConfig
from trajectories.hold import Hold
from trajectories.lawnmower import Lawnmower
from trajectories.rectangle import Rectangle, rectangle_corners
from trajectories.supervisor import SafetyConfig
from trajectories.waypoints import Waypoints

__all__ = [
    "CircleSpec",
    "HoldSpec",
    "LawnmowerSpec",
    "Plan",
    "PlanSettings",
    "RectangleSpec",
    "WaypointsSpec",
    "load_plan",
    "parse_plan",
]


@dataclass(frozen=True, slots=True)
class PlanSettings:
    """The ``[plan]`` table: the sequence around the pattern."""

    name: str = setting("flight", help="a name for logs and summaries")
    takeoff_height_m: float = setting(1.5, min=0.2, max=20.0, help="take-off height above the floor, metres")
    climb_m_s: float = setting(0.3, min=0.05, max=3.0, help="climb rate of the take-off")
    descent_m_s: float = setting(0.3, min=0.05, max=3.0, help="descent rate of the landing")
    floor_m: float = setting(0.0, min=-10.0, max=10.0, help="world z of the floor")
    hold_before_s: float = setting(5.0, min=0.0, max=600.0, help="hold before the pattern")
    hold_after_s: float = setting(5.0, min=0.0, max=600.0, help="hold after the pattern")
    transit_speed_m_s: float = setting(
        0.3, min=0.05, max=3.0, help="speed of the move to the pattern's start"
    )
    accel_m_s2: float = setting(0.5, min=0.05, max=10.0, help="acceleration of take-off, transit and landing")
    reference_headroom: float = setting(
        0.8, min=0.5, max=1.0,
        help="take-off, transit and landing move at most this share of the controller's speed limits "
        "(1: up to the limits)",
    )
    rate_hz: float = setting(100.0, min=5.0, max=500.0, help="control loop rate")
    arm_timeout_s: float = setting(60.0, min=1.0, max=3600.0, help="how long to wait for the pilot to arm")
    preflight_timeout_s: float = setting(5.0, min=0.1, max=120.0, help="how long to wait for mocap at start")
    landed_timeout_s: float = setting(30.0, min=1.0, max=600.0, help="how long a landing may take")
    log_dir: str = setting("", help="where flight logs go (empty: ./flightlogs)")


@dataclass(frozen=True, slots=True)
class CircleSpec:
    """``[pattern] kind = "circle"``."""

    centre_m: tuple[float, ...] = setting((0.0, 0.0), length=2, help="x, y of the centre, metres")
    radius_m: float = setting(1.0, min=0.05, max=50.0, help="radius, metres")
    height_m: float = setting(1.5, min=0.1, max=50.0, help="height, metres")
    period_s: float = setting(0.0, min=0.0, max=3600.0, help="seconds per lap (or give speed_m_s)")
    speed_m_s: float = setting(0.0, min=0.0, max=10.0, help="speed along the circle (or give period_s)")
    laps: int = setting(1, min=1, max=1000, help="number of laps")
    direction: str = setting("ccw", help="'ccw' or 'cw' seen from above")
    yaw: YawMode = setting(YawMode.INWARD, help="inward, outward, tangent or fixed")
    yaw_deg: float = setting(0.0, min=-360.0, max=360.0, help="heading for yaw = 'fixed'")
    start_angle_deg: float = setting(180.0, min=-360.0, max=360.0, help="start point angle about the centre")
    accel_m_s2: float = setting(0.5, min=0.01, max=10.0, help="speed ramp at start and end")

    @staticmethod
    def _check(obj: CircleSpec, path: str, key: str) -> None:
        if (obj.period_s > 0.0) == (obj.speed_m_s > 0.0):
            raise ConfigError(
                path,
                f"{key}.period_s",
                "give exactly one of period_s and speed_m_s",
                "set period_s (seconds per lap) or speed_m_s, not both",
                obj.period_s,
            )
        _check_direction(obj.direction, path, key)

    def build(self) -> Pattern:
        return Circle(
            centre_m=(self.centre_m[0], self.centre_m[1]),
            radius_m=self.radius_m,
            height_m=self.height_m,
            period_s=self.period_s or None,
            speed_m_s=self.speed_m_s or None,
            laps=self.laps,
            clockwise=self.direction == "cw",
            yaw_mode=self.yaw,
            fixed_yaw_rad=math.radians(self.yaw_deg),
            start_angle_rad=math.radians(self.start_angle_deg),
            accel_m_s2=self.accel_m_s2,
        )


@dataclass(frozen=True, slots=True)
class RectangleSpec:
    """``[pattern] kind = "rectangle"``: centre + size (+ rotation), or explicit corners."""

    centre_m: tuple[float, ...] = setting((0.0, 0.0), length=2, help="x, y of the centre, metres")
    size_m: tuple[float, ...] = setting((2.0, 1.0), length=2, min=0.01, help="length along x, width along y")
    rotation_deg: float = setting(0.0, min=-360.0, max=360.0, help="rotation of the rectangle about z")
    start_corner: int = setting(0, min=0, max=3, help="0: (-x,-y), 1: (+x,-y), 2: (+x,+y), 3: (-x,+y)")
    direction: str = setting("ccw", help="'ccw' or 'cw' seen from above")
    corners_m: tuple[tuple[float, ...], ...] = setting((), help="explicit [x, y] corners in flying order")
    height_m: float = setting(1.5, min=0.1, max=50.0, help="height, metres")
    speed_m_s: float = setting(0.1, min=0.01, max=10.0, help="cruise speed along the sides")
    accel_m_s2: float = setting(0.2, min=0.01, max=10.0, help="speed ramp at each side's ends")
    turn_s: float = setting(5.0, min=0.0, max=120.0, help="seconds for each turn in place at a corner")
    laps: int = setting(1, min=1, max=1000, help="number of laps")
    yaw: YawMode = setting(YawMode.INWARD, help="inward, outward, travel or fixed")
    yaw_deg: float = setting(0.0, min=-360.0, max=360.0, help="heading for yaw = 'fixed'")

    @staticmethod
    def _check(obj: RectangleSpec, path: str, key: str) -> None:
        _check_direction(obj.direction, path, key)
        if obj.corners_m and (len(obj.corners_m) < 3 or any(len(c) != 2 for c in obj.corners_m)):
            raise ConfigError(
                path,
                f"{key}.corners_m",
                "needs 3 or more [x, y] pairs",
                "write corners_m = [[x, y], [x, y], ...]",
                obj.corners_m,
            )

    def build(self) -> Pattern:
        if self.corners_m:
            corners = [(c[0], c[1]) for c in self.corners_m]
        else:
            corners = rectangle_corners(
                self.centre_m, self.size_m, math.radians(self.rotation_deg), self.start_corner
            )
            if self.direction == "cw":
                corners = [corners[0], *reversed(corners[1:])]
        return Rectangle(
            corners,
            self.height_m,
            self.speed_m_s,
            self.accel_m_s2,
            self.turn_s,
            self.laps,
            self.yaw,
            math.radians(self.yaw_deg),
        )


@dataclass(frozen=True, slots=True)
class LawnmowerSpec:
    """``[pattern] kind = "lawnmower"``: an area given by its centre (or a corner) and size."""

    centre_m: tuple[float, ...] = setting((0.0, 0.0), length=2, help="x, y of the area's centre")
    origin_m: tuple[float, ...] = setting((), help="x, y of the start corner instead of centre_m")
    size_m: tuple[float, ...] = setting((2.0, 1.0), length=2, min=0.0, help="along the lanes, across them")
    spacing_m: float = setting(0.5, min=0.01, max=50.0, help="distance between lanes")
    lane_dir_deg: float = setting(0.0, min=-360.0, max=360.0, help="direction of the lanes (0 = +x)")
    height_m: float = setting(1.5, min=0.1, max=50.0, help="height, metres")
    speed_m_s: float = setting(0.1, min=0.01, max=10.0, help="cruise speed")
    accel_m_s2: float = setting(0.2, min=0.01, max=10.0, help="speed ramp at each lane's ends")
    turn_s: float = setting(5.0, min=0.0, max=120.0, help="seconds for each turn in place")
    laps: int = setting(1, min=1, max=1000, help="number of coverage passes")
    yaw: YawMode = setting(YawMode.TRAVEL, help="travel or fixed")
    yaw_deg: float = setting(0.0, min=-360.0, max=360.0, help="heading for yaw = 'fixed'")
    return_to_start: bool = setting(True, help="fly back to the start corner at the end of each pass")

    @staticmethod
    def _check(obj: LawnmowerSpec, path: str, key: str) -> None:
        if obj.origin_m and len(obj.origin_m) != 2:
            raise ConfigError(path, f"{key}.origin_m", "expected 2 values", "give [x, y]", obj.origin_m)
        if obj.yaw not in (YawMode.TRAVEL, YawMode.FIXED):
            raise ConfigError(
                path,
                f"{key}.yaw",
                f"{obj.yaw.value!r} is not allowed here",
                "use travel or fixed",
                obj.yaw.value,
            )
        if obj.laps > 1 and not obj.return_to_start:
            raise ConfigError(
                path,
                f"{key}.laps",
                "several passes need return_to_start = true",
                "set return_to_start = true or laps = 1",
                obj.laps,
            )

    def build(self) -> Pattern:
        if self.origin_m:
            origin = (self.origin_m[0], self.origin_m[1])
        else:
            a = math.radians(self.lane_dir_deg)
            hx, hy = self.size_m[0] / 2.0, self.size_m[1] / 2.0
            origin = (
                self.centre_m[0] - math.cos(a) * hx + math.sin(a) * hy,
                self.centre_m[1] - math.sin(a) * hx - math.cos(a) * hy,
            )
        return Lawnmower(
            origin,
            self.size_m,
            self.spacing_m,
            self.height_m,
            self.speed_m_s,
            self.accel_m_s2,
            self.turn_s,
            math.radians(self.lane_dir_deg),
            self.laps,
            self.yaw,
            math.radians(self.yaw_deg),
            self.return_to_start,
        )


@dataclass(frozen=True, slots=True)
class WaypointsSpec:
    """``[pattern] kind = "waypoints"`` (or ``"line"`` with two points)."""

    points_m: tuple[tuple[float, ...], ...] = setting(help="[x, y, z] points, metres")
    speed_m_s: float = setting(0.3, min=0.01, max=10.0, help="cruise speed")
    accel_m_s2: float = setting(0.3, min=0.01, max=10.0, help="speed ramp at each point")
    yaw: YawMode = setting(YawMode.FIXED, help="travel or fixed")
    yaw_deg: float = setting(0.0, min=-360.0, max=360.0, help="heading for yaw = 'fixed'")
    turn_s: float = setting(2.0, min=0.0, max=120.0, help="seconds for each turn in place")

    @staticmethod
    def _check(obj: WaypointsSpec, path: str, key: str) -> None:
        if len(obj.points_m) < 2 or any(len(p) != 3 for p in obj.points_m):
            raise ConfigError(
                path,
                f"{key}.points_m",
                "needs 2 or more [x, y, z] points",
                "write points_m = [[x, y, z], [x, y, z], ...]",
                obj.points_m,
            )
        if obj.yaw not in (YawMode.TRAVEL, YawMode.FIXED):
            raise ConfigError(
                path,
                f"{key}.yaw",
                f"{obj.yaw.value!r} is not allowed here",
                "use travel or fixed",
                obj.yaw.value,
            )

    def build(self) -> Pattern:
        return Waypoints(
            self.points_m, self.speed_m_s, self.accel_m_s2, math.radians(self.yaw_deg), self.yaw, self.turn_s
        )


@dataclass(frozen=True, slots=True)
class HoldSpec:
    """``[pattern] kind = "hold"``: stay at a point."""

    position_m: tuple[float, ...] = setting((0.0, 0.0, 1.5), length=3, help="x, y, z, metres")
    yaw_deg: float = setting(0.0, min=-360.0, max=360.0, help="heading")
    duration_s: float = setting(10.0, min=0.01, max=3600.0, help="seconds")

    def build(self) -> Pattern:
        p = self.position_m
        return Hold((p[0], p[1], p[2]), math.radians(self.yaw_deg), self.duration_s)


PatternSpec = CircleSpec | RectangleSpec | LawnmowerSpec | WaypointsSpec | HoldSpec

PATTERN_KINDS: dict[str, type[Any]] = {
    "circle": CircleSpec,
    "rectangle": RectangleSpec,
    "lawnmower": LawnmowerSpec,
    "waypoints": WaypointsSpec,
    "line": WaypointsSpec,
    "hold": HoldSpec,
}


def _check_direction(direction: str, path: str, key: str) -> None:
    if direction not in ("ccw", "cw"):
        raise ConfigError(
            path, f"{key}.direction", f"{direction!r} is not allowed", "use 'ccw' or 'cw'", direction
        )


@dataclass(frozen=True, slots=True)
class Plan:
    """A whole flight plan.

    Attributes:
        settings: the ``[plan]`` table.
        pattern: the ``[pattern]`` table (one of the ``*Spec`` classes).
        controller: gains and limits.
        safety: supervisor thresholds and geofence.
        source_path: where it came from.
        tables: the raw ``[controller]`` / ``[safety]`` tables of a parsed plan (None when built
            in Python), so :meth:`with_lab_defaults` can layer them over the lab's.
    """

    settings: PlanSettings
    pattern: PatternSpec
    controller: ControllerConfig = dataclasses.field(default_factory=ControllerConfig)
    safety: SafetyConfig = dataclasses.field(default_factory=SafetyConfig)
    source_path: str = "<dict>"
    tables: Mapping[str, Any] | None = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def name(self) -> str:
        return self.settings.name

    def build_pattern(self) -> Pattern:
        """The pattern object (pure); raises ConfigError (naming the file and ``pattern.<key>``)
        if the values make no pattern."""
        try:
            return self.pattern.build()
        except PlanError as exc:
            key = f"pattern.{exc.key}" if exc.key else "pattern"
            raise ConfigError(self.source_path, key, exc.problem, exc.fix, exc.value) from exc

    def with_lab_defaults(self, lab: LabConfig) -> Plan:
        """This plan with the lab's own ``[control]`` and ``[safety]`` tables as defaults.

        A lab config may describe its controller gains and its room (geofence, battery limit)
        once; a plan's ``[controller]`` / ``[safety]`` keys override them key by key (the
        ``[safety.geofence]`` sub-table too). Plans built in Python (no raw tables) are kept.

        Raises:
            ConfigError: the merged tables are invalid (naming the lab file and key).
        """
        lab_ctl = lab.capability_tables.get("control", {})
        lab_safe = lab.capability_tables.get("safety", {})
        if not lab_ctl and not lab_safe:
            return self
        if self.tables is None:
            return self
        ctl = _merge(lab_ctl, self.tables.get("controller", {}))
        safe = _merge(lab_safe, self.tables.get("safety", {}))
        where = f"{lab.source_path} + {self.source_path}"
        return dataclasses.replace(
            self,
            controller=load_section(ControllerConfig, ctl, path=where, prefix="controller"),
            safety=load_section(SafetyConfig, safe, path=where, prefix="safety"),
        )

    def with_safety(self, **keys: Any) -> Plan:
        """A copy with some ``[safety]`` keys set as if the plan's file had them (so they also win
        over the lab's ``[safety]``), e.g. ``plan.with_safety(allow_hover_on_companion_loss=True)``."""
        tables = None
        if self.tables is not None:
            tables = {**self.tables, "safety": {**self.tables.get("safety", {}), **keys}}
        return dataclasses.replace(self, safety=dataclasses.replace(self.safety, **keys), tables=tables)

    def with_changes(self, **sections: Any) -> Plan:
        """A copy with some sections replaced, e.g. ``plan.with_changes(controller=cfg)``."""
        return dataclasses.replace(self, **sections)


def parse_plan(table: Mapping[str, Any], path: str = "<dict>") -> Plan:
    """Validate a plan given as a TOML-shaped mapping.

    Raises:
        ConfigError: unknown sections or keys, missing pattern, bad values (naming file and key).
    """
    known = {"plan", "pattern", "controller", "safety"}
    for key in table:
        if key not in known:
            raise ConfigError(path, key, "unknown section", f"use only: {', '.join(sorted(known))}", key)
    if "pattern" not in table:
        raise ConfigError(
            path, "pattern", "missing [pattern] table", "add [pattern] with kind = 'circle' (or other)"
        )
    pat = dict(table["pattern"])
    kind = pat.pop("kind", None)
    if pat.get("yaw") == "tangent":
        pat["yaw"] = YawMode.TRAVEL.value  # the circle's word for facing the direction of travel
    if kind not in PATTERN_KINDS:
        raise ConfigError(
            path,
            "pattern.kind",
            f"{kind!r} is not a pattern kind",
            f"use one of: {', '.join(PATTERN_KINDS)}",
            kind,
        )
    spec = load_section(PATTERN_KINDS[kind], pat, path=path, prefix="pattern")
    settings = load_section(PlanSettings, table.get("plan", {}), path=path, prefix="plan")
    controller = load_section(ControllerConfig, table.get("controller", {}), path=path, prefix="controller")
    safety = load_section(SafetyConfig, table.get("safety", {}), path=path, prefix="safety")
    raw = {k: table[k] for k in ("controller", "safety") if k in table}
    plan = Plan(settings, spec, controller, safety, path, raw)
    plan.build_pattern()  # surface pattern errors at load time
    return plan


def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` updated by ``over``; sub-tables merged one level down."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = {**out[k], **v}
        else:
            out[k] = v
    return out


def load_plan(path: str | Path) -> Plan:
    """Read and validate a plan TOML file (ConfigError naming file and key on any problem)."""
    return parse_plan(load_toml(path), str(path))
