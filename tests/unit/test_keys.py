"""Key-expression naming (flightkit.bus.keys)."""

from __future__ import annotations

import pytest

from flightkit.bus.keys import Keys, check_name
from flightkit.errors import BusError


def test_keys_of_a_namespace() -> None:
    k = Keys("uav1")
    assert k.mocap_pose("uav1") == "uav1/mocap/uav1/pose"
    assert k.mocap_all() == "uav1/mocap/*/pose"
    assert k.camera_image("color") == "uav1/camera/color/image"
    assert k.camera_compressed("left") == "uav1/camera/left/image/compressed"
    assert k.camera_info("depth") == "uav1/camera/depth/camera_info"
    assert k.tf() == "uav1/tf"
    assert k.odometry("orb") == "uav1/odometry/orb"
    assert k.everything() == "uav1/**"


def test_nested_namespace_is_allowed() -> None:
    assert Keys("lab2/uav-3").mocap_pose("cf_1") == "lab2/uav-3/mocap/cf_1/pose"


@pytest.mark.parametrize("bad", ["", "a b", "a*", "a/b", "$x", "a?", "a#", "**"])
def test_bad_names_are_refused_with_the_value(bad: str) -> None:
    with pytest.raises(BusError, match="not a valid bus name") as info:
        Keys("uav1").mocap_pose(bad)
    assert repr(bad) in str(info.value)


@pytest.mark.parametrize("bad", ["", "uav 1", "uav1/", "/uav1", "uav*"])
def test_bad_namespaces_are_refused(bad: str) -> None:
    with pytest.raises(BusError):
        Keys(bad)


def test_check_name_returns_the_name() -> None:
    assert check_name("color_1", "camera") == "color_1"
