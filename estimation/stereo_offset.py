"""Online estimate of a stereo pair's disparity offset (px): the constant ``b`` such that the
depth is ``Z = fx B / (d + b)`` for the measured disparity ``d``.

A rectified pair whose calibration is slightly off (principal points, or a baseline a fraction
of a percent wrong seen as a shift) measures every disparity a fraction of a pixel short or
long. Near points barely notice; far ones get a depth error that grows with depth squared, and
the motion fitted to them takes a scale and shape error. ``b`` is observable from the motion:
image motion is proportional to inverse depth ``(d + b) / (f B)``, so across near and far points
its intercept in ``d`` gives ``b``. Each pair of frames (rotation held at the estimate, which the
far points pin down) is one linear fit of the translation ``t`` and ``c = b t``; the pairs' moments
of ``b``, corrected for the noise of ``t`` and ``c``, are summed with a zero-mean prior
(``prior_sigma_px``). Pairs whose translation cannot show the offset (a camera at rest) and
ill-conditioned fits (a planar scene; a fit claiming more than the clip alone, which truncates
one tail: an offset near the clip would read low) are skipped (docs/estimation-log.md, fifth
and eleventh passes).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from estimation._offset_kernel import offset_pair_moments

__all__ = ["DisparityOffset"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

_HUBER = 2.0
"""Huber threshold of the pair fit's residuals, in units of their robust (MAD) noise."""


class DisparityOffset:
    """The running disparity offset of one stereo rig.

    Args:
        fx, fy, cx, cy: the rectified camera, px.
        baseline_m: the stereo baseline, m.
        track_sigma_px: the tracks' noise, px: a pair whose translation changes its tracks' image
            motion by less than this per pixel of offset (over all its tracks) is skipped.
        prior_sigma_px: standard deviation of the zero-mean prior on the offset, px.
        max_offset_px: the estimate is clipped to +-this, px; a pair fit that alone claims more is skipped.
    """

    def __init__(
        self,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        baseline_m: float,
        track_sigma_px: float,
        prior_sigma_px: float = 0.5,
        max_offset_px: float = 1.0,
    ) -> None:
        self.fx, self.fy, self.cx, self.cy, self.fb = fx, fy, cx, cy, fx * baseline_m
        self.max_offset_px = max_offset_px
        self.track_sigma_px = track_sigma_px
        self._prior_info = 1.0 / prior_sigma_px**2
        self._num = 0.0  # sum over pairs of t' M c (bias-corrected): b x the information
        self._den = 0.0  # sum over pairs of t' M t (bias-corrected): the information (1/px^2)
        self._prev: tuple[I64, F64, F64] | None = None
        self.pairs = 0

    @property
    def offset_px(self) -> float:
        """The current estimate, px."""
        b = self._num / (max(self._den, 0.0) + self._prior_info)
        return float(np.clip(b, -self.max_offset_px, self.max_offset_px))

    @property
    def waiting(self) -> bool:
        """No observation waits for its pair (the start, or after :meth:`forget`)."""
        return self._prev is None

    def forget(self) -> None:
        """The next observation starts a new pair (after a frame without measurements)."""
        self._prev = None

    def observe(self, ids: I64, und_px: F64, disparity_px: F64, T_cur_prev: F64 | None) -> None:
        """This frame's raw disparities (no offset) of the tracks ``ids`` at undistorted pixels
        ``und_px``, and the estimated motion since the previous observation (None: unknown); the
        pair (previous, this frame) is fitted."""
        obs = (ids.copy(), und_px.copy(), disparity_px.copy())
        prev, self._prev = self._prev, obs
        if prev is None or T_cur_prev is None:
            return
        common, ia, ib = np.intersect1d(prev[0], ids, assume_unique=True, return_indices=True)
        if len(common) < 20:
            return
        moments = self._fit(prev[1][ia], prev[2][ia], und_px[ib], T_cur_prev)
        # A pair that claims no information, or an offset beyond the clip on its own, is noise of an
        # ill-conditioned fit (a planar scene: every track at one depth), not a measurement.
        if moments is not None and moments[1] > 0 and abs(moments[0]) <= self.max_offset_px * moments[1]:
            self._num += moments[0]
            self._den += moments[1]
            self.pairs += 1

    def _fit(self, uv0: F64, d0: F64, uv1: F64, T_cur_ref: F64) -> tuple[float, float] | None:
        """One pair's moments of the offset: (t' M c - E[noise], t' M t - E[noise]) from the linear
        fit of ``t`` and ``c = b t`` (``M``: the information of ``c``), each unbiased in expectation."""
        n = len(uv0)
        R, t_prior = T_cur_ref[:3, :3], T_cur_ref[:3, 3]
        # A 1 px offset moves a track's image motion by |t| / B px (its translational flow over its
        # disparity): below the tracks' noise over all n tracks the pair cannot see the offset, and
        # its fit would turn any unmodelled common image motion (a camera at rest) into one.
        if np.linalg.norm(t_prior) * self.fx / self.fb * np.sqrt(n) < self.track_sigma_px:
            return None
        num, den, ok = offset_pair_moments(
            np.ascontiguousarray(uv0, dtype=np.float64),
            np.ascontiguousarray(d0, dtype=np.float64),
            np.ascontiguousarray(uv1, dtype=np.float64),
            np.ascontiguousarray(R, dtype=np.float64),
            np.ascontiguousarray(t_prior, dtype=np.float64),
            np.array((self.fx, self.fy, self.cx, self.cy), dtype=np.float64),
            self.fb,
            self.offset_px,
            _HUBER,
        )
        return (num, den) if ok else None
