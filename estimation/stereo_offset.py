"""Online estimate of a stereo pair's disparity offset (px): the constant ``b`` such that the
depth is ``Z = fx B / (d + b)`` for the measured disparity ``d``.

A rectified pair whose calibration is slightly off (principal points, or a baseline a fraction
of a percent wrong seen as a shift) measures every disparity a fraction of a pixel short or
long. Near points barely notice; far ones get a depth error that grows with depth squared, and
the motion fitted to them takes a scale and shape error. ``b`` is observable from the motion:
between two frames, the depths of near and far points change consistently with one
translation only under the right ``b``. Each pair of frames gives an estimate of ``b`` jointly
with the translation (the rotation held at the estimate, which the far points pin down), with
its information; the running estimate is their information-weighted mean with a zero-mean
prior (``prior_sigma_px``), so a camera that does not translate keeps ``b = 0``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["DisparityOffset"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

_HUBER = 2.0
"""Huber threshold of the joint fit's residuals, in units of each channel's noise."""


class DisparityOffset:
    """The running disparity offset of one stereo rig.

    Args:
        fx, fy, cx, cy: the rectified camera, px.
        baseline_m: the stereo baseline, m.
        prior_sigma_px: standard deviation of the zero-mean prior on the offset, px.
        max_offset_px: the estimate is clipped to +-this, px.
        min_parallax_px: a pair is fitted once the common tracks moved this far (median, px) since
            the reference observation (0: every pair of consecutive observations).
    """

    def __init__(
        self,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        baseline_m: float,
        prior_sigma_px: float = 0.5,
        max_offset_px: float = 1.0,
        min_parallax_px: float = 0.0,
    ) -> None:
        self.fx, self.fy, self.cx, self.cy, self.fb = fx, fy, cx, cy, fx * baseline_m
        self.max_offset_px = max_offset_px
        self.min_parallax_px = min_parallax_px
        self._T_cur_ref: F64 | None = None  # the motion since the reference observation
        self._prior_info = 1.0 / prior_sigma_px**2
        self._info = self._prior_info  # information of the estimate (1/px^2)
        self._sum = 0.0  # information-weighted sum of the per-pair estimates
        self._prev: tuple[I64, F64, F64] | None = None
        self.pairs = 0

    @property
    def offset_px(self) -> float:
        """The current estimate, px."""
        b = self._sum / self._info
        return float(np.clip(b, -self.max_offset_px, self.max_offset_px))

    def forget(self) -> None:
        """The next observation starts a new pair (after a frame without measurements)."""
        self._prev = None

    def observe(self, ids: I64, und_px: F64, disparity_px: F64, T_cur_prev: F64 | None) -> None:
        """This frame's raw disparities (no offset) of the tracks ``ids`` at undistorted pixels
        ``und_px``, and the estimated motion since the previous observation (None: unknown).

        The pair (reference, this frame) is fitted once the common tracks moved ``min_parallax_px``
        (with little image motion, track noise biases the fit: docs/estimation-log.md, fourth
        pass); then this frame becomes the reference."""
        obs = (ids.copy(), und_px.copy(), disparity_px.copy())
        prev = self._prev
        if prev is None or T_cur_prev is None:
            self._prev, self._T_cur_ref = obs, np.eye(4)
            return
        assert self._T_cur_ref is not None
        T_cur_ref = T_cur_prev @ self._T_cur_ref
        common, ia, ib = np.intersect1d(prev[0], ids, assume_unique=True, return_indices=True)
        if len(common) < 20:
            self._prev, self._T_cur_ref = obs, np.eye(4)
            return
        if self.min_parallax_px > 0:
            moved = float(np.median(np.linalg.norm(und_px[ib] - prev[1][ia], axis=1)))
            if moved < self.min_parallax_px:
                self._T_cur_ref = T_cur_ref  # keep the reference, wait for more motion
                return
        self._prev, self._T_cur_ref = obs, np.eye(4)
        est = self._fit(prev[1][ia], prev[2][ia], und_px[ib], disparity_px[ib], T_cur_ref)
        # A pair that knows the offset less well than the prior (little translation) is skipped.
        if est is not None and est[1] >= self._prior_info:
            b, info = est
            self._sum += info * b
            self._info += info
            self.pairs += 1

    def _point_residuals(self, p: F64, R: F64, x0: F64, rho: F64, d0: F64, uv1: F64, d1: F64) -> F64:
        """(4, N) residuals, px: the disparity in the first frame, the position and disparity in
        the second, of points at inverse depths ``rho`` (first frame) under translation and offset ``p``."""
        t, b = p[:3], p[3]
        X0 = x0 / np.maximum(rho, 1e-6)[:, None]
        Y = X0 @ R.T + t
        z1 = np.maximum(Y[:, 2], 1e-3)
        return np.stack(
            [
                self.fb * rho - b - d0,
                self.fx * Y[:, 0] / z1 + self.cx - uv1[:, 0],
                self.fy * Y[:, 1] / z1 + self.cy - uv1[:, 1],
                self.fb / z1 - b - d1,
            ]
        )

    def _residuals(self, p: F64, R: F64, x0: F64, d0: F64, uv1: F64, d1: F64, w: F64) -> F64:
        """Every point's residuals (noise-weighted by ``w``, 4 per point) with its inverse depth
        fitted (both disparities are measurements: no error-in-variables bias)."""
        rho = np.maximum(d0 + p[3], 1e-3) / self.fb
        for _ in range(2):
            r = self._point_residuals(p, R, x0, rho, d0, uv1, d1) * w[:, None]
            h = 1e-4 * rho
            J = (self._point_residuals(p, R, x0, rho + h, d0, uv1, d1) * w[:, None] - r) / h
            rho = np.maximum(rho - np.einsum("kn,kn->n", J, r) / np.maximum(np.einsum("kn,kn->n", J, J), 1e-12), 1e-6)
        out: F64 = (self._point_residuals(p, R, x0, rho, d0, uv1, d1) * w[:, None]).ravel()
        return out

    def _fit(self, uv0: F64, d0: F64, uv1: F64, d1: F64, T_cur_prev: F64) -> tuple[float, float] | None:
        """Gauss-Newton (Huber) on the translation and the offset, each point's inverse depth
        eliminated, each channel weighted by its robust noise level; returns (offset, information)."""
        n = len(uv0)
        x0 = np.c_[(uv0[:, 0] - self.cx) / self.fx, (uv0[:, 1] - self.cy) / self.fy, np.ones(n)]
        R = T_cur_prev[:3, :3]
        p = np.r_[T_cur_prev[:3, 3], self.offset_px]
        ones = np.ones(4)
        r = self._residuals(p, R, x0, d0, uv1, d1, ones).reshape(4, n)
        # Noise of each channel (MAD; at least 0.05 px): residuals in units of it.
        s_uv = max(1.4826 * float(np.median(np.abs(r[1:3]))), 0.05)
        s_d = max(1.4826 * float(np.median(np.abs(r[[0, 3]]))), 0.05)
        w = np.array([1.0 / s_d, 1.0 / s_uv, 1.0 / s_uv, 1.0 / s_d])
        steps = np.array([1e-4, 1e-4, 1e-4, 1e-3])
        H = np.eye(4)
        r = self._residuals(p, R, x0, d0, uv1, d1, w)
        for _ in range(3):
            J = np.empty((len(r), 4))
            for k in range(4):
                dp = np.zeros(4)
                dp[k] = steps[k]
                J[:, k] = (self._residuals(p + dp, R, x0, d0, uv1, d1, w) - r) / steps[k]
            a = np.abs(r)
            hw = np.where(a <= _HUBER, 1.0, _HUBER / np.maximum(a, 1e-12))
            H = J.T @ (J * hw[:, None])
            g = J.T @ (hw * r)
            try:
                delta = -np.linalg.solve(H + 1e-9 * np.eye(4), g)
            except np.linalg.LinAlgError:
                return None
            p = p + delta
            r = self._residuals(p, R, x0, d0, uv1, d1, w)
            if abs(delta[3]) < 1e-4 and np.linalg.norm(delta[:3]) < 1e-6:
                break
        try:
            var_bb = float(np.linalg.inv(H)[3, 3])  # residuals are in units of their noise
        except np.linalg.LinAlgError:
            return None
        if not np.isfinite(p[3]) or not var_bb > 0 or abs(p[3]) > 3 * self.max_offset_px:
            return None
        return float(p[3]), 1.0 / var_bb
