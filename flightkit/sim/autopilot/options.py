"""Configuration of the simulated autopilot: endpoint strings, non-firmware knobs, default stream rates.

What differs between firmwares lives in :mod:`flightkit.sim.personality`; what is left
(where it listens, its MAVLink ids, signing, the local frame's origin and heading, parameter
and stream-rate overrides, timing of the control loop) is an :class:`AutopilotOptions`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.errors import EndpointError

__all__ = ['AutopilotOptions', 'DEFAULT_STREAM_RATES_HZ', 'parse_endpoint']

mav = mavlink2  # enums and message classes


# message id -> default rate (Hz) of the streams every client gets
DEFAULT_STREAM_RATES_HZ: Mapping[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 2.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mav.MAVLINK_MSG_ID_VFR_HUD: 4.0,
}


def parse_endpoint(url: str) -> tuple[str, str, int]:
    """Split ``udpin:HOST:PORT`` / ``udpout:HOST:PORT`` (``://`` forms too) into (kind, host, port).

    Raises:
        EndpointError: when the string is not one of those forms.
    """
    text = url.strip()
    kind, sep, rest = text.partition(":")
    rest = rest.removeprefix("//")
    kind = kind.lower()
    if kind == "udp":
        kind = "udpin"
    host, _, port_s = rest.rpartition(":")
    if not sep or kind not in ("udpin", "udpout") or not host or not port_s.isdigit():
        raise EndpointError(
            f"simulator endpoint {url!r} is not understood; "
            "use udpin:HOST:PORT (listen) or udpout:HOST:PORT (send)"
        )
    port = int(port_s)
    if port > 65535 or (kind == "udpout" and port == 0):
        raise EndpointError(
            f"port {port} in {url!r} is not usable; give a port from 1 to 65535 (0 only for udpin)"
        )
    return kind, host, port


@dataclass(frozen=True, slots=True)
class AutopilotOptions:
    """Knobs of the simulated autopilot that are not firmware behaviour.

    Attributes:
        url: ``udpin:HOST:PORT`` (listen; answer every sender) or ``udpout:HOST:PORT`` (send
            to a listening client, as PX4 SITL does). Port 0 with udpin picks a free port.
        local_port: with udpout, the local port to send from (0 = any; PX4 SITL uses 14580).
        system_id, component_id: our MAVLink ids.
        ready_after_s: the estimator "converges" this long after start; before that, arming
            is refused with the firmware's reason (0 for tests).
        signing_key: 32-byte MAVLink 2 signing key; None = signing off.
        origin_lat_deg, origin_lon_deg, origin_alt_m: global position of the local origin.
        heading_offset_rad: rotation of the autopilot's local frame about world z.
        params: parameter overrides, e.g. ``{"COM_OF_LOSS_T": 0.5}``.
        stream_rates_hz: stream-rate overrides by MAVLink message id (0 = off).
        tick_wall_s: wall-clock period of the control loop.
        battery_endurance_s: armed time from a full to an empty battery; None = the
            personality's (ArduPilot 450 s: ``battery_low`` at 20 % after 6 min, as SITL).
        client_timeout_s: a udpin client silent this long (sim time) is forgotten.
    """

    url: str = "udpin:127.0.0.1:14540"
    local_port: int = 0
    system_id: int = 1
    component_id: int = 1
    ready_after_s: float = 2.0
    signing_key: bytes | None = None
    origin_lat_deg: float = 47.397742
    origin_lon_deg: float = 8.545594
    origin_alt_m: float = 488.0
    heading_offset_rad: float = 0.0
    params: Mapping[str, float] = field(default_factory=dict)
    stream_rates_hz: Mapping[int, float] = field(default_factory=dict)
    tick_wall_s: float = 0.005
    battery_endurance_s: float | None = None
    client_timeout_s: float = 60.0
