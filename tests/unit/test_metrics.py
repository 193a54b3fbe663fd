"""Evaluation metrics on synthetic trajectories with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation.evaluation import ErrorStats, ape, evaluate, lab_errors, rpe, rpe_pairs, umeyama
from estimation.timing import TimingTable
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import EstimationError


def _traj(n: int = 200, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    pos = np.column_stack([np.cos(t), np.sin(1.3 * t), 0.3 * t]) + rng.normal(0, 0.001, (n, 3))
    q = Rotation.from_rotvec(np.column_stack([0.2 * np.sin(t), 0.1 * t, t])).as_quat()
    return Trajectory(
        (1_000_000_000 + np.round(t * 1e9)).astype(np.int64), pos, np.column_stack([q[:, 3], q[:, :3]]), "gt"
    )


def _moved(traj: Trajectory, R: Rotation, t: np.ndarray, s: float = 1.0) -> Trajectory:  # noqa: N803
    q = (R * traj.rotations).as_quat()
    return Trajectory(
        traj.stamps_ns, s * R.apply(traj.positions) + t, np.column_stack([q[:, 3], q[:, :3]]), "est"
    )


def test_umeyama_recovers_a_similarity() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    R = Rotation.from_euler("xyz", [10, -20, 70], degrees=True)  # noqa: N806
    dst = 2.5 * R.apply(src) + [1.0, 2.0, 3.0]
    r, t, s = umeyama(src, dst, with_scale=True)
    assert np.allclose(r, R.as_matrix()) and np.allclose(t, [1, 2, 3]) and s == pytest.approx(2.5)
    r, t, s = umeyama(src, dst, with_scale=False)
    assert s == 1.0 and np.allclose(r, R.as_matrix(), atol=1e-9)


def test_umeyama_rejects_degenerate_points() -> None:
    line = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    with pytest.raises(EstimationError, match="degenerate"):
        umeyama(line, line)
    with pytest.raises(EstimationError, match="at least 3"):
        umeyama(line[:2], line[:2])


def test_ape_is_zero_after_alignment_and_sees_the_offset_without() -> None:
    gt = _traj()
    est = _moved(gt, Rotation.from_euler("z", 30, degrees=True), np.array([0.5, -1.0, 2.0]))
    for method in ("se3", "sim3"):
        res = ape(est, gt, method)
        assert res.translation.max < 1e-9 and res.rotation.max < 1e-9 and res.n_pairs == len(gt)
    raw = ape(est, gt, "none")
    assert raw.rotation.min == pytest.approx(np.radians(30), abs=1e-9)
    assert raw.translation.min > 0.1


def test_sim3_recovers_the_scale_of_a_monocular_estimate() -> None:
    gt = _traj()
    est = _moved(gt, Rotation.from_euler("y", -15, degrees=True), np.array([1.0, 0, 0]), s=0.25)
    res = ape(est, gt, "sim3")
    assert res.alignment.scale == pytest.approx(4.0, rel=1e-9)
    assert res.translation.rmse < 1e-9
    assert ape(est, gt, "se3").translation.rmse > 0.1


def test_constant_offset_gives_known_ape_statistics() -> None:
    gt = _traj()
    est = Trajectory(gt.stamps_ns, gt.positions + [0.03, 0.04, 0.0], gt.quats_wxyz)
    res = ape(est, gt, "none")
    assert res.translation.rmse == pytest.approx(0.05) and res.translation.std == pytest.approx(
        0.0, abs=1e-12
    )


def test_rpe_pairs_by_frames_and_metres() -> None:
    pos = np.column_stack([np.arange(11) * 0.3, np.zeros(11), np.zeros(11)])
    assert rpe_pairs(pos, 5).tolist() == [[0, 5], [5, 10]]
    assert rpe_pairs(pos, 3, all_pairs=True).tolist() == [[i, i + 3] for i in range(8)]
    # Every 0.3 m step; 1 m is reached after 4 steps (1.2 m >= 1.0).
    assert rpe_pairs(pos, 1.0, "m").tolist() == [[0, 4], [4, 8]]
    with pytest.raises(EstimationError, match="no pose pairs"):
        rpe_pairs(pos, 100, "m")
    with pytest.raises(EstimationError, match="integer"):
        rpe_pairs(pos, 1.5, "frames")


def test_rpe_measures_a_per_step_scale_drift() -> None:
    gt = _traj()
    # Estimate whose every step is 10 % longer: RPE translation = 0.1 * step length.
    steps = np.diff(gt.positions, axis=0)
    est_pos = np.vstack([gt.positions[:1], gt.positions[:1] + np.cumsum(1.1 * steps, axis=0)])
    est = Trajectory(gt.stamps_ns, est_pos, gt.quats_wxyz)
    res = rpe(est, gt, 1, "frames")
    gt_steps_body = np.linalg.norm(steps, axis=1)
    assert np.allclose(res.translation_errors_m, 0.1 * gt_steps_body)
    assert res.rotation.max < 1e-9


def test_lab_relative_equals_rpe_delta_one_and_absolute_accumulates() -> None:
    gt = _traj(seed=3)
    rng = np.random.default_rng(4)
    noise = Rotation.from_rotvec(rng.normal(0, 0.01, (len(gt), 3)))
    q = (gt.rotations * noise).as_quat()
    est = _moved(
        Trajectory(
            gt.stamps_ns,
            gt.positions + rng.normal(0, 0.01, gt.positions.shape),
            np.column_stack([q[:, 3], q[:, :3]]),
        ),
        Rotation.from_euler("x", 50, degrees=True),
        np.array([3.0, 0, 0]),
    )
    lab = lab_errors(est, gt)
    r = rpe(est, gt, 1, "frames")
    assert np.allclose(lab.relative_translation_m, r.translation_errors_m, atol=1e-12)
    assert np.allclose(lab.relative_rotation_rad, r.rotation_errors_rad, atol=1e-12)
    # Absolute starts at zero (the estimate is started at the first ground-truth pose).
    assert lab.absolute_translation_m[0] < 1e-12 and lab.absolute_rotation_rad[0] < 1e-9
    # An exact estimate in another frame has zero lab errors everywhere.
    exact = _moved(gt, Rotation.from_euler("z", 90, degrees=True), np.array([0, 5.0, 0]))
    e = lab_errors(exact, gt)
    assert e.absolute_translation.max < 1e-9 and e.relative_rotation.max < 1e-9
    d = e.to_dict()
    assert set(d) == {
        "relative_translation",
        "relative_rotation",
        "absolute_translation",
        "absolute_rotation",
    }


def test_evaluate_associates_by_time_and_reports_everything() -> None:
    gt = _traj(400)
    est = gt.subset(np.arange(10, 390, 4))
    shifted = Trajectory(est.stamps_ns + 3_000_000, est.positions, est.quats_wxyz)  # 3 ms late
    rep = evaluate(shifted, gt, alignment="se3", delta=2)
    assert rep.ape.n_pairs == len(est) and rep.rpe.n_pairs == len(est) // 2 - (1 if len(est) % 2 == 0 else 0)
    assert rep.ape.translation.max < 1e-9
    out = rep.to_dict()
    assert out["poses"]["matched"] == len(est) and out["rpe"]["delta_unit"] == "frames"
    late = Trajectory(est.stamps_ns + 50_000_000, est.positions, est.quats_wxyz)
    assert evaluate(late, gt, max_diff_s=0.06).ape.n_pairs == len(est)
    far = Trajectory(est.stamps_ns + 10**12, est.positions, est.quats_wxyz)
    with pytest.raises(EstimationError, match="within 0.01 s"):
        ape(far, gt)


def test_error_stats_match_numpy() -> None:
    e = np.array([1.0, 2.0, 2.0, 5.0])
    s = ErrorStats.of(e)
    assert (s.rmse, s.mean, s.median, s.min, s.max, s.count) == (
        pytest.approx(np.sqrt(34 / 4)),
        2.5,
        2.0,
        1.0,
        5.0,
        4,
    )
    assert s.std == pytest.approx(np.std(e))
    with pytest.raises(EstimationError):
        ErrorStats.of([])


def test_timing_table_from_stage_ms() -> None:
    t = TimingTable.from_stage_ms({"features": [1.0, 3.0], "3d": [], "total": [4.0, 6.0]})
    assert [r.name for r in t.rows] == ["features", "total"]
    assert t.row("features").share == pytest.approx(0.4) and t.fps == pytest.approx(200.0)
    assert "features" in t.format() and t.to_dict()["frames"] == 2
    with pytest.raises(EstimationError):
        TimingTable.from_stage_ms({"features": []})
