"""Rectangle (and any convex polygon): straight sides, yaw perpendicular to the side, turns in place."""

from __future__ import annotations

import math
from collections.abc import Sequence

from flightkit.errors import PlanError
from flightkit.frames import Vec3Tuple
from trajectories.base import (
    PiecewisePattern,
    Reference,
    Segment,
    YawMode,
    chain,
    heading_rad,
    unwrap_next,
)

__all__ = ["Rectangle", "rectangle_corners"]


def rectangle_corners(
    centre_m: Sequence[float], size_m: Sequence[float], rotation_rad: float = 0.0, start_corner: int = 0
) -> list[tuple[float, float]]:
    """The four corners of a rectangle, counter-clockwise, starting at ``start_corner``.

    Corner 0 is the (-x, -y) corner of the unrotated rectangle, then (+x, -y), (+x, +y), (-x, +y).
    """
    hx, hy = size_m[0] / 2.0, size_m[1] / 2.0
    c, s = math.cos(rotation_rad), math.sin(rotation_rad)
    local = [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
    pts = [(centre_m[0] + c * x - s * y, centre_m[1] + s * x + c * y) for x, y in local]
    k = start_corner % 4
    return pts[k:] + pts[:k]


class Rectangle(PiecewisePattern):
    """Laps around a rectangle (or any convex polygon) given by its corners, in flying order.

    Each side is a rest-to-rest move at ``speed_m_s`` with the speed ramped within
    ``accel_m_s2``; along a side the yaw is held perpendicular to it (INWARD: looking into the
    polygon, OUTWARD: away), or along it (TRAVEL), or fixed (FIXED). At each corner the vehicle
    stops and turns in place to the next side's yaw over ``turn_s`` (a rectangle: 90 degrees).
    A lap ends at the first corner after the last turn, so laps repeat exactly.

    Raises:
        PlanError: fewer than 3 corners, a degenerate side, or a non-positive speed.
    """

    def __init__(
        self,
        corners_m: Sequence[Sequence[float]],
        height_m: float,
        speed_m_s: float = 0.1,
        accel_m_s2: float = 0.2,
        turn_s: float = 5.0,
        laps: int = 1,
        yaw_mode: YawMode = YawMode.INWARD,
        fixed_yaw_rad: float = 0.0,
        name: str = "rectangle",
    ) -> None:
        pts = [(float(p[0]), float(p[1])) for p in corners_m]
        if len(pts) < 3:
            raise PlanError(
                f"needs at least 3 corners, got {len(pts)}",
                "give 3 or more corners",
                pattern=name,
                key="corners_m",
                value=len(pts),
            )
        if not speed_m_s > 0.0 or not accel_m_s2 > 0.0 or turn_s < 0.0:
            bad = "speed_m_s" if not speed_m_s > 0.0 else "accel_m_s2" if not accel_m_s2 > 0.0 else "turn_s"
            raise PlanError(
                f"speed_m_s ({speed_m_s}) and accel_m_s2 ({accel_m_s2}) must be positive, "
                f"turn_s ({turn_s}) not negative",
                f"fix {bad}",
                pattern=name,
                key=bad,
                value={"speed_m_s": speed_m_s, "accel_m_s2": accel_m_s2, "turn_s": turn_s}[bad],
            )
        n = len(pts)
        for i in range(n):
            if math.dist(pts[i], pts[(i + 1) % n]) < 1e-6:
                raise PlanError(
                    f"corners {i} and {(i + 1) % n} coincide at {pts[i]}",
                    "remove the repeated corner",
                    pattern=name,
                    key="corners_m",
                    value=pts[i],
                )
        area2 = sum(pts[i][0] * pts[(i + 1) % n][1] - pts[(i + 1) % n][0] * pts[i][1] for i in range(n))
        ccw = area2 > 0.0
        inward_offset = (math.pi / 2.0) if ccw else (-math.pi / 2.0)
        offset = {
            YawMode.INWARD: inward_offset,
            YawMode.OUTWARD: -inward_offset,
            YawMode.TRAVEL: 0.0,
        }.get(yaw_mode)
        yaws: list[float] = []
        prev = 0.0
        for i in range(n + 1):
            if offset is None:
                yaw = fixed_yaw_rad if i == 0 else yaws[0]
            else:
                yaw = heading_rad(pts[i % n], pts[(i + 1) % n]) + offset
            yaw = unwrap_next(prev, yaw)
            yaws.append(yaw)
            prev = yaw
        points: list[Vec3Tuple] = [(x, y, float(height_m)) for x, y in pts] + [
            (pts[0][0], pts[0][1], float(height_m))
        ]
        segs: list[Segment] = chain(points, yaws, speed_m_s, accel_m_s2, turn_s)
        self.corners_m = tuple(pts)
        self.height_m = float(height_m)
        super().__init__(name, segs, laps)

    def start(self) -> Reference:
        return self.reference(0.0)
