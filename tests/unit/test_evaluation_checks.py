"""``vo eval``'s alignment warnings (estimation.evaluation_checks): a nearly straight path, a
path that barely moves, and none for a path that spans a plane."""

from __future__ import annotations

import math

import numpy as np

from estimation.evaluation import evaluate
from estimation.evaluation_checks import alignment_warnings, first_pose_rotation_rmse_deg
from flightkit.datasets.trajectory import Trajectory


def _traj(positions: np.ndarray, yaw_rad: np.ndarray, name: str) -> Trajectory:
    n = len(positions)
    T = np.tile(np.eye(4), (n, 1, 1))
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, :3, 3] = positions
    return Trajectory.from_matrices(np.arange(n, dtype=np.int64) * 100_000_000, T, name=name)


def test_a_straight_drive_warns_and_reports_the_first_pose_rotation() -> None:
    n = 50
    gt_pos = np.c_[np.linspace(0.0, 60.0, n), 0.01 * np.sin(np.arange(n)), np.zeros(n)]
    gt = _traj(gt_pos, np.zeros(n), "gt")
    # an estimate with a yaw drift of 0.02 deg a frame and a little position noise
    yaw = np.radians(0.02) * np.arange(n)
    est = _traj(gt_pos + np.random.default_rng(0).normal(0, 0.02, (n, 3)), yaw, "est")
    report = evaluate(est, gt)
    warnings = alignment_warnings(report)
    assert len(warnings) == 1 and "nearly a straight line" in warnings[0]
    expected = math.degrees(float(np.sqrt(np.mean(yaw**2))))
    assert abs(first_pose_rotation_rmse_deg(report) - expected) < 1e-6


def test_a_camera_at_rest_warns_that_the_alignment_fits_noise() -> None:
    n = 20
    rng = np.random.default_rng(1)
    gt = _traj(rng.normal(0, 2e-4, (n, 3)), np.zeros(n), "gt")
    est = _traj(rng.normal(0, 5e-4, (n, 3)), np.zeros(n), "est")
    warnings = alignment_warnings(evaluate(est, gt))
    assert len(warnings) == 1 and "barely moves" in warnings[0]


def test_a_circle_needs_no_warning_and_none_alignment_never_warns() -> None:
    n = 60
    a = np.linspace(0, 2 * math.pi, n)
    gt = _traj(np.c_[np.cos(a), np.sin(a), np.zeros(n)], a, "gt")
    est = _traj(np.c_[np.cos(a), np.sin(a), 0.01 * np.ones(n)], a, "est")
    assert alignment_warnings(evaluate(est, gt)) == []
    line = _traj(np.c_[np.linspace(0, 10, n), np.zeros(n), np.zeros(n)], np.zeros(n), "line")
    assert alignment_warnings(evaluate(line, line, alignment="none")) == []
