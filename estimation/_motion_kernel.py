"""The per-frame rotation bookkeeping of the keyframe pipelines, compiled (numba, nopython, float64,
no fastmath): the SO(3) logarithm, a step scaled to another interval (the constant-velocity
prediction) and the mean rate of a step (the rolling shutter's).

They replace ``cv2.Rodrigues`` there (docs/estimation-log.md, twenty-third pass), which first
projects the matrix onto SO(3) by an SVD and takes the angle from the trace alone; these take the
rotations as they are (every caller's comes from a pose estimate or a product of them) and the
angle from both the trace and the skew part, so they agree with it to ~1e-12, not bit for bit
(``tests/unit/test_kernels.py``).

Compiled once and cached on disk next to this module, as ``estimation._kernels``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation._pose_kernel import _rotvec_matrix

__all__ = ["scaled_step", "step_rate"]

F64 = npt.NDArray[np.float64]

_HALF_TURN_COS = -0.9
"""Below this cosine of the angle (~154 deg) the axis comes from the symmetric part of the matrix,
where the skew part (2 sin(angle) times the axis) vanishes."""


@njit(cache=True)
def _log(R: Any, transpose: bool, out: Any) -> None:
    """``out`` (3,) = the rotation vector (axis times angle, rad) of ``R`` (3, 3), or of ``R.T``."""
    a = R[2, 1] - R[1, 2]
    b = R[0, 2] - R[2, 0]
    c = R[1, 0] - R[0, 1]
    if transpose:
        a, b, c = -a, -b, -c
    s2 = 0.5 * math.sqrt(a * a + b * b + c * c)  # sin(angle)
    cos_a = min(1.0, max(-1.0, (R[0, 0] + R[1, 1] + R[2, 2] - 1.0) * 0.5))
    angle = math.atan2(s2, cos_a)  # (acos of the trace alone loses the small angles)
    if cos_a > _HALF_TURN_COS:
        k = angle / (2.0 * s2) if s2 > 0.0 else 0.5
        out[0], out[1], out[2] = a * k, b * k, c * k
        return
    # Near a half turn: R = cos I + sin [n]x + (1 - cos) n n^T, so n_i^2 = (R_ii - cos) / (1 - cos)
    # and R_ij + R_ji = 2 (1 - cos) n_i n_j give the axis up to its sign, which the skew part gives.
    d = 1.0 - cos_a
    x = math.sqrt(max(0.0, (R[0, 0] - cos_a) / d))
    y = math.sqrt(max(0.0, (R[1, 1] - cos_a) / d))
    z = math.sqrt(max(0.0, (R[2, 2] - cos_a) / d))
    if x >= y and x >= z:
        y = math.copysign(y, R[0, 1] + R[1, 0])
        z = math.copysign(z, R[0, 2] + R[2, 0])
    elif y >= z:
        x = math.copysign(x, R[0, 1] + R[1, 0])
        z = math.copysign(z, R[1, 2] + R[2, 1])
    else:
        x = math.copysign(x, R[0, 2] + R[2, 0])
        y = math.copysign(y, R[1, 2] + R[2, 1])
    k = angle / math.sqrt(x * x + y * y + z * z)
    if x * a + y * b + z * c < 0.0:
        k = -k
    out[0], out[1], out[2] = x * k, y * k, z * k


@njit(cache=True)
def scaled_step(T: Any, factor: float) -> F64:
    """The rigid step ``T`` (4, 4) scaled to ``factor`` times its interval at a constant velocity:
    its rotation vector and its translation times ``factor`` (a new (4, 4))."""
    w = np.empty(3)
    _log(T, False, w)
    out = np.zeros((4, 4))
    _rotvec_matrix(w[0] * factor, w[1] * factor, w[2] * factor, out)
    for r in range(3):
        out[r, 3] = T[r, 3] * factor
    out[3, 3] = 1.0
    return out


@njit(cache=True)
def step_rate(T_cur_prev: Any, dt_s: float) -> tuple[F64, F64]:
    """The mean angular rate (rad/s) and velocity (m/s) of a step ``T_cur_prev`` over ``dt_s``:
    the rotation vector of ``R.T`` and ``-t``, each over ``dt_s``."""
    omega = np.empty(3)
    _log(T_cur_prev, True, omega)
    v = np.empty(3)
    for r in range(3):
        omega[r] /= dt_s
        v[r] = -T_cur_prev[r, 3] / dt_s
    return omega, v
