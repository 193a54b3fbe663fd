"""Descriptor matching with the right norm, Lowe's ratio test and geometric constraints.

The norm always comes from the :class:`~estimation.features.Features` (Hamming for ORB,
L2 for SIFT): matching binary descriptors with L2, a classic bug, cannot happen here.

* :func:`match_descriptors`: brute-force k=2 matching, ratio test, optional mutual check.
* :func:`match_stereo_rows`: left/right matching restricted to the same image row (rectified
  stereo) and a disparity range, so only row-consistent candidates compete in the ratio test.
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
    ``[min_disparity_px, max_disparity_px]``; the ratio test is applied among those only (a
    feature with one candidate keeps it). Only the candidates in each left feature's row band
    are compared (the right features sorted by row), not every pair: for ORB-1000 at 320x240
    on EuRoC, ~27 candidates each instead of ~780, 2.0 instead of 9.3 ms (no N x M arrays).

    Returns:
        ``(il, ir, disparity_px)``, ascending in ``il``; disparities are float32.
    """
    if left.norm != right.norm:
        raise EstimationError(
            f"cannot match descriptors of norms {left.norm} and {right.norm}; use one extractor kind"
        )
    empty = np.empty(0, np.intp), np.empty(0, np.intp), np.empty(0, np.float32)
    if len(left) == 0 or len(right) == 0:
        return empty
    pl, pr = left.pts_px, right.pts_px
    # Candidate pairs: the right features whose row lies in each left feature's band (a hair
    # wider than the test below, which is the exact one, in the points' own precision).
    order = np.argsort(pr[:, 1], kind="stable")
    y_sorted = pr[order, 1].astype(np.float64)
    band = float(max_dy_px) + 1e-3
    lo = np.searchsorted(y_sorted, pl[:, 1] - band, side="left")
    hi = np.searchsorted(y_sorted, pl[:, 1] + band, side="right")
    counts = hi - lo
    n_pairs = int(counts.sum())
    if n_pairs == 0:
        return empty
    q = np.repeat(np.arange(len(pl)), counts)
    t = order[np.arange(n_pairs) - np.repeat(np.cumsum(counts) - counts - lo, counts)]
    dy = np.abs(pl[q, 1] - pr[t, 1])
    disp = pl[q, 0] - pr[t, 0]
    ok = (dy <= max_dy_px) & (disp >= min_disparity_px) & (disp <= max_disparity_px)
    q, t = q[ok], t[ok]
    if len(q) == 0:
        return empty
    if left.norm == cv2.NORM_HAMMING and left.descriptors.shape[1] % 8 == 0:
        # Hamming distance: XOR 8 bytes at a time, count the set bits.
        dl = np.ascontiguousarray(left.descriptors).view(np.uint64)
        dr = np.ascontiguousarray(right.descriptors).view(np.uint64)
        dist = np.bitwise_count(dl[q] ^ dr[t]).sum(axis=1, dtype=np.int64).astype(np.float64)
    elif left.norm == cv2.NORM_HAMMING:
        x = left.descriptors[q] ^ right.descriptors[t]
        dist = np.bitwise_count(x).sum(axis=1, dtype=np.int64).astype(np.float64)
    else:
        diff = left.descriptors[q].astype(np.float32) - right.descriptors[t].astype(np.float32)
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff, dtype=np.float64))
    # Per left feature (q is grouped): the best candidate, and the second best distance (the
    # ratio test's reference; a tie for the best fails the test whichever of the two is "best").
    starts = np.flatnonzero(np.r_[True, q[1:] != q[:-1]])
    sizes = np.diff(np.r_[starts, len(q)])
    best = np.minimum.reduceat(dist, starts)
    at_best = np.flatnonzero(dist == np.repeat(best, sizes))
    group = np.repeat(np.arange(len(starts)), sizes)[at_best]
    first = at_best[np.r_[True, group[1:] != group[:-1]]]
    rest = dist.copy()
    rest[first] = np.inf
    second = np.minimum.reduceat(rest, starts)
    keep = (sizes == 1) | (best < ratio * second)
    il, ir = q[first[keep]], t[first[keep]]
    if len(il) == 0:
        return empty
    # One right feature may be claimed by several left ones: keep none of those (ambiguous).
    uniq, n_claims = np.unique(ir, return_counts=True)
    dup = np.isin(ir, uniq[n_claims > 1])
    il, ir = il[~dup], ir[~dup]
    return il.astype(np.intp), ir.astype(np.intp), (pl[il, 0] - pr[ir, 0]).astype(np.float32)
