"""Lawnmower (boustrophedon) coverage of a rectangular area, with an optional return leg."""

from __future__ import annotations

import math
from collections.abc import Sequence

from flightkit.errors import PlanError
from flightkit.frames import Vec3Tuple
from trajectories.base import PiecewisePattern, Reference, YawMode, chain, heading_rad, unwrap_next

__all__ = ["Lawnmower", "lawnmower_points"]


def lawnmower_points(
    origin_m: Sequence[float], size_m: Sequence[float], spacing_m: float, lane_dir_rad: float = 0.0
) -> list[tuple[float, float]]:
    """Turning points of a lawnmower path over a rectangle.

    The rectangle has one corner at ``origin_m`` and extends ``size_m[0]`` along the lane
    direction ``lane_dir_rad`` and ``size_m[1]`` to its left. Lanes are ``spacing_m`` apart;
    the last lane lies on the far edge (the spacing is never exceeded).
    """
    length, width = float(size_m[0]), float(size_m[1])
    n_lanes = max(1, math.ceil(width / spacing_m - 1e-9)) + 1 if width > 0 else 1
    step = width / (n_lanes - 1) if n_lanes > 1 else 0.0
    c, s = math.cos(lane_dir_rad), math.sin(lane_dir_rad)
    pts: list[tuple[float, float]] = []
    for k in range(n_lanes):
        a, b = (0.0, length) if k % 2 == 0 else (length, 0.0)
        for x in (a, b):
            y = k * step
            pts.append((origin_m[0] + c * x - s * y, origin_m[1] + s * x + c * y))
    return pts


class Lawnmower(PiecewisePattern):
    """Parallel lanes over a rectangle, then (``return_to_start``) a straight leg back to the start.

    Lanes and the shifts between them are rest-to-rest moves at ``speed_m_s`` ramped within
    ``accel_m_s2``. With ``yaw_mode`` TRAVEL the vehicle faces the direction of travel and turns
    in place at each corner over ``turn_s``; with FIXED it keeps ``fixed_yaw_rad`` and only
    stops at corners. With the return leg a lap ends where it began, so laps repeat.
    """

    def __init__(
        self,
        origin_m: Sequence[float],
        size_m: Sequence[float],
        spacing_m: float,
        height_m: float,
        speed_m_s: float = 0.1,
        accel_m_s2: float = 0.2,
        turn_s: float = 5.0,
        lane_dir_rad: float = 0.0,
        laps: int = 1,
        yaw_mode: YawMode = YawMode.TRAVEL,
        fixed_yaw_rad: float = 0.0,
        return_to_start: bool = True,
    ) -> None:
        if not spacing_m > 0.0:
            raise PlanError(
                f"lane spacing must be positive, got {spacing_m} m",
                "give a spacing > 0",
                pattern="lawnmower",
                key="spacing_m",
                value=spacing_m,
            )
        if size_m[0] <= 0.0 or size_m[1] < 0.0:
            raise PlanError(
                f"size must be positive, got {tuple(size_m)} m",
                "give a length > 0 and a width >= 0",
                pattern="lawnmower",
                key="size_m",
                value=tuple(size_m),
            )
        if yaw_mode not in (YawMode.TRAVEL, YawMode.FIXED):
            raise PlanError(
                f"{yaw_mode.value!r} is not allowed here",
                "use travel or fixed",
                pattern="lawnmower",
                key="yaw_mode",
                value=yaw_mode.value,
            )
        if not speed_m_s > 0.0 or not accel_m_s2 > 0.0:
            raise PlanError(
                f"speed ({speed_m_s} m/s) and accel ({accel_m_s2} m/s^2) must be positive",
                "give both > 0",
                pattern="lawnmower",
                key="speed_m_s" if not speed_m_s > 0.0 else "accel_m_s2",
                value=speed_m_s if not speed_m_s > 0.0 else accel_m_s2,
            )
        if laps > 1 and not return_to_start:
            raise PlanError(
                f"{laps} laps need return_to_start = true",
                "set return_to_start = true or laps = 1",
                pattern="lawnmower",
                key="laps",
                value=laps,
            )
        if yaw_mode is YawMode.TRAVEL and not turn_s > 0.0:
            raise PlanError(
                "yaw = 'travel' turns in place at every corner, which takes time",
                "give turn_s > 0 or yaw = 'fixed'",
                pattern="lawnmower",
                key="turn_s",
                value=turn_s,
            )
        pts2 = lawnmower_points(origin_m, size_m, spacing_m, lane_dir_rad)
        if return_to_start and math.dist(pts2[-1], pts2[0]) > 1e-9:
            pts2.append(pts2[0])
        z = float(height_m)
        points: list[Vec3Tuple] = [(x, y, z) for x, y in pts2]
        yaws: list[float] = []
        prev = 0.0
        for i in range(len(points) - 1):
            yaw = fixed_yaw_rad if yaw_mode is YawMode.FIXED else heading_rad(points[i], points[i + 1])
            yaw = unwrap_next(prev if i else 0.0, yaw)
            yaws.append(yaw)
            prev = yaw
        if return_to_start and laps > 1 and yaw_mode is YawMode.TRAVEL:
            yaws.append(unwrap_next(yaws[-1], yaws[0]))  # face the first lane again to close the lap
        self.points_m = tuple(points)
        super().__init__("lawnmower", chain(points, yaws, speed_m_s, accel_m_s2, turn_s), laps)

    def start(self) -> Reference:
        return self.reference(0.0)
