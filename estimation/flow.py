"""Optical flow: pyramidal Lucas-Kanade tracking and 6-DoF velocity from image motion.

Tracking
    :func:`track_klt` tracks points forward, then back, and keeps only those that return
    within ``fb_max_px`` of where they started (forward-backward check).

Velocity
    A static point at normalised image position (x, y) and depth Z, seen by a camera moving
    with linear velocity v and angular velocity w (both in the camera frame, OpenCV axes),
    moves in the image as ``[xdot, ydot] = L(x, y, Z) @ [v, w]`` with the interaction
    matrix::

        L = [[-1/Z,    0, x/Z,      x*y, -(1 + x*x),  y],
             [   0, -1/Z, y/Z, 1 + y*y,       -x*y, -x]]

    Three points give six equations for the six unknowns; :func:`velocity_ransac` solves
    a whole batch of 3-point samples at once and scores every hypothesis against every point in
    one compiled pass, then refits on the inliers (least squares, then Cauchy-reweighted).
    :func:`integrate_velocity` turns (v, w, dt) into the relative pose, and
    :func:`polish_motion` makes it exact (the interaction matrix is a first-order model).

    Depth comes from a depth image per point, or, for a camera looking at the ground, from
    the stereo altitude ``Z = f * B / d`` (:func:`stereo_altitude_m`, median over the best
    row-consistent ORB matches).
"""

from __future__ import annotations

import logging
import math
from typing import Any, cast

import cv2
import numpy as np
import numpy.typing as npt

from estimation import _kernels
from estimation.features import DescriptorExtractor
from estimation.lk import ImagePyramid, lk_track, pyramid_of
from estimation.matching import match_stereo_rows
from estimation.motion import invert, make_T
from estimation.pnp import refine_pose

__all__ = [
    "integrate_velocity",
    "interaction_matrix",
    "polish_motion",
    "stereo_altitude_m",
    "track_klt",
    "velocity_lstsq",
    "velocity_ransac",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
Image = npt.NDArray[np.uint8]


def track_klt(
    prev: Image | ImagePyramid,
    cur: Image | ImagePyramid,
    pts_prev: npt.NDArray[np.float32],
    fb_max_px: float | None = 1.0,
    win_px: int = 21,
    levels: int = 3,
    guess: npt.NDArray[np.float32] | None = None,
    back_levels: int | None = None,
    max_iters: int = 20,
    trust_guess_px: float | npt.NDArray[np.float64] = 0.0,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Track points from ``prev`` to ``cur`` with a forward-backward consistency check.

    Args:
        prev, cur: 8-bit images, or their pyramids (:class:`ImagePyramid`, built once per image
            and shared by every track from or into it; an image's is built here).
        pts_prev: (N, 2) float32 positions in ``prev``.
        fb_max_px: a track is kept when tracking it back lands within this distance; None
            skips the backward pass (half the cost; for callers with their own check).
        guess: (N, 2) predicted positions in ``cur`` (e.g. from a motion prior), or None.
        back_levels: pyramid levels of the backward pass (None: ``levels``). It starts at the
            point's old position, so a correct track returns at once and a wrong one does not.
        max_iters: LK iterations per level at most (it also stops on a 0.03 px step).
        trust_guess_px: with ``guess``, a track that ends within this distance of its guess is
            kept without the backward pass (the guess is evidence of its own); only the others
            are tracked back (0: all are). A scalar or one value per point.

    Returns:
        ``(pts_cur, ok)``: (N, 2) float32 positions and (N,) bool validity.
    """
    n = len(pts_prev)
    if n == 0:
        return np.empty((0, 2), np.float32), np.zeros(0, dtype=bool)
    back = levels if back_levels is None else back_levels
    prev_pyr = pyramid_of(prev, max(levels, back), win_px)
    cur_pyr = pyramid_of(cur, max(levels, back), win_px)
    p0 = np.ascontiguousarray(pts_prev, dtype=np.float32).reshape(-1, 2)
    p1, ok = lk_track(prev_pyr, cur_pyr, p0, guess, levels, win_px, max_iters)
    if fb_max_px is None:
        return p1, ok
    check = ok
    trust = np.asarray(trust_guess_px, dtype=np.float64)
    if guess is not None and np.any(trust > 0):
        dg = p1 - np.asarray(guess, dtype=np.float32).reshape(-1, 2)
        check = ok & (np.einsum("ni,ni->n", dg, dg) >= trust * trust)
    sel = np.flatnonzero(check)
    if len(sel) == 0:
        return p1, ok
    p0s = p0[sel]
    p0b, st2 = lk_track(cur_pyr, prev_pyr, p1[sel], p0s, back, win_px, max_iters)
    fb = np.einsum("ni,ni->n", p0b - p0s, p0b - p0s)
    ok[sel] = st2 & (fb < fb_max_px * fb_max_px)
    return p1, ok


def interaction_matrix(x: F64, y: F64, Z: F64 | float) -> F64:
    """Stacked interaction matrices, shape (N, 2, 6), for normalised points (x, y) at depth Z."""
    n = len(x)
    inv_z = np.broadcast_to(1.0 / np.asarray(Z, dtype=np.float64), (n,))
    L = np.zeros((n, 2, 6))
    L[:, 0, 0] = -inv_z
    L[:, 0, 2] = x * inv_z
    L[:, 0, 3] = x * y
    L[:, 0, 4] = -(1.0 + x * x)
    L[:, 0, 5] = y
    L[:, 1, 1] = -inv_z
    L[:, 1, 2] = y * inv_z
    L[:, 1, 3] = 1.0 + y * y
    L[:, 1, 4] = -x * y
    L[:, 1, 5] = -x
    return L


def velocity_lstsq(L: F64, flow: F64) -> F64:
    """Least-squares twist ``[v, w]`` (6,) from interaction matrices (N, 2, 6) and flow (N, 2)."""
    A = L.reshape(-1, 6)
    b = flow.reshape(-1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    return np.asarray(sol, dtype=np.float64)


def velocity_ransac(
    xn_prev: F64,
    xn_cur: F64,
    Z: F64 | float,
    dt_s: float,
    threshold: float,
    max_iters: int = 200,
    confidence: float = 0.999,
    rng: np.random.Generator | None = None,
    batch: int = 128,
    robust_iters: int = 0,
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Camera twist from normalised point motion with a vectorised 3-point RANSAC.

    Args:
        xn_prev, xn_cur: (N, 2) normalised image coordinates ``K^-1 [u, v, 1]`` of the same
            points in the previous and current image.
        Z: depths (N,) or one depth for all (a camera above flat ground), metres.
        dt_s: time between the images.
        threshold: inlier threshold on the flow error in normalised units per second
            (pixels / f / dt).
        robust_iters: after the least-squares refit on the inliers, this many reweighted
            refits (Cauchy weights ``1 / (1 + (e / s)^2)`` with ``s = threshold / 2``): tracks
            whose flow disagrees by a sizeable fraction of the threshold count less than those
            that agree, instead of all inliers counting fully (0: off).

    Returns:
        ``(twist, inliers)``: twist (6,) = linear velocity (m/s) then angular velocity
        (rad/s), both in the camera frame; inliers (N,) bool. A zero twist and no inliers
        when fewer than 3 points are usable.
    """
    from estimation.motion import ransac_iterations

    n = len(xn_prev)
    if n < 3 or dt_s <= 0:
        return np.zeros(6), np.zeros(n, dtype=bool)
    mid = 0.5 * (xn_prev + xn_cur)
    flow = (xn_cur - xn_prev) / dt_s
    L = interaction_matrix(mid[:, 0], mid[:, 1], Z)
    rng = rng if rng is not None else np.random.default_rng(0)
    thr2 = threshold * threshold
    best_count, best_mask = -1, np.zeros(n, dtype=bool)
    needed, drawn = max_iters, 0
    A_all = np.ascontiguousarray(L.reshape(n, 2, 6))
    flow_c = np.ascontiguousarray(flow)
    while drawn < needed:
        k = min(batch, needed - drawn)
        idx = np.stack([rng.choice(n, 3, replace=False) for _ in range(k)]) if n < 8 else rng.integers(0, n, (k, 3))
        # Each hypothesis solved (normal equations, 1e-9 ridge) and scored against every
        # track in one compiled loop; the batch's first best.
        _, count, inl = _kernels.flow_hypotheses(A_all, flow_c, idx.astype(np.int64), 1e-9, thr2)
        if count > best_count:
            best_count, best_mask = int(count), inl
            needed = ransac_iterations(best_count / n, 3, confidence, max_iters)
        drawn += k
    # Least-squares refit on the inliers, then reweighted refits (or a second plain one),
    # in one compiled call.
    ok, twist, e2 = _kernels.flow_refit(A_all, flow_c, best_mask, thr2, int(robust_iters))
    if not ok:
        return np.zeros(6), np.zeros(n, dtype=bool)
    return twist, e2 < thr2


def integrate_velocity(twist: F64, dt_s: float) -> F64:
    """Relative pose ``T_prev_cur`` (4x4) of a camera moving with ``twist`` for ``dt_s``.

    The twist's linear part is applied along the mid-interval attitude (second order).
    """
    v, w = twist[:3], twist[3:]
    R = cv2.Rodrigues(w * dt_s)[0]
    R_half = cv2.Rodrigues(0.5 * w * dt_s)[0]
    return make_T(R, R_half @ (v * dt_s))


def polish_motion(T_ref_cur: F64, xn_ref: F64, z_ref_m: F64, xn_cur: F64, huber: float) -> F64:
    """The exact motion behind a velocity estimate: Gauss-Newton on the reprojection of the
    reference points (normalised coordinates ``xn_ref`` at depths ``z_ref_m``) into the
    current image (``xn_cur``), started from ``T_ref_cur`` (the integrated velocity).

    The interaction matrix is the image motion's first-order model; over an interval of
    several frames (a reference held while the points move ``flow_ref_px``) it errs by a
    fraction of a percent of the motion, the same sign frame after frame, and that drifts.
    The reprojection is exact for any motion. ``huber``: Huber threshold, normalised units
    (pixels / focal length). Returns ``T_ref_cur`` (4x4), the input when fewer than 4 points.
    """
    X_ref = np.c_[xn_ref * z_ref_m[:, None], z_ref_m]
    return invert(refine_pose(invert(T_ref_cur), X_ref, xn_cur, np.eye(3), huber_px=huber))


def _bytes(descriptors: npt.NDArray[np.integer[Any] | np.floating[Any]]) -> npt.NDArray[np.uint8]:
    """Binary (Hamming-norm) descriptors as the uint8 array they are."""
    return cast("npt.NDArray[np.uint8]", descriptors)


def stereo_altitude_m(
    left: npt.NDArray[np.uint8],
    right: npt.NDArray[np.uint8],
    fx_px: float,
    baseline_m: float,
    extractor: DescriptorExtractor | None = None,
    best_fraction: float = 0.5,
    max_dy_px: float = 1.5,
) -> tuple[float, int]:
    """Distance to the scene in front of a rectified stereo pair, ``Z = f * B / d``.

    ORB features are matched along rows (:func:`~estimation.matching.match_stereo_rows`),
    the ``best_fraction`` of matches by descriptor distance is kept, and the median
    disparity gives Z. Meant for a camera looking down at roughly flat ground.

    Returns:
        ``(Z_m, n_matches)``; ``Z_m`` is NaN when fewer than 5 matches survive.
    """
    ex = extractor if extractor is not None else DescriptorExtractor("orb", 500)
    fl = ex.extract(left)
    fr = ex.extract(right)
    il, ir, disp = match_stereo_rows(fl, fr, max_dy_px=max_dy_px)
    if len(il) < 5:
        return math.nan, len(il)
    dist = (
        np.count_nonzero(np.unpackbits(_bytes(fl.descriptors)[il] ^ _bytes(fr.descriptors)[ir], axis=1), axis=1)
        if fl.norm == cv2.NORM_HAMMING
        else np.linalg.norm(fl.descriptors[il].astype(np.float32) - fr.descriptors[ir].astype(np.float32), axis=1)
    )
    keep = np.argsort(dist, kind="stable")[: max(5, int(len(il) * best_fraction))]
    d = float(np.median(disp[keep]))
    if d <= 0:
        return math.nan, len(keep)
    return fx_px * baseline_m / d, len(keep)
