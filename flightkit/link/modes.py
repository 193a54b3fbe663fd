"""Flight-mode tables for PX4 and ArduPilot (Copter), as data.

A MAVLink HEARTBEAT carries the firmware's mode in ``custom_mode`` (meaningful when
``base_mode`` has MAV_MODE_FLAG_CUSTOM_MODE_ENABLED). The two firmwares encode it
differently:

* PX4 packs a main mode in bits 16-23 and an AUTO sub-mode in bits 24-31
  (OFFBOARD = 6 << 16 = 393216, AUTO.LOITER "Hold" = 4 << 16 | 3 << 24 = 50593792).
  MAV_CMD_DO_SET_MODE takes ``param1 = base_mode``, ``param2 = main``, ``param3 = sub``.
* ArduCopter numbers its modes (GUIDED = 4, LOITER = 5, LAND = 9, BRAKE = 17) and
  MAV_CMD_DO_SET_MODE takes ``param1 = base_mode``, ``param2 = number``.

Both link backends and the simulator (:mod:`flightkit.sim.personality`) use these tables,
so a mode is spelled once.

Aliases: a :class:`~flightkit.link.base.FlightMode` the firmware does not have under that
name resolves to its nearest equivalent when *setting* a mode (:func:`resolve_mode`):
on PX4, ``LOITER`` means Hold; on ArduPilot, ``HOLD`` means BRAKE (stop and hold the
position without relying on RC sticks, unlike LOITER). Decoding always reports the mode
the firmware is really in.
"""

from __future__ import annotations

from dataclasses import dataclass

from flightkit.config import Autopilot
from flightkit.errors import LinkError
from flightkit.link.base import FlightMode

__all__ = [
    "ARDUPILOT_COPTER_MODES",
    "MAV_AUTOPILOT_ARDUPILOTMEGA",
    "MAV_AUTOPILOT_PX4",
    "MAV_MODE_FLAG_CUSTOM_MODE_ENABLED",
    "MAV_MODE_FLAG_SAFETY_ARMED",
    "PX4_MODES",
    "ModeCommand",
    "autopilot_from_heartbeat",
    "custom_mode_for",
    "decode_mode",
    "mode_from_command",
    "px4_custom_mode",
    "resolve_mode",
    "set_mode_params",
]

MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4's HEARTBEAT custom_mode: main mode in bits 16-23, sub mode in bits 24-31."""
    return (main_mode << 16) | (sub_mode << 24)


# PX4 main modes: MANUAL 1, ALTCTL 2, POSCTL 3, AUTO 4, ACRO 5, OFFBOARD 6, STABILIZED 7.
# AUTO sub-modes: READY 1, TAKEOFF 2, LOITER 3, MISSION 4, RTL 5, LAND 6.
PX4_MODES: dict[FlightMode, int] = {
    FlightMode.MANUAL: px4_custom_mode(1),
    FlightMode.ALTCTL: px4_custom_mode(2),
    FlightMode.POSCTL: px4_custom_mode(3),
    FlightMode.OFFBOARD: px4_custom_mode(6),
    FlightMode.STABILIZED: px4_custom_mode(7),
    FlightMode.TAKEOFF: px4_custom_mode(4, 2),
    FlightMode.HOLD: px4_custom_mode(4, 3),
    FlightMode.RTL: px4_custom_mode(4, 5),
    FlightMode.LAND: px4_custom_mode(4, 6),
}

# ArduCopter mode numbers (ArduCopter/mode.h).
ARDUPILOT_COPTER_MODES: dict[FlightMode, int] = {
    FlightMode.STABILIZED: 0,  # STABILIZE
    FlightMode.ALTCTL: 2,  # ALT_HOLD
    FlightMode.GUIDED: 4,
    FlightMode.LOITER: 5,
    FlightMode.RTL: 6,
    FlightMode.LAND: 9,
    FlightMode.POSCTL: 16,  # POSHOLD
    FlightMode.BRAKE: 17,
}

_ALIASES: dict[Autopilot, dict[FlightMode, FlightMode]] = {
    Autopilot.PX4: {FlightMode.LOITER: FlightMode.HOLD},
    Autopilot.ARDUPILOT: {FlightMode.HOLD: FlightMode.BRAKE},
}

_TABLES: dict[Autopilot, dict[FlightMode, int]] = {
    Autopilot.PX4: PX4_MODES,
    Autopilot.ARDUPILOT: ARDUPILOT_COPTER_MODES,
}
_REVERSE: dict[Autopilot, dict[int, FlightMode]] = {
    ap: {code: mode for mode, code in table.items()} for ap, table in _TABLES.items()
}


@dataclass(frozen=True, slots=True)
class ModeCommand:
    """What to put in MAV_CMD_DO_SET_MODE, and what the heartbeat shows afterwards.

    Attributes:
        mode: the mode actually requested (after aliasing).
        custom_mode: the HEARTBEAT ``custom_mode`` that confirms the switch.
        params: param1..param3 of MAV_CMD_DO_SET_MODE (the rest are 0).
    """

    mode: FlightMode
    custom_mode: int
    params: tuple[float, float, float]


def autopilot_from_heartbeat(mav_autopilot: int) -> Autopilot | None:
    """Map HEARTBEAT.autopilot (MAV_AUTOPILOT) to our enum; None for anything else."""
    if mav_autopilot == MAV_AUTOPILOT_PX4:
        return Autopilot.PX4
    if mav_autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return Autopilot.ARDUPILOT
    return None


def resolve_mode(autopilot: Autopilot, mode: FlightMode) -> FlightMode:
    """The firmware's name for ``mode`` (see the module docstring for aliases).

    Raises:
        LinkError: the firmware has no such mode.
    """
    mode = _ALIASES[autopilot].get(mode, mode)
    if mode not in _TABLES[autopilot]:
        have = ", ".join(m.value for m in _TABLES[autopilot])
        raise LinkError(f"{autopilot.value} has no {mode.value} mode; use one of: {have}")
    return mode


def custom_mode_for(autopilot: Autopilot, mode: FlightMode) -> int:
    """HEARTBEAT ``custom_mode`` of ``mode`` on ``autopilot`` (aliases resolved)."""
    return _TABLES[autopilot][resolve_mode(autopilot, mode)]


def set_mode_params(autopilot: Autopilot, mode: FlightMode) -> ModeCommand:
    """The MAV_CMD_DO_SET_MODE parameters that select ``mode``.

    Raises:
        LinkError: the firmware has no such mode.
    """
    resolved = resolve_mode(autopilot, mode)
    custom = _TABLES[autopilot][resolved]
    base = float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    if autopilot is Autopilot.PX4:
        params = (base, float((custom >> 16) & 0xFF), float((custom >> 24) & 0xFF))
    else:
        params = (base, float(custom), 0.0)
    return ModeCommand(resolved, custom, params)


def decode_mode(autopilot: Autopilot, base_mode: int, custom_mode: int) -> FlightMode:
    """The FlightMode a HEARTBEAT reports; UNKNOWN if the custom mode is not in the table."""
    if not base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return FlightMode.UNKNOWN
    if autopilot is Autopilot.PX4:
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        # Non-AUTO main modes carry no sub-mode; ignore stray bits there.
        key = px4_custom_mode(main, sub) if main == 4 else px4_custom_mode(main)
        return _REVERSE[autopilot].get(key, FlightMode.UNKNOWN)
    return _REVERSE[autopilot].get(custom_mode, FlightMode.UNKNOWN)


def mode_from_command(autopilot: Autopilot, params: tuple[float, float, float]) -> FlightMode:
    """Decode MAV_CMD_DO_SET_MODE param1..3 (for simulators); UNKNOWN if not in the table."""
    base, p2, p3 = (int(p) for p in params)
    if autopilot is Autopilot.PX4:
        custom = px4_custom_mode(p2, p3 if p2 == 4 else 0)
    else:
        custom = p2
    return decode_mode(autopilot, base, custom)
