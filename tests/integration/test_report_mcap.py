"""The reporter reads pose samples from an MCAP recording written by our recorder."""

from pathlib import Path

import numpy as np
import pytest

from capture.recorder import Recorder, StreamSample
from estimation.report.reporter import read_mcap_samples
from flightkit.bus.msgs import PoseStamped, schema_text
from flightkit.errors import DatasetError
from flightkit.frames import Transform


def test_read_mcap_samples_round_trip(tmp_path: Path) -> None:
    out = tmp_path / "poses.mcap"
    rec = Recorder(out, schema_text)
    truth = [Transform.from_xyz_yaw([0.1 * i, -0.2 * i, 1.5], 0.05 * i) for i in range(50)]
    for i, T in enumerate(truth):
        stamp = 1_700_000_000_000_000_000 + i * 10_000_000
        msg = PoseStamped.from_transform(stamp, "mocap", T)
        rec.offer(StreamSample("uav1/mocap/uav1/pose", PoseStamped.TYPE, bytes(msg.encode()), i, stamp, stamp))
    assert rec.close().error == ""
    samples = read_mcap_samples(out)
    assert len(samples) == 50
    for s, T in zip(samples, truth, strict=True):
        np.testing.assert_allclose(s.T_world_body.translation, T.translation)
        assert s.T_world_body.almost_equal(T, 1e-12, 1e-9)
    assert samples[1].stamp_ns - samples[0].stamp_ns == 10_000_000
    with pytest.raises(DatasetError, match="no PoseStamped topic"):
        read_mcap_samples(out, topic="/nope")
