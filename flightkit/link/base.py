"""The vehicle link interface: what flight code may ask of an autopilot.

Everything above ``flightkit/link/`` speaks in the world frame (ENU, z up) and the body
frame (FLU); the backends translate to MAVLink's NED/FRD at the wire. Two backends
implement :class:`VehicleLink`: :class:`~flightkit.link.mavlink.MavlinkLink` (pymavlink)
and :class:`~flightkit.link.mavsdk.MavsdkLink` (MAVSDK), and config alone picks one.
"""

from __future__ import annotations

import enum
import inspect
import math
import sys
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

import numpy as np
import numpy.typing as npt

from flightkit.config import Autopilot
from flightkit.errors import SetpointError
from flightkit.frames import Transform
from flightkit.link.failsafe import (
    ARDUPILOT_FALLBACK_PARAMS,
    ARDUPILOT_PARAMS,
    PX4_PARAMS,
    CompanionLoss,
    companion_loss,
)

__all__ = [
    "BatteryState",
    "ExternalPose",
    "ExternalPoseKind",
    "FirmwareTraits",
    "FlightMode",
    "LandedState",
    "SetpointFrame",
    "Telemetry",
    "VehicleInfo",
    "VehicleLink",
    "VelocitySetpoint",
    "firmware_traits",
    "offboard_mode_for",
    "read_companion_loss",
]


class FlightMode(enum.Enum):
    """Flight modes across autopilots. Each backend maps these to its firmware's custom modes.

    ``OFFBOARD`` (PX4) and ``GUIDED`` (ArduPilot) are the modes in which the vehicle follows
    our setpoints; :func:`offboard_mode_for` picks the right one.
    """

    MANUAL = "MANUAL"
    STABILIZED = "STABILIZED"
    ALTCTL = "ALTCTL"
    POSCTL = "POSCTL"
    OFFBOARD = "OFFBOARD"
    HOLD = "HOLD"  # PX4 AUTO.LOITER
    TAKEOFF = "TAKEOFF"
    LAND = "LAND"
    RTL = "RTL"
    GUIDED = "GUIDED"
    LOITER = "LOITER"
    BRAKE = "BRAKE"
    UNKNOWN = "UNKNOWN"


def offboard_mode_for(autopilot: Autopilot) -> FlightMode:
    """The mode in which ``autopilot`` follows external setpoints."""
    return FlightMode.OFFBOARD if autopilot is Autopilot.PX4 else FlightMode.GUIDED


@dataclass(frozen=True, slots=True)
class FirmwareTraits:
    """How a firmware must be driven; flight code asks these instead of naming the firmware.

    Attributes:
        control_mode: the mode in which it follows external setpoints (OFFBOARD, GUIDED).
        setpoint_prestream_s: setpoints it wants to have received before it accepts that mode
            and arming (PX4 refuses OFFBOARD without a recent setpoint stream).
        liftoff_m: > 0 when the vehicle leaves the ground only on the autopilot's own take-off
            command (ArduCopter: velocity setpoints on the ground do not spin it up); the height
            to let it lift by before our controller climbs the rest. 0: our setpoints lift off.
        autopilot: the firmware these traits describe.
        failsafe_params: the parameters that decide what it does when flightkit stops
            (:mod:`flightkit.link.failsafe`); read before arming.
        failsafe_param_fallbacks: older names to read when one of those is absent.
    """

    control_mode: FlightMode
    setpoint_prestream_s: float
    liftoff_m: float
    autopilot: Autopilot = Autopilot.PX4
    failsafe_params: tuple[str, ...] = ()
    failsafe_param_fallbacks: Mapping[str, str] = field(default_factory=dict)

    def companion_loss(self, params: Mapping[str, float], our_system_id: int) -> CompanionLoss:
        """What the vehicle does on its own when flightkit (system ``our_system_id``) stops, from
        the values of :attr:`failsafe_params` read from it (a missing name: could not be read)."""
        return companion_loss(self.autopilot, params, our_system_id)


def firmware_traits(autopilot: Autopilot) -> FirmwareTraits:
    """The traits of ``autopilot``'s firmware (PX4 or ArduCopter)."""
    if autopilot is Autopilot.PX4:
        return FirmwareTraits(
            FlightMode.OFFBOARD, setpoint_prestream_s=1.2, liftoff_m=0.0,
            autopilot=Autopilot.PX4, failsafe_params=PX4_PARAMS,
        )
    # ArduCopter climbs at its own rate on that command (WPNAV_SPEED_UP, 2.5 m/s by default: above
    # the supervisor's 2 m/s limit on a tall take-off), so it lifts the vehicle only this far.
    return FirmwareTraits(
        FlightMode.GUIDED, setpoint_prestream_s=0.1, liftoff_m=0.3, autopilot=Autopilot.ARDUPILOT,
        failsafe_params=ARDUPILOT_PARAMS, failsafe_param_fallbacks=ARDUPILOT_FALLBACK_PARAMS,
    )


class LandedState(enum.Enum):
    """MAV_LANDED_STATE, as reported in EXTENDED_SYS_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class SetpointFrame(enum.Enum):
    """Frame of a velocity setpoint as given to :meth:`VehicleLink.set_velocity`.

    ``WORLD``: the autopilot's local frame expressed ENU (sent as MAV_FRAME_LOCAL_NED);
    right when the autopilot fuses mocap and its local frame matches the world.
    ``BODY``: yaw-aligned body frame, FLU (sent as MAV_FRAME_BODY_NED, relative to the
    vehicle's current heading); right when the autopilot's heading is not the lab's.
    """

    WORLD = "world"
    BODY = "body"


class ExternalPoseKind(enum.Enum):
    """MAVLink message used for external pose (PX4 EKF2 ignores ATT_POS_MOCAP)."""

    VISION_POSITION_ESTIMATE = "vision_position_estimate"
    ODOMETRY = "odometry"


@dataclass(frozen=True, slots=True)
class VelocitySetpoint:
    """A velocity command with a yaw or yaw-rate target, optionally a full kinematic target.

    Attributes:
        vel_m_s: (x, y, z) velocity in ``frame`` (ENU for WORLD, FLU for BODY), m/s.
        frame: see :class:`SetpointFrame`.
        yaw_rad: absolute heading, world ENU (counter-clockwise from x); None = not commanded.
        yaw_rate_rad_s: yaw rate, positive counter-clockwise (seen from above); None = not
            commanded. Give at most one of ``yaw_rad`` and ``yaw_rate_rad_s``; giving neither
            holds the current heading (yaw rate 0).
        pos_m: position target in the autopilot's local frame (ENU, WORLD frame only); the
            velocity is then its feed-forward. None = velocity control.
        accel_m_s2: acceleration feed-forward (ENU, WORLD frame only, with ``pos_m``).
    """

    vel_m_s: tuple[float, float, float]
    frame: SetpointFrame = SetpointFrame.WORLD
    yaw_rad: float | None = None
    yaw_rate_rad_s: float | None = None
    pos_m: tuple[float, float, float] | None = None
    accel_m_s2: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        for name in ("vel_m_s", "pos_m", "accel_m_s2"):
            raw = getattr(self, name)
            if raw is None:
                continue
            v = tuple(float(x) for x in raw)
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise SetpointError(f"setpoint {name} must be 3 finite numbers, got {raw!r}")
            object.__setattr__(self, name, v)
        if (self.pos_m is not None or self.accel_m_s2 is not None) and self.frame is not SetpointFrame.WORLD:
            raise SetpointError(
                "a position or acceleration target needs the WORLD frame (the autopilot's local frame); "
                "use output_frame = 'local_ned' with setpoint = 'pva'"
            )
        if self.accel_m_s2 is not None and self.pos_m is None:
            raise SetpointError("an acceleration feed-forward needs a position target too; give pos_m")
        if self.yaw_rad is not None and self.yaw_rate_rad_s is not None:
            raise SetpointError("give yaw_rad or yaw_rate_rad_s, not both")
        for name in ("yaw_rad", "yaw_rate_rad_s"):
            val = getattr(self, name)
            if val is not None and not math.isfinite(val):
                raise SetpointError(f"{name} must be finite, got {val!r}")

    @staticmethod
    def zero(frame: SetpointFrame = SetpointFrame.WORLD) -> VelocitySetpoint:
        """Stop: zero velocity, zero yaw rate."""
        return VelocitySetpoint((0.0, 0.0, 0.0), frame, yaw_rate_rad_s=0.0)

    def check_limits(
        self,
        max_horizontal_m_s: float,
        max_vertical_m_s: float,
        max_yaw_rate_rad_s: float,
        max_accel_m_s2: float = math.inf,
    ) -> None:
        """Raise SetpointError if this setpoint exceeds the given limits."""
        if self.accel_m_s2 is not None and math.hypot(*self.accel_m_s2) > max_accel_m_s2 + 1e-9:
            raise SetpointError(
                f"acceleration {math.hypot(*self.accel_m_s2):.3f} m/s^2 exceeds the limit {max_accel_m_s2:.3f} m/s^2; "
                "soften the reference or raise the limit in config"
            )
        vh = math.hypot(self.vel_m_s[0], self.vel_m_s[1])
        if vh > max_horizontal_m_s + 1e-9:
            raise SetpointError(
                f"horizontal speed {vh:.3f} m/s exceeds the limit {max_horizontal_m_s:.3f} m/s; "
                "slow the command or raise the limit in config"
            )
        if abs(self.vel_m_s[2]) > max_vertical_m_s + 1e-9:
            raise SetpointError(
                f"vertical speed {self.vel_m_s[2]:.3f} m/s exceeds the limit {max_vertical_m_s:.3f} m/s; "
                "slow the command or raise the limit in config"
            )
        if self.yaw_rate_rad_s is not None and abs(self.yaw_rate_rad_s) > max_yaw_rate_rad_s + 1e-9:
            raise SetpointError(
                f"yaw rate {self.yaw_rate_rad_s:.3f} rad/s exceeds the limit {max_yaw_rate_rad_s:.3f} rad/s"
            )


@dataclass(frozen=True, slots=True)
class ExternalPose:
    """A pose from mocap or VO for the autopilot's estimator.

    Attributes:
        stamp_ns: when the pose was valid (the estimator's or mocap's timestamp), ns since epoch.
        T_world_body: body (FLU) pose in the world (ENU) frame.
        pos_std_m: position standard deviation (isotropic), for the covariance.
        rot_std_rad: attitude standard deviation (isotropic), for the covariance.
        vel_world_m_s: optional velocity in the world frame (sent with ODOMETRY).
        quality_pct: 0-100 quality (ODOMETRY), -1 = unknown.
        reset_counter: bump when the estimator's frame jumps (re-initialisation).
    """

    stamp_ns: int
    T_world_body: Transform
    pos_std_m: float = 0.01
    rot_std_rad: float = 0.02
    vel_world_m_s: tuple[float, float, float] | None = None
    quality_pct: int = -1
    reset_counter: int = 0


@dataclass(frozen=True, slots=True)
class BatteryState:
    voltage_v: float = math.nan
    remaining_pct: float = math.nan  # 0-100; NaN when the autopilot does not estimate it


@dataclass(frozen=True, slots=True)
class VehicleInfo:
    """What the autopilot's heartbeat and AUTOPILOT_VERSION say about it."""

    system_id: int
    component_id: int
    autopilot: Autopilot
    vehicle_type: int  # MAV_TYPE
    firmware_version: str = ""
    our_system_id: int = 255
    """flightkit's own MAVLink system id on this link (``link.source_system``), as the autopilot
    sees it in our HEARTBEAT."""

    @property
    def traits(self) -> FirmwareTraits:
        """How this firmware must be driven (:func:`firmware_traits`)."""
        return firmware_traits(self.autopilot)


@dataclass(frozen=True, slots=True)
class Telemetry:
    """A snapshot of the vehicle state, in flightkit frames.

    Attributes:
        stamp_s: clock time (``Clock.monotonic_s``) of the newest message in the snapshot.
        pos_local_enu_m: position in the autopilot's local frame, expressed ENU.
        vel_local_enu_m_s: velocity in the autopilot's local frame, expressed ENU.
        R_local_body_quat_wxyz: attitude of the FLU body in the local ENU frame.
        yaw_local_rad: heading in the local ENU frame (counter-clockwise from x).
        heartbeat_age_s: clock seconds since the last autopilot HEARTBEAT (inf if none yet).
    """

    stamp_s: float = 0.0
    armed: bool = False
    mode: FlightMode = FlightMode.UNKNOWN
    custom_mode: int = 0
    landed_state: LandedState = LandedState.UNDEFINED
    pos_local_enu_m: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    vel_local_enu_m_s: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    R_local_body_quat_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    yaw_local_rad: float = math.nan
    battery: BatteryState = field(default_factory=BatteryState)
    heartbeat_age_s: float = math.inf

    @property
    def pos_array(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.pos_local_enu_m, dtype=np.float64)


class LinkLifetime:
    """``async with link:`` connects on entry (waiting for the heartbeat) and closes on exit;
    the backends inherit it."""

    async def connect(self) -> VehicleInfo:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()


class _StaticProtocolMeta(type(Protocol)):  # type: ignore[misc]
    """Protocol metaclass whose ``isinstance`` looks members up without running them.

    Python 3.11's runtime-checkable protocols test each member with ``hasattr``, which
    evaluates properties: a link whose ``info`` raises LinkError before ``connect()`` would
    make ``isinstance(link, VehicleLink)`` raise instead of answering. Python 3.12 and later
    look members up statically (``inspect.getattr_static``); this does the same on 3.11.
    """

    def __instancecheck__(cls, instance: object) -> bool:
        if sys.version_info >= (3, 12) or not cls.__dict__.get("_is_protocol", False):
            return bool(super().__instancecheck__(instance))
        missing = object()
        for name in typing._get_protocol_attrs(cls):  # type: ignore[attr-defined]
            value = inspect.getattr_static(instance, name, missing)
            if value is missing or (callable(getattr(cls, name, None)) and value is None):
                return False
        return True


@runtime_checkable
class VehicleLink(Protocol, metaclass=_StaticProtocolMeta):
    """A connection to one autopilot.

    Use as an async context manager (``async with link:``): entering connects and waits for
    the heartbeat; leaving stops any setpoint stream and closes the connection. Methods
    that talk to the autopilot block (await) until it acknowledges, or raise
    :class:`~flightkit.errors.LinkTimeout` / :class:`~flightkit.errors.CommandRejected`.
    """

    @property
    def info(self) -> VehicleInfo:
        """The connected autopilot (raises LinkError before connect)."""
        ...

    @property
    def telemetry(self) -> Telemetry:
        """Latest state; returns immediately."""
        ...

    @property
    def statustext(self) -> tuple[str, ...]:
        """Recent STATUSTEXT lines from the autopilot, oldest first."""
        ...

    async def connect(self) -> VehicleInfo:
        """Open the connection and wait for the autopilot's heartbeat (LinkTimeout otherwise)."""
        ...

    async def close(self) -> None:
        """Stop the setpoint stream and close the connection; idempotent."""
        ...

    async def arm(self) -> None:
        """Arm; returns when the heartbeat shows armed. CommandRejected carries the reason."""
        ...

    async def disarm(self, force: bool = False) -> None:
        """Disarm; returns when the heartbeat shows disarmed."""
        ...

    async def set_mode(self, mode: FlightMode) -> None:
        """Switch flight mode; returns when the heartbeat shows it.

        For OFFBOARD the setpoint stream must already be running (see
        :meth:`start_setpoint_stream`), as PX4 requires.
        """
        ...

    async def takeoff(self, altitude_m: float) -> None:
        """Command a take-off to ``altitude_m`` above home; returns when acknowledged."""
        ...

    async def land(self) -> None:
        """Command a landing at the current position; returns when acknowledged."""
        ...

    async def start_setpoint_stream(self, rate_hz: float | None = None) -> None:
        """Start streaming the current setpoint (initially zero velocity) in the background.

        If the caller does not call :meth:`set_velocity` for ``setpoint_timeout_s`` the
        stream sends an explicit stop (zero velocity) instead of repeating a stale command.
        """
        ...

    async def stop_setpoint_stream(self) -> None:
        """Stop streaming (sends one last zero-velocity setpoint); idempotent."""
        ...

    def set_velocity(self, setpoint: VelocitySetpoint, *, send_now: bool = False) -> None:
        """Replace the streamed setpoint; returns immediately. The stream must be running.

        ``send_now`` also puts it on the wire at once (where the backend can: pymavlink) instead of
        at the stream's next tick; a backend that paces its own sends ignores it."""
        ...

    async def send_vision_pose(
        self, pose: ExternalPose, kind: ExternalPoseKind = ExternalPoseKind.VISION_POSITION_ESTIMATE
    ) -> None:
        """Send an external pose to the autopilot's estimator; returns once sent."""
        ...

    async def set_ekf_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Set the EKF origin (SET_GPS_GLOBAL_ORIGIN) for a vehicle without GPS."""
        ...

    async def wait_for(self, predicate: object, timeout_s: float, what: str) -> Telemetry:
        """Wait until ``predicate(telemetry)`` is true; LinkTimeout naming ``what`` otherwise."""
        ...

    async def read_params(self, names: Sequence[str]) -> dict[str, float]:
        """Read autopilot parameters by name; blocks up to about ``link.command_timeout_s``.

        Returns the values that arrived (integer parameters as whole floats); a name missing
        from the result could not be read (no such parameter, or no answer in time).
        """
        ...

    async def __aenter__(self) -> Self: ...

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...


async def read_companion_loss(link: VehicleLink) -> CompanionLoss:
    """What the connected vehicle would do on its own if flightkit stopped: reads the failsafe
    parameters its firmware's traits name (older names for those absent) and judges them.

    Blocks up to about twice ``link.command_timeout_s`` when parameters do not answer.
    """
    traits = link.info.traits
    values = await link.read_params(traits.failsafe_params)
    older = [old for name, old in traits.failsafe_param_fallbacks.items() if name not in values]
    if older:
        values.update(await link.read_params(older))
    return traits.companion_loss(values, link.info.our_system_id)
