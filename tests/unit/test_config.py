import math
from pathlib import Path

import numpy as np
import pytest

from flightkit.config import Autopilot, LabConfig, LinkBackend, load_config
from flightkit.errors import ConfigError


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "lab.toml"
    p.write_text(text)
    return p


def test_defaults_are_valid() -> None:
    cfg = load_config()
    assert isinstance(cfg, LabConfig)
    assert cfg.link.setpoint_rate_hz == 50.0
    assert cfg.vehicle.autopilot is Autopilot.PX4


def test_full_file_loads(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        """
[vehicle]
namespace = "cf7"
autopilot = "ardupilot"
[link]
url = "udpin:0.0.0.0:14550"
backend = "mavsdk"
setpoint_rate_hz = 100
[mocap]
body = "cf7"
[mocap.T_world_mocap]
translation_m = [1.0, 2.0, 0.0]
rpy_deg = [0.0, 0.0, 90.0]
[bus]
connect = ["tcp/192.168.1.10:7447"]
""",
    )
    cfg = load_config(p)
    assert cfg.source_path == str(p)
    assert cfg.vehicle.autopilot is Autopilot.ARDUPILOT
    assert cfg.link.backend is LinkBackend.MAVSDK
    assert cfg.link.setpoint_rate_hz == 100.0 and isinstance(cfg.link.setpoint_rate_hz, float)
    assert cfg.bus.connect == ("tcp/192.168.1.10:7447",)
    T = cfg.mocap.T_world_mocap.to_transform()
    # mocap x axis points along world y after a 90 deg yaw
    np.testing.assert_allclose(T.apply([1.0, 0.0, 0.0]), [1.0, 3.0, 0.0], atol=1e-12)


@pytest.mark.parametrize(
    ("text", "key", "fragment"),
    [
        ("[link]\nurll = 'x'\n", "link.urll", "unknown key"),
        ("[lnk]\n", "lnk", "unknown key"),
        ("[link]\nbaud = 'fast'\n", "link.baud", "expected an integer"),
        ("[link]\nsetpoint_rate_hz = 0.5\n", "link.setpoint_rate_hz", "out of range"),
        ("[vehicle]\nautopilot = 'betaflight'\n", "vehicle.autopilot", "not allowed"),
        ("[mocap.T_world_mocap]\ntranslation_m = [1, 2]\n", "mocap.T_world_mocap.translation_m", "expected 3"),
        ("[mocap.T_world_mocap]\nquat_wxyz = [1, 1, 0, 0]\n", "mocap.T_world_mocap.quat_wxyz", "norm"),
        ("[sim]\nspeed = nan\n", "sim.speed", "not finite"),
    ],
)
def test_errors_name_file_key_value_and_fix(tmp_path: Path, text: str, key: str, fragment: str) -> None:
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(p)
    err = info.value
    assert err.path == str(p)
    assert err.key == key
    assert fragment in str(err)
    assert str(p) in str(err) and key in str(err)
    assert err.fix  # every error says what to do


def test_out_of_range_message_carries_value(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, "[link]\nsetpoint_rate_hz = 9999\n"))
    assert "9999" in str(info.value) and "give a value from 2 to 500" in str(info.value)


def test_syntax_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(write(tmp_path, "[link\n"))
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml")


def test_camera_intrinsics_defaults_and_mount() -> None:
    cam = load_config().camera
    fx, fy, cx, cy = cam.intrinsics()
    assert fx == fy == cam.width_px / 2
    assert math.isclose(cx, (cam.width_px - 1) / 2)
    T_body_camera = cam.T_body_camera.to_transform()
    # The lab mount looks forward and 45 degrees down: optical axis (camera z) in the body frame.
    z_body = T_body_camera.rotation.apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(z_body, [math.sqrt(0.5), 0.0, -math.sqrt(0.5)], atol=1e-12)


def test_capability_sections_are_carried_and_validated_by_their_owner(tmp_path: Path) -> None:
    from dataclasses import dataclass

    from flightkit.settings import setting

    @dataclass(frozen=True, slots=True)
    class ReportSection:
        rate_hz: float = setting(10.0, min=0.1, max=100.0)

    cfg = load_config(write(tmp_path, "[report]\nrate_hz = 20\n[link]\nbaud = 115200\n"))
    assert cfg.section("report", ReportSection).rate_hz == 20.0
    assert cfg.section("capture", ReportSection).rate_hz == 10.0  # absent: defaults
    bad = load_config(write(tmp_path, "[report]\nrate_hz = 1000\n"))
    with pytest.raises(ConfigError, match="report.rate_hz"):
        bad.section("report", ReportSection)
    with pytest.raises(ConfigError, match="nonsense: is not a registered capability section"):
        cfg.section("nonsense", ReportSection)
