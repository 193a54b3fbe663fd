"""Line and waypoints: straight legs between points, stopping at each one."""

from __future__ import annotations

import math
from collections.abc import Sequence

from flightkit.errors import PlanError
from flightkit.frames import Vec3Tuple
from trajectories.base import PiecewisePattern, Turn, YawMode, chain, heading_rad, unwrap_next

__all__ = ["Line", "Waypoints"]


class Waypoints(PiecewisePattern):
    """Fly through ``points_m`` (world ENU, metres), stopping at each.

    Legs are rest-to-rest moves at ``speed_m_s`` within ``accel_m_s2``. Yaw: FIXED keeps
    ``start_yaw_rad`` throughout; TRAVEL turns in place (over ``turn_s``) to face each leg's
    horizontal direction before flying it (purely vertical legs keep the previous yaw), and
    optionally turns back to ``end_yaw_rad`` at the end.
    """

    def __init__(
        self,
        points_m: Sequence[Sequence[float]],
        speed_m_s: float = 0.3,
        accel_m_s2: float = 0.3,
        start_yaw_rad: float = 0.0,
        yaw_mode: YawMode = YawMode.FIXED,
        turn_s: float = 2.0,
        end_yaw_rad: float | None = None,
        name: str = "waypoints",
    ) -> None:
        pts: list[Vec3Tuple] = [(float(p[0]), float(p[1]), float(p[2])) for p in points_m]
        if len(pts) < 2:
            raise PlanError(
                f"needs at least 2 points, got {len(pts)}",
                "give a start and an end point",
                pattern=name,
                key="points_m",
                value=len(pts),
            )
        if not speed_m_s > 0.0 or not accel_m_s2 > 0.0:
            raise PlanError(
                f"speed ({speed_m_s} m/s) and accel ({accel_m_s2} m/s^2) must be positive",
                "give both > 0",
                pattern=name,
                key="speed_m_s" if not speed_m_s > 0.0 else "accel_m_s2",
                value=speed_m_s if not speed_m_s > 0.0 else accel_m_s2,
            )
        if yaw_mode not in (YawMode.FIXED, YawMode.TRAVEL):
            raise PlanError(
                f"{yaw_mode.value!r} is not allowed here",
                "use travel or fixed",
                pattern=name,
                key="yaw_mode",
                value=yaw_mode.value,
            )
        # drop repeated points
        dedup = [pts[0]] + [p for a, p in zip(pts, pts[1:], strict=False) if math.dist(a, p) > 1e-9]
        yaws: list[float] = []
        prev = float(start_yaw_rad)
        for i in range(len(dedup) - 1):
            a, b = dedup[i], dedup[i + 1]
            if yaw_mode is YawMode.TRAVEL and math.hypot(b[0] - a[0], b[1] - a[1]) > 1e-6:
                prev = unwrap_next(prev, heading_rad(a, b))
            yaws.append(prev)
        if end_yaw_rad is not None:
            yaws.append(unwrap_next(yaws[-1] if yaws else prev, end_yaw_rad))
        segs = chain(dedup, yaws, speed_m_s, accel_m_s2, turn_s) if len(dedup) > 1 else []
        if yaws and yaws[0] != start_yaw_rad:
            segs.insert(0, Turn(dedup[0], float(start_yaw_rad), yaws[0], turn_s))
        if not segs:  # all points equal: a zero-length pattern still needs a duration
            segs = [Turn(dedup[0], float(start_yaw_rad), float(start_yaw_rad), 1e-3)]
        self.points_m = tuple(dedup)
        super().__init__(name, segs, 1)


class Line(Waypoints):
    """A straight line from ``start_m`` to ``end_m`` at a fixed yaw (or turning to face it)."""

    def __init__(
        self,
        start_m: Sequence[float],
        end_m: Sequence[float],
        speed_m_s: float = 0.3,
        accel_m_s2: float = 0.3,
        yaw_rad: float = 0.0,
        end_yaw_rad: float | None = None,
        turn_s: float = 2.0,
    ) -> None:
        super().__init__(
            [start_m, end_m], speed_m_s, accel_m_s2, yaw_rad, YawMode.FIXED, turn_s, end_yaw_rad, name="line"
        )
