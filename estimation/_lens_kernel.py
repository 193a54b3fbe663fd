"""The lens model of ``CameraGeometry`` compiled: OpenCV's radial-tangential distortion with up to
eight coefficients ``(k1, k2, p1, p2, k3, k4, k5, k6)``, both ways.

:func:`undistort` is ``cv2.undistortPoints(px, K, dist, P=K)`` (its default five fixed-point
steps) and :func:`project` is ``cv2.projectPoints`` of points already in the camera frame, written
out operation by operation in OpenCV's order, so both give the same bits
(``tests/unit/test_lens_kernel.py``). Coefficients past the eighth (thin prism, tilt) are not
here: ``CameraGeometry`` keeps OpenCV for those.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation._kernels import transform

__all__ = ["MAX_COEFFS", "UNDISTORT_STEPS", "coefficients", "project", "undistort"]

MAX_COEFFS = 8
"""The distortion coefficients these kernels model (the rational model's eight)."""

UNDISTORT_STEPS = 5
"""Fixed-point steps of :func:`undistort` (``cv2.undistortPoints``' default criteria)."""


def coefficients(dist: npt.NDArray[np.float64]) -> npt.NDArray[np.float64] | None:
    """``dist`` padded with zeros to :data:`MAX_COEFFS`, or None when it has nonzero coefficients
    past them (OpenCV's thin-prism and tilt terms)."""
    if np.any(dist[MAX_COEFFS:] != 0.0):
        return None
    k = np.zeros(MAX_COEFFS)
    k[: min(len(dist), MAX_COEFFS)] = dist[:MAX_COEFFS]
    return k


@njit(cache=True)
def undistort(px: Any, fx: float, fy: float, cx: float, cy: float, k: Any) -> npt.NDArray[np.float64]:
    """(N, 2) undistorted pixels (float64, the same pinhole) of (N, 2) image pixels ``px`` under the
    coefficients ``k`` (:func:`coefficients`)."""
    n = px.shape[0]
    out = np.empty((n, 2))
    ifx = 1.0 / fx
    ify = 1.0 / fy
    for i in range(n):
        u = np.float64(px[i, 0])
        v = np.float64(px[i, 1])
        x = (u - cx) * ifx
        y = (v - cy) * ify
        x0 = x
        y0 = y
        for _ in range(UNDISTORT_STEPS):
            r2 = x * x + y * y
            icdist = (1 + ((k[7] * r2 + k[6]) * r2 + k[5]) * r2) / (1 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2)
            if icdist < 0:  # outside the model's valid radius: the pixel as if undistorted
                x = (u - cx) * ifx
                y = (v - cy) * ify
                break
            dx = 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
            dy = k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
            x = (x0 - dx) * icdist
            y = (y0 - dy) * icdist
        out[i, 0] = fx * x + cx
        out[i, 1] = fy * y + cy
    return out


@njit(cache=True)
def project(
    X: Any,
    T: Any,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    k: Any,
    width: float,
    height: float,
    margin: float,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """``estimation._kernels.project`` through the lens: (N, 2) float32 pixels of (N, 3) points under
    ``T`` with the coefficients ``k``, and (N,) "in front (z > 0.05 m) and within ``margin`` px of
    the image" (judged on the float64 pixels)."""
    Xc = transform(X, T)
    n = Xc.shape[0]
    uv = np.empty((n, 2), np.float32)
    inside = np.empty(n, np.bool_)
    for i in range(n):
        z = Xc[i, 2]
        iz = 1.0 / z if z != 0.0 else 1.0
        x = Xc[i, 0] * iz
        y = Xc[i, 1] * iz
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        a1 = 2 * x * y
        a2 = r2 + 2 * x * x
        a3 = r2 + 2 * y * y
        cdist = 1 + k[0] * r2 + k[1] * r4 + k[4] * r6
        icdist2 = 1.0 / (1 + k[5] * r2 + k[6] * r4 + k[7] * r6)
        u = (x * cdist * icdist2 + k[2] * a1 + k[3] * a2) * fx + cx
        v = (y * cdist * icdist2 + k[2] * a3 + k[3] * a1) * fy + cy
        uv[i, 0] = u
        uv[i, 1] = v
        inside[i] = z > 0.05 and u > -margin and u < width + margin and v > -margin and v < height + margin
    return uv, inside
