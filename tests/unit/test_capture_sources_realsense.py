"""Pure parts of the capture sources: RealSense intrinsics -> CameraInfo, depth units, device specs."""

from __future__ import annotations

import enum
import importlib.util
from types import SimpleNamespace

import numpy as np
import pytest

from capture.sources.opencv import parse_device
from capture.sources.realsense import camera_model_from_intrinsics, depth_to_mm, import_realsense
from flightkit.bus.image_msgs import CameraInfo
from flightkit.bus.msg_base import Header
from flightkit.errors import CaptureError


class Distortion(enum.Enum):  # how pyrealsense2 spells its models (rs.distortion.brown_conrady ...)
    none = 0
    brown_conrady = 1
    kannala_brandt4 = 2
    inverse_brown_conrady = 3


def intrinsics(
    model: Distortion = Distortion.brown_conrady, coeffs: tuple[float, ...] = (0.0,) * 5
) -> SimpleNamespace:
    return SimpleNamespace(
        width=848, height=480, fx=421.5, fy=420.9, ppx=424.2, ppy=241.7, model=model, coeffs=list(coeffs)
    )


def test_intrinsics_become_camera_info() -> None:
    model = camera_model_from_intrinsics(intrinsics(coeffs=(0.1, -0.2, 0.001, 0.002, 0.05)))
    assert (model.width_px, model.height_px) == (848, 480)
    assert model.dist == (0.1, -0.2, 0.001, 0.002, 0.05)
    info = model.camera_info(123, "uav1/camera_color_optical")
    back = CameraInfo.decode(info.encode())
    assert back.k == (421.5, 0.0, 424.2, 0.0, 420.9, 241.7, 0.0, 0.0, 1.0)
    assert back.d == (0.1, -0.2, 0.001, 0.002, 0.05) and back.distortion_model == "plumb_bob"
    assert back.header == Header(123, "uav1/camera_color_optical")
    assert (back.width, back.height) == (848, 480)


def test_zero_coefficients_mean_no_distortion_and_fisheye_is_refused() -> None:
    assert camera_model_from_intrinsics(intrinsics()).dist == ()
    assert camera_model_from_intrinsics(intrinsics(Distortion.kannala_brandt4)).dist == ()  # zeros: harmless
    with pytest.raises(CaptureError, match="kannala_brandt4"):
        camera_model_from_intrinsics(intrinsics(Distortion.kannala_brandt4, (0.1, 0.0, 0.0, 0.0, 0.0)))
    with pytest.raises(CaptureError, match="not usable"):
        camera_model_from_intrinsics(SimpleNamespace(width=0, height=480, fx=1.0, fy=1.0, ppx=0.0, ppy=0.0))


def test_depth_scale_conversion_to_millimetres() -> None:
    raw = np.array([[0, 1, 1000, 65535]], np.uint16)
    same = depth_to_mm(raw, 0.001)
    assert same.dtype == np.uint16 and np.array_equal(same, raw) and same is not raw
    # 0.1 mm units (D4xx high-accuracy presets): rounded to the nearest millimetre, 0 stays 0.
    fine = np.array([[0, 4, 5, 12345, 65535]], np.uint16)
    assert depth_to_mm(fine, 0.0001).tolist() == [[0, 0, 0, 1234, 6554]]  # round half to even at 0.5
    # TUM-style 1/5000 m counts: exact for multiples of 5.
    assert depth_to_mm(np.array([[5, 5000, 65535]], np.uint16), 1 / 5000).tolist() == [[1, 1000, 13107]]
    # Float metres (scale 1): NaN, negative and out-of-range become 0 (no data).
    metres = np.array([[0.5, np.nan, -1.0, 70.0, np.inf]], np.float32)
    assert depth_to_mm(metres, 1.0).tolist() == [[500, 0, 0, 0, 0]]
    # Coarser units that overflow 16-bit millimetres are dropped, not wrapped.
    assert depth_to_mm(np.array([[60000]], np.uint16), 0.01).tolist() == [[0]]


def test_depth_buffer_is_reused() -> None:
    buf = np.empty((2, 3), np.uint16)
    out = depth_to_mm(np.full((2, 3), 2000, np.uint16), 0.0005, buf)
    assert out is buf and np.all(buf == 1000)
    assert depth_to_mm(np.zeros((4, 4), np.uint16), 0.001, buf).shape == (4, 4)  # wrong size: a new buffer


@pytest.mark.skipif(importlib.util.find_spec("pyrealsense2") is not None, reason="pyrealsense2 is installed")
def test_missing_package_says_how_to_install() -> None:
    with pytest.raises(CaptureError, match=r"pip install flightkit\[realsense\]"):
        import_realsense()


def test_device_specs() -> None:
    assert parse_device("0") == 0 and parse_device(2) == 2
    assert parse_device("/dev/video2") == "/dev/video2"
    assert parse_device(" rtsp://cam/stream ") == "rtsp://cam/stream"
