"""Hand-eye calibration: the camera's mount ``T_body_camera`` from paired relative motions.

The body moves by ``A = T_world_body(i)^-1 @ T_world_body(j)`` (mocap) while the camera moves by
``B = T_x_camera(i)^-1 @ T_x_camera(j)`` (VO, or a board seen by the camera; ``x`` is any
fixed frame). With ``X = T_body_camera``, ``A @ X = X @ B`` for every pair. OpenCV's
``calibrateHandEye`` is not in every build (OpenCV 5's Python binding lacks it), so it is
solved here, in closed form and then refined:

1. rotation: the rotation vectors correspond, ``rotvec(R_A) = R_X @ rotvec(R_B)``; ``R_X`` is
   their Kabsch (SVD) fit;
2. translation: ``(R_A - I) t_X = R_X t_B - t_A``, linear least squares;
3. pairs with more than 5x the median residual of 1-2 are left out (VO resets) and 1-2 redone;
4. both together by nonlinear least squares on the residuals of ``A X = X B`` (metres and
   radians), starting from there.

It needs rotations about two axes that are not parallel: about one axis only, the rotation is
free about that axis and the translation along it is unobservable; with no rotation, nothing is.
:func:`solve_hand_eye` refuses both with :class:`~flightkit.errors.CalibrationError`.

Pure numpy/scipy.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

from flightkit.calibration.rates import rotations_of
from flightkit.errors import CalibrationError
from flightkit.frames import Transform

__all__ = ["HandEyeEstimate", "TimedPoses", "estimate_hand_eye", "motion_pairs", "solve_hand_eye"]

_NS = 1_000_000_000


class TimedPoses(Protocol):
    """Stamped poses, e.g. :class:`flightkit.datasets.trajectory.Trajectory`: ``stamps_ns`` (N,),
    ``positions`` (N, 3) metres, ``quats_wxyz`` (N, 4)."""

    @property
    def stamps_ns(self) -> npt.NDArray[np.int64]: ...

    @property
    def positions(self) -> npt.NDArray[np.float64]: ...

    @property
    def quats_wxyz(self) -> npt.NDArray[np.float64]: ...


@dataclass(frozen=True, slots=True)
class HandEyeEstimate:
    """The estimated camera mount and how well it explains the motions.

    Attributes:
        T_body_camera: camera (OpenCV) in the body (FLU).
        residual_m: RMS translation residual of ``A X = X B`` over the pairs, metres.
        residual_deg: RMS rotation residual, degrees.
        pairs: relative motions used.
        axis_spread: how far the rotation axes are from parallel, 0 (one axis) to 1 (all
            directions): the second singular value of the angle-weighted axes over the first.
        rotation_deg: median rotation angle of the pairs, degrees.
        outliers: pairs left out because the closed-form solution could not explain them
            (more than 5x the median residual: a VO reset, a tracking swap).
    """

    T_body_camera: Transform
    residual_m: float
    residual_deg: float
    pairs: int
    axis_spread: float
    rotation_deg: float
    outliers: int = 0


def _excitation(rotvecs_a: npt.NDArray[np.float64], min_angle_rad: float) -> tuple[npt.NDArray[np.bool_], float, float]:
    angles = np.linalg.norm(rotvecs_a, axis=1)
    big = angles >= min_angle_rad
    if big.sum() < 3:
        return big, 0.0, float(np.degrees(np.median(angles))) if angles.size else 0.0
    s = np.linalg.svd(rotvecs_a[big], compute_uv=False)
    return big, float(s[1] / s[0]) if s[0] > 0 else 0.0, float(np.degrees(np.median(angles)))


def solve_hand_eye(
    body_motions: Sequence[Transform],
    camera_motions: Sequence[Transform],
    *,
    min_angle_deg: float = 2.0,
    min_axis_spread: float = 0.1,
    refine: bool = True,
) -> HandEyeEstimate:
    """Solve ``A X = X B`` for ``X = T_body_camera``.

    Args:
        body_motions: ``A_k``, the body's relative motions (in the body frame of the first pose).
        camera_motions: ``B_k``, the camera's over the same intervals (metric translation).
        min_angle_deg: pairs rotating less than this do not count towards the excitation.
        min_axis_spread: the smallest :attr:`HandEyeEstimate.axis_spread` accepted.
        refine: run the nonlinear refinement after the closed form.

    Raises:
        CalibrationError: different counts, too little rotation, or rotation about one axis only.
    """
    if len(body_motions) != len(camera_motions):
        raise CalibrationError(
            f"{len(body_motions)} body motions but {len(camera_motions)} camera motions; pair them one to one",
            "T_body_camera",
        )
    n = len(body_motions)
    if n < 3:
        raise CalibrationError(f"{n} motion pairs are too few for hand-eye; record a longer motion", "T_body_camera")
    ra = Rotation.concatenate([m.rotation for m in body_motions])
    rb = Rotation.concatenate([m.rotation for m in camera_motions])
    ta = np.array([m.translation for m in body_motions])
    tb = np.array([m.translation for m in camera_motions])
    va, vb = ra.as_rotvec(), rb.as_rotvec()
    big, spread, median_deg = _excitation(va, math.radians(min_angle_deg))
    if big.sum() < 3:
        raise CalibrationError(
            f"too little rotation to tell: only {int(big.sum())} of {n} motions turn the body by "
            f"{min_angle_deg:g} degrees or more (median {median_deg:.2f} deg); T_body_camera needs rotation: "
            "rotate the body about at least two axes (roll and pitch swings of 20-40 degrees as well as yaw)",
            "T_body_camera",
        )
    if spread < min_axis_spread:
        raise CalibrationError(
            f"the body rotated about one axis only (axis spread {spread:.3f}, needs {min_axis_spread:g}): the "
            "camera's rotation about that axis and its offset along it cannot be told apart; "
            "rotate the body about at least two axes (roll or pitch as well as yaw)",
            "T_body_camera",
        )
    R_x, t_x = _closed_form(ra, ta, tb, va, vb, big)  # noqa: N806
    # pairs the closed form cannot explain at all (a VO reset, a mocap swap) are left out
    res_t, res_r = _residuals(ra, ta, rb, tb, R_x, t_x)
    et, er = np.linalg.norm(res_t, axis=1), np.linalg.norm(res_r, axis=1)
    keep = (et <= max(5.0 * float(np.median(et)), 1e-3)) & (er <= max(5.0 * float(np.median(er)), math.radians(0.05)))
    outliers = int(n - keep.sum())
    if outliers and keep.sum() >= 3 and (big & keep).sum() >= 3:
        ra, rb, ta, tb, va, vb, big = ra[keep], rb[keep], ta[keep], tb[keep], va[keep], vb[keep], big[keep]
        R_x, t_x = _closed_form(ra, ta, tb, va, vb, big)  # noqa: N806
    else:
        outliers = 0
    if refine:
        R_x, t_x = _refine(ra, ta, rb, tb, R_x, t_x)  # noqa: N806
    res_t, res_r = _residuals(ra, ta, rb, tb, R_x, t_x)
    return HandEyeEstimate(
        Transform(R_x, t_x),
        float(np.sqrt(np.mean(np.sum(res_t**2, axis=1)))),
        float(np.degrees(np.sqrt(np.mean(np.sum(res_r**2, axis=1))))),
        n - outliers,
        spread,
        median_deg,
        outliers,
    )


def _closed_form(
    ra: Rotation, ta: npt.NDArray[np.float64], tb: npt.NDArray[np.float64], va: npt.NDArray[np.float64],
    vb: npt.NDArray[np.float64], big: npt.NDArray[np.bool_],
) -> tuple[Rotation, npt.NDArray[np.float64]]:
    # 1. rotation: Kabsch on the rotation vectors (only pairs that turn carry direction)
    H = vb[big].T @ va[big]  # noqa: N806
    U, _, Vt = np.linalg.svd(H)  # noqa: N806
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])  # noqa: N806
    R_x = Rotation.from_matrix(Vt.T @ D @ U.T)  # noqa: N806
    # 2. translation: (R_A - I) t = R_X t_B - t_A
    return R_x, _translation(ra, ta, tb, R_x)


def _translation(
    ra: Rotation, ta: npt.NDArray[np.float64], tb: npt.NDArray[np.float64], R_x: Rotation  # noqa: N803
) -> npt.NDArray[np.float64]:
    A = (ra.as_matrix() - np.eye(3)).reshape(-1, 3)  # noqa: N806
    b = (R_x.apply(tb) - ta).reshape(-1)
    t, *_ = np.linalg.lstsq(A, b, rcond=None)
    return np.asarray(t, dtype=np.float64)


def _residuals(
    ra: Rotation, ta: npt.NDArray[np.float64], rb: Rotation, tb: npt.NDArray[np.float64], R_x: Rotation,  # noqa: N803
    t_x: npt.NDArray[np.float64],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    # A X vs X B: translation R_A t_X + t_A - (R_X t_B + t_X); rotation log((R_A R_X)^-1 R_X R_B)
    res_t = ra.apply(t_x) + ta - (R_x.apply(tb) + t_x)
    res_r = ((ra * R_x).inv() * (R_x * rb)).as_rotvec()
    return np.asarray(res_t, dtype=np.float64), np.asarray(res_r, dtype=np.float64)


def _refine(
    ra: Rotation, ta: npt.NDArray[np.float64], rb: Rotation, tb: npt.NDArray[np.float64], R_x: Rotation,  # noqa: N803
    t_x: npt.NDArray[np.float64],
) -> tuple[Rotation, npt.NDArray[np.float64]]:
    def fun(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        rt, rr = _residuals(ra, ta, rb, tb, Rotation.from_rotvec(x[:3]) * R_x, x[3:])
        return np.concatenate([rt.reshape(-1), rr.reshape(-1)])

    sol = least_squares(fun, np.concatenate([np.zeros(3), t_x]), method="lm", xtol=1e-12, ftol=1e-12)
    return Rotation.from_rotvec(sol.x[:3]) * R_x, np.asarray(sol.x[3:], dtype=np.float64)


def motion_pairs(
    body: TimedPoses,
    camera: TimedPoses,
    *,
    camera_to_body_ns: Callable[[npt.NDArray[np.int64]], npt.NDArray[np.int64]] | None = None,
    steps_s: Sequence[float] = (0.25, 0.5, 1.0),
) -> tuple[list[Transform], list[Transform]]:
    """Paired relative motions of the body and the camera over the camera's frames.

    The body's pose is interpolated (slerp, linear) at each camera frame's stamp moved onto the
    body's time base by ``camera_to_body_ns`` (e.g. ``TimeOffsetEstimate.camera_to_mocap_ns``);
    frames outside the body's span are left out. Pairs are frames ``steps_s`` apart.

    Raises:
        CalibrationError: fewer than 3 frames inside the body's span.
    """
    cam_st = np.asarray(camera.stamps_ns, dtype=np.int64)
    on_body = camera_to_body_ns(cam_st) if camera_to_body_ns is not None else cam_st
    origin = int(np.asarray(body.stamps_ns)[0])
    t_b, r_b = rotations_of(body, origin)
    t_c = (np.asarray(on_body, dtype=np.int64) - origin).astype(np.float64) / _NS
    inside = (t_c >= t_b[0]) & (t_c <= t_b[-1])
    if inside.sum() < 3:
        raise CalibrationError(
            f"only {int(inside.sum())} camera frames fall inside the mocap recording; check the time offset",
            "T_body_camera",
        )
    idx = np.flatnonzero(inside)
    tq = t_c[idx]
    rot_b = Slerp(t_b, r_b)(tq)
    pos = np.asarray(body.positions, dtype=np.float64)
    pos_b = np.stack([np.interp(tq, t_b, pos[:, k]) for k in range(3)], axis=1)
    cam_pos = np.asarray(camera.positions, dtype=np.float64)[idx]
    _, rot_c_all = rotations_of(camera, int(cam_st[0]))
    rot_c = rot_c_all[idx]
    period = float(np.median(np.diff(tq))) if tq.size > 1 else 1.0
    body_motions: list[Transform] = []
    cam_motions: list[Transform] = []
    for step_s in steps_s:
        k = max(1, round(step_s / period))
        if k >= tq.size:
            continue
        i, j = np.arange(tq.size - k), np.arange(k, tq.size)
        ra = rot_b[i].inv() * rot_b[j]
        ta = rot_b[i].inv().apply(pos_b[j] - pos_b[i])
        rc = rot_c[i].inv() * rot_c[j]
        tc = rot_c[i].inv().apply(cam_pos[j] - cam_pos[i])
        body_motions.extend(Transform(ra[n], ta[n]) for n in range(i.size))
        cam_motions.extend(Transform(rc[n], tc[n]) for n in range(i.size))
    return body_motions, cam_motions


def estimate_hand_eye(
    body: TimedPoses,
    camera: TimedPoses,
    *,
    camera_to_body_ns: Callable[[npt.NDArray[np.int64]], npt.NDArray[np.int64]] | None = None,
    steps_s: Sequence[float] = (0.25, 0.5, 1.0),
    min_angle_deg: float = 2.0,
    min_axis_spread: float = 0.1,
) -> HandEyeEstimate:
    """``T_body_camera`` from a mocap body trajectory and a camera trajectory (see :func:`motion_pairs`
    and :func:`solve_hand_eye`).

    Raises:
        CalibrationError: no overlap, too little rotation, or rotation about one axis only.
    """
    a, b = motion_pairs(body, camera, camera_to_body_ns=camera_to_body_ns, steps_s=steps_s)
    return solve_hand_eye(a, b, min_angle_deg=min_angle_deg, min_axis_spread=min_axis_spread)
