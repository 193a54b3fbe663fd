"""flightkit.calibration: rates, time offset, hand-eye, clock offset, latency, results, board."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flightkit.calibration import (
    METADATA_RECORD,
    CalibrationResult,
    Exchange,
    angular_rates,
    estimate_clock_offset,
    estimate_hand_eye,
    estimate_time_offset,
    latency_stats,
    predict_pose,
    solve_hand_eye,
    transform_difference,
    velocity_from_poses,
)
from flightkit.calibration.board import BoardDetector, BoardSpec, aruco_available
from flightkit.datasets.mcap_reader import transform_from_json
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import CalibrationError, FlightkitError
from flightkit.frames import Transform

T0_NS = 1_700_000_000_000_000_000
T_BC = Transform.from_xyz_euler_deg([0.08, 0.0, -0.02], "xz", [135.0, 90.0])  # the lab's mount


def rocking(t: float) -> Transform:
    """A body rocking about all three axes with unrelated periods, moving along a slow circle."""
    angles = [
        0.35 * math.sin(2 * math.pi * t / 2.3 + 0.4) + 0.2 * math.sin(2 * math.pi * t / 3.7),
        0.30 * math.sin(2 * math.pi * t / 2.9 + 1.1) + 0.2 * math.sin(2 * math.pi * t / 4.3 + 2.0),
        0.40 * math.sin(2 * math.pi * t / 3.3 + 2.5) + 0.3 * math.sin(2 * math.pi * t / 5.9 + 0.7),
    ]
    pos = [math.cos(0.3 * t), math.sin(0.3 * t), 1.5 + 0.2 * math.sin(0.5 * t)]
    return Transform(Rotation.from_euler("ZYX", angles[::-1]), np.array(pos))


def sample(truth, stamps_true_ns: np.ndarray, stamps_out_ns: np.ndarray | None = None,
           right: Transform | None = None, name: str = "") -> Trajectory:
    poses = [truth((int(t) - T0_NS) / 1e9) @ (right or Transform.identity()) for t in stamps_true_ns]
    return Trajectory.from_transforms(stamps_true_ns if stamps_out_ns is None else stamps_out_ns, poses, name)


def grid_ns(rate_hz: float, duration_s: float) -> np.ndarray:
    return T0_NS + np.round(np.arange(int(duration_s * rate_hz) + 1) / rate_hz * 1e9).astype(np.int64)


# ---------------------------------------------------------------------------------------------- rates


def test_angular_rates_of_a_constant_rotation_are_exact_in_the_body_frame() -> None:
    omega = np.array([0.3, -0.2, 0.5])
    R0 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)  # noqa: N806
    st = grid_ns(100.0, 2.0)
    traj = Trajectory.from_transforms(
        st, [Transform(R0 * Rotation.from_rotvec(omega * (t - T0_NS) / 1e9)) for t in st]
    )
    rates = angular_rates(traj, origin_ns=T0_NS)
    np.testing.assert_allclose(rates.omega_rad_s, np.tile(omega, (len(st) - 1, 1)), atol=1e-9)
    np.testing.assert_allclose(rates.stamps_s[:2], [0.005, 0.015], atol=1e-12)
    uni = rates.resampled(50.0)
    assert np.allclose(np.diff(uni.stamps_s), 0.02)
    np.testing.assert_allclose(uni.norm_rad_s, np.linalg.norm(omega), atol=1e-9)


def test_angular_rates_refuse_unsorted_stamps() -> None:
    traj = Trajectory(np.array([3, 2, 1], dtype=np.int64), np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1)))
    with pytest.raises(CalibrationError, match="increase"):
        angular_rates(traj)


# ---------------------------------------------------------------------------------------------- time offset


@pytest.mark.parametrize("offset_ms", [0.0, 37.0, -62.5, 100.0])
def test_time_offset_is_found_to_well_under_a_millisecond(offset_ms: float) -> None:
    mocap = sample(rocking, grid_ns(120.0, 30.0), name="mocap")
    true_cam = grid_ns(30.0, 30.0)
    camera = sample(rocking, true_cam, true_cam + round(offset_ms * 1e6), right=T_BC)
    est = estimate_time_offset(mocap, camera)
    assert est.offset_s * 1e3 == pytest.approx(offset_ms, abs=0.2)
    assert abs(est.drift_ppm) < 10.0
    assert est.correlation > 0.999
    assert est.offset_uncertainty_s < 1e-3
    # moving camera stamps onto the mocap time base undoes the offset
    np.testing.assert_allclose(est.camera_to_mocap_ns(camera.stamps_ns), true_cam, atol=3e5)


def test_drift_is_found_within_20_ppm() -> None:
    mocap = sample(rocking, grid_ns(120.0, 60.0))
    true_cam = grid_ns(30.0, 60.0)
    drift_ppm, offset_s = 150.0, 0.05
    cam_st = true_cam + np.round((offset_s + drift_ppm * 1e-6 * (true_cam - T0_NS) / 1e9) * 1e9).astype(np.int64)
    est = estimate_time_offset(mocap, sample(rocking, true_cam, cam_st, right=T_BC))
    assert est.drift_estimated
    assert est.drift_ppm == pytest.approx(drift_ppm, abs=20.0)
    expected = offset_s + drift_ppm * 1e-6 * (est.ref_ns - T0_NS) / 1e9
    assert est.offset_s == pytest.approx(expected, abs=1e-3)


def test_time_offset_refuses_a_recording_without_rotation() -> None:
    def translate(t: float) -> Transform:
        return Transform(translation=np.array([math.sin(t), 0.5 * t, 1.0]))

    mocap = sample(translate, grid_ns(120.0, 20.0))
    camera = sample(translate, grid_ns(30.0, 20.0), right=T_BC)
    with pytest.raises(CalibrationError, match="too little rotation to tell.*at least two axes") as exc:
        estimate_time_offset(mocap, camera)
    assert exc.value.quantity == "time offset"
    assert isinstance(exc.value, FlightkitError)


# ---------------------------------------------------------------------------------------------- hand-eye


def test_hand_eye_recovers_the_mount_exactly_from_clean_motions() -> None:
    st = grid_ns(30.0, 20.0)
    mocap = sample(rocking, grid_ns(120.0, 20.0))
    camera = sample(rocking, st, right=T_BC)
    he = estimate_hand_eye(mocap, camera)
    dm, ddeg = transform_difference(he.T_body_camera, T_BC)
    assert dm < 1e-4 and ddeg < 0.01
    assert he.residual_m < 1e-3 and he.residual_deg < 0.05
    assert he.axis_spread > 0.3


def test_hand_eye_closed_form_on_exact_pairs() -> None:
    rng = np.random.default_rng(3)
    A, B = [], []  # noqa: N806
    for _ in range(20):
        a = Transform(Rotation.from_rotvec(rng.normal(0, 0.5, 3)), rng.normal(0, 0.3, 3))
        A.append(a)
        B.append(T_BC.inverse() @ a @ T_BC)
    he = solve_hand_eye(A, B, refine=False)
    assert he.T_body_camera.almost_equal(T_BC, tol_m=1e-9, tol_rad=1e-9)


def test_hand_eye_refuses_rotation_about_one_axis_and_none() -> None:
    def yaw_only(t: float) -> Transform:
        return Transform(Rotation.from_euler("z", 0.8 * math.sin(t)), np.array([math.sin(0.7 * t), 0.2 * t, 1.0]))

    def translate(t: float) -> Transform:
        return Transform(translation=np.array([math.sin(t), 0.3 * t, 1.0]))

    for truth, match in ((yaw_only, "one axis only"), (translate, "too little rotation to tell")):
        mocap = sample(truth, grid_ns(120.0, 15.0))
        camera = sample(truth, grid_ns(30.0, 15.0), right=T_BC)
        with pytest.raises(CalibrationError, match=match):
            estimate_hand_eye(mocap, camera)


# ---------------------------------------------------------------------------------------------- host clocks


def test_clock_offset_from_symmetric_exchanges_is_exact() -> None:
    ex = [Exchange(t, t + 5_000 + 1_000_000, t + 7_000 + 1_000_000, t + 12_000) for t in range(0, 10**9, 10**7)]
    est = estimate_clock_offset(ex, fit_drift=False)
    assert est.offset_ns == pytest.approx(1_000_000)
    assert est.rtt_min_ns == 10_000
    assert est.uncertainty_ns == pytest.approx(5_000)


def test_clock_offset_and_drift_with_queueing_delays() -> None:
    rng = np.random.default_rng(0)
    offset_ns, drift_ppm = 3_250_000.0, 80.0
    ex = []
    for t0 in np.arange(0, 120e9, 50e6):
        up = 200_000 + rng.exponential(2e6)  # a 0.2 ms wire plus queues, each way
        down = 200_000 + rng.exponential(2e6)
        remote = lambda local: local + offset_ns + drift_ppm * 1e-6 * local  # noqa: E731
        t1 = remote(t0 + up)
        t2 = t1 + 100_000
        t3 = t0 + up + 100_000 / (1 + drift_ppm * 1e-6) + down
        ex.append(Exchange(int(t0), int(t1), int(t2), int(t3)))
    est = estimate_clock_offset(ex)
    assert est.offset_at_ns(60 * 10**9) == pytest.approx(offset_ns + drift_ppm * 60e3, abs=50_000)
    assert est.drift_ppm == pytest.approx(drift_ppm, abs=5.0)
    assert est.kept < est.exchanges
    with pytest.raises(CalibrationError, match="negative round trip"):
        estimate_clock_offset([Exchange(100, 0, 0, 50)])


# ---------------------------------------------------------------------------------------------- latency


def test_latency_percentiles_per_stage_and_end_to_end() -> None:
    n = 101
    capture = np.arange(n) * 1e7
    stamps = {
        "capture": capture,
        "bus": capture + 1e6,
        "runner": capture + 1e6 + np.arange(n) * 1e4,  # 0 .. 1 ms more
        "setpoint": capture + 3e6 + np.arange(n) * 1e4,
    }
    stats = latency_stats(stamps)
    names = [s.name for s in stats.stages]
    assert names == ["capture->bus", "bus->runner", "runner->setpoint", "capture->setpoint"]
    assert stats.stages[0].p50_ms == pytest.approx(1.0)
    assert stats.stages[1].p50_ms == pytest.approx(0.5)
    assert stats.stages[1].p99_ms == pytest.approx(0.99)
    assert stats.total.max_ms == pytest.approx(4.0)
    with pytest.raises(CalibrationError, match="at least two stages"):
        latency_stats({"capture": capture})


def test_pose_prediction_at_constant_velocity_is_exact() -> None:
    v = np.array([1.0, -0.5, 0.2])
    w = np.array([0.0, 0.1, 0.6])

    def pose(t: float) -> Transform:
        return Transform(Rotation.from_rotvec(w * t), v * t)

    vel, omega = velocity_from_poses(pose(1.0), pose(1.01), 0.01)
    np.testing.assert_allclose(vel, v, atol=1e-9)
    np.testing.assert_allclose(omega, w, atol=1e-9)
    assert predict_pose(pose(1.0), vel, omega, 0.05).almost_equal(pose(1.05), tol_m=1e-9, tol_rad=1e-9)


# ---------------------------------------------------------------------------------------------- result


def _result() -> CalibrationResult:
    return CalibrationResult(
        time_offset_ms=12.5, time_offset_uncertainty_ms=0.2, drift_ppm=35.0, drift_uncertainty_ppm=3.0,
        drift_estimated=True, ref_ns=T0_NS, correlation=0.998,
        T_body_camera=Transform.from_xyz_euler_deg([0.081, 0.001, -0.02], "xz", [135.5, 90.0]),
        residual_m=0.002, residual_deg=0.1, pairs=300, configured_T_body_camera=T_BC,
        source={"recording": "run.mcap"},
    )


def test_result_round_trips_through_json_and_recording_metadata(tmp_path) -> None:
    res = _result()
    back = CalibrationResult.read_json(res.write_json(tmp_path / "cal.json"))
    assert back.to_dict() == res.to_dict()
    meta = res.to_metadata()
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items())
    assert CalibrationResult.from_metadata(meta).to_dict() == res.to_dict()
    # the mount is stored in the recorder's extrinsics format
    assert transform_from_json(meta["T_body_camera"]).almost_equal(res.T_body_camera, 1e-12, 1e-12)
    assert METADATA_RECORD.startswith("calibration")
    dm, ddeg = res.difference_to_configured
    assert dm == pytest.approx(math.dist([0.081, 0.001, -0.02], [0.08, 0.0, -0.02]))
    assert ddeg == pytest.approx(0.5, abs=1e-6)
    doc = json.loads(res.to_json())
    assert doc["handeye"]["difference_to_configured"]["rotation_deg"] == pytest.approx(0.5, abs=1e-6)


def test_result_merges_time_and_hand_eye_and_refuses_foreign_documents() -> None:
    time_only = CalibrationResult(time_offset_ms=5.0, drift_ppm=0.0, source={"a": "1"})
    he_only = CalibrationResult(T_body_camera=T_BC, residual_m=0.001, source={"b": "2"})
    both = time_only.merged(he_only)
    assert both.time_offset_ms == 5.0 and both.T_body_camera is T_BC and both.source == {"a": "1", "b": "2"}
    with pytest.raises(CalibrationError, match="not a flightkit calibration"):
        CalibrationResult.from_json('{"schema": "other"}')
    with pytest.raises(CalibrationError, match="not JSON"):
        CalibrationResult.from_json("{")


# ---------------------------------------------------------------------------------------------- board


@pytest.mark.skipif(not aruco_available(), reason="this OpenCV has no aruco")
def test_charuco_board_pose_from_a_synthetic_view() -> None:
    K = np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]])  # noqa: N806
    det = BoardDetector(BoardSpec(), K)
    px = 100
    T = Transform.from_xyz_euler_deg([-0.1, -0.12, 0.5], "xyz", [10, -15, 5])  # noqa: N806
    R = T.rotation.as_matrix()  # noqa: N806
    H = K @ np.column_stack([R[:, 0], R[:, 1], T.translation]) @ np.diag([det.spec.square_m / px] * 2 + [1.0])  # noqa: N806
    view = cv2.warpPerspective(det.image(px), H, (640, 480), flags=cv2.INTER_AREA, borderValue=128)
    pose = det.detect(view)
    assert pose is not None and pose.corners >= 20
    dm, ddeg = transform_difference(pose.T_camera_board, T)
    assert dm < 0.003 and ddeg < 0.5
    assert pose.reprojection_px < 1.0
    assert det.detect(np.full((480, 640), 128, np.uint8)) is None


def test_result_moves_mocap_stamps_onto_the_camera_clock() -> None:
    res = CalibrationResult(time_offset_ms=10.0, drift_ppm=100.0, ref_ns=T0_NS)
    out = res.mocap_to_camera_ns([T0_NS, T0_NS + 10**10])
    assert list(out - np.array([T0_NS, T0_NS + 10**10])) == [10_000_000, 11_000_000]
    with pytest.raises(CalibrationError, match="no time offset"):
        CalibrationResult().mocap_to_camera_ns([0])


@pytest.mark.skipif(not aruco_available(), reason="this OpenCV has no aruco")
def test_hand_eye_from_a_charuco_board_fixed_in_the_room() -> None:
    from flightkit.calibration.board import board_camera_poses, parse_board

    K = np.array([[320.0, 0, 319.5], [0, 320.0, 239.5], [0, 0, 1]])  # noqa: N806
    det = BoardDetector(parse_board("5x7:0.04:0.03"), K)
    px = 120
    board_img = det.image(px)

    def body(t: float) -> Transform:  # rocking about three axes in place, +-12 degrees
        a = [0.2 * math.sin(2 * math.pi * t / 2.3), 0.18 * math.sin(2 * math.pi * t / 3.1 + 1.0),
             0.2 * math.sin(2 * math.pi * t / 3.7 + 2.0)]
        return Transform(Rotation.from_euler("ZYX", a[::-1]), np.array([0.05 * math.sin(t), 0.0, 1.2]))

    T_world_board = body(0.0) @ T_BC @ Transform(translation=np.array([-0.1, -0.14, 0.45]))  # noqa: N806
    stamps = grid_ns(15.0, 16.0)
    s = det.spec.square_m / px

    def views():
        for st in stamps:
            T_cb = (body((int(st) - T0_NS) / 1e9) @ T_BC).inverse() @ T_world_board  # noqa: N806
            R = T_cb.rotation.as_matrix()  # noqa: N806
            H = K @ np.column_stack([R[:, 0], R[:, 1], T_cb.translation]) @ np.diag([s, s, 1.0])  # noqa: N806
            yield int(st), cv2.warpPerspective(board_img, H, (640, 480), flags=cv2.INTER_AREA, borderValue=128)

    kept, poses, errors = board_camera_poses(det, views())
    assert len(kept) > 0.9 * len(stamps) and max(errors) < 1.0
    camera = Trajectory.from_transforms(np.array(kept, dtype=np.int64), poses)
    he = estimate_hand_eye(sample(body, grid_ns(120.0, 16.0)), camera)
    dm, ddeg = transform_difference(he.T_body_camera, T_BC)
    assert dm < 0.002 and ddeg < 0.2, (dm, ddeg)
    with pytest.raises(CalibrationError, match="SQUARESxSQUARES"):
        parse_board("5:0.04")
    assert parse_board("apriltag:6x6:0.05:0.04") == BoardSpec(6, 6, 0.05, 0.04, "", "apriltag")
    assert parse_board("apriltag:6x6:0.05:0.04").dictionary_name == "DICT_APRILTAG_36h11"
    with pytest.raises(CalibrationError, match="2x2 tags"):
        parse_board("apriltag:1x6:0.05:0.04")


def test_a_vo_reset_mid_flight_is_left_out() -> None:
    st = grid_ns(30.0, 30.0)
    mocap = sample(rocking, grid_ns(120.0, 30.0))
    clean = sample(rocking, st, st + 20_000_000, right=T_BC)
    jump = Transform.from_xyz_euler_deg([0.3, -0.1, 0.05], "xyz", [20.0, -10.0, 35.0])
    poses = [(jump @ T if i >= 400 else T) for i, T in enumerate(clean.transforms())]  # re-initialised at frame 400
    camera = Trajectory.from_transforms(clean.stamps_ns, poses)
    est = estimate_time_offset(mocap, camera)
    assert est.offset_s == pytest.approx(0.020, abs=2e-4)
    assert est.outliers >= 1
    he = estimate_hand_eye(mocap, camera, camera_to_body_ns=est.camera_to_mocap_ns)
    dm, ddeg = transform_difference(he.T_body_camera, T_BC)
    assert dm < 1e-3 and ddeg < 0.02
    assert he.outliers >= 3  # the pairs that straddle the reset, one per step


def test_stream_health_names_the_bound_it_breaks() -> None:
    from flightkit.calibration import stream_health

    now = T0_NS + 2 * 10**9
    good = T0_NS + np.arange(0, 2 * 10**9, 10**9 // 100)  # 100 Hz up to 10 ms ago
    h = stream_health(good, now)
    assert h.rate_hz == pytest.approx(100.0, rel=1e-3) and h.age_s == pytest.approx(0.01) and h.jitter_ms < 1e-6
    assert h.problems(min_rate_hz=50.0, max_age_s=0.05, max_jitter_ms=5.0) == []
    bad = good[::4].copy()  # 25 Hz
    bad[10] += 15_000_000
    probs = stream_health(bad, now + 10**8).problems(min_rate_hz=50.0, max_age_s=0.05, max_jitter_ms=5.0)
    assert len(probs) == 3
    assert "below 50 Hz" in probs[0] and "above 50 ms" in probs[1] and "above 5 ms" in probs[2]
    with pytest.raises(CalibrationError, match="not flowing"):
        stream_health([T0_NS], now)


def test_interval_rates_take_instants_a_rounding_error_outside_the_track_at_its_ends() -> None:
    from scipy.spatial.transform import Slerp

    from flightkit.calibration.rates import interval_rates

    times = np.linspace(0.0, 16.0 - 1e-9, 161)  # a track whose end is not a round number
    track = Slerp(times, Rotation.from_rotvec(np.outer(times, [0.0, 0.0, 0.5])))  # 0.5 rad/s yaw
    start = np.array([0.0, 8.0, times[-1] - 0.1])
    stop = start + 0.1 + 1e-12  # the last interval ends a rounding error past the track
    w = interval_rates(track, start, stop)
    assert w.shape == (3, 3)
    assert np.allclose(w[:, 2], 0.5, atol=1e-6)
