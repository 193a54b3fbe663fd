"""The pymavlink :class:`~flightkit.link.base.VehicleLink` backend.

:class:`MavlinkLink` talks MAVLink 2 to a PX4 or ArduPilot autopilot (or the simulator)
over UDP, TCP or serial with pymavlink's codec. The package, by concern:

* :mod:`~flightkit.link.mavlink.link`: :class:`MavlinkLink` itself (connection, reader
  thread, heartbeat, arm/mode/takeoff/land, external pose);
* :mod:`~flightkit.link.mavlink.stream`: the background velocity-setpoint stream
  (:class:`~flightkit.link.mavlink.stream.SetpointStream`, its thread and its timing);
* :mod:`~flightkit.link.mavlink.commands`: COMMAND_LONG, COMMAND_ACK, retries and refusals;
* :mod:`~flightkit.link.mavlink.telemetry`: decoding received messages into the vehicle
  state, and waiting on it;
* :mod:`~flightkit.link.mavlink.encoding`: pure encoders (setpoints, poses) and constants.

Import the public names from here: ``from flightkit.link.mavlink import MavlinkLink``.
"""

from __future__ import annotations

from flightkit.link.mavlink.encoding import (
    HARD_MAX_ACCEL_M_S2,
    HARD_MAX_HORIZONTAL_M_S,
    HARD_MAX_VERTICAL_M_S,
    HARD_MAX_YAW_RATE_RAD_S,
    TYPE_MASK_PVA_YAW,
    TYPE_MASK_PVA_YAW_RATE,
    TYPE_MASK_VELOCITY_ONLY,
    TYPE_MASK_VELOCITY_YAW,
    TYPE_MASK_VELOCITY_YAW_RATE,
    SetpointFields,
    check_hard_limits,
    encode_odometry,
    encode_velocity_setpoint,
    encode_vision_position_estimate,
    heartbeat_type_for_component,
)
from flightkit.link.mavlink.link import LinkStats, MavlinkLink

__all__ = [
    "HARD_MAX_ACCEL_M_S2",
    "HARD_MAX_HORIZONTAL_M_S",
    "HARD_MAX_VERTICAL_M_S",
    "HARD_MAX_YAW_RATE_RAD_S",
    "TYPE_MASK_PVA_YAW",
    "TYPE_MASK_PVA_YAW_RATE",
    "TYPE_MASK_VELOCITY_ONLY",
    "TYPE_MASK_VELOCITY_YAW",
    "TYPE_MASK_VELOCITY_YAW_RATE",
    "LinkStats",
    "MavlinkLink",
    "SetpointFields",
    "check_hard_limits",
    "encode_odometry",
    "encode_velocity_setpoint",
    "encode_vision_position_estimate",
    "heartbeat_type_for_component",
]
