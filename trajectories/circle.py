"""Circle: constant-speed laps around a centre at a fixed height, speed ramped in and out."""

from __future__ import annotations

import math
from dataclasses import dataclass

from flightkit.errors import PlanError
from flightkit.frames import Vec3Tuple
from trajectories.base import Reference, YawMode, trapezoid, trapezoid_duration_s, unwrap_next

__all__ = ["Circle"]


@dataclass(frozen=True, slots=True)
class Circle:
    """Laps of a horizontal circle.

    Give exactly one of ``period_s`` (seconds per lap) and ``speed_m_s``. The speed ramps up
    over the start of the first lap and down over the end of the last one within
    ``accel_m_s2`` (``inf`` = jump to full speed), so laps close exactly at rest.

    Attributes:
        centre_m: (x, y) of the centre, world ENU, metres.
        radius_m: radius, metres.
        height_m: z of the circle, metres.
        period_s: seconds per lap at cruise speed (or None when ``speed_m_s`` is given).
        speed_m_s: cruise speed along the circle (or None when ``period_s`` is given).
        laps: number of laps.
        clockwise: direction seen from above (False = counter-clockwise).
        yaw_mode: INWARD (look at the centre), OUTWARD, TRAVEL (tangent) or FIXED.
        fixed_yaw_rad: heading for FIXED.
        start_angle_rad: angle of the start point around the centre (pi: start at centre - (r, 0)).
        accel_m_s2: tangential acceleration limit of the ramps.
    """

    centre_m: tuple[float, float] = (0.0, 0.0)
    radius_m: float = 1.0
    height_m: float = 1.5
    period_s: float | None = None
    speed_m_s: float | None = None
    laps: int = 1
    clockwise: bool = False
    yaw_mode: YawMode = YawMode.INWARD
    fixed_yaw_rad: float = 0.0
    start_angle_rad: float = math.pi
    accel_m_s2: float = 0.5

    def __post_init__(self) -> None:
        if not self.radius_m > 0.0:
            raise PlanError(
                f"radius must be positive, got {self.radius_m} m",
                "give a radius > 0",
                pattern="circle",
                key="radius_m",
                value=self.radius_m,
            )
        if (self.period_s is None) == (self.speed_m_s is None):
            raise PlanError(
                f"period_s = {self.period_s} and speed_m_s = {self.speed_m_s}",
                "give the circle either period_s or speed_m_s, not both or neither",
                pattern="circle",
                key="period_s",
            )
        if self.period_s is not None and not self.period_s > 0.0:
            raise PlanError(
                f"period must be positive, got {self.period_s} s",
                "give a period > 0",
                pattern="circle",
                key="period_s",
                value=self.period_s,
            )
        if self.speed_m_s is not None and not self.speed_m_s > 0.0:
            raise PlanError(
                f"speed must be positive, got {self.speed_m_s} m/s",
                "give a speed > 0",
                pattern="circle",
                key="speed_m_s",
                value=self.speed_m_s,
            )
        if self.laps < 1:
            raise PlanError(
                f"laps must be at least 1, got {self.laps}",
                "give laps >= 1",
                pattern="circle",
                key="laps",
                value=self.laps,
            )
        if not self.accel_m_s2 > 0.0:
            raise PlanError(
                f"must be positive, got {self.accel_m_s2} m/s^2",
                "give an acceleration > 0",
                pattern="circle",
                key="accel_m_s2",
                value=self.accel_m_s2,
            )

    @property
    def name(self) -> str:
        return "circle"

    @property
    def cruise_speed_m_s(self) -> float:
        if self.speed_m_s is not None:
            return self.speed_m_s
        assert self.period_s is not None
        return 2.0 * math.pi * self.radius_m / self.period_s

    @property
    def _arc_m(self) -> float:
        return 2.0 * math.pi * self.radius_m * self.laps

    @property
    def duration_s(self) -> float:
        return trapezoid_duration_s(self._arc_m, self.cruise_speed_m_s, self.accel_m_s2)

    @property
    def lap_duration_s(self) -> float:
        return self.duration_s / self.laps

    @property
    def _sign(self) -> float:
        return -1.0 if self.clockwise else 1.0

    def _yaw0(self) -> float:
        th = self.start_angle_rad
        yaw = {
            YawMode.INWARD: th + math.pi,
            YawMode.OUTWARD: th,
            YawMode.TRAVEL: th + self._sign * math.pi / 2.0,
            YawMode.FIXED: self.fixed_yaw_rad,
        }[self.yaw_mode]
        return unwrap_next(0.0, yaw)

    def start(self) -> Reference:
        return self.reference(0.0)

    def reference(self, t_s: float) -> Reference:
        dur = self.duration_s
        t = min(max(t_s, 0.0), dur)
        s, v = trapezoid(t, self._arc_m, self.cruise_speed_m_s, self.accel_m_s2)
        r = self.radius_m
        sgn = self._sign
        dth = sgn * s / r
        th = self.start_angle_rad + dth
        c, si = math.cos(th), math.sin(th)
        pos: Vec3Tuple = (self.centre_m[0] + r * c, self.centre_m[1] + r * si, self.height_m)
        vel: Vec3Tuple = (-sgn * v * si, sgn * v * c, 0.0)
        if self.yaw_mode is YawMode.FIXED:
            yaw, rate = self._yaw0(), 0.0
        else:
            yaw, rate = self._yaw0() + dth, sgn * v / r
        lap = min(int(s / (2.0 * math.pi * r) + 1e-9), self.laps - 1)
        return Reference(t, pos, vel, yaw, rate, lap, t_s >= dur)
