"""Rolling-shutter row timing: each image row is exposed a little later than the one above it,
so a moving camera sees every row from another pose. These functions move a measurement from
its row's time to the frame's stamp (taken as mid-readout), to first order in the camera's
motion rate, before any geometry uses it.

The model: row ``v`` is exposed at ``stamp + (v - (H - 1) / 2) * readout_s / H``, and over that
short time the camera turns and moves at a constant rate (:class:`CameraRate`, in its own
OpenCV frame). A static point at ``X_row`` in the camera at the row's time is at
``X_mid = X_row + dt * (omega x X_row + v)`` in the camera at the stamp.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation._motion_kernel import step_rate

__all__ = ["CameraRate", "RollingShutter", "move_pixels"]

F64 = npt.NDArray[np.float64]
Rows = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True, slots=True, eq=False)
class CameraRate:
    """The camera's motion rate at a frame, in its own (OpenCV) frame.

    Attributes:
        omega_rad_s: (3,) angular rate, rad/s.
        velocity_m_s: (3,) velocity, m/s.
    """

    omega_rad_s: F64
    velocity_m_s: F64

    def minus(self, other: CameraRate) -> CameraRate:
        """The difference of two rates."""
        return CameraRate(self.omega_rad_s - other.omega_rad_s, self.velocity_m_s - other.velocity_m_s)

    @staticmethod
    def from_step(T_cur_prev: F64, dt_s: float) -> CameraRate:
        """The mean rate over a step ``T_cur_prev`` (prev-camera to cur-camera) of ``dt_s``."""
        omega, v = step_rate(np.ascontiguousarray(T_cur_prev, dtype=np.float64), float(dt_s))
        return CameraRate(omega, v)


_FAR_M = 1e9
"""The depth given to a point whose depth is unknown: its velocity part vanishes."""

_NO_DEPTH = np.empty(0)
"""``move_pixels``' depths when none are given (every point infinitely far)."""


class RollingShutter:
    """Row timing of one rolling-shutter camera (pixels are undistorted ones of ``K``).

    Args:
        readout_s: time from the first row's exposure to the last's, s (> 0).
        height_px: image rows.
        fx, fy, cx, cy: the pinhole model of the undistorted pixels.
    """

    def __init__(self, readout_s: float, height_px: int, fx: float, fy: float, cx: float, cy: float) -> None:
        self.readout_s = float(readout_s)
        self.height_px = int(height_px)
        self.fx, self.fy, self.cx, self.cy = fx, fy, cx, cy
        # A row's exposure time minus the stamp's is (row - mid_row_px) * row_s.
        self.mid_row_px = 0.5 * (self.height_px - 1)
        self.row_s = self.readout_s / self.height_px

    def row_dt_s(self, rows_px: Rows) -> F64:
        """Each row's exposure time minus the stamp's, s."""
        return (np.asarray(rows_px, dtype=np.float64) - self.mid_row_px) * self.row_s

    def max_shift_px(self, rate: CameraRate) -> float:
        """About the largest pixel shift the rate's rotation makes between the stamp and the
        first or last row (to tell whether a change of rate matters)."""
        w = rate.omega_rad_s
        f = max(self.fx, self.fy)
        return 0.5 * self.readout_s * f * float(np.hypot(np.hypot(w[0], w[1]), 0.5 * w[2]))

    def points(self, X_row: F64, rows_px: Rows, rate: CameraRate) -> F64:
        """3D points measured at their rows' times (camera frame, m), in the camera at the stamp."""
        dt = self.row_dt_s(rows_px)
        w, v = rate.omega_rad_s, rate.velocity_m_s
        x, y, z = X_row[:, 0], X_row[:, 1], X_row[:, 2]
        out = np.empty_like(X_row, dtype=np.float64)
        out[:, 0] = x + dt * (w[1] * z - w[2] * y + v[0])
        out[:, 1] = y + dt * (w[2] * x - w[0] * z + v[1])
        out[:, 2] = z + dt * (w[0] * y - w[1] * x + v[2])
        return out

    def pixels(self, und_px: F64, rows_px: Rows, rate: CameraRate, z_m: F64 | None = None) -> F64:
        """Undistorted pixels seen at their rows' times, where the camera at the stamp sees the
        same points. ``z_m``: the points' depths (for the velocity's part); where it is None or
        not finite only the rotation is undone."""
        n = len(und_px)
        if n == 0:
            return np.asarray(und_px, dtype=np.float64)
        # The rows' times (row_dt_s) and the depths' stand-ins are computed in the compiled loop.
        return move_pixels(
            np.ascontiguousarray(und_px, dtype=np.float64),
            np.ascontiguousarray(rows_px, dtype=np.float64),
            self.mid_row_px,
            self.row_s,
            _NO_DEPTH if z_m is None else np.ascontiguousarray(z_m, dtype=np.float64),
            z_m is not None,
            rate.omega_rad_s,
            rate.velocity_m_s,
            self.fx,
            self.fy,
            self.cx,
            self.cy,
        )


@njit(cache=True)
def move_pixels(
    und: Any,
    rows: Any,
    mid_row: float,
    row_s: float,
    z: Any,
    has_z: bool,
    w: Any,
    v: Any,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
) -> F64:
    """:meth:`RollingShutter.pixels` in one compiled loop: each pixel's row time minus the stamp's
    is ``(rows[i] - mid_row) * row_s`` (:meth:`RollingShutter.row_dt_s`); its depth ``z[i]``
    (``_FAR_M`` where not finite; without ``has_z`` infinite: no velocity part)."""
    n = und.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        x = (und[i, 0] - cx) / fx
        y = (und[i, 1] - cy) / fy
        dt = (rows[i] - mid_row) * row_s
        zi = (z[i] if np.isfinite(z[i]) else _FAR_M) if has_z else np.inf
        inv_z = 1.0 / zi
        # b = (x, y, 1) moved by dt * (w x b + v / z)
        bx = x + dt * (w[1] - w[2] * y + v[0] * inv_z)
        by = y + dt * (w[2] * x - w[0] + v[1] * inv_z)
        bz = 1.0 + dt * (w[0] * y - w[1] * x + v[2] * inv_z)
        out[i, 0] = fx * bx / bz + cx
        out[i, 1] = fy * by / bz + cy
    return out
