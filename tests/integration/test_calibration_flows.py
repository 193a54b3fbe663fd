"""A calibration flows into the datasets: ``flightkit capture calibrate --write`` on a simulated
recording with a known offset, drift and mount, then ``export`` (EuRoC ``sensor.yaml``, TUM
ground truth) and ``vo eval`` use the stored result or a given ``--calibration FILE.json``."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from capture.recorder import Compression, Recorder, StreamSample
from flightkit.bus.msgs import CameraInfo, Header, Image, PoseStamped, schema_text
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


def write_camera_recording(path: Path, st: CalibrationStreams, w: int = 16, h: int = 12) -> None:
    """Mocap poses (mocap frame) and tiny gray images with their camera_info at the camera's stamps."""
    rec = Recorder(path, schema_text, compression=Compression.NONE, metadata={
        "extrinsics": {"T_body_camera": transform_to_json(CONFIGURED),
                       "T_world_mocap": transform_to_json(Transform.identity()), "mocap_body": "uav1"}})
    seq: dict[str, int] = {}

    def put(topic: str, msgtype: str, payload: bytes, stamp: int) -> None:
        seq[topic] = seq.get(topic, 0) + 1
        rec.offer(StreamSample(topic, msgtype, payload, seq[topic], stamp, stamp, True))

    events = [(int(t), 0, i) for i, t in enumerate(st.mocap.stamps_ns)]
    events += [(int(t), 1, i) for i, t in enumerate(st.camera.stamps_ns)]
    img = np.full((h, w), 128, np.uint8)
    poses = st.mocap.transforms()
    for stamp, kind, i in sorted(events):
        if kind == 0:
            put("uav1/mocap/uav1/pose", PoseStamped.TYPE,
                bytes(PoseStamped.from_transform(stamp, "mocap", poses[i]).encode()), stamp)
            continue
        hdr = Header(stamp, "uav1/camera_gray_optical")
        put("uav1/camera/gray/image", Image.TYPE, bytes(Image.from_array(hdr, img, "mono8").encode()), stamp)
        put("uav1/camera/gray/camera_info", CameraInfo.TYPE,
            bytes(CameraInfo.from_intrinsics(hdr, w, h, 12.0, 12.0, 7.5, 5.5).encode()), stamp)
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
    assert 20e6 < float(np.mean(want)) < 30e6  # 45 ms offset - 20 ms latency, plus drift
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
