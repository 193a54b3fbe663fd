"""A simulated PX4 / ArduPilot autopilot speaking real MAVLink 2 over UDP.

:class:`SimAutopilot` binds a real UDP socket and behaves, as seen from the wire, like the
firmware its :class:`~flightkit.sim.personality.Personality` describes: heartbeats with the
firmware's custom-mode numbers, message streams whose rates clients can change, commands
answered with COMMAND_ACK, the parameter protocol, arming checks, take-off, landing, RTL,
velocity / position setpoints with the firmware's rules (PX4 OFFBOARD stream requirements
and loss failsafe, ArduPilot GUIDED timeout and GCS failsafe), external vision fusion, and MAVLink 2 signing.
It drives a :class:`~flightkit.sim.dynamics.QuadDynamics` on a :class:`~flightkit.clock.Clock`,
so a whole flight can run many times faster than real time.

Frames: the dynamics live in the lab's world frame (ENU). The autopilot's local frame has its
origin at the vehicle's start position and is rotated by ``heading_offset_rad`` about z
(``R_world_local = Rz(heading_offset_rad)``), as a real autopilot's north need not be the
lab's x axis. On the wire the local frame is NED, as MAVLink wants.

Threads: one receives datagrams and handles each message at once (so COMMAND_ACKs go out
without waiting for a tick); one runs the control loop (physics, modes, streams). Both take
one lock; nothing else in the process needs to know.

Package layout (one concern per module): :mod:`.options` (``AutopilotOptions``, endpoint
strings), :mod:`.core` (state, frames, sending), :mod:`.flight` (modes, control,
estimator), :mod:`.telemetry` (outbound streams), :mod:`.commands` (inbound messages),
:mod:`.server` (``SimAutopilot``: socket, threads, control tick).
"""

from __future__ import annotations

from flightkit.sim.autopilot.options import DEFAULT_STREAM_RATES_HZ, AutopilotOptions, parse_endpoint
from flightkit.sim.autopilot.server import SimAutopilot

__all__ = ["DEFAULT_STREAM_RATES_HZ", "AutopilotOptions", "SimAutopilot", "parse_endpoint"]
