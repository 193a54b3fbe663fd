"""The reporter reads pose samples from an MCAP recording written by our recorder, in the world
frame: recorded mocap poses are in the mocap system's frame and the recording says where that is."""

import logging
from pathlib import Path

import numpy as np
import pytest

from capture.recorder import Recorder, StreamSample
from estimation.report.reporter import read_mcap_samples
from flightkit.bus.msg_base import schema_text
from flightkit.bus.pose_msgs import PoseStamped
from flightkit.datasets.mcap_reader import transform_to_json
from flightkit.errors import DatasetError, FrameError
from flightkit.frames import Transform

T_WORLD_MOCAP = Transform.from_xyz_yaw([0.5, -0.3, 0.0], np.deg2rad(30.0))
TOPIC = "uav1/mocap/uav1/pose"


def _truth() -> list[Transform]:
    return [Transform.from_xyz_yaw([0.1 * i, -0.2 * i, 1.5], 0.05 * i) for i in range(50)]


def _record(
    out: Path, poses: list[Transform], *, frame_id: str = "mocap", T_world_mocap: Transform | None = None  # noqa: N803
) -> Path:
    metadata: dict[str, dict[str, str]] = {}
    if T_world_mocap is not None:
        metadata["extrinsics"] = {"T_world_mocap": transform_to_json(T_world_mocap)}
    rec = Recorder(out, schema_text, metadata=metadata)
    for i, T in enumerate(poses):
        stamp = 1_700_000_000_000_000_000 + i * 10_000_000
        msg = PoseStamped.from_transform(stamp, frame_id, T)
        rec.offer(StreamSample(TOPIC, PoseStamped.TYPE, bytes(msg.encode()), i, stamp, stamp))
    assert rec.close().error == ""
    return out


def test_mocap_poses_are_placed_in_the_world_by_the_recordings_calibration(tmp_path: Path) -> None:
    truth_mocap = _truth()
    out = _record(tmp_path / "poses.mcap", truth_mocap, T_world_mocap=T_WORLD_MOCAP)
    samples = read_mcap_samples(out)
    assert len(samples) == 50
    for s, T in zip(samples, truth_mocap, strict=True):
        expected = T_WORLD_MOCAP @ T
        assert s.T_world_body.almost_equal(expected, 1e-9, 1e-9)
        # and not the raw mocap-frame pose: the calibration is 0.58 m and 30 deg away
        assert np.linalg.norm(s.T_world_body.translation - T.translation) > 0.3
    assert samples[1].stamp_ns - samples[0].stamp_ns == 10_000_000
    # an explicit calibration overrides the recording's own
    samples = read_mcap_samples(out, T_world_mocap=Transform.identity())
    assert samples[7].T_world_body.almost_equal(truth_mocap[7], 1e-9, 1e-9)


def test_world_frame_poses_are_taken_as_they_are(tmp_path: Path) -> None:
    truth = _truth()
    out = _record(tmp_path / "poses.mcap", truth, frame_id="world", T_world_mocap=T_WORLD_MOCAP)
    for s, T in zip(read_mcap_samples(out), truth, strict=True):
        assert s.T_world_body.almost_equal(T, 1e-9, 1e-9)


def test_a_recording_without_calibration_says_so(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    truth = _truth()
    out = _record(tmp_path / "poses.mcap", truth)
    with caplog.at_level(logging.WARNING):
        samples = read_mcap_samples(out)
    assert "no T_world_mocap metadata" in caplog.text
    assert samples[3].T_world_body.almost_equal(truth[3], 1e-9, 1e-9)


def test_an_unknown_frame_is_refused_by_name(tmp_path: Path) -> None:
    out = _record(tmp_path / "poses.mcap", _truth(), frame_id="odom_42", T_world_mocap=T_WORLD_MOCAP)
    with pytest.raises(FrameError, match="odom_42"):
        read_mcap_samples(out)


def test_a_missing_topic_is_named(tmp_path: Path) -> None:
    out = _record(tmp_path / "poses.mcap", _truth(), T_world_mocap=T_WORLD_MOCAP)
    with pytest.raises(DatasetError, match="no PoseStamped topic"):
        read_mcap_samples(out, topic="/nope")
