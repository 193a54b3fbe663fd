"""Take-off and landing references: vertical moves at a climb / descent rate, and the open-ended
lift-off climb."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from flightkit.errors import PlanError
from flightkit.frames import Vec3Tuple
from trajectories.base import Move, PiecewisePattern, Reference

__all__ = ["Land", "LiftOff", "Takeoff"]


class Takeoff(PiecewisePattern):
    """Climb vertically from ``start_m`` to ``height_m`` at ``climb_m_s`` (ramped within ``accel_m_s2``)."""

    def __init__(
        self,
        start_m: Vec3Tuple,
        height_m: float,
        climb_m_s: float = 0.3,
        accel_m_s2: float = 0.5,
        yaw_rad: float = 0.0,
    ) -> None:
        if not climb_m_s > 0.0:
            raise PlanError(
                f"climb rate must be positive, got {climb_m_s} m/s",
                "give a climb rate > 0",
                pattern="takeoff",
                key="climb_m_s",
                value=climb_m_s,
            )
        top = (float(start_m[0]), float(start_m[1]), float(height_m))
        start = (float(start_m[0]), float(start_m[1]), float(start_m[2]))
        if top[2] <= start[2]:
            raise PlanError(
                f"target height {height_m} m is not above the start height {start[2]:.2f} m",
                "take off to a height above the vehicle",
                pattern="takeoff",
                key="height_m",
                value=height_m,
            )
        self.height_m = float(height_m)
        super().__init__("takeoff", [Move(start, top, climb_m_s, accel_m_s2, float(yaw_rad))], 1)


class Land(PiecewisePattern):
    """Descend vertically from ``start_m`` at ``descent_m_s`` down to ``floor_m - push_m``.

    The reference goes ``push_m`` below the floor so the vehicle keeps pressing down until the
    autopilot reports the landed state; the runner ends the landing on that state, not on time.
    """

    def __init__(
        self,
        start_m: Vec3Tuple,
        descent_m_s: float = 0.3,
        floor_m: float = 0.0,
        push_m: float = 0.3,
        accel_m_s2: float = 0.5,
        yaw_rad: float = 0.0,
    ) -> None:
        if not descent_m_s > 0.0:
            raise PlanError(
                f"descent rate must be positive, got {descent_m_s} m/s",
                "give a descent rate > 0",
                pattern="land",
                key="descent_m_s",
                value=descent_m_s,
            )
        start = (float(start_m[0]), float(start_m[1]), float(start_m[2]))
        bottom = (start[0], start[1], min(float(floor_m), start[2]) - float(push_m))
        super().__init__("land", [Move(start, bottom, descent_m_s, accel_m_s2, float(yaw_rad))], 1)


@dataclass
class LiftOff:
    """Lift-off reference: stay over ``start_m`` and climb at ``climb_m_s``, open-ended.

    The height reference is the measured height (``height_of()``; no vertical P term): the climb
    is pure feed-forward, so motor spin-up does not build a position error that overshoots later.
    """

    start_m: Vec3Tuple
    yaw_rad: float
    climb_m_s: float
    height_of: Callable[[], float | None] = field(default=lambda: None)
    name: str = "climb"
    laps: int = 1
    lap_duration_s: float = math.inf
    duration_s: float = math.inf

    def reference(self, t_s: float) -> Reference:
        z = self.height_of()
        if z is None:
            z = self.start_m[2]
        return Reference(t_s, (self.start_m[0], self.start_m[1], z), (0.0, 0.0, self.climb_m_s), self.yaw_rad)
