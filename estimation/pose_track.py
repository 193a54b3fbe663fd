"""The pose a VO run carries from frame to frame: the current camera pose, the last measured
step (the constant-velocity prediction) and the sanity check of a new step."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from estimation._motion_kernel import scaled_step
from estimation.motion import rotation_angle_rad

__all__ = ["PoseTrack", "scale_motion"]

F64 = npt.NDArray[np.float64]


def scale_motion(T_step: F64, factor: float) -> F64:
    """Scale a relative motion (constant velocity for a different dt)."""
    if abs(factor - 1.0) < 1e-3:
        return T_step.copy()
    T: F64 = scaled_step(np.ascontiguousarray(T_step, dtype=np.float64), float(factor))
    return T


class PoseTrack:
    """The camera pose ``T_world_cam``, the last accepted step ``T_step`` (``T_cur_prev`` over
    ``step_dt_s``) and the previous frame's stamp.

    Args:
        T_world_cam0: the first camera pose.
        max_speed_m_s, max_rate_rad_s: a step faster than these is implausible.
    """

    def __init__(self, T_world_cam0: F64, max_speed_m_s: float, max_rate_rad_s: float) -> None:
        self.T_world_cam = T_world_cam0.copy()
        self.T_step: F64 | None = None
        self.step_dt_s = 0.0
        self.prev_stamp_ns = 0
        self.max_speed_m_s = max_speed_m_s
        self.max_rate_rad_s = max_rate_rad_s

    def dt_s(self, stamp_ns: int) -> float:
        """Seconds since the previous frame (at least 0.1 ms)."""
        return max((stamp_ns - self.prev_stamp_ns) * 1e-9, 1e-4)

    def predict(self, dt_s: float) -> F64:
        """The predicted ``T_cur_prev`` after ``dt_s`` (constant velocity; identity at first)."""
        if self.T_step is None or self.step_dt_s <= 0:
            return np.eye(4)
        return scale_motion(self.T_step, dt_s / self.step_dt_s)

    def plausible(self, T_cur_prev: F64, dt_s: float) -> bool:
        """The step is within the speed and turn-rate limits."""
        dt = max(dt_s, 1e-3)
        x, y, z = float(T_cur_prev[0, 3]), float(T_cur_prev[1, 3]), float(T_cur_prev[2, 3])
        speed = math.sqrt(x * x + y * y + z * z) / dt
        rate = rotation_angle_rad(T_cur_prev[:3, :3]) / dt
        return speed <= self.max_speed_m_s and rate <= self.max_rate_rad_s

    def measured(self, T_cur_prev: F64, dt_s: float) -> None:
        """Record a measured (not predicted) step: the next prediction's velocity."""
        self.T_step, self.step_dt_s = T_cur_prev, dt_s
