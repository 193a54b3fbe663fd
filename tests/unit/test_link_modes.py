"""PX4 and ArduPilot mode tables."""

from __future__ import annotations

import pytest

from flightkit.config import Autopilot
from flightkit.errors import LinkError
from flightkit.link.base import FlightMode
from flightkit.link.modes import (
    ARDUPILOT_COPTER_MODES,
    PX4_MODES,
    autopilot_from_heartbeat,
    custom_mode_for,
    decode_mode,
    mode_from_command,
    resolve_mode,
    set_mode_params,
)


def test_px4_custom_modes_match_the_firmware() -> None:
    # Values observed in PX4 1.14 heartbeats (FACTS.md).
    assert PX4_MODES[FlightMode.OFFBOARD] == 393216
    assert PX4_MODES[FlightMode.POSCTL] == 196608
    assert PX4_MODES[FlightMode.HOLD] == 50593792
    assert PX4_MODES[FlightMode.LAND] == 100925440


def test_ardupilot_copter_numbers() -> None:
    assert ARDUPILOT_COPTER_MODES[FlightMode.GUIDED] == 4
    assert ARDUPILOT_COPTER_MODES[FlightMode.LOITER] == 5
    assert ARDUPILOT_COPTER_MODES[FlightMode.LAND] == 9
    assert ARDUPILOT_COPTER_MODES[FlightMode.BRAKE] == 17


@pytest.mark.parametrize("autopilot", list(Autopilot))
def test_every_mode_round_trips_through_heartbeat_and_command(autopilot: Autopilot) -> None:
    table = PX4_MODES if autopilot is Autopilot.PX4 else ARDUPILOT_COPTER_MODES
    for mode, custom in table.items():
        cmd = set_mode_params(autopilot, mode)
        assert cmd.mode is mode and cmd.custom_mode == custom
        assert decode_mode(autopilot, 1 | 128, custom) is mode  # armed flag does not matter
        assert mode_from_command(autopilot, cmd.params) is mode


def test_px4_do_set_mode_params() -> None:
    assert set_mode_params(Autopilot.PX4, FlightMode.OFFBOARD).params == (1.0, 6.0, 0.0)
    assert set_mode_params(Autopilot.PX4, FlightMode.LAND).params == (1.0, 4.0, 6.0)
    assert set_mode_params(Autopilot.ARDUPILOT, FlightMode.GUIDED).params == (1.0, 4.0, 0.0)


def test_aliases_resolve_to_the_firmware_equivalent() -> None:
    assert resolve_mode(Autopilot.PX4, FlightMode.LOITER) is FlightMode.HOLD
    assert resolve_mode(Autopilot.ARDUPILOT, FlightMode.HOLD) is FlightMode.BRAKE
    assert custom_mode_for(Autopilot.ARDUPILOT, FlightMode.HOLD) == 17


def test_missing_modes_raise_with_the_alternatives() -> None:
    with pytest.raises(LinkError, match="px4 has no GUIDED mode; use one of: .*OFFBOARD"):
        set_mode_params(Autopilot.PX4, FlightMode.GUIDED)
    with pytest.raises(LinkError, match="ardupilot has no OFFBOARD mode; use one of: .*GUIDED"):
        set_mode_params(Autopilot.ARDUPILOT, FlightMode.OFFBOARD)


def test_decoding_unknown_and_non_custom_modes() -> None:
    assert decode_mode(Autopilot.PX4, 0, 393216) is FlightMode.UNKNOWN  # custom mode flag not set
    assert decode_mode(Autopilot.PX4, 1, 8 << 16) is FlightMode.UNKNOWN  # RATTITUDE: not in our table
    assert decode_mode(Autopilot.PX4, 1, (6 << 16) | (3 << 24)) is FlightMode.OFFBOARD  # stray sub-mode bits
    assert decode_mode(Autopilot.ARDUPILOT, 1, 13) is FlightMode.UNKNOWN  # SPORT


def test_autopilot_from_heartbeat() -> None:
    assert autopilot_from_heartbeat(12) is Autopilot.PX4
    assert autopilot_from_heartbeat(3) is Autopilot.ARDUPILOT
    assert autopilot_from_heartbeat(8) is None  # MAV_AUTOPILOT_INVALID (a GCS)
