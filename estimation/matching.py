"""Descriptor matching with the right norm, Lowe's ratio test and geometric constraints.

The norm always comes from the :class:`~estimation.features.Features` (Hamming for ORB,
L2 for SIFT): matching binary descriptors with L2, a classic bug, cannot happen here.

* :func:`match_descriptors`: brute-force k=2 matching, ratio test, optional mutual check.
* :func:`match_stereo_rows`: left/right matching restricted to the same image row (rectified
  stereo) and a disparity range, by a mask given to the matcher, so only row-consistent
  candidates compete in the ratio test.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from estimation.features import Features
from flightkit.errors import EstimationError

__all__ = ["match_descriptors", "match_stereo_rows"]

Index = npt.NDArray[np.intp]


def _ratio_filter(knn: object, ratio: float) -> tuple[Index, Index, npt.NDArray[np.float32]]:
    q, t, d = [], [], []
    for pair in knn:  # type: ignore[attr-defined]
        if len(pair) == 0:
            continue
        if len(pair) == 1 or pair[0].distance < ratio * pair[1].distance:
            m = pair[0]
            q.append(m.queryIdx)
            t.append(m.trainIdx)
            d.append(m.distance)
    return np.array(q, np.intp), np.array(t, np.intp), np.array(d, np.float32)


def match_descriptors(
    a: Features, b: Features, ratio: float = 0.8, mutual: bool = True
) -> tuple[Index, Index]:
    """Match ``a`` to ``b``; returns index arrays ``(ia, ib)`` of equal length.

    Args:
        a, b: features from the same kind of extractor (same norm).
        ratio: Lowe's ratio test threshold (best distance < ratio * second best).
        mutual: also require that ``a[ia]`` is the best match of ``b[ib]`` (cross check).

    Raises:
        EstimationError: the two feature sets use different norms.
    """
    if a.norm != b.norm:
        raise EstimationError(
            f"cannot match descriptors of norms {a.norm} and {b.norm}; use one extractor kind"
        )
    if len(a) < 2 or len(b) < 2:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    bf = cv2.BFMatcher(a.norm, crossCheck=False)
    ia, ib, _ = _ratio_filter(bf.knnMatch(a.descriptors, b.descriptors, k=2), ratio)
    if mutual and len(ia):
        back = bf.match(b.descriptors, a.descriptors)
        best_a = np.full(len(b), -1, np.intp)
        for m in back:
            best_a[m.queryIdx] = m.trainIdx
        keep = best_a[ib] == ia
        ia, ib = ia[keep], ib[keep]
    return ia, ib


def match_stereo_rows(
    left: Features,
    right: Features,
    max_dy_px: float = 1.5,
    min_disparity_px: float = 0.5,
    max_disparity_px: float = 256.0,
    ratio: float = 0.8,
) -> tuple[Index, Index, npt.NDArray[np.float32]]:
    """Row-consistent matches between rectified left and right features.

    Candidates must lie within ``max_dy_px`` rows and have a disparity ``xl - xr`` in
    ``[min_disparity_px, max_disparity_px]``; the ratio test is applied among those only.

    Returns:
        ``(il, ir, disparity_px)``; disparities are float32.
    """
    if left.norm != right.norm:
        raise EstimationError(
            f"cannot match descriptors of norms {left.norm} and {right.norm}; use one extractor kind"
        )
    if len(left) == 0 or len(right) == 0:
        return np.empty(0, np.intp), np.empty(0, np.intp), np.empty(0, np.float32)
    pl, pr = left.pts_px, right.pts_px
    dy = np.abs(pl[:, None, 1] - pr[None, :, 1])
    disp = pl[:, None, 0] - pr[None, :, 0]
    mask = ((dy <= max_dy_px) & (disp >= min_disparity_px) & (disp <= max_disparity_px)).astype(np.uint8)
    bf = cv2.BFMatcher(left.norm, crossCheck=False)
    knn = bf.knnMatch(left.descriptors, right.descriptors, k=2, mask=mask)
    il, ir, _ = _ratio_filter(knn, ratio)
    if len(il) == 0:
        return il, ir, np.empty(0, np.float32)
    # One right feature may be claimed by several left ones: keep none of those (ambiguous).
    uniq, counts = np.unique(ir, return_counts=True)
    dup = np.isin(ir, uniq[counts > 1])
    il, ir = il[~dup], ir[~dup]
    return il, ir, (pl[il, 0] - pr[ir, 0]).astype(np.float32)
