"""A camera's rolling-shutter readout from its calibration, over the bus, into a recording and back,
and into live VO.

A source publishes on one Zenoh session and a BusRecorder on a second one (joined over loopback TCP)
writes the MCAP file; the camera's answer to the calibration query lands in ``calibration.<camera>``
(flightkit/bus/camera_calibration.py), which McapSequence, export and ``capture info`` read.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from capture.bus_recorder import BusRecorder
from capture.export import export_recording
from capture.info import recording_info
from capture.sources.opencv import OpenCVCameraPublisher, camera_model_from_calibration
from flightkit.bus.keys import Keys
from flightkit.clock import SimClock
from flightkit.datasets import open_sequence
from flightkit.datasets.mcap_metadata import with_metadata
from flightkit.datasets.mcap_reader import RecordingReader
from flightkit.errors import CaptureError, DatasetError
from tests.conftest import wait
from tests.integration.test_capture_sources import make_video, write_lab_recording


@pytest.mark.parametrize("fmt", ["bgr8", "jpeg"])
def test_a_calibration_readout_reaches_the_recording(
    sessions: tuple[object, object], tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The calibration file's readout_s travels over the bus to a recorder on another session,
    into calibration.color, and reads back as the sequence's intrinsics."""
    from flightkit.cli.main import main as flightkit_main

    pub_s, rec_s = sessions
    video = tmp_path / "clip.avi"
    make_video(video, 6, readout_s=0.02)
    out = tmp_path / "rs.mcap"
    cam = OpenCVCameraPublisher(pub_s, Keys("uav1"), str(video), SimClock(speed=20.0), color_format=fmt)
    assert cam.model.readout_s == 0.02  # camera_model_from_calibration keeps it
    with BusRecorder(rec_s, out, ["uav1/**"], compression="none") as rec:
        wait(lambda: cam.has_subscribers, 10, "the recorder to subscribe")
        with cam:
            assert cam.wait_finished(30) == 6
            wait(lambda: "uav1/camera/color/camera_info" in rec.calibrated, 10, "the calibration record")
            rec.wait_for(lambda st: st.get(cam.info_key) is not None and st[cam.info_key].count >= 6, 10)
    record = RecordingReader(out).metadata["calibration.color"]
    assert record["readout_s"] == "0.02" and record["topic"] == "uav1/camera/color/camera_info"
    assert record["k"].split()[0] == "150.0"  # still the camera_info's calibration beside it
    seq = open_sequence(out)
    assert seq.intrinsics.readout_s == 0.02 and seq.intrinsics.fx == 150.0
    assert recording_info(out).readouts_s == {"/uav1/camera/color/camera_info": 0.02}
    assert flightkit_main(["capture", "info", str(out)]) == 0
    assert "rolling shutter: /uav1/camera/color readout 20 ms" in capsys.readouterr().out


def test_a_recording_without_a_readout_reads_as_a_global_shutter(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Recordings made before readouts were recorded (no readout_s, or no calibration record at all)."""
    from flightkit.cli.main import main as flightkit_main

    src = tmp_path / "old.mcap"
    write_lab_recording(src, frames=4)
    assert not any(name.startswith("calibration.") for name in RecordingReader(src).metadata)
    assert open_sequence(src).intrinsics.readout_s == 0.0
    old = with_metadata(src, tmp_path / "old_record.mcap", "calibration.color",
                        {"topic": "uav1/camera/color/camera_info", "source": "camera_info"})
    seq = open_sequence(old)
    assert seq.intrinsics.readout_s == 0.0 and seq.depth_intrinsics is not None
    assert seq.depth_intrinsics.readout_s == 0.0
    assert recording_info(old).readouts_s == {}
    assert flightkit_main(["capture", "info", str(old)]) == 0
    assert "rolling shutter" not in capsys.readouterr().out
    # Another vehicle's colour camera in the record: not this one's readout.
    other = with_metadata(src, tmp_path / "other.mcap", "calibration.color",
                          {"topic": "uav2/camera/color/camera_info", "readout_s": "0.02"})
    assert open_sequence(other).intrinsics.readout_s == 0.0


def test_a_fleet_recording_keeps_each_vehicles_readout(sessions: tuple[object, object], tmp_path: Path) -> None:
    """Two vehicles' colour cameras under one recorder: both records are named calibration.color,
    and each camera reads back its own readout (by its topic)."""
    from flightkit.bus.streams import CameraModel, CameraStream

    pub_s, rec_s = sessions
    out = tmp_path / "fleet.mcap"
    readouts = {"uav1": 0.02, "uav2": 0.0}
    cams = {
        ns: CameraStream(pub_s, Keys(ns), "color", CameraModel(160, 120, 150.0, 150.0, 80.0, 60.0, readout_s=r), "rgb8")
        for ns, r in readouts.items()
    }
    frame = np.zeros((120, 160, 3), np.uint8)
    try:
        with BusRecorder(rec_s, out, ["uav1/**", "uav2/**"], compression="none") as rec:
            wait(lambda: all(c.has_subscribers for c in cams.values()), 10, "the recorder to subscribe")
            for i, cam in enumerate(cams.values()):
                cam.publish(1_000 + i, frame)
            wait(lambda: len(rec.calibrated) == 2, 10, "both calibration records")
    finally:
        for cam in cams.values():
            cam.close()
    reader = RecordingReader(out)
    for ns, readout in readouts.items():
        assert reader.camera_readout_s(f"/{ns}/camera/color/camera_info") == readout, ns
    assert recording_info(out).readouts_s == {"/uav1/camera/color/camera_info": 0.02}


@pytest.mark.parametrize("bad", ["fast", "-0.01", "nan", "inf"])
def test_a_malformed_readout_is_refused_naming_the_record(tmp_path: Path, bad: str) -> None:
    src = tmp_path / "src.mcap"
    write_lab_recording(src, frames=4)
    rec = with_metadata(src, tmp_path / "bad.mcap", "calibration.color",
                        {"topic": "uav1/camera/color/camera_info", "readout_s": bad})
    with pytest.raises(DatasetError, match=r"record calibration\.color gives readout_s") as info:
        open_sequence(rec)
    assert repr(bad) in str(info.value) and "with_metadata" in str(info.value)
    with pytest.raises(CaptureError, match=r"calibration\.color"):
        export_recording(rec, tmp_path / "tum", "tum")
    assert np.isnan(recording_info(rec).readouts_s["/uav1/camera/color/camera_info"])


def test_a_bad_calibration_readout_is_refused(tmp_path: Path) -> None:
    calib = tmp_path / "cal.json"
    calib.write_text(json.dumps({"fx": 100, "fy": 100, "cx": 80, "cy": 60, "width": 160, "height": 120,
                                 "readout_s": -0.02}))
    with pytest.raises(CaptureError, match=r"cal\.json: camera readout_s is -0\.02; give the rolling shutter"):
        camera_model_from_calibration(calib)


@pytest.mark.parametrize("served", [0.02, None])
def test_live_vo_takes_the_readout_the_camera_serves(sessions: tuple[object, object], served: float | None) -> None:
    """Live VO asks the camera for its calibration at its first camera_info: a flightkit camera's
    readout joins the intrinsics; a driver that serves none (camera_info only) is a global shutter."""
    from estimation.live import LiveVo
    from flightkit.bus.image_msgs import CameraInfo
    from flightkit.bus.pubsub import BusPublisher
    from flightkit.bus.streams import CameraModel, CameraStream
    from flightkit.frames import Transform

    pub_s, vo_s = sessions
    keys = Keys("uav1")
    model = CameraModel(160, 120, 150.0, 150.0, 80.0, 60.0, readout_s=served or 0.0)

    async def main() -> object:
        async with LiveVo(vo_s, keys, SimClock(), T_body_camera=Transform()) as vo:
            if served is not None:
                cam = CameraStream(pub_s, keys, "color", model, "rgb8")
                frame = np.zeros((120, 160, 3), np.uint8)
                send = lambda i: cam.publish(i, frame)  # noqa: E731
            else:  # another driver: camera_info, no calibration key
                info = BusPublisher(pub_s, keys.camera_info("color"), CameraInfo, reliable=True)
                cam = info
                send = lambda i: info.put(model.camera_info(i, "color_optical").encode(), i)  # noqa: E731
            try:
                for i in range(1, 2000):
                    send(i)
                    if vo.camera is not None:
                        break
                    await asyncio.sleep(0.005)
            finally:
                cam.close()
            assert vo.camera is not None, "live VO never got the camera"
            return vo.camera

    camera = asyncio.run(main())
    assert camera.fx == 150.0 and camera.width == 160  # type: ignore[attr-defined]
    assert camera.readout_s == (served or 0.0)  # type: ignore[attr-defined]
