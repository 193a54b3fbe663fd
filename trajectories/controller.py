"""The tracking controller: velocity feed-forward plus proportional (and optional integral) feedback.

    v_world = v_ref + Kp (p_ref - p) + Ki * integral(p_ref - p)

with separate horizontal and vertical gains, the horizontal speed limited as a vector (the
direction is kept) and the vertical speed clipped. The command is then expressed in the frame
the autopilot is told to use:

* ``BODY``: the world command rotated into the yaw-aligned body frame by the yaw *measured by
  mocap*; right for autopilots whose own heading estimate is not the lab's (no mocap fusion).
  Yaw is then commanded as a rate (an absolute heading would be in the autopilot's frame).
* ``WORLD`` (local NED at the wire): when the autopilot fuses mocap so its local frame is the
  world; yaw may be commanded as an absolute setpoint or as a rate.

With ``setpoint = "pva"`` (LOCAL_NED only) the velocity above is sent together with the
reference position as a position target and the reference acceleration as feed-forward
(SET_POSITION_TARGET_LOCAL_NED with all three), so the autopilot's own position controller
tracks the reference without the lag of its velocity shaping; the mocap-error term stays in
the velocity. The acceleration is limited in norm (``max_accel_m_s2``); the control loop keeps
the position inside the geofence.

The yaw rate command is ``yaw_rate_ref + Kp_yaw * wrap(yaw_ref - yaw)``. With
``feedforward = False`` the controller reduces to the lab's original P-only law (no ``v_ref``,
no ``yaw_rate_ref``), kept so the improvement can be measured side by side.

Pure: numpy-free float arithmetic, about 10 us per step.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

from flightkit.frames import Vec3Tuple, wrap_angle_rad
from flightkit.link.base import SetpointFrame, VelocitySetpoint
from flightkit.settings import setting
from trajectories.base import Reference

__all__ = ["ControlOutput", "ControllerConfig", "OutputFrame", "SetpointKind", "VelocityController", "YawControl"]


class OutputFrame(enum.Enum):
    """Frame of the velocity setpoints sent to the autopilot."""

    BODY = "body"
    LOCAL_NED = "local_ned"

    @property
    def setpoint_frame(self) -> SetpointFrame:
        return SetpointFrame.BODY if self is OutputFrame.BODY else SetpointFrame.WORLD


class SetpointKind(enum.Enum):
    """What the setpoints carry: a velocity (the baseline), or position + velocity + acceleration."""

    VELOCITY = "velocity"
    PVA = "pva"


class YawControl(enum.Enum):
    """How yaw is commanded: an absolute heading (``setpoint``, LOCAL_NED only) or a ``rate``."""

    SETPOINT = "setpoint"
    RATE = "rate"


@dataclass(frozen=True, slots=True)
class ControllerConfig:
    """Gains and limits; a ``[controller]`` table in a plan. Defaults are the lab's own."""

    kp_horizontal: float = setting(1.0, min=0.0, max=20.0, help="horizontal position gain, 1/s")
    kp_vertical: float = setting(1.0, min=0.0, max=20.0, help="vertical position gain, 1/s")
    ki_horizontal: float = setting(0.0, min=0.0, max=20.0, help="horizontal integral gain, 1/s^2")
    ki_vertical: float = setting(0.0, min=0.0, max=20.0, help="vertical integral gain, 1/s^2")
    integral_limit_m_s: float = setting(0.2, min=0.0, max=5.0, help="largest integral contribution, m/s")
    kp_yaw: float = setting(1.0, min=0.0, max=20.0, help="yaw gain, 1/s")
    max_horizontal_m_s: float = setting(1.0, min=0.01, max=20.0, help="horizontal speed limit")
    max_vertical_m_s: float = setting(0.4, min=0.01, max=10.0, help="vertical speed limit")
    max_yaw_rate_rad_s: float = setting(1.0, min=0.01, max=10.0, help="yaw rate limit")
    feedforward: bool = setting(True, help="add the reference velocity and yaw rate (false: P-only law)")
    output_frame: OutputFrame = setting(OutputFrame.BODY, help="body or local_ned")
    yaw_control: YawControl = setting(YawControl.RATE, help="rate or setpoint (setpoint needs local_ned)")
    setpoint: SetpointKind = setting(
        SetpointKind.VELOCITY, help="velocity, or pva: position + velocity + acceleration (needs local_ned)"
    )
    max_accel_m_s2: float = setting(2.0, min=0.1, max=8.0, help="acceleration feed-forward limit (pva), m/s^2")

    @staticmethod
    def _check(obj: ControllerConfig, path: str, key: str) -> None:
        from flightkit.errors import ConfigError

        if obj.output_frame is not OutputFrame.BODY:
            return
        # settings that need the autopilot's local frame: (name, in use, why not in the body frame, what to do)
        for name, used, why, fix in (
            (
                "setpoint",
                obj.setpoint is SetpointKind.PVA,
                "position targets are in the autopilot's local frame, which the body frame is not",
                "use setpoint = 'velocity', or output_frame = 'local_ned' when the autopilot fuses mocap",
            ),
            (
                "yaw_control",
                obj.yaw_control is YawControl.SETPOINT,
                "an absolute yaw setpoint is meaningless in the body frame",
                "use yaw_control = 'rate', or output_frame = 'local_ned' when the autopilot fuses mocap",
            ),
        ):
            if used:
                raise ConfigError(path, f"{key}.{name}" if key else name, why, fix, getattr(obj, name).value)


@dataclass(frozen=True, slots=True)
class ControlOutput:
    """One controller step.

    Attributes:
        setpoint: what to send.
        vel_world_m_s: the limited command in the world frame (ENU).
        error_m: p_ref - p, world ENU.
        yaw_error_rad: wrapped yaw_ref - yaw.
        saturated: True when a speed limit cut the command.
    """

    setpoint: VelocitySetpoint
    vel_world_m_s: Vec3Tuple
    error_m: Vec3Tuple
    yaw_error_rad: float
    saturated: bool

    @property
    def error_norm_m(self) -> float:
        return math.sqrt(self.error_m[0] ** 2 + self.error_m[1] ** 2 + self.error_m[2] ** 2)


@dataclass(slots=True)
class VelocityController:
    """Stateful (integral) wrapper around the control law; call :meth:`step` every cycle."""

    config: ControllerConfig = field(default_factory=ControllerConfig)
    _int: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])

    def reset(self) -> None:
        """Clear the integral (call when a new phase starts or after a hold)."""
        self._int = [0.0, 0.0, 0.0]

    @property
    def integral_m_s(self) -> Vec3Tuple:
        """Current integral contribution (world ENU, m/s)."""
        c = self.config
        return (c.ki_horizontal * self._int[0], c.ki_horizontal * self._int[1], c.ki_vertical * self._int[2])

    def step(self, ref: Reference, pos_m: Vec3Tuple, yaw_rad: float, dt_s: float) -> ControlOutput:
        """Compute the setpoint for the measured position ``pos_m`` (world ENU) and heading ``yaw_rad``.

        ``dt_s`` is the time since the previous step (for the integral); 0 disables integration.
        Returns immediately.
        """
        c = self.config
        ex = ref.pos_m[0] - pos_m[0]
        ey = ref.pos_m[1] - pos_m[1]
        ez = ref.pos_m[2] - pos_m[2]
        if c.feedforward:
            fx, fy, fz = ref.vel_m_s
            ff_rate = ref.yaw_rate_rad_s
        else:
            fx = fy = fz = 0.0
            ff_rate = 0.0
        # P + feed-forward + current integral
        ix, iy, iz = self.integral_m_s
        vx = fx + c.kp_horizontal * ex + ix
        vy = fy + c.kp_horizontal * ey + iy
        vz = fz + c.kp_vertical * ez + iz
        vh = math.hypot(vx, vy)
        sat_h = vh > c.max_horizontal_m_s
        if sat_h:
            k = c.max_horizontal_m_s / vh
            vx, vy = vx * k, vy * k
        sat_v = abs(vz) > c.max_vertical_m_s
        if sat_v:
            vz = math.copysign(c.max_vertical_m_s, vz)
        # integrate with anti-windup: freeze an axis group while it is saturated, clamp the contribution
        if dt_s > 0.0:
            if c.ki_horizontal > 0.0 and not sat_h:
                lim = c.integral_limit_m_s / c.ki_horizontal
                self._int[0] = min(max(self._int[0] + ex * dt_s, -lim), lim)
                self._int[1] = min(max(self._int[1] + ey * dt_s, -lim), lim)
            if c.ki_vertical > 0.0 and not sat_v:
                lim = c.integral_limit_m_s / c.ki_vertical
                self._int[2] = min(max(self._int[2] + ez * dt_s, -lim), lim)
        yaw_err = wrap_angle_rad(ref.yaw_rad - yaw_rad)
        frame = c.output_frame.setpoint_frame
        if c.output_frame is OutputFrame.BODY:
            cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
            out = (cy * vx + sy * vy, -sy * vx + cy * vy, vz)
        else:
            out = (vx, vy, vz)
        target_m: Vec3Tuple | None = None
        accel_m_s2: Vec3Tuple | None = None
        if c.setpoint is SetpointKind.PVA:
            target_m = ref.pos_m
            ax, ay, az = ref.accel_m_s2
            norm = math.sqrt(ax * ax + ay * ay + az * az)
            k = min(1.0, c.max_accel_m_s2 / norm) if norm > 0.0 else 1.0
            accel_m_s2 = (ax * k, ay * k, az * k)
        if c.yaw_control is YawControl.SETPOINT:
            sp = VelocitySetpoint(
                out, frame, yaw_rad=wrap_angle_rad(ref.yaw_rad), pos_m=target_m, accel_m_s2=accel_m_s2
            )
        else:
            rate = ff_rate + c.kp_yaw * yaw_err
            rate = min(max(rate, -c.max_yaw_rate_rad_s), c.max_yaw_rate_rad_s)
            sp = VelocitySetpoint(out, frame, yaw_rate_rad_s=rate, pos_m=target_m, accel_m_s2=accel_m_s2)
        return ControlOutput(sp, (vx, vy, vz), (ex, ey, ez), yaw_err, sat_h or sat_v)

    def hold(self) -> VelocitySetpoint:
        """Zero velocity, keep the current yaw (yaw rate 0), in the configured frame."""
        return VelocitySetpoint.zero(self.config.output_frame.setpoint_frame)
