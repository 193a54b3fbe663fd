"""Hold: stay at one pose for a while."""

from __future__ import annotations

from flightkit.errors import PlanError
from flightkit.frames import Vec3Tuple
from trajectories.base import PiecewisePattern, Turn

__all__ = ["Hold"]


class Hold(PiecewisePattern):
    """Hold ``pos_m`` (world ENU) at heading ``yaw_rad`` for ``duration_s`` seconds."""

    def __init__(self, pos_m: Vec3Tuple, yaw_rad: float, duration_s: float) -> None:
        if not duration_s > 0.0:
            raise PlanError(
                f"duration must be positive, got {duration_s} s",
                "hold for a duration > 0",
                pattern="hold",
                key="duration_s",
                value=duration_s,
            )
        p = (float(pos_m[0]), float(pos_m[1]), float(pos_m[2]))
        self.pos_m = p
        self.yaw_rad = float(yaw_rad)
        super().__init__("hold", [Turn(p, self.yaw_rad, self.yaw_rad, float(duration_s))], 1)
