"""Rectified stereo: sparse disparity along rows, dense SGBM disparity, triangulation.

A rectified pair has both cameras' image rows aligned, so a left pixel (u, v) appears in
the right image at (u - d, v) with disparity d > 0 and depth ``Z = fx * B / d``.

* :func:`sparse_disparity` finds d for chosen left points with pyramidal LK constrained to
  rows afterwards (|dy| small), from an initial disparity guess; ~0.5 ms for 300 points.
* :func:`row_disparity` searches each left point's row over a disparity range by zero-mean
  normalised cross-correlation (blind to the cameras' gain and offset), unique peaks only.
* :class:`DenseDisparity` wraps ``cv2.StereoSGBM`` (all pixels; 6.5 ms at 320x240).
* :func:`triangulate` turns pixels + disparities into 3D points with range checks.

All points are in the rectified left camera frame (OpenCV axes), metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from estimation._row_kernel import row_match
from estimation.flow import track_klt
from estimation.lk import ImagePyramid
from flightkit.errors import EstimationError

__all__ = ["DenseDisparity", "StereoRig", "row_disparity", "sparse_disparity", "triangulate"]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class StereoRig:
    """A rectified stereo pair: common pinhole intrinsics (px) and baseline (m)."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float

    def __post_init__(self) -> None:
        if not self.baseline_m > 0:
            raise EstimationError(
                f"stereo baseline must be positive, got {self.baseline_m} m; check the calibration"
            )

    @property
    def K(self) -> F64:  # noqa: N802
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def depth_to_disparity(self, z_m: float) -> float:
        return self.fx * self.baseline_m / z_m


def sparse_disparity(
    left: npt.NDArray[np.uint8] | ImagePyramid,
    right: npt.NDArray[np.uint8] | ImagePyramid,
    pts_left: npt.NDArray[np.float32],
    init_disparity_px: npt.NDArray[np.float32] | float = 0.0,
    max_dy_px: float = 1.0,
    min_disparity_px: float = 0.5,
    max_disparity_px: float = 400.0,
    fb_max_px: float | None = 1.0,
    win_px: int = 21,
    levels: int = 3,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Disparity of left points by LK tracking into the right image along rows.

    Args:
        left, right: rectified 8-bit images, or their pyramids.
        pts_left: (N, 2) float32 left pixels.
        init_disparity_px: starting guess (N,) or scalar (a point's last disparity helps a lot
            for near objects, whose disparity exceeds the pyramid's reach).
        max_dy_px: matches that leave the row by more than this are rejected.
        fb_max_px: forward-backward check tolerance (None: rely on the row check only).

    Returns:
        ``(disparity_px, ok)``, (N,) float32 and bool.
    """
    n = len(pts_left)
    if n == 0:
        return np.empty(0, np.float32), np.zeros(0, dtype=bool)
    guess = np.array(pts_left, dtype=np.float32, copy=True)
    guess[:, 0] -= np.asarray(init_disparity_px, dtype=np.float32)
    pr, ok = track_klt(left, right, pts_left, fb_max_px=fb_max_px, win_px=win_px, levels=levels, guess=guess)
    disp = (pts_left[:, 0] - pr[:, 0]).astype(np.float32)
    ok &= np.abs(pr[:, 1] - pts_left[:, 1]) <= max_dy_px
    ok &= (disp >= min_disparity_px) & (disp <= max_disparity_px)
    return disp, ok


def row_disparity(
    left: npt.NDArray[np.uint8],
    right: npt.NDArray[np.uint8],
    pts_left: npt.NDArray[np.float32],
    min_disparity_px: npt.NDArray[np.float32] | float,
    max_disparity_px: npt.NDArray[np.float32] | float,
    win_px: int = 11,
    min_score: float = 0.8,
    max_cost_ratio: float = 0.7,
    min_std: float = 2.0,
    refine_iters: int = 3,
    refine_y: bool = True,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Disparity of left points by a search along their rows (``estimation._row_kernel``).

    Args:
        left, right: rectified 8-bit images of one size.
        pts_left: (N, 2) float32 left pixels.
        min_disparity_px, max_disparity_px: the range searched, (N,) or scalar, px; a best peak at
            either end is refused (the match may lie beyond it).
        win_px: the patch's side, px (odd).
        min_score: the best zero-mean normalised cross-correlation must reach this.
        max_cost_ratio: the best match's ``1 - score`` must be at most this share of the next
            peak's (repeated texture fails).
        min_std: patches flatter than this standard deviation (grey levels) are not matched.
        refine_iters: Gauss-Newton iterations along x with gain and bias (0: parabola only).
        refine_y: the Gauss-Newton fit may also shift the match off the row (up to 1 px).

    Returns:
        ``(disparity_px, ok)``, (N,) float32 and bool.

    Raises:
        EstimationError: the images differ in size or are not 8-bit grey.
    """
    if left.shape != right.shape or left.ndim != 2 or left.dtype != np.uint8 or right.dtype != np.uint8:
        raise EstimationError(
            f"row_disparity got images {left.shape} {left.dtype} and {right.shape} {right.dtype}; "
            "pass two rectified 8-bit grey images of one size"
        )
    pts = np.ascontiguousarray(pts_left, dtype=np.float32).reshape(-1, 2)
    n = len(pts)
    # The range within +-the image width (no match lies beyond it; an infinite bound means no limit).
    w = float(left.shape[1])
    lo = np.broadcast_to(np.clip(np.asarray(min_disparity_px, dtype=np.float32), -w, w), (n,))
    hi = np.broadcast_to(np.clip(np.asarray(max_disparity_px, dtype=np.float32), -w, w), (n,))
    disp, _, ok = row_match(
        np.ascontiguousarray(left),
        np.ascontiguousarray(right),
        pts,
        np.ascontiguousarray(lo),
        np.ascontiguousarray(hi),
        win_px // 2,
        float(min_score),
        float(max_cost_ratio),
        float(min_std),
        int(refine_iters),
        bool(refine_y),
    )
    ok &= (disp >= lo) & (disp <= hi)
    return disp, ok


def triangulate(
    pts_px: npt.ArrayLike,
    disparity_px: npt.ArrayLike,
    rig: StereoRig,
    min_depth_m: float = 0.1,
    max_depth_m: float = 80.0,
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """3D points (N, 3) in the left camera from pixels and disparities, and a validity mask
    (positive disparity, depth inside ``[min_depth_m, max_depth_m]``)."""
    p = np.asarray(pts_px, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(disparity_px, dtype=np.float64).reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = rig.fx * rig.baseline_m / d
    ok = np.isfinite(z) & (d > 0) & (z >= min_depth_m) & (z <= max_depth_m)
    z = np.where(ok, z, 1.0)
    X = np.empty((len(p), 3))
    X[:, 0] = (p[:, 0] - rig.cx) / rig.fx * z
    X[:, 1] = (p[:, 1] - rig.cy) / rig.fy * z
    X[:, 2] = z
    return X, ok


class DenseDisparity:
    """Semi-global block matching (``cv2.StereoSGBM``), disparity in pixels as float32.

    The output buffer is allocated once per image size and reused (page faults are
    expensive on small computers); the returned array is overwritten by the next call.
    """

    def __init__(self, num_disparities: int = 64, block_size: int = 5) -> None:
        nd = max(16, (num_disparities + 15) // 16 * 16)
        self._sgbm = cv2.StereoSGBM.create(
            minDisparity=0,
            numDisparities=nd,
            blockSize=block_size,
            P1=8 * block_size * block_size,
            P2=32 * block_size * block_size,
            uniquenessRatio=10,
            speckleWindowSize=50,
            speckleRange=2,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )
        self._raw: npt.NDArray[np.int16] | None = None
        self._out: npt.NDArray[np.float32] | None = None

    def compute(self, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
        """Disparity (H, W) float32, <= 0 where unknown. Returns immediately."""
        if self._raw is None or self._raw.shape != left.shape[:2]:
            self._raw = np.empty(left.shape[:2], np.int16)
            self._out = np.empty(left.shape[:2], np.float32)
        assert self._out is not None
        self._sgbm.compute(left, right, self._raw)
        np.multiply(self._raw, np.float32(1.0 / 16.0), out=self._out, casting="unsafe")
        return self._out

    @staticmethod
    def lookup(
        disparity: npt.NDArray[np.float32], pts_px: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.float32]:
        """Disparity at pixel positions (nearest pixel), NaN outside the image."""
        h, w = disparity.shape
        u = np.rint(pts_px[:, 0]).astype(np.intp)
        v = np.rint(pts_px[:, 1]).astype(np.intp)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        out = np.full(len(pts_px), np.nan, np.float32)
        out[inside] = disparity[v[inside], u[inside]]
        return out
