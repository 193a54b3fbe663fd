"""How each autopilot firmware behaves, as data.

The simulated autopilot (:mod:`flightkit.sim.autopilot`) has one implementation of arming,
modes, take-off, landing and setpoint handling; what differs between PX4 and ArduPilot
(custom-mode numbers, which mode follows setpoints, what happens when setpoints stop, the
texts it sends, the parameters it exposes, how long things take) lives here, in a
:class:`Personality`. The values come from the firmware documentation and from runs of
PX4 1.14 SITL and ArduCopter 4.7 SITL (see ``/work/shared/FACTS.md`` and ``docs/sim.md``).

The custom-mode numbers are not repeated here: they are the link's own tables
(:data:`~flightkit.link.modes.PX4_MODES`, :data:`~flightkit.link.modes.ARDUPILOT_COPTER_MODES`),
so the simulator and the backends cannot disagree on a mode.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from flightkit.config import Autopilot
from flightkit.errors import SimError
from flightkit.link.base import FlightMode
from flightkit.link.modes import (
    ARDUPILOT_COPTER_MODES,
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_PX4,
    PX4_MODES,
    px4_custom_mode,
)
from flightkit.sim.posctl import PosCtlLimits

__all__ = [
    "ARDUPILOT",
    "PX4",
    "LossAction",
    "ParamSpec",
    "ParamType",
    "Personality",
    "personality_for",
    "px4_custom_mode",
]

# MAV_FRAME values accepted by SET_POSITION_TARGET_LOCAL_NED
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_LOCAL_OFFSET_NED = 7
MAV_FRAME_BODY_NED = 8
MAV_FRAME_BODY_OFFSET_NED = 9


class ParamType(enum.IntEnum):
    """MAV_PARAM_TYPE of a parameter."""

    INT8 = 2
    INT16 = 4
    INT32 = 6
    REAL32 = 9


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One autopilot parameter: default value, type and allowed range."""

    default: float
    type: ParamType = ParamType.REAL32
    min: float = -math.inf
    max: float = math.inf


class LossAction(enum.Enum):
    """What the autopilot does when the external setpoint stream stops."""

    FAILSAFE_MODE = "failsafe_mode"  # PX4: after COM_OF_LOSS_T switch to the COM_OBL_RC_ACT mode and brake
    KEEP_THEN_BRAKE = (
        "keep_then_brake"  # ArduPilot: keep the last velocity GUID_TIMEOUT, then brake, stay GUIDED
    )


@dataclass(frozen=True, slots=True)
class Personality:
    """Everything that differs between the simulated firmwares.

    Attributes:
        autopilot: which firmware this is.
        mav_autopilot: HEARTBEAT ``autopilot`` field (MAV_AUTOPILOT).
        custom_modes: flight mode -> HEARTBEAT custom_mode.
        boot_mode: the mode after boot.
        setpoint_mode: the mode that follows SET_POSITION_TARGET_LOCAL_NED.
        hold_mode: the mode the vehicle enters after a take-off completes.
        takeoff_mode: the mode during a commanded take-off (None: stays in the current mode).
        accepted_frames: MAV_FRAMEs accepted for SET_POSITION_TARGET_LOCAL_NED.
        stream_required_s: setpoints must have streamed this long before OFFBOARD is
            allowed in the air / arming in OFFBOARD is allowed (PX4); 0 = not required.
        stream_max_gap_s: a gap longer than this restarts the stream count (PX4 needs >= 2 Hz).
        loss_action: what happens when setpoints stop.
        loss_timeout_param: parameter holding the loss timeout (COM_OF_LOSS_T / GUID_TIMEOUT).
        takeoff_param7_amsl: MAV_CMD_NAV_TAKEOFF param7 is AMSL (PX4) rather than relative (ArduPilot).
        takeoff_requires_mode: take-off is accepted only in these modes (empty = any mode).
        takeoff_requires_armed: take-off is refused while disarmed.
        spinup_s: after arming, motors spin this long before any thrust.
        thrust_ramp_s: then climb authority ramps from 0 to full over this time.
        land_speed_m_s: final descent speed.
        disarm_after_land_s: auto-disarm this long after touchdown (< 0: never).
        disarm_preflight_s: auto-disarm when armed on the ground without taking off (< 0: never).
        statustext_needs_gcs: STATUSTEXT is sent only after a GCS HEARTBEAT was heard (PX4).
        statustext_suffix: appended to every STATUSTEXT (PX4 ends its texts with a tab).
        texts: message templates, keyed by situation.
        params: the parameters exposed over the parameter protocol.
        param_bytewise: int params are sent bytewise in the float (PX4), else C-cast (ArduPilot).
        firmware_version: (major, minor, patch) for AUTOPILOT_VERSION.
        ev_enable_param: parameter that turns external vision fusion on.
        lab_params: what a lab set up as ``docs/hardware.md`` recommends changes from the
            defaults (the simulated lab applies them; the bare autopilot serves the defaults).
        reject_result: MAV_RESULT sent when arming, a mode change or a take-off is refused
            (PX4 1 TEMPORARILY_REJECTED, ArduPilot 4 FAILED).
        ack_set_mode_message: answer the SET_MODE message with a COMMAND_ACK (ArduPilot does).
        posctl_limits: the firmware's position-controller limits from its parameters; None =
            velocity setpoints reach the vehicle unshaped (PX4 offboard velocity control).
        takeoff_climb_max_m_s: the take-off's climb-speed cap over the firmware's climb parameter
            (ArduCopter: 0.5 m/s, fitted to the measured 0.41 m top of its 0.3 m lift).
        accel_time_constant_s: lag of the achieved acceleration behind the commanded one
            (ArduCopter: its attitude input shaping, ATC_INPUT_TC 0.15 s).
        takeoff_spool_s: after a take-off command, the vehicle stays on the ground this long
            (ArduCopter spools the motors and ramps the take-off throttle first).
        battery_endurance_s: armed time from a full to an empty battery (the sim options may
            override it).
    """

    autopilot: Autopilot
    mav_autopilot: int
    custom_modes: Mapping[FlightMode, int]
    boot_mode: FlightMode
    setpoint_mode: FlightMode
    hold_mode: FlightMode
    land_mode: FlightMode
    rtl_mode: FlightMode
    takeoff_mode: FlightMode | None
    accepted_frames: frozenset[int]
    stream_required_s: float
    stream_max_gap_s: float
    loss_action: LossAction
    loss_timeout_param: str
    takeoff_param7_amsl: bool
    takeoff_requires_mode: frozenset[FlightMode]
    takeoff_requires_armed: bool
    spinup_s: float
    thrust_ramp_s: float
    land_speed_m_s: float
    disarm_after_land_s: float
    disarm_preflight_s: float
    statustext_needs_gcs: bool
    statustext_suffix: str
    texts: Mapping[str, str]
    params: Mapping[str, ParamSpec]
    param_bytewise: bool
    firmware_version: tuple[int, int, int]
    ev_enable_param: str
    reject_result: int = 1
    lab_params: Mapping[str, float] = field(default_factory=dict)
    ack_set_mode_message: bool = False
    vehicle_name: str = field(default="")
    posctl_limits: Callable[[Mapping[str, float]], PosCtlLimits] | None = None
    takeoff_spool_s: float = 0.0
    accel_time_constant_s: float = 0.0
    takeoff_climb_max_m_s: float = math.inf
    battery_endurance_s: float = 1200.0

    def mode_of(self, custom_mode: int) -> FlightMode | None:
        """The flight mode a custom_mode number means, or None when it is not one of ours."""
        for mode, number in self.custom_modes.items():
            if number == custom_mode:
                return mode
        return None

    def text(self, key: str, **kwargs: object) -> str:
        """A STATUSTEXT line for ``key`` (formatted, without the suffix)."""
        return self.texts[key].format(**kwargs)


PX4 = Personality(
    autopilot=Autopilot.PX4,
    mav_autopilot=MAV_AUTOPILOT_PX4,
    custom_modes=MappingProxyType(PX4_MODES),
    boot_mode=FlightMode.POSCTL,
    setpoint_mode=FlightMode.OFFBOARD,
    hold_mode=FlightMode.HOLD,
    land_mode=FlightMode.LAND,
    rtl_mode=FlightMode.RTL,
    takeoff_mode=FlightMode.TAKEOFF,
    accepted_frames=frozenset({MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_NED}),
    stream_required_s=1.0,
    stream_max_gap_s=0.5,
    loss_action=LossAction.FAILSAFE_MODE,
    loss_timeout_param="COM_OF_LOSS_T",
    takeoff_param7_amsl=True,
    takeoff_requires_mode=frozenset(),
    takeoff_requires_armed=False,
    spinup_s=1.0,
    thrust_ramp_s=3.0,
    land_speed_m_s=0.7,
    disarm_after_land_s=2.0,
    disarm_preflight_s=10.0,
    statustext_needs_gcs=True,
    statustext_suffix="\t",
    texts=MappingProxyType(
        {
            "not_ready": "Arming denied: Resolve system health failures",
            "no_offboard": "Arming denied: No offboard signal",
            "offboard_refused": "Switching to Offboard is currently not available",
            "armed": "Armed by external command",
            "disarmed": "Disarmed by external command",
            "auto_disarm_land": "Disarmed by landing",
            "auto_disarm_preflight": "Disarmed by auto preflight disarming",
            "offboard_lost": "Failsafe activated: No offboard signal",
            "takeoff_low": "Using minimum takeoff altitude: {alt:.2f} m",
            "takeoff_detected": "Takeoff detected",
            "landing": "Landing at current position",
            "landed": "Landing detected",
            "frame_rejected": "Offboard: MAV_FRAME {frame} not supported, use LOCAL_NED or BODY_NED",
            "ev_fusion_on": "EKF2 starting vision fusion",
            "ev_fusion_off": "EKF2 stopping vision fusion",
            "rtl": "RTL: start return at {alt:.1f} m",
        }
    ),
    params=MappingProxyType(
        {
            "COM_OF_LOSS_T": ParamSpec(1.0, ParamType.REAL32, 0.0, 60.0),
            "COM_OBL_RC_ACT": ParamSpec(0, ParamType.INT32, -1, 7),
            "COM_DISARM_LAND": ParamSpec(2.0, ParamType.REAL32, -1.0, 20.0),
            "COM_DISARM_PRFLT": ParamSpec(10.0, ParamType.REAL32, -1.0, 20.0),
            "MIS_TAKEOFF_ALT": ParamSpec(2.5, ParamType.REAL32, 0.0, 100.0),
            "MPC_TKO_SPEED": ParamSpec(1.5, ParamType.REAL32, 0.2, 10.0),
            "MPC_LAND_SPEED": ParamSpec(0.7, ParamType.REAL32, 0.2, 5.0),
            "MPC_XY_VEL_MAX": ParamSpec(12.0, ParamType.REAL32, 0.0, 20.0),
            "MPC_Z_VEL_MAX_UP": ParamSpec(3.0, ParamType.REAL32, 0.5, 8.0),
            "MPC_Z_VEL_MAX_DN": ParamSpec(1.5, ParamType.REAL32, 0.5, 4.0),
            "MPC_YAWRAUTO_MAX": ParamSpec(45.0, ParamType.REAL32, 0.0, 360.0),
            "RTL_RETURN_ALT": ParamSpec(3.0, ParamType.REAL32, 0.0, 150.0),
            "EKF2_EV_CTRL": ParamSpec(0, ParamType.INT32, 0, 15),
            "EKF2_HGT_REF": ParamSpec(1, ParamType.INT32, 0, 3),
            "EKF2_EV_DELAY": ParamSpec(0.0, ParamType.REAL32, 0.0, 300.0),
            "SYS_AUTOSTART": ParamSpec(10040, ParamType.INT32, 0, 9999999),
            "MAV_SYS_ID": ParamSpec(1, ParamType.INT32, 1, 250),
            # what it does when flightkit stops (read by the preflight; docs/hardware.md)
            "COM_RCL_EXCEPT": ParamSpec(0, ParamType.INT32, 0, 7),
            "NAV_RCL_ACT": ParamSpec(2, ParamType.INT32, 0, 6),
            "COM_RC_IN_MODE": ParamSpec(3, ParamType.INT32, 0, 4),
        }
    ),
    param_bytewise=True,
    firmware_version=(1, 14, 0),
    ev_enable_param="EKF2_EV_CTRL",
    reject_result=1,
    ack_set_mode_message=False,
    vehicle_name="PX4 quadrotor (simulated)",
)


ARDUPILOT = Personality(
    autopilot=Autopilot.ARDUPILOT,
    mav_autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA,
    custom_modes=MappingProxyType(ARDUPILOT_COPTER_MODES),
    boot_mode=FlightMode.STABILIZED,
    setpoint_mode=FlightMode.GUIDED,
    hold_mode=FlightMode.GUIDED,
    land_mode=FlightMode.LAND,
    rtl_mode=FlightMode.RTL,
    takeoff_mode=None,
    accepted_frames=frozenset(
        {MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_OFFSET_NED, MAV_FRAME_BODY_NED, MAV_FRAME_BODY_OFFSET_NED}
    ),
    stream_required_s=0.0,
    stream_max_gap_s=math.inf,
    loss_action=LossAction.KEEP_THEN_BRAKE,
    loss_timeout_param="GUID_TIMEOUT",
    takeoff_param7_amsl=False,
    takeoff_requires_mode=frozenset({FlightMode.GUIDED}),
    takeoff_requires_armed=True,
    spinup_s=0.5,
    thrust_ramp_s=0.5,
    land_speed_m_s=0.5,
    disarm_after_land_s=1.0,
    disarm_preflight_s=10.0,
    statustext_needs_gcs=False,
    statustext_suffix="",
    texts=MappingProxyType(
        {
            "not_ready": "PreArm: Need Position Estimate",
            "no_offboard": "PreArm: Need Position Estimate",
            "offboard_refused": "Mode change failed: GUIDED requires position",
            "armed": "Arming motors",
            "disarmed": "Disarming motors",
            "auto_disarm_land": "Disarming motors",
            "auto_disarm_preflight": "Disarming motors",
            "offboard_lost": "Guided: velocity command timeout, braking",
            "takeoff_low": "Takeoff altitude too low, using {alt:.2f} m",
            "takeoff_detected": "Takeoff started",
            "landing": "Land: descending",
            "landed": "Land complete",
            "frame_rejected": "Guided: MAV_FRAME {frame} not supported",
            "ev_fusion_on": "EKF3 IMU0 is using external nav data",
            "ev_fusion_off": "EKF3 IMU0 stopped using external nav data",
            "rtl": "RTL: returning at {alt:.1f} m",
            "gcs_lost": "GCS Failsafe",
            "takeoff_not_armed": "Takeoff: vehicle not armed",
            "takeoff_wrong_mode": "Takeoff: only in GUIDED",
        }
    ),
    params=MappingProxyType(
        {
            "GUID_TIMEOUT": ParamSpec(3.0, ParamType.REAL32, 0.1, 5.0),
            "WPNAV_ACCEL": ParamSpec(250.0, ParamType.REAL32, 50.0, 500.0),
            "WPNAV_ACCEL_Z": ParamSpec(100.0, ParamType.REAL32, 50.0, 500.0),
            "PSC_JERK_XY": ParamSpec(5.0, ParamType.REAL32, 1.0, 20.0),
            "PSC_JERK_Z": ParamSpec(5.0, ParamType.REAL32, 5.0, 50.0),
            "PSC_POSXY_P": ParamSpec(1.0, ParamType.REAL32, 0.5, 2.0),
            "PSC_POSZ_P": ParamSpec(1.0, ParamType.REAL32, 1.0, 3.0),
            "WPNAV_SPEED": ParamSpec(500.0, ParamType.REAL32, 10.0, 2000.0),
            "WPNAV_SPEED_UP": ParamSpec(250.0, ParamType.REAL32, 10.0, 1000.0),
            "WPNAV_SPEED_DN": ParamSpec(150.0, ParamType.REAL32, 10.0, 500.0),
            "LAND_SPEED": ParamSpec(50.0, ParamType.INT16, 30.0, 200.0),
            "PILOT_TKOFF_ALT": ParamSpec(0.0, ParamType.REAL32, 0.0, 1000.0),
            "DISARM_DELAY": ParamSpec(10, ParamType.INT8, 0, 127),
            "RTL_ALT": ParamSpec(1500.0, ParamType.INT32, 200.0, 300000.0),
            "VISO_TYPE": ParamSpec(0, ParamType.INT8, 0, 3),
            "EK3_SRC1_POSXY": ParamSpec(3, ParamType.INT8, 0, 6),
            "EK3_SRC1_POSZ": ParamSpec(1, ParamType.INT8, 0, 6),
            "EK3_SRC1_YAW": ParamSpec(1, ParamType.INT8, 0, 6),
            "SYSID_THISMAV": ParamSpec(1, ParamType.INT16, 1, 255),
            "FRAME_CLASS": ParamSpec(1, ParamType.INT8, 0, 20),
            # what it does when flightkit stops (read by the preflight; docs/hardware.md)
            "FS_GCS_ENABLE": ParamSpec(0, ParamType.INT8, 0, 7),
            "FS_GCS_TIMEOUT": ParamSpec(5.0, ParamType.REAL32, 2.0, 120.0),
            "MAV_GCS_SYSID": ParamSpec(255, ParamType.INT16, 1, 255),
        }
    ),
    param_bytewise=False,
    firmware_version=(4, 7, 0),
    ev_enable_param="VISO_TYPE",
    reject_result=4,
    lab_params=MappingProxyType({"FS_GCS_ENABLE": 5.0}),  # land when flightkit's heartbeat stops
    ack_set_mode_message=True,
    vehicle_name="ArduCopter (simulated)",
    posctl_limits=PosCtlLimits.from_ardupilot_params,
    takeoff_spool_s=2.5,
    accel_time_constant_s=0.15,
    takeoff_climb_max_m_s=0.5,
    battery_endurance_s=450.0,
)


def personality_for(autopilot: Autopilot | str) -> Personality:
    """The personality of ``autopilot`` (an :class:`Autopilot` or ``"px4"`` / ``"ardupilot"``)."""
    if isinstance(autopilot, str):
        try:
            autopilot = Autopilot(autopilot.lower())
        except ValueError:
            raise SimError(f"unknown autopilot {autopilot!r}; use 'px4' or 'ardupilot'") from None
    return PX4 if autopilot is Autopilot.PX4 else ARDUPILOT
