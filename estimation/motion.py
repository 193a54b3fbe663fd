"""Relative motion estimates and the rigid-transform helpers every estimator shares.

Conventions: every estimator returns :class:`Motion` whose ``T_cur_ref`` (4x4) maps points
expressed in the *reference* camera frame (the earlier frame or keyframe) into the *current*
camera frame, ``X_cur = R @ X_ref + t``; camera frames are OpenCV (x right, y down, z
forward). The pose update is ``T_world_cur = T_world_ref @ inv(T_cur_ref)``.

Inputs are numpy arrays: 3D points (N, 3) metres, pixels (N, 2), the intrinsic matrix
``K`` (3, 3). The estimators themselves: :mod:`estimation.rigid` (3D-3D), :mod:`estimation.pnp`
(3D-2D) and :mod:`estimation.essential` (2D-2D with metric scale from depth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from estimation import _kernels

__all__ = ["Motion", "failed_motion", "invert", "make_T", "median", "ransac_iterations", "rotation_angle_rad"]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


@dataclass(frozen=True, slots=True, eq=False)
class Motion:
    """A relative motion estimate.

    Attributes:
        T_cur_ref: (4, 4) maps reference-camera points into the current camera frame.
        inliers: (N,) bool, which correspondences support the estimate.
        ok: False when the estimator could not produce a trustworthy motion (too few
            points or inliers); ``T_cur_ref`` is then the identity.
        scale: Umeyama similarity scale (1.0 for rigid estimates).
    """

    T_cur_ref: F64
    inliers: Mask
    ok: bool
    scale: float = 1.0

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def R(self) -> F64:
        return self.T_cur_ref[:3, :3]

    @property
    def t(self) -> F64:
        return self.T_cur_ref[:3, 3]


def median(a: npt.NDArray[np.floating]) -> float:
    """``float(np.median(a))`` of a non-empty 1-D float array, bit for bit, without
    ``np.median``'s generic machinery (~4x cheaper on a few hundred values, where the VO
    calls it every frame). NaN when ``a`` holds a NaN."""
    n = len(a)
    h = n // 2
    if n % 2:
        p = np.partition(a, (h, n - 1))
        return float("nan") if p[-1] != p[-1] else float(p[h])
    p = np.partition(a, (h - 1, h, n - 1))
    # np.median's mean of the two middle values: their sum divided by 2.
    return float("nan") if p[-1] != p[-1] else float((p[h - 1] + p[h]) / 2)


_EYE4 = np.eye(4)
_EYE4.flags.writeable = False  # copied, never written (np.eye costs 5x a copy)


def make_T(R: npt.ArrayLike, t: npt.ArrayLike) -> F64:
    """4x4 homogeneous matrix from R (3, 3) and t (3,)."""
    T = _EYE4.copy()
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: F64) -> F64:
    """Inverse of a rigid 4x4 transform (no general matrix inverse; a new array)."""
    Ti: F64 = _kernels.invert_rigid(np.ascontiguousarray(T, dtype=np.float64))
    return Ti


def rotation_angle_rad(R: F64) -> float:
    """Angle of a rotation matrix, radians in [0, pi]."""
    c = (float(R[0, 0]) + float(R[1, 1]) + float(R[2, 2]) - 1.0) * 0.5  # (np.trace's sum, in its order)
    return math.acos(min(1.0, max(-1.0, c)))


def failed_motion(n: int) -> Motion:
    """The motion of an estimator that could not estimate one: identity, no inliers, not ok."""
    return Motion(np.eye(4), np.zeros(n, dtype=bool), False)


def ransac_iterations(inlier_ratio: float, sample_size: int, confidence: float, max_iters: int) -> int:
    """Number of RANSAC draws for ``confidence`` of one all-inlier sample."""
    w = min(max(inlier_ratio, 1e-9), 1.0)
    p_good = w**sample_size
    if p_good >= 1.0 - 1e-12:
        return 1
    if p_good < 1e-12:
        return max_iters
    n = math.log(1.0 - confidence) / math.log(1.0 - p_good)
    return int(min(max_iters, max(1, math.ceil(n))))
