"""Checks of an evaluation's trustworthiness, for ``flightkit vo eval`` and ``vo run --eval``.

An SE(3)/Sim(3) alignment fits the estimate to the ground truth's *positions*. When those
positions lie nearly on a line (a car driving straight), the rotation about that line is
free: the fit picks whatever roll lowers the position error, and the aligned rotation error
(APE rot) measures that choice, not the estimate (22.7 deg on a straight KITTI drive, issue 15).
When the path barely moves (a camera at rest), the alignment fits the noise. Both are
reported as warnings, with the rotation error of the estimate with only its first pose aligned.
"""

from __future__ import annotations

import math

import numpy as np

from estimation.evaluation import Alignment, EvaluationReport

__all__ = ["LINE_RATIO", "alignment_warnings", "first_pose_rotation_rmse_deg"]

LINE_RATIO = 0.02
"""The path counts as a line when its spread across its main direction (second singular value
of the centred positions) is below this fraction of the spread along it."""


def first_pose_rotation_rmse_deg(report: EvaluationReport) -> float:
    """RMSE (deg) of the rotation error with the estimate's first pose put on the ground
    truth's (no fit to the positions): the lab's absolute rotation error."""
    r = report.lab.absolute_rotation_rad
    return math.degrees(float(np.sqrt(np.mean(r * r)))) if len(r) else math.nan


def alignment_warnings(report: EvaluationReport) -> list[str]:
    """One sentence per reason the alignment of ``report`` is ill-conditioned (none if it is fine)."""
    if report.ape.alignment.method is Alignment.NONE:
        return []
    p = np.asarray(report.ape.gt.positions, dtype=np.float64)
    if len(p) < 3:
        return []
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False) / math.sqrt(len(p))
    rot0 = first_pose_rotation_rmse_deg(report)
    out = []
    ate = report.ape.translation.rmse
    if sv[0] <= 3.0 * ate:
        out.append(
            f"the ground truth barely moves (RMS spread {sv[0]:.4f} m, not much more than the ATE of {ate:.4f} m), "
            f"so the {report.ape.alignment.method.value} alignment fits noise; compare the errors with alignment "
            f"none (rotation error with the first pose aligned: {rot0:.3f} deg RMSE)"
        )
    elif sv[1] < LINE_RATIO * sv[0]:
        out.append(
            f"the ground-truth path is nearly a straight line ({sv[1]:.3f} m of spread across it, "
            f"{sv[0]:.2f} m along it), so the {report.ape.alignment.method.value} alignment cannot fix the "
            f"rotation about it and the aligned rotation error (APE rot) is unreliable; the rotation error "
            f"with the first pose aligned is {rot0:.3f} deg RMSE"
        )
    return out
