"""``flightkit calibrate`` on a recording of a simulated calibration flight with known errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.writer import CompressionType, Writer

from flightkit.bus.pose_msgs import PoseStamped
from flightkit.calibration import METADATA_RECORD, CalibrationResult, transform_difference
from flightkit.cli.main import main
from flightkit.datasets.mcap_reader import RecordingReader, transform_to_json
from flightkit.datasets.trajectory import write_tum
from flightkit.frames import Transform
from flightkit.sim.calibration_flight import CalibrationStreams, calibration_motion, simulate_streams
from flightkit.sim.timing_errors import SimTimingErrors
from trajectories.patterns import Circle

TRUE_MOUNT = Transform.from_xyz_euler_deg([0.085, -0.004, -0.017], "xz", [133.0, 91.5])
CONFIGURED = Transform.from_xyz_euler_deg([0.08, 0.0, -0.02], "xz", [135.0, 90.0])


def write_recording(path: Path, st: CalibrationStreams) -> None:
    """A recording as the recorder writes it: mocap poses in the mocap frame, extrinsics metadata."""
    with path.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE)
        w.start("ros2", "test")
        sid = w.register_schema("geometry_msgs/msg/PoseStamped", "ros2msg", b"")
        cid = w.register_channel("/uav1/mocap/uav1/pose", "cdr", sid)
        for i, (stamp, T) in enumerate(zip(st.mocap.stamps_ns, st.mocap.transforms(), strict=True)):  # noqa: N806
            w.add_message(cid, int(stamp), bytes(PoseStamped.from_transform(int(stamp), "mocap", T).encode()),
                          int(stamp), i)
        w.add_metadata("extrinsics", {"T_body_camera": transform_to_json(CONFIGURED),
                                      "T_world_mocap": transform_to_json(Transform.identity()), "mocap_body": "uav1"})
        w.finish()


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, CalibrationStreams]:
    root = tmp_path_factory.mktemp("cal")
    st = simulate_streams(calibration_motion(Circle(radius_m=1.0, period_s=20.0, laps=2, height_m=1.5)), 40.0,
                          errors=SimTimingErrors(0.045, 100.0, 0.02), T_body_camera=TRUE_MOUNT)
    rec, cam = root / "cal.mcap", root / "vo.txt"
    write_recording(rec, st)
    write_tum(cam, st.camera)
    return rec, cam, st


def test_calibrate_handeye_prints_json_and_stores_the_result(flight, tmp_path: Path, capsys) -> None:
    rec, cam, st = flight
    out_json = tmp_path / "cal.json"
    out_rec = tmp_path / "calibrated.mcap"
    code = main(["calibrate", "handeye", str(rec), "--camera-trajectory", str(cam), "--json",
                 "--write", str(out_json), "--write", str(out_rec)])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    ref_ns = doc["time"]["ref_ns"]
    assert doc["time"]["offset_ms"] == pytest.approx(st.errors.expected_offset_s(ref_ns, st.start_ns) * 1e3, abs=1.0)
    assert doc["time"]["drift_ppm"] == pytest.approx(100.0, abs=20.0)
    res = CalibrationResult.read_json(out_json)
    dm, ddeg = transform_difference(res.T_body_camera, TRUE_MOUNT)
    assert dm < 0.002 and ddeg < 0.2
    # compared with the recording's configured mount
    want = transform_difference(TRUE_MOUNT, CONFIGURED)
    assert doc["handeye"]["difference_to_configured"]["rotation_deg"] == pytest.approx(want[1], abs=0.2)
    # the copy carries everything plus the record
    reader = RecordingReader(out_rec)
    stored = CalibrationResult.from_metadata(reader.calibration().calibration[METADATA_RECORD])
    assert stored.to_dict() == res.to_dict()
    assert len(reader.pose_trajectory("/uav1/mocap/uav1/pose")) == len(st.mocap)


def test_calibrate_time_table(flight, capsys) -> None:
    rec, cam, _ = flight
    assert main(["calibrate", "time", str(rec), "--camera-trajectory", str(cam)]) == 0
    out = capsys.readouterr().out
    assert "time offset (camera - mocap)" in out and "ppm" in out


def test_calibrate_refuses_a_pure_translation_with_exit_code_1(tmp_path: Path, capsys) -> None:
    st = simulate_streams(calibration_motion(Circle(radius_m=1.0, period_s=20.0, height_m=1.5), rock_deg=(0, 0, 0),
                                             follow_yaw=False), 20.0, T_body_camera=TRUE_MOUNT)
    rec, cam = tmp_path / "flat.mcap", tmp_path / "vo.txt"
    write_recording(rec, st)
    write_tum(cam, st.camera)
    assert main(["calibrate", "time", str(rec), "--camera-trajectory", str(cam)]) == 1
    err = capsys.readouterr().err
    assert "too little rotation to tell" in err and "at least two axes" in err


def test_export_applies_a_stored_calibration(tmp_path: Path) -> None:
    from capture.export import export_recording
    from flightkit.calibration import CalibrationResult
    from flightkit.datasets.mcap_metadata import with_metadata
    from flightkit.datasets.trajectory import read_tum
    from tests.integration.test_capture_sources import write_lab_recording

    rec = tmp_path / "lab.mcap"
    write_lab_recording(rec, frames=12)
    cal = CalibrationResult(time_offset_ms=5.0, drift_ppm=0.0, ref_ns=0, T_body_camera=TRUE_MOUNT)
    calibrated = with_metadata(rec, tmp_path / "cal.mcap", METADATA_RECORD, cal.to_metadata())
    plain = export_recording(rec, tmp_path / "plain", "tum")
    applied = export_recording(calibrated, tmp_path / "applied", "tum")
    assert any("calibrate" in n for n in applied.notes) and not any("calibrate" in n for n in plain.notes)
    gt_plain = read_tum(tmp_path / "plain" / "groundtruth.txt")
    gt_cal = read_tum(tmp_path / "applied" / "groundtruth.txt")
    # the same mocap samples, 5 ms later on the camera's clock, seen through the calibrated mount
    assert list(gt_cal.stamps_ns - gt_plain.stamps_ns) == [5_000_000] * len(gt_plain)
    body = gt_plain.transform(3)  # plain export: T_body_camera from tf (identity) -> the body pose
    assert gt_cal.transform(3).almost_equal(body @ TRUE_MOUNT, tol_m=1e-6, tol_rad=1e-6)
    assert export_recording(calibrated, tmp_path / "off", "tum", use_calibration=False).notes == plain.notes


def test_a_recording_sequence_reads_with_its_stored_calibration(tmp_path: Path) -> None:
    from flightkit.calibration import CalibrationResult
    from flightkit.datasets import open_sequence
    from flightkit.datasets.mcap_metadata import with_metadata
    from tests.integration.test_capture_sources import write_lab_recording

    rec = tmp_path / "lab.mcap"
    write_lab_recording(rec, frames=12)
    cal = CalibrationResult(time_offset_ms=5.0, drift_ppm=0.0, ref_ns=0, T_body_camera=TRUE_MOUNT)
    calibrated = with_metadata(rec, rec, METADATA_RECORD, cal.to_metadata())  # in place
    assert calibrated == rec
    seq = open_sequence(rec)
    raw = open_sequence(rec, use_calibration=False)
    assert seq.T_body_camera.almost_equal(TRUE_MOUNT)
    gt, gt_raw = seq.groundtruth(), raw.groundtruth()
    assert list(gt.stamps_ns - gt_raw.stamps_ns) == [5_000_000] * len(gt)
    assert len(list(seq.frames())) == len(raw) == 12
