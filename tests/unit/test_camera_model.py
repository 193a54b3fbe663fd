"""A published camera's calibration (flightkit.bus.streams.CameraModel) and where its readout is served."""

from __future__ import annotations

import dataclasses
import math

import pytest

from flightkit.bus.camera_calibration import calibration_key
from flightkit.bus.keys import Keys
from flightkit.bus.streams import CameraModel
from flightkit.errors import BusError


def test_the_readout_defaults_to_a_global_shutter_and_goes_into_the_metadata() -> None:
    assert CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5).readout_s == 0.0
    model = CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5, readout_s=0.02)
    meta = model.as_metadata()
    assert meta["readout_s"] == "0.02" and meta["fx"] == "500.0"
    assert float(meta["readout_s"]) == model.readout_s  # the string reads back exactly


@pytest.mark.parametrize("bad", [-0.001, math.nan, math.inf, "fast", None])
def test_a_bad_readout_is_refused_with_the_value_and_the_fix(bad: object) -> None:
    with pytest.raises(BusError, match="give the rolling shutter's readout in seconds") as info:
        CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5, readout_s=bad)  # type: ignore[arg-type]
    assert repr(bad) in str(info.value)
    with pytest.raises(BusError):
        dataclasses.replace(CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5), readout_s=bad)


def test_the_calibration_key_sits_beside_camera_info() -> None:
    keys = Keys("uav1")
    assert keys.camera_calibration("color") == "uav1/camera/color/calibration"
    assert calibration_key(keys.camera_info("color")) == keys.camera_calibration("color")
    assert calibration_key("/replay/uav1/camera/left/camera_info") == "replay/uav1/camera/left/calibration"
    with pytest.raises(BusError, match="not a camera_info key"):
        calibration_key("uav1/camera/color/image")
