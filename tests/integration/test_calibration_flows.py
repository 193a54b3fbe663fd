"""A calibration flows into the datasets: ``flightkit capture calibrate --write`` on a simulated
recording with a known offset, drift and mount, then ``export`` (EuRoC ``sensor.yaml``, TUM
ground truth) and ``vo eval`` use the stored result or a given ``--calibration FILE.json``."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture.recorder import Compression, Recorder, StreamSample
from flightkit.bus.image_msgs import CameraInfo, Image
from flightkit.bus.msg_base import Header, schema_text
from flightkit.bus.pose_msgs import PoseStamped
from flightkit.calibration import CalibrationResult, transform_difference
from flightkit.cli.main import main
from flightkit.datasets.mcap_reader import transform_to_json
from flightkit.datasets.trajectory import read_tum, write_tum
from flightkit.frames import Transform
from flightkit.sim.calibration_flight import CalibrationStreams, calibration_motion, simulate_streams
from flightkit.sim.timing_errors import SimTimingErrors
from trajectories.patterns import Circle

TRUE_MOUNT = Transform.from_xyz_euler_deg([0.085, -0.004, -0.017], "xz", [133.0, 91.5])
CONFIGURED = Transform.from_xyz_euler_deg([0.08, 0.0, -0.02], "xz", [135.0, 90.0])
ERRORS = SimTimingErrors(camera_time_offset_s=0.045, camera_drift_ppm=100.0, mocap_latency_s=0.02)


def write_camera_recording(path: Path, st: CalibrationStreams, w: int = 16, h: int = 12,
                           image: Callable[[int], np.ndarray] | None = None, f_px: float = 12.0) -> None:
    """Mocap poses (mocap frame) and gray images (``image(i)`` of camera frame i, default flat
    grey) with their camera_info (focal length ``f_px``, centred) at the camera's stamps."""
    rec = Recorder(path, schema_text, compression=Compression.NONE, metadata={
        "extrinsics": {"T_body_camera": transform_to_json(CONFIGURED),
                       "T_world_mocap": transform_to_json(Transform.identity()), "mocap_body": "uav1"}})
    seq: dict[str, int] = {}

    def put(topic: str, msgtype: str, payload: bytes, stamp: int) -> None:
        seq[topic] = seq.get(topic, 0) + 1
        rec.offer(StreamSample(topic, msgtype, payload, seq[topic], stamp, stamp, True))

    events = [(int(t), 0, i) for i, t in enumerate(st.mocap.stamps_ns)]
    events += [(int(t), 1, i) for i, t in enumerate(st.camera.stamps_ns)]
    flat = np.full((h, w), 128, np.uint8)
    poses = st.mocap.transforms()
    for stamp, kind, i in sorted(events):
        if kind == 0:
            put("uav1/mocap/uav1/pose", PoseStamped.TYPE,
                bytes(PoseStamped.from_transform(stamp, "mocap", poses[i]).encode()), stamp)
            continue
        hdr = Header(stamp, "uav1/camera_gray_optical")
        img = flat if image is None else image(i)
        put("uav1/camera/gray/image", Image.TYPE, bytes(Image.from_array(hdr, img, "mono8").encode()), stamp)
        put("uav1/camera/gray/camera_info", CameraInfo.TYPE,
            bytes(CameraInfo.from_intrinsics(hdr, w, h, f_px, f_px, (w - 1) / 2, (h - 1) / 2).encode()), stamp)
    assert rec.close().error == ""


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path, CalibrationStreams]:
    """The recording (calibrated in place by ``capture calibrate --write``), its untouched copy,
    and the calibration file written beside it."""
    root = tmp_path_factory.mktemp("flows")
    st = simulate_streams(calibration_motion(Circle(radius_m=1.0, period_s=20.0, laps=2, height_m=1.5)), 40.0,
                          errors=ERRORS, T_body_camera=TRUE_MOUNT)
    rec, plain, vo = root / "cal.mcap", root / "plain.mcap", root / "vo.txt"
    write_camera_recording(rec, st)
    plain.write_bytes(rec.read_bytes())
    write_tum(vo, st.camera)
    cal_json = root / "cal.json"
    code = main(["capture", "calibrate", "handeye", str(rec), "--camera-trajectory", str(vo),
                 "--write", str(cal_json), "--write", str(rec)])
    assert code == 0
    return rec, plain, cal_json, st


def _yaml_number(text: str, key: str) -> float:
    m = re.search(rf"^{key}: ([-+0-9.eE]+)", text, re.MULTILINE)
    assert m is not None, f"{key} missing from sensor.yaml"
    return float(m.group(1))


def test_euroc_export_carries_the_measured_mount_and_time_offset(calibrated, tmp_path: Path) -> None:
    rec, _, cal_json, st = calibrated
    res = CalibrationResult.read_json(cal_json)
    assert main(["export", str(rec), "--format", "euroc", "-o", str(tmp_path / "euroc")]) == 0
    text = (tmp_path / "euroc" / "mav0" / "cam0" / "sensor.yaml").read_text()
    data = re.search(r"T_BS:.*?data: \[([^\]]*)\]", text, re.DOTALL)
    assert data is not None
    T_bs = Transform.from_matrix(np.array([float(v) for v in data.group(1).split(",")]).reshape(4, 4))  # noqa: N806
    dm, ddeg = transform_difference(T_bs, TRUE_MOUNT)
    assert dm < 0.002 and ddeg < 0.2  # the measured mount, not the configured one
    assert transform_difference(T_bs, CONFIGURED)[1] > 1.0
    expected_s = ERRORS.expected_offset_s(int(_yaml_number(text, "time_ref_ns")), st.start_ns)
    assert _yaml_number(text, "time_offset_s") == pytest.approx(expected_s, abs=1e-3)
    assert _yaml_number(text, "time_drift_ppm") == pytest.approx(100.0, abs=20.0)
    assert _yaml_number(text, "time_offset_s") == pytest.approx(res.time_offset_ms * 1e-3)


def test_tum_export_shifts_the_ground_truth_by_the_stored_or_given_calibration(calibrated, tmp_path: Path) -> None:
    rec, plain, cal_json, _ = calibrated
    res = CalibrationResult.read_json(cal_json)
    runs = {"raw": [str(plain)], "stored": [str(rec)], "given": [str(plain), "--calibration", str(cal_json)]}
    gt = {}
    for name, args in runs.items():
        assert main(["export", *args, "--format", "tum", "-o", str(tmp_path / name)]) == 0
        gt[name] = read_tum(tmp_path / name / "groundtruth.txt")
    want = res.mocap_to_camera_ns(gt["raw"].stamps_ns) - gt["raw"].stamps_ns
    assert 44e6 < float(np.mean(want)) < 50e6  # 45 ms offset plus drift (the mocap stamps capture time)
    for name in ("stored", "given"):
        assert np.array_equal(gt[name].stamps_ns - gt["raw"].stamps_ns, want)
        # the same body pose, seen through the measured mount instead of the configured one
        body = gt["raw"].transform(100) @ CONFIGURED.inverse()
        assert gt[name].transform(100).almost_equal(body @ res.T_body_camera, tol_m=1e-6, tol_rad=1e-6)


def test_vo_eval_takes_a_calibration_file_for_a_recording(calibrated, tmp_path: Path, capsys) -> None:
    _, plain, cal_json, st = calibrated
    est = tmp_path / "est.txt"
    write_tum(est, st.camera)  # the camera's true motion at its own stamps
    capsys.readouterr()
    errors = {}
    for name, extra in (("raw", []), ("given", ["--calibration", str(cal_json)])):
        assert main(["vo", "eval", str(est), str(plain), "--json", "--max-diff", "0.01", *extra]) == 0
        errors[name] = json.loads(capsys.readouterr().out)["ape"]["translation_m"]["rmse"]
    # on the camera's clock and through the measured mount the truth matches the camera's motion
    assert errors["given"] < 0.001 < 0.004 < errors["raw"], errors
    assert main(["vo", "eval", str(est), str(est), "--calibration", str(cal_json)]) == 1
    assert "applies to a .mcap recording" in capsys.readouterr().err


def test_handeye_from_an_apriltag_grid_in_a_simulated_recording(tmp_path: Path) -> None:
    """The body rocks in place under a room-fixed grid of 4 x 4 AprilTags (36h11) while the
    camera, 30 ms late, films it: ``calibrate handeye --board apriltag:...`` finds the mount."""
    from flightkit.calibration.board import BoardDetector, aruco_available, parse_board

    if not aruco_available():
        pytest.skip("this OpenCV has no aruco")
    spec = "apriltag:4x4:0.06:0.048"
    w, h, f = 320, 240, 200.0
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])  # noqa: N806
    det = BoardDetector(parse_board(spec), K)
    px = 100
    board_img = det.image(px)

    def body(t: float) -> Transform:  # rocking about three axes, +-17 degrees, never repeating
        a = [0.3 * math.sin(2 * math.pi * t / 2.3), 0.27 * math.sin(2 * math.pi * t / 3.1 + 1.0),
             0.3 * math.sin(2 * math.pi * t / 3.7 + 2.0)]
        return Transform(Rotation.from_euler("ZYX", a[::-1]), np.array([0.05 * math.sin(t), 0.0, 1.2]))

    # the board 0.28 m in front of the camera at the start, about centred
    T_world_board = body(0.0) @ TRUE_MOUNT @ Transform(translation=np.array([-0.1, -0.1, 0.28]))  # noqa: N806
    st = simulate_streams(body, 24.0, errors=SimTimingErrors(camera_time_offset_s=0.03), T_body_camera=TRUE_MOUNT,
                          camera_rate_hz=10.0)
    s = det.spec.square_m / px

    def view(i: int) -> np.ndarray:
        t_s = (int(st.camera_truth_ns[i]) - st.start_ns) / 1e9
        T_cb = (body(t_s) @ TRUE_MOUNT).inverse() @ T_world_board  # noqa: N806
        R = T_cb.rotation.as_matrix()  # noqa: N806
        H = K @ np.column_stack([R[:, 0], R[:, 1], T_cb.translation]) @ np.diag([s, s, 1.0])  # noqa: N806
        return cv2.warpPerspective(board_img, H, (w, h), flags=cv2.INTER_AREA, borderValue=128)

    rec = tmp_path / "apriltag.mcap"
    write_camera_recording(rec, st, w, h, image=view, f_px=f)
    out = tmp_path / "cal.json"
    assert main(["capture", "calibrate", "handeye", str(rec), "--board", spec, "--write", str(out)]) == 0
    res = CalibrationResult.read_json(out)
    dm, ddeg = transform_difference(res.T_body_camera, TRUE_MOUNT)
    assert dm < 0.002 and ddeg < 0.2, (dm, ddeg)
    # 24 s at 10 Hz of board poses: the offset is looser than a calibration flight's 1 ms
    assert abs(res.time_offset_ms - 30.0) < 3.0 * res.time_offset_uncertainty_ms < 6.0
    assert res.source["camera_motion"] == f"apriltag board {spec}"
