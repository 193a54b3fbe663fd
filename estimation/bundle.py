"""Local bundle adjustment: refine the last few keyframe poses and the points they see.

Minimises the robust (soft-L1: a smooth Huber) reprojection error of every observation over
camera poses and 3D points with ``scipy.optimize.least_squares`` (trust-region reflective) and a sparse
Jacobian pattern: each residual pair depends on one camera's six parameters and one
point's three, so the normal equations stay sparse and a window of 5 keyframes x 300
points solves in tens of milliseconds.

Parametrisation: camera ``c`` is ``T_cam_world`` as (rotation vector, translation); the
first ``n_fixed`` cameras are held fixed (they anchor the gauge: position, orientation and,
for stereo/RGB-D points, the scale already fixed by depth).
"""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from estimation.motion import invert
from flightkit.errors import EstimationError

__all__ = ["bundle_adjust", "rotate_rotvec"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]


def rotate_rotvec(points: F64, rotvecs: F64) -> F64:
    """Rotate points (N, 3) by rotation vectors (N, 3) (Rodrigues' formula, vectorised)."""
    theta: F64 = np.linalg.norm(rotvecs, axis=1)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        k: F64 = np.where(theta > 1e-12, rotvecs / theta, 0.0)
    cos, sin = np.cos(theta), np.sin(theta)
    dot: F64 = np.sum(points * k, axis=1)[:, None]
    return cos * points + sin * np.cross(k, points) + dot * (1.0 - cos) * k


def bundle_adjust(
    T_world_cams: F64,
    points_world: F64,
    cam_idx: npt.NDArray[np.intp],
    pt_idx: npt.NDArray[np.intp],
    uv_px: F64,
    K: F64,
    n_fixed: int = 1,
    loss_scale_px: float = 1.5,
    max_nfev: int = 30,
    disparity_px: F64 | None = None,
    baseline_m: float = 0.1,
) -> tuple[F64, F64] | None:
    """Refine camera poses and points by robust reprojection error.

    Args:
        T_world_cams: (C, 4, 4) camera poses in the world.
        points_world: (P, 3) point positions.
        cam_idx, pt_idx: (n_obs,) observation -> camera, point.
        uv_px: (n_obs, 2) observed (undistorted) pixels.
        K: (3, 3) intrinsics.
        n_fixed: the first cameras held fixed (>= 1).
        loss_scale_px: the robust loss's scale (pixels): residuals beyond it count about linearly.
        max_nfev: cap on function evaluations.
        disparity_px: (n_obs,) measured disparity of each observation (stereo, or depth
            expressed as ``fx * baseline_m / z``), NaN where unknown. Adds a third residual
            per observation, ``fx * B / z_predicted - disparity``, which holds the metric
            scale (without it a window of two-view points lets the scale drift).
        baseline_m: the (real or virtual) baseline B of ``disparity_px``.

    Returns:
        ``(T_world_cams, points_world)`` refined, or None when the problem is too small or
        the solver failed (the inputs are then best kept). Blocks for the solve.

    Raises:
        EstimationError: inconsistent array shapes.
    """
    C, P, n_obs = len(T_world_cams), len(points_world), len(cam_idx)  # noqa: N806
    if len(pt_idx) != n_obs or uv_px.shape != (n_obs, 2):
        raise EstimationError(
            f"bundle_adjust got {n_obs} camera indices, {len(pt_idx)} point indices and uv of shape "
            f"{uv_px.shape}; pass one camera index, point index and pixel per observation"
        )
    n_fixed = max(1, n_fixed)
    n_free = C - n_fixed
    if n_free < 1 or P < 3 or 2 * n_obs < 6 * n_free + 3 * P + 10:
        return None
    T_cw = np.stack([invert(T) for T in T_world_cams])
    rv0 = Rotation.from_matrix(T_cw[:, :3, :3]).as_rotvec()
    t0 = T_cw[:, :3, 3]
    x0 = np.concatenate([np.c_[rv0[n_fixed:], t0[n_fixed:]].ravel(), points_world.ravel()])
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    free_obs = cam_idx >= n_fixed

    def unpack(x: F64) -> tuple[F64, F64, F64]:
        cams = x[: 6 * n_free].reshape(n_free, 6)
        rv = np.concatenate([rv0[:n_fixed], cams[:, :3]])
        tt = np.concatenate([t0[:n_fixed], cams[:, 3:]])
        return rv, tt, x[6 * n_free :].reshape(P, 3)

    has_d = np.zeros(n_obs, dtype=bool) if disparity_px is None else np.isfinite(disparity_px)
    d_obs = np.flatnonzero(has_d)
    d_meas = np.zeros(0) if disparity_px is None else disparity_px[d_obs]
    fb = fx * baseline_m

    def residuals(x: F64) -> F64:
        rv, tt, pts = unpack(x)
        Xc = rotate_rotvec(pts[pt_idx], rv[cam_idx]) + tt[cam_idx]
        z = np.maximum(Xc[:, 2], 1e-6)
        r = np.empty(2 * n_obs + len(d_obs))
        r[0 : 2 * n_obs : 2] = fx * Xc[:, 0] / z + cx - uv_px[:, 0]
        r[1 : 2 * n_obs : 2] = fy * Xc[:, 1] / z + cy - uv_px[:, 1]
        r[2 * n_obs :] = fb / z[d_obs] - d_meas
        return r

    # Sparsity: residual rows -> (point columns, free camera columns).
    rows_l: list[npt.NDArray[np.intp]] = []
    cols_l: list[npt.NDArray[np.intp]] = []
    obs_rows = [2 * np.arange(n_obs), 2 * np.arange(n_obs) + 1]
    obs_sel = [np.arange(n_obs), np.arange(n_obs)]
    obs_rows.append(2 * n_obs + np.arange(len(d_obs)))
    obs_sel.append(d_obs)
    for r_idx, o_idx in zip(obs_rows, obs_sel, strict=True):
        for j in range(3):
            rows_l.append(r_idx)
            cols_l.append(6 * n_free + 3 * pt_idx[o_idx] + j)
        fo = free_obs[o_idx]
        for j in range(6):
            rows_l.append(r_idx[fo])
            cols_l.append(6 * (cam_idx[o_idx][fo] - n_fixed) + j)
    rr, cc = np.concatenate(rows_l), np.concatenate(cols_l)
    A = coo_matrix((np.ones(len(rr), np.int8), (rr, cc)), shape=(2 * n_obs + len(d_obs), len(x0))).tocsr()
    try:
        sol = least_squares(
            residuals,
            x0,
            jac_sparsity=A,
            method="trf",
            # Soft-L1, not Huber: with Huber the solver stopped far from the optimum
            # (docs/estimation-log.md, "LK windows at native resolution", local BA).
            loss="soft_l1",
            f_scale=loss_scale_px,
            x_scale="jac",
            max_nfev=max_nfev,
            xtol=1e-8,
            ftol=1e-8,
        )
    except (ValueError, np.linalg.LinAlgError) as exc:
        logger.debug("bundle adjustment failed: %s", exc)
        return None
    if not np.all(np.isfinite(sol.x)):
        return None
    rv, tt, pts = unpack(sol.x)
    out = np.empty_like(T_world_cams)
    Rm = Rotation.from_rotvec(rv).as_matrix()
    for c in range(C):
        T = np.eye(4)
        T[:3, :3] = Rm[c]
        T[:3, 3] = tt[c]
        out[c] = invert(T)
    out[:n_fixed] = T_world_cams[:n_fixed]
    return out, pts
