"""isinstance(link, VehicleLink) answers without connecting (a property that raises is not run)."""

from __future__ import annotations

import pytest

from flightkit.clock import WallClock
from flightkit.config import Autopilot, LinkConfig
from flightkit.errors import LinkError
from flightkit.link.base import VehicleLink
from flightkit.link.mavlink import MavlinkLink
from flightkit.link.mavsdk import MavsdkLink


def test_unconnected_backends_are_vehicle_links() -> None:
    cfg = LinkConfig(url="udpin://127.0.0.1:0")
    pymavlink_link = MavlinkLink(cfg, Autopilot.PX4, WallClock())
    with pytest.raises(LinkError, match="not connected"):
        _ = pymavlink_link.info  # the property raises before connect() ...
    assert isinstance(pymavlink_link, VehicleLink)  # ... and isinstance still answers
    # MAVSDK needs a fixed port in its URL; nothing is opened before connect().
    mavsdk_link = MavsdkLink(LinkConfig(url="udpin://127.0.0.1:14540"), Autopilot.PX4, WallClock())
    with pytest.raises(LinkError, match="not connected"):
        _ = mavsdk_link.info
    assert isinstance(mavsdk_link, VehicleLink)


class _MissingMembers:
    @property
    def info(self) -> object:
        raise LinkError("not connected")


def test_objects_lacking_members_are_not_vehicle_links() -> None:
    assert not isinstance(_MissingMembers(), VehicleLink)
    assert not isinstance(object(), VehicleLink)


def test_a_method_set_to_none_blocks_the_match() -> None:
    link = MavlinkLink(LinkConfig(url="udpin://127.0.0.1:0"), Autopilot.PX4, WallClock())
    link.arm = None  # type: ignore[assignment,method-assign]
    assert not isinstance(link, VehicleLink)


def test_command_results_are_named_as_mavlink_defines_them() -> None:
    from flightkit.link.mavlink.encoding import result_name

    assert result_name(2) == "DENIED"
    assert result_name(6) == "CANCELLED"  # missing from pymavlink 2.4's table
    assert result_name(9) == "COMMAND_UNSUPPORTED_MAV_FRAME"
    assert result_name(42) == "MAV_RESULT_42"
