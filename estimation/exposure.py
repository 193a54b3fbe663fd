"""Exposure changes between consecutive images, measured and undone before tracking.

A camera's automatic exposure scales every pixel of a frame by about the same gain. LK
tracking minimises intensity differences, so a gain change between two frames pulls every
track along its intensity gradient (the patch is matched where the brightness agrees) and
fails the forward-backward check on many others.

:func:`exposure_gain` measures the gain at the tracked points: the brightness of the image
around each point (the mean over a cell, from an area-averaged image) in the previous frame
and around its predicted position in the current one. The log-ratios' median is the gain; it
is returned only when it is significant against the ratios' own spread (more than
``z_min`` standard errors of the median from 1), so scene changes and prediction errors on a
steady exposure leave the images untouched. :func:`match_exposure` then scales the brighter
of the two images down to the other, which saturates nothing.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["exposure_gain", "match_exposure"]

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]

_MIN_POINTS = 20
"""Fewer usable points than this: no measurement (gain 1)."""

_DARK, _BRIGHT = 10.0, 245.0
"""Cell means outside (_DARK, _BRIGHT) are left out: near black or saturated, they do not scale."""

_SE_OF_MEDIAN = 1.2533 * 1.4826
"""Standard error of a median of n Gaussian samples is this times their MAD over sqrt(n)."""


def _cell_means(image: U8, cell_px: int) -> F32:
    h, w = image.shape[:2]
    size = (max(1, w // cell_px), max(1, h // cell_px))
    return np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), dtype=np.float32)


def _sample(means: F32, px: F32, cell_px: int) -> npt.NDArray[np.float64]:
    q = (np.asarray(px, np.float32) / cell_px - 0.5).reshape(-1, 1, 2)
    out = cv2.remap(means, q[:, :, 0], q[:, :, 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(out, dtype=np.float64).ravel()


def exposure_gain(prev: U8, cur: U8, px_prev: F32, px_cur: F32, cell_px: int, z_min: float = 3.0) -> float:
    """The exposure gain from ``prev`` to ``cur`` (``cur ~ gain * prev``), or exactly 1.0 when it is
    not measurable or not significant.

    Args:
        prev, cur: consecutive 8-bit images.
        px_prev: (N, 2) tracked points in ``prev``; px_cur: where they are expected in ``cur``
            (a prediction is enough: the brightness is averaged over cells of ``cell_px``).
        z_min: significance, in standard errors of the log-ratios' median.
    """
    if len(px_prev) < _MIN_POINTS:
        return 1.0
    a = _sample(_cell_means(prev, cell_px), px_prev, cell_px)
    b = _sample(_cell_means(cur, cell_px), px_cur, cell_px)
    good = (a > _DARK) & (a < _BRIGHT) & (b > _DARK) & (b < _BRIGHT)
    n = int(np.count_nonzero(good))
    if n < _MIN_POINTS:
        return 1.0
    log_ratio = np.log(b[good] / a[good])
    med = float(np.median(log_ratio))
    se = _SE_OF_MEDIAN * float(np.median(np.abs(log_ratio - med))) / math.sqrt(n)
    return math.exp(med) if abs(med) > z_min * se else 1.0


def match_exposure(prev: U8, cur: U8, gain: float) -> tuple[U8, U8]:
    """``prev`` and ``cur`` brought to one exposure (``cur ~ gain * prev``): the brighter one scaled
    down, so nothing saturates. Returns the inputs themselves when ``gain`` is 1."""
    if gain == 1.0:
        return prev, cur
    if gain > 1.0:
        return prev, np.asarray(cv2.convertScaleAbs(cur, alpha=1.0 / gain), dtype=np.uint8)
    return np.asarray(cv2.convertScaleAbs(prev, alpha=gain), dtype=np.uint8), cur
