"""The MAVSDK :class:`~flightkit.link.base.VehicleLink` backend.

:class:`MavsdkLink` drives a PX4 or ArduPilot autopilot (or the simulator) through MAVSDK 4.x,
the native binding with its asyncio API. The package, by concern (named as in
:mod:`flightkit.link.mavlink` where the concepts match):

* :mod:`~flightkit.link.mavsdk.link`: :class:`MavsdkLink` itself (connect/close,
  arm/mode/takeoff/land, external pose, waits);
* :mod:`~flightkit.link.mavsdk.stream`: the background velocity-setpoint stream on the
  offboard plugin (:class:`~flightkit.link.mavsdk.stream.SetpointStream`), and how its
  semantics differ from the pymavlink backend's;
* :mod:`~flightkit.link.mavsdk.commands`: plugin calls with deadlines, refusals with the
  autopilot's reasons, MAV_CMD_DO_SET_MODE through ``mavlink_direct``;
* :mod:`~flightkit.link.mavsdk.telemetry`: the telemetry subscriptions folded into the
  vehicle state, and waiting on it;
* :mod:`~flightkit.link.mavsdk.connection`: the MAVSDK instance, its plugins, its log lines;
* :mod:`~flightkit.link.mavsdk.encoding`: pure conversions (URLs, setpoints, poses).

Import the public names from here: ``from flightkit.link.mavsdk import MavsdkLink``.
"""

from __future__ import annotations

from flightkit.link.mavsdk.encoding import (
    NedPose,
    external_pose_to_ned,
    mavsdk_url,
    pose_covariance_upper,
    setpoint_to_mavsdk,
)
from flightkit.link.mavsdk.link import MavsdkLink

__all__ = [
    "MavsdkLink",
    "NedPose",
    "external_pose_to_ned",
    "mavsdk_url",
    "pose_covariance_upper",
    "setpoint_to_mavsdk",
]
