"""What the autopilot does when flightkit stops, from its parameters (flightkit.link.failsafe)."""

from __future__ import annotations

import struct

import pytest

from flightkit.config import Autopilot
from flightkit.link.base import firmware_traits
from flightkit.link.failsafe import ARDUPILOT_PARAMS, PX4_PARAMS, companion_loss
from flightkit.link.mavlink.encoding import decode_param_value

APM_DEFAULTS = {"FS_GCS_ENABLE": 0.0, "FS_GCS_TIMEOUT": 5.0, "GUID_TIMEOUT": 3.0, "MAV_GCS_SYSID": 255.0}
PX4_DEFAULTS = {
    "COM_OF_LOSS_T": 1.0,
    "COM_OBL_RC_ACT": 0.0,
    "COM_RCL_EXCEPT": 0.0,
    "NAV_RCL_ACT": 2.0,
    "COM_RC_IN_MODE": 3.0,
}


def apm(**changes: float) -> dict[str, float]:
    return {**APM_DEFAULTS, **changes}


def px4(**changes: float) -> dict[str, float]:
    return {**PX4_DEFAULTS, **changes}


def test_arducopter_defaults_hover_until_the_battery_runs_out() -> None:
    v = companion_loss(Autopilot.ARDUPILOT, APM_DEFAULTS, 255)
    assert v.hovers
    assert v.summary == (
        "if flightkit stops: ArduCopter keeps the last velocity 3 s (GUID_TIMEOUT), brakes, then hovers "
        "armed in GUIDED until the battery runs out (FS_GCS_ENABLE = 0)"
    )
    assert "set FS_GCS_ENABLE = 5" in v.reason and v.unread == ()


@pytest.mark.parametrize(("enable", "action"), [(5, "lands"), (1, "returns (RTL) and lands")])
def test_arducopter_gcs_failsafe_watching_us_lands(enable: int, action: str) -> None:
    v = companion_loss(Autopilot.ARDUPILOT, apm(FS_GCS_ENABLE=enable, FS_GCS_TIMEOUT=3.5), 255)
    assert not v.hovers and v.reason == ""
    assert f"3.5 s (FS_GCS_TIMEOUT) after flightkit's last heartbeat its GCS failsafe {action}" in v.summary


def test_arducopter_gcs_failsafe_brake_hovers() -> None:
    v = companion_loss(Autopilot.ARDUPILOT, apm(FS_GCS_ENABLE=7), 255)
    assert v.hovers and "FS_GCS_ENABLE = 7" in v.summary and "set FS_GCS_ENABLE = 5" in v.reason


def test_arducopter_gcs_failsafe_watching_another_system_hovers() -> None:
    v = companion_loss(Autopilot.ARDUPILOT, apm(FS_GCS_ENABLE=5, MAV_GCS_SYSID=255), 200)
    assert v.hovers and "set MAV_GCS_SYSID = 200" in v.reason


def test_older_arducopter_names_its_gcs_sysid_sysid_mygcs() -> None:
    params = apm(FS_GCS_ENABLE=5)
    del params["MAV_GCS_SYSID"]
    assert not companion_loss(Autopilot.ARDUPILOT, {**params, "SYSID_MYGCS": 255.0}, 255).hovers
    v = companion_loss(Autopilot.ARDUPILOT, {**params, "SYSID_MYGCS": 254.0}, 255)
    assert v.hovers and "SYSID_MYGCS = 254" in v.reason


@pytest.mark.parametrize("missing", ["FS_GCS_ENABLE", "MAV_GCS_SYSID"])
def test_an_unread_arducopter_parameter_is_named_and_assumed_to_hover(missing: str) -> None:
    params = apm(FS_GCS_ENABLE=5)
    del params[missing]
    v = companion_loss(Autopilot.ARDUPILOT, params, 255)
    assert v.hovers and missing in v.unread
    assert v.reason.startswith(f"{missing} could not be read")
    assert f"({missing} could not be read from the vehicle; assumed the worst)" in v.summary


def test_an_unread_timeout_is_said_but_does_not_refuse() -> None:
    params = apm(FS_GCS_ENABLE=5)
    del params["GUID_TIMEOUT"]
    v = companion_loss(Autopilot.ARDUPILOT, params, 255)
    assert not v.hovers and v.unread == ("GUID_TIMEOUT",)
    assert "GUID_TIMEOUT (unknown)" in v.summary


def test_px4_defaults_fall_back_to_position_mode_and_rc_loss_returns() -> None:
    v = companion_loss(Autopilot.PX4, PX4_DEFAULTS, 255)
    assert not v.hovers
    assert "after 1 s (COM_OF_LOSS_T) to Position mode" in v.summary and "Return (NAV_RCL_ACT = 2)" in v.summary


@pytest.mark.parametrize(
    ("changes", "why"),
    [
        ({"COM_OBL_RC_ACT": 5, "COM_RCL_EXCEPT": 2}, "RC loss is ignored in Hold"),
        ({"COM_OBL_RC_ACT": 5, "COM_RCL_EXCEPT": 7}, "RC loss is ignored in Hold"),
        ({"NAV_RCL_ACT": 0}, "does not end the flight (NAV_RCL_ACT = 0)"),
        ({"COM_OBL_RC_ACT": 5, "NAV_RCL_ACT": 1}, "does not end the flight (NAV_RCL_ACT = 1)"),
        ({"COM_RC_IN_MODE": 4}, "manual control is disabled"),
    ],
)
def test_px4_settings_that_never_end_the_hover_are_refused(changes: dict[str, float], why: str) -> None:
    v = companion_loss(Autopilot.PX4, px4(**changes), 255)
    assert v.hovers and why in v.reason and "set COM_OBL_RC_ACT = 4 (Land)" in v.reason
    assert "hovers armed until the battery runs out" in v.summary


@pytest.mark.parametrize(("act", "says"), [(3, "Return mode"), (4, "Land mode"), (7, "disarm")])
def test_px4_offboard_loss_actions_that_end_the_flight(act: int, says: str) -> None:
    v = companion_loss(Autopilot.PX4, px4(COM_OBL_RC_ACT=act, COM_RC_IN_MODE=4), 255)
    assert not v.hovers and says in v.summary


def test_px4_hold_with_rc_loss_excepted_only_in_offboard_still_returns() -> None:
    assert not companion_loss(Autopilot.PX4, px4(COM_OBL_RC_ACT=5, COM_RCL_EXCEPT=4), 255).hovers


@pytest.mark.parametrize("missing", ["COM_OBL_RC_ACT", "NAV_RCL_ACT", "COM_RC_IN_MODE"])
def test_an_unread_px4_parameter_is_named_and_assumed_to_hover(missing: str) -> None:
    params = px4()
    del params[missing]
    v = companion_loss(Autopilot.PX4, params, 255)
    assert v.hovers and missing in v.unread and "could not" in v.reason


def test_the_traits_name_the_parameters_of_each_firmware() -> None:
    assert firmware_traits(Autopilot.ARDUPILOT).failsafe_params == ARDUPILOT_PARAMS
    assert firmware_traits(Autopilot.ARDUPILOT).failsafe_param_fallbacks == {"MAV_GCS_SYSID": "SYSID_MYGCS"}
    assert firmware_traits(Autopilot.PX4).failsafe_params == PX4_PARAMS
    assert firmware_traits(Autopilot.PX4).companion_loss(PX4_DEFAULTS, 255) == companion_loss(
        Autopilot.PX4, PX4_DEFAULTS, 255
    )


@pytest.mark.parametrize(("value", "ptype"), [(5, 6), (-1, 6), (200, 1), (-3, 2), (40000, 3), (255, 4)])
def test_param_values_decode_bytewise_and_c_cast(value: int, ptype: int) -> None:
    fmt = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 6: "<i"}[ptype]
    raw = struct.pack(fmt, value).ljust(4, b"\0")
    wire = struct.unpack("<f", raw)[0]
    assert decode_param_value(wire, ptype, bytewise=True) == value
    assert decode_param_value(float(value), ptype, bytewise=False) == value
    assert decode_param_value(2.5, 9, bytewise=True) == 2.5  # REAL32 is the float itself


def test_the_simulated_firmwares_serve_the_factory_defaults_and_the_lab_set_up_lands() -> None:
    from flightkit.sim.personality import ARDUPILOT, PX4

    apm_factory = {n: float(s.default) for n, s in ARDUPILOT.params.items()}
    assert {n: apm_factory[n] for n in APM_DEFAULTS} == APM_DEFAULTS  # ArduCopter 4.7 as shipped
    assert companion_loss(Autopilot.ARDUPILOT, apm_factory, 255).hovers
    assert not companion_loss(Autopilot.ARDUPILOT, {**apm_factory, **ARDUPILOT.lab_params}, 255).hovers
    px4_factory = {n: float(s.default) for n, s in PX4.params.items()}
    assert {n: px4_factory[n] for n in PX4_DEFAULTS} == PX4_DEFAULTS  # PX4 1.14 as shipped
    assert not companion_loss(Autopilot.PX4, px4_factory, 255).hovers and not PX4.lab_params
