"""What the autopilot does on its own when flightkit stops: its companion-loss failsafe.

When the flight script dies (or its link drops), the setpoints and flightkit's HEARTBEAT stop
and the firmware's own settings decide what the vehicle does. :func:`companion_loss` reads
those settings (parameter values, as read from the vehicle) into a :class:`CompanionLoss`:
one line saying what the vehicle would do, and whether that is "hover armed until the battery
runs out", which the preflight refuses (``docs/safety.md``; the parameters and measurements
behind each rule are in ``docs/hardware.md``).

A parameter that could not be read is named, and the answer assumes the worst (hovering).
Pure: no IO, the values come in a mapping.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from flightkit.config import Autopilot

__all__ = [
    "ARDUPILOT_FALLBACK_PARAMS",
    "ARDUPILOT_PARAMS",
    "PX4_PARAMS",
    "CompanionLoss",
    "companion_loss",
]

ARDUPILOT_PARAMS = ("FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "GUID_TIMEOUT", "MAV_GCS_SYSID")
"""ArduCopter: the GCS failsafe, its timeout, the GUIDED velocity timeout and whose heartbeat
the failsafe watches."""

ARDUPILOT_FALLBACK_PARAMS: Mapping[str, str] = {"MAV_GCS_SYSID": "SYSID_MYGCS"}
"""Older names to read when the 4.7 name is absent (ArduCopter 4.6 and earlier)."""

PX4_PARAMS = ("COM_OF_LOSS_T", "COM_OBL_RC_ACT", "COM_RCL_EXCEPT", "NAV_RCL_ACT", "COM_RC_IN_MODE")
"""PX4: offboard-loss timeout and action, and the manual-control (RC) loss failsafe that
decides whether a Position/Hold fallback ever ends without a pilot."""

_APM_GCS_ACTIONS = {
    1: "returns (RTL) and lands",
    2: "returns (RTL) and lands",
    3: "returns (SmartRTL or RTL) and lands",
    4: "returns (SmartRTL, else lands) and lands",
    5: "lands",
    6: "returns (DO_LAND_START or RTL) and lands",
}

_APM_GCS_BRAKE = 7  # "Brake or Land": BRAKE whenever it has a position, and BRAKE never lands

_PX4_OFFBOARD_LOSS_MODES = {
    0: "Position mode",
    1: "Altitude mode",
    2: "Manual mode",
    3: "Return mode",
    4: "Land mode",
    5: "Hold mode",
    6: "flight termination",
    7: "disarm",
}
_PX4_PILOT_MODES = frozenset({0, 1, 2})  # need manual control: an RC pilot flies it
_PX4_HOLD = 5
_PX4_RCL_EXCEPT_HOLD = 2  # COM_RCL_EXCEPT bit 1: ignore RC loss in Hold
_PX4_RC_DISABLED = 4  # COM_RC_IN_MODE: no manual control at all
_PX4_RCL_ENDS_FLIGHT = {2: "Return", 3: "Land", 5: "flight termination", 6: "disarm"}


@dataclass(frozen=True, slots=True)
class CompanionLoss:
    """The autopilot's own reaction to flightkit stopping, as its parameters describe it.

    Attributes:
        summary: one line, "if flightkit stops: ...".
        hovers: it would hover armed until the battery runs out (also when that cannot be
            ruled out because a parameter could not be read).
        reason: when ``hovers``: one sentence saying which setting causes it and what to set.
        unread: the parameters that could not be read.
    """

    summary: str
    hovers: bool
    reason: str = ""
    unread: tuple[str, ...] = ()


def companion_loss(autopilot: Autopilot, params: Mapping[str, float], our_system_id: int) -> CompanionLoss:
    """What ``autopilot`` does when flightkit (MAVLink system ``our_system_id``) stops.

    ``params`` holds the values read from the vehicle; a name missing from it could not be read.
    """
    if autopilot is Autopilot.PX4:
        return _px4(params)
    return _ardupilot(params, our_system_id)


def _get(params: Mapping[str, float], name: str) -> float | None:
    v = params.get(name)
    return None if v is None or not math.isfinite(v) else float(v)


def _unread_note(unread: list[str]) -> str:
    if not unread:
        return ""
    names = ", ".join(unread)
    return f" ({names} could not be read from the vehicle; assumed the worst)"


def _ardupilot(params: Mapping[str, float], our_system_id: int) -> CompanionLoss:
    unread: list[str] = []
    guid = _get(params, "GUID_TIMEOUT")
    if guid is None:
        unread.append("GUID_TIMEOUT")
    keep = f"keeps the last velocity {guid:g} s (GUID_TIMEOUT), brakes" if guid is not None else (
        "keeps the last velocity for GUID_TIMEOUT (unknown), brakes"
    )
    enable = _get(params, "FS_GCS_ENABLE")
    gcs_id = _get(params, "MAV_GCS_SYSID")
    gcs_name = "MAV_GCS_SYSID"
    if gcs_id is None and _get(params, "SYSID_MYGCS") is not None:
        gcs_id, gcs_name = _get(params, "SYSID_MYGCS"), "SYSID_MYGCS"
    hover = f"if flightkit stops: ArduCopter {keep}, then hovers armed in GUIDED until the battery runs out"

    def hovering(note: str, reason: str) -> CompanionLoss:
        return CompanionLoss(hover + note + _unread_note(unread), True, reason, tuple(unread))

    if enable is None:
        unread.append("FS_GCS_ENABLE")
        return hovering(
            "",
            "FS_GCS_ENABLE could not be read, so nothing shows that ArduCopter's GCS failsafe would land "
            "the vehicle; check the link, or set FS_GCS_ENABLE = 5 (land) and read it back",
        )
    if enable == 0:
        return hovering(
            " (FS_GCS_ENABLE = 0)",
            "ArduCopter's GCS failsafe is off (FS_GCS_ENABLE = 0); set FS_GCS_ENABLE = 5 (land) so the "
            "vehicle lands when flightkit's heartbeat stops (docs/hardware.md)",
        )
    if enable == _APM_GCS_BRAKE:
        return hovering(
            " (FS_GCS_ENABLE = 7: its GCS failsafe brakes and holds in BRAKE)",
            "ArduCopter's GCS failsafe with FS_GCS_ENABLE = 7 switches to BRAKE, which holds the vehicle "
            "armed in the air while it has a position; set FS_GCS_ENABLE = 5 (land)",
        )
    if gcs_id is None:
        unread.append("MAV_GCS_SYSID")
        return hovering(
            "",
            "MAV_GCS_SYSID could not be read, so nothing shows that ArduCopter's GCS failsafe watches "
            f"flightkit's heartbeat (system {our_system_id}); set MAV_GCS_SYSID = {our_system_id}",
        )
    if int(gcs_id) != our_system_id:
        return hovering(
            f" (its GCS failsafe watches system {int(gcs_id)}, not flightkit's {our_system_id})",
            f"ArduCopter's GCS failsafe watches the heartbeat of system {gcs_name} = {int(gcs_id)}, but "
            f"flightkit is system {our_system_id}; set {gcs_name} = {our_system_id} (or link.source_system "
            f"= {int(gcs_id)})",
        )
    action = _APM_GCS_ACTIONS.get(int(enable), f"takes failsafe action {int(enable)}")
    timeout = _get(params, "FS_GCS_TIMEOUT")
    after = f"{timeout:g} s (FS_GCS_TIMEOUT)" if timeout is not None else "FS_GCS_TIMEOUT (unknown)"
    if timeout is None:
        unread.append("FS_GCS_TIMEOUT")
    return CompanionLoss(
        f"if flightkit stops: ArduCopter {keep}, and {after} after flightkit's last heartbeat its GCS "
        f"failsafe {action} (FS_GCS_ENABLE = {int(enable)})" + _unread_note(unread),
        False,
        unread=tuple(unread),
    )


def _px4(params: Mapping[str, float]) -> CompanionLoss:
    unread: list[str] = []
    loss_t = _get(params, "COM_OF_LOSS_T")
    if loss_t is None:
        unread.append("COM_OF_LOSS_T")
    after = f"after {loss_t:g} s (COM_OF_LOSS_T)" if loss_t is not None else "after COM_OF_LOSS_T (unknown)"
    action = _get(params, "COM_OBL_RC_ACT")
    if action is None:
        unread.append("COM_OBL_RC_ACT")
        return CompanionLoss(
            f"if flightkit stops: PX4 leaves OFFBOARD {after} for an unknown mode" + _unread_note(unread),
            True,
            "COM_OBL_RC_ACT could not be read, so nothing shows what PX4 does when the offboard setpoints "
            "stop; check the link, or set COM_OBL_RC_ACT = 4 (Land) and read it back",
            tuple(unread),
        )
    act = int(action)
    mode = _PX4_OFFBOARD_LOSS_MODES.get(act, f"offboard-loss action {act}")
    head = f"if flightkit stops: PX4 switches {after} to {mode} (COM_OBL_RC_ACT = {act})"
    if act not in _PX4_PILOT_MODES and act != _PX4_HOLD:
        tail = {3: ", returns and lands", 4: " and lands", 6: ": the motors stop in the air", 7: ": the motors stop"}
        return CompanionLoss(head + tail.get(act, "") + _unread_note(unread), False, unread=tuple(unread))
    # Position/Altitude/Manual wait for a pilot; Hold hovers. Without a pilot only the
    # manual-control (RC) loss failsafe can end it.
    rc_mode = _get(params, "COM_RC_IN_MODE")
    rcl_act = _get(params, "NAV_RCL_ACT")
    excepts = _get(params, "COM_RCL_EXCEPT")
    for name, v in (("COM_RC_IN_MODE", rc_mode), ("NAV_RCL_ACT", rcl_act), ("COM_RCL_EXCEPT", excepts)):
        if v is None:
            unread.append(name)
    wait = "an RC pilot flies it" if act in _PX4_PILOT_MODES else "it hovers"
    why = ""
    if rc_mode is None or rcl_act is None or (act == _PX4_HOLD and excepts is None):
        why = "the RC-loss failsafe settings could not all be read"
    elif int(rc_mode) == _PX4_RC_DISABLED:
        why = "manual control is disabled (COM_RC_IN_MODE = 4), so no RC-loss failsafe ends it"
    elif act == _PX4_HOLD and excepts is not None and int(excepts) & _PX4_RCL_EXCEPT_HOLD:
        why = "RC loss is ignored in Hold (COM_RCL_EXCEPT bit 1)"
    elif int(rcl_act) not in _PX4_RCL_ENDS_FLIGHT:
        why = f"the RC-loss action does not end the flight (NAV_RCL_ACT = {int(rcl_act)})"
    if why:
        return CompanionLoss(
            f"{head}: {wait}; without a pilot it hovers armed until the battery runs out, as {why}"
            + _unread_note(unread),
            True,
            f"PX4 would hover armed until the battery runs out if flightkit stops: {mode} "
            f"(COM_OBL_RC_ACT = {act}) and {why}; set COM_OBL_RC_ACT = 4 (Land)",
            tuple(unread),
        )
    assert rcl_act is not None
    ends = _PX4_RCL_ENDS_FLIGHT[int(rcl_act)]
    return CompanionLoss(
        f"{head}: {wait}; without RC the RC-loss failsafe switches to {ends} (NAV_RCL_ACT = {int(rcl_act)})"
        + _unread_note(unread),
        False,
        unread=tuple(unread),
    )
