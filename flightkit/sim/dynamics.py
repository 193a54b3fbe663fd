"""Quadrotor dynamics at the level a velocity-controlled autopilot exposes.

The simulated vehicle is what the autopilot's inner loops make of it: velocity follows the
commanded velocity with a first-order lag and an acceleration limit, heading follows a yaw
or yaw-rate target with a rate limit, roll and pitch follow from the acceleration (a
quadrotor tilts to accelerate). Around that sit the things flight code must cope with:
ground contact (the vehicle sits on z = 0, never sinks, cannot slide), motor spin-up and a
thrust ramp after arming before it can lift off, free fall when the motors stop in the
air, wind gusts, and position-sensor noise with a slow wander.

Pure numpy and the stdlib; deterministic for a given seed and sequence of ``step`` calls.
All vectors are in the world frame, ENU (z up), metres and seconds.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from flightkit.errors import SetpointError, SimError
from flightkit.frames import Transform, wrap_angle_rad

__all__ = ["DynamicsParams", "DynamicsState", "MotorState", "QuadDynamics"]

GRAVITY_M_S2 = 9.80665
_GROUND_EPS_M = 1e-6


class MotorState(enum.Enum):
    OFF = "off"
    SPINUP = "spinup"  # armed, motors spinning at idle, no lift yet
    RAMP = "ramp"  # thrust ramping up: climb authority grows from 0 to 1
    RUNNING = "running"


@dataclass(frozen=True, slots=True)
class DynamicsParams:
    """Physical and inner-loop parameters of the simulated quadrotor.

    Attributes:
        velocity_time_constant_s: first-order lag of velocity tracking.
        max_accel_m_s2: limit on the norm of the commanded acceleration.
        accel_time_constant_s: first-order lag between the commanded and the achieved
            acceleration (the attitude loop's response; 0 = immediate).
        yaw_time_constant_s: first-order lag of yaw-rate tracking.
        max_yaw_rate_rad_s: yaw rate limit.
        yaw_gain_1_s: yaw error (rad) to yaw-rate (rad/s) gain when an absolute yaw is commanded.
        spinup_s: after arming, idle spin before any lift.
        thrust_ramp_s: climb authority ramps from 0 to 1 over this time after spin-up.
        drag_1_s: how strongly air moving relative to the vehicle pushes it (1/s); only
            matters with wind.
        wind_gust_m_s: peak speed of random horizontal gusts (0 = calm).
        gust_interval_s: mean time between random gusts.
        gust_duration_s: duration of one gust (a 1 - cos profile).
        pos_noise_m: white noise std-dev on the sensed position.
        pos_wander_m: std-dev of a slow random wander (Ornstein-Uhlenbeck) on the sensed position.
        pos_wander_time_s: correlation time of that wander.
        seed: RNG seed (gusts and noise).
    """

    velocity_time_constant_s: float = 0.25
    max_accel_m_s2: float = 4.0
    accel_time_constant_s: float = 0.0
    yaw_time_constant_s: float = 0.1
    max_yaw_rate_rad_s: float = math.radians(90.0)
    yaw_gain_1_s: float = 2.5
    spinup_s: float = 1.0
    thrust_ramp_s: float = 3.0
    drag_1_s: float = 0.3
    wind_gust_m_s: float = 0.0
    gust_interval_s: float = 5.0
    gust_duration_s: float = 2.0
    pos_noise_m: float = 0.0
    pos_wander_m: float = 0.0
    pos_wander_time_s: float = 10.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "velocity_time_constant_s",
            "max_accel_m_s2",
            "yaw_time_constant_s",
            "max_yaw_rate_rad_s",
        ):
            if not getattr(self, name) > 0.0:
                raise SimError(f"DynamicsParams.{name} must be > 0, got {getattr(self, name)}; give a positive value")
        nonneg = ("accel_time_constant_s", "spinup_s", "thrust_ramp_s", "wind_gust_m_s", "pos_noise_m", "pos_wander_m")
        for name in (*nonneg, "drag_1_s"):
            if getattr(self, name) < 0.0:
                raise SimError(f"DynamicsParams.{name} must be >= 0, got {getattr(self, name)}; give 0 (off) or more")


@dataclass(frozen=True, slots=True)
class DynamicsState:
    """A snapshot of the true vehicle state (world ENU, body FLU).

    Attributes:
        time_s: simulated time of the snapshot (seconds since the dynamics were created).
        pos_enu_m, vel_enu_m_s, accel_enu_m_s2: shape (3,).
        yaw_rad: heading, counter-clockwise from world x.
        roll_rad, pitch_rad: tilt (FLU; positive pitch is nose down).
        on_ground: resting on the floor.
        motors: motor state; ``thrust_fraction`` is the climb authority in [0, 1].
        wind_enu_m_s: current wind.
    """

    time_s: float
    pos_enu_m: npt.NDArray[np.float64]
    vel_enu_m_s: npt.NDArray[np.float64]
    accel_enu_m_s2: npt.NDArray[np.float64]
    yaw_rad: float
    yaw_rate_rad_s: float
    roll_rad: float
    pitch_rad: float
    on_ground: bool
    motors: MotorState
    thrust_fraction: float
    wind_enu_m_s: npt.NDArray[np.float64]

    @property
    def rotation(self) -> Rotation:
        """R_world_body (FLU in ENU): yaw, then pitch, then roll about the moving axes."""
        return Rotation.from_euler("ZYX", [self.yaw_rad, self.pitch_rad, self.roll_rad])

    def T_world_body(self, dt_s: float = 0.0) -> Transform:
        """The body pose, optionally extrapolated ``dt_s`` ahead with the current velocities."""
        pos = self.pos_enu_m + self.vel_enu_m_s * dt_s
        if pos[2] < 0.0:
            pos = pos.copy()
            pos[2] = 0.0
        yaw = self.yaw_rad + self.yaw_rate_rad_s * dt_s
        rot = Rotation.from_euler("ZYX", [yaw, self.pitch_rad, self.roll_rad])
        return Transform(rot, pos)


class _Gust:
    __slots__ = ("direction", "duration_s", "peak_m_s", "start_s")

    def __init__(self, start_s: float, duration_s: float, peak: npt.NDArray[np.float64]) -> None:
        self.start_s = start_s
        self.duration_s = duration_s
        self.peak_m_s = peak

    def value(self, t_s: float) -> npt.NDArray[np.float64] | None:
        u = (t_s - self.start_s) / self.duration_s
        if u < 0.0:
            return np.zeros(3)
        if u > 1.0:
            return None
        return self.peak_m_s * (0.5 * (1.0 - math.cos(2.0 * math.pi * u)))


class QuadDynamics:
    """The true state of the simulated quadrotor, advanced by :meth:`step`.

    Not thread-safe: the owner (the simulated autopilot) serialises calls.

    Args:
        params: physical parameters.
        pos_enu_m: initial position (z = 0 means on the floor).
        yaw_rad: initial heading.
    """

    def __init__(
        self,
        params: DynamicsParams | None = None,
        pos_enu_m: npt.ArrayLike = (0.0, 0.0, 0.0),
        yaw_rad: float = 0.0,
    ) -> None:
        self.params = params or DynamicsParams()
        self._rng = np.random.default_rng(self.params.seed)
        self._t = 0.0
        self._pos = np.array(pos_enu_m, dtype=np.float64).reshape(3)
        if self._pos[2] < 0.0:
            raise SimError(f"initial position is below the floor (z = {self._pos[2]:.3f} m); give z >= 0")
        self._vel = np.zeros(3)
        self._acc = np.zeros(3)
        self._acc_ctrl = np.zeros(3)  # the acceleration the inner loops achieve, before wind
        self._yaw = wrap_angle_rad(float(yaw_rad))
        self._yaw_rate = 0.0
        self._on_ground = bool(self._pos[2] <= _GROUND_EPS_M)
        self._armed = False
        self._armed_at_s = 0.0
        self._cmd_vel = np.zeros(3)
        self._cmd_acc = np.zeros(3)
        self._cmd_yaw: float | None = None
        self._cmd_yaw_rate = 0.0
        self._gusts: list[_Gust] = []
        self._next_gust_s = self._draw_gust_gap()
        self._wind = np.zeros(3)
        self._wander = np.zeros(3)

    # ------------------------------------------------------------------ inputs

    @property
    def time_s(self) -> float:
        return self._t

    @property
    def armed(self) -> bool:
        return self._armed

    @property
    def on_ground(self) -> bool:
        return self._on_ground

    @property
    def pos_enu_m(self) -> npt.NDArray[np.float64]:
        return self._pos.copy()

    @property
    def vel_enu_m_s(self) -> npt.NDArray[np.float64]:
        return self._vel.copy()

    @property
    def yaw_rad(self) -> float:
        return self._yaw

    def set_armed(self, armed: bool) -> None:
        """Start (spin-up, thrust ramp) or stop the motors. Stopping in the air means falling."""
        if armed and not self._armed:
            self._armed_at_s = self._t
        self._armed = armed
        if not armed:
            self._cmd_vel = np.zeros(3)
            self._cmd_acc = np.zeros(3)
            self._cmd_yaw = None
            self._cmd_yaw_rate = 0.0

    def command(
        self,
        vel_enu_m_s: npt.ArrayLike,
        yaw_rad: float | None = None,
        yaw_rate_rad_s: float | None = None,
        accel_enu_m_s2: npt.ArrayLike | None = None,
    ) -> None:
        """Set the velocity target (world ENU) and an absolute heading or a yaw rate.

        With neither ``yaw_rad`` nor ``yaw_rate_rad_s`` the heading is held (rate 0).
        ``accel_enu_m_s2`` is an acceleration feed-forward added to the velocity loop's own.
        """
        v = np.asarray(vel_enu_m_s, dtype=np.float64).reshape(3)
        a = np.zeros(3) if accel_enu_m_s2 is None else np.asarray(accel_enu_m_s2, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(a))):
            raise SetpointError(
                f"velocity command must be finite, got {v} m/s ({a} m/s^2 feed-forward); "
                "check the controller output for NaN"
            )
        self._cmd_vel = v.copy()
        self._cmd_acc = a.copy()
        self._cmd_yaw = None if yaw_rad is None else wrap_angle_rad(float(yaw_rad))
        self._cmd_yaw_rate = 0.0 if yaw_rate_rad_s is None else float(yaw_rate_rad_s)

    def inject_gust(self, peak_enu_m_s: npt.ArrayLike, duration_s: float = 2.0) -> None:
        """Add a gust starting now: wind rises to ``peak_enu_m_s`` and falls back (1 - cos)."""
        if duration_s <= 0.0:
            raise SimError(f"gust duration must be > 0 s, got {duration_s}; give a positive duration")
        self._gusts.append(_Gust(self._t, duration_s, np.asarray(peak_enu_m_s, dtype=np.float64).reshape(3)))

    def teleport(self, pos_enu_m: npt.ArrayLike, yaw_rad: float | None = None) -> None:
        """Put the vehicle somewhere (at rest); for set-up and tests."""
        self._pos = np.array(pos_enu_m, dtype=np.float64).reshape(3)
        self._pos[2] = max(self._pos[2], 0.0)
        self._vel[:] = 0.0
        self._acc[:] = 0.0
        self._acc_ctrl = np.zeros(3)
        if yaw_rad is not None:
            self._yaw = wrap_angle_rad(float(yaw_rad))
        self._yaw_rate = 0.0
        self._on_ground = bool(self._pos[2] <= _GROUND_EPS_M)

    # ------------------------------------------------------------------ state

    def motor_state(self) -> tuple[MotorState, float]:
        """Motor state and climb authority in [0, 1]."""
        if not self._armed:
            return MotorState.OFF, 0.0
        since = self._t - self._armed_at_s
        p = self.params
        if since < p.spinup_s:
            return MotorState.SPINUP, 0.0
        if p.thrust_ramp_s > 0.0 and since < p.spinup_s + p.thrust_ramp_s:
            return MotorState.RAMP, (since - p.spinup_s) / p.thrust_ramp_s
        return MotorState.RUNNING, 1.0

    def state(self) -> DynamicsState:
        motors, frac = self.motor_state()
        a = self._acc
        c, s = math.cos(self._yaw), math.sin(self._yaw)
        a_fwd = c * a[0] + s * a[1]
        a_left = -s * a[0] + c * a[1]
        g = GRAVITY_M_S2 + (a[2] if not self._on_ground else 0.0)
        g = max(g, 1.0)
        pitch = math.atan2(a_fwd, g) if not self._on_ground else 0.0
        roll = -math.atan2(a_left, g) if not self._on_ground else 0.0
        return DynamicsState(
            time_s=self._t,
            pos_enu_m=self._pos.copy(),
            vel_enu_m_s=self._vel.copy(),
            accel_enu_m_s2=self._acc.copy(),
            yaw_rad=self._yaw,
            yaw_rate_rad_s=self._yaw_rate,
            roll_rad=roll,
            pitch_rad=pitch,
            on_ground=self._on_ground,
            motors=motors,
            thrust_fraction=frac,
            wind_enu_m_s=self._wind.copy(),
        )

    def sensed_pos_enu_m(self) -> npt.NDArray[np.float64]:
        """The position a position sensor would report now: truth + wander + white noise."""
        out = self._pos + self._wander
        if self.params.pos_noise_m > 0.0:
            out = out + self._rng.normal(0.0, self.params.pos_noise_m, 3)
        return out

    # ------------------------------------------------------------------ integration

    def step(self, dt_s: float) -> None:
        """Advance the state by ``dt_s`` seconds (split internally into steps of at most 10 ms)."""
        if dt_s < 0.0:
            raise SimError(f"time cannot go backwards (dt = {dt_s} s); step by 0 or more")
        n = max(1, math.ceil(dt_s / 0.01 - 1e-9))
        h = dt_s / n
        for _ in range(n):
            self._step(h)

    def _draw_gust_gap(self) -> float:
        if self.params.wind_gust_m_s <= 0.0:
            return math.inf
        return float(self._rng.exponential(self.params.gust_interval_s))

    def _update_wind(self, h: float) -> None:
        p = self.params
        if self._t >= self._next_gust_s:
            heading = self._rng.uniform(-math.pi, math.pi)
            peak = p.wind_gust_m_s * self._rng.uniform(0.5, 1.0)
            self._gusts.append(
                _Gust(
                    self._t, p.gust_duration_s, np.array([math.cos(heading), math.sin(heading), 0.0]) * peak
                )
            )
            self._next_gust_s = self._t + p.gust_duration_s + self._draw_gust_gap()
        wind = np.zeros(3)
        alive: list[_Gust] = []
        for gust in self._gusts:
            val = gust.value(self._t)
            if val is not None:
                wind += val
                alive.append(gust)
        self._gusts = alive
        self._wind = wind
        if p.pos_wander_m > 0.0:
            tau = p.pos_wander_time_s
            sigma = p.pos_wander_m * math.sqrt(2.0 * h / tau)
            self._wander += -self._wander * (h / tau) + self._rng.normal(0.0, sigma, 3)

    def _step(self, h: float) -> None:
        p = self.params
        self._update_wind(h)
        motors, authority = self.motor_state()

        if motors is MotorState.OFF:
            if self._on_ground:
                self._vel[:] = 0.0
                self._acc[:] = 0.0
                self._acc_ctrl = np.zeros(3)
                self._yaw_rate = 0.0
            else:  # falling: gravity and drag
                acc = p.drag_1_s * (self._wind - self._vel)
                acc[2] -= GRAVITY_M_S2
                self._acc = acc
                self._vel = self._vel + acc * h
                self._pos = self._pos + self._vel * h
            self._t += h
            self._ground_contact()
            return

        cmd = self._cmd_vel.copy()
        if self._on_ground:
            # No lift before spin-up and the thrust ramp are over (thrust below weight);
            # no sliding or turning on the floor.
            cmd[:2] = 0.0
            cmd[2] = max(0.0, cmd[2]) if motors is MotorState.RUNNING else 0.0
            if cmd[2] <= 0.0:
                self._vel[:] = 0.0
                self._acc[:] = 0.0
                self._acc_ctrl = np.zeros(3)
                self._yaw_rate = 0.0
                self._t += h
                return

        acc = (cmd - self._vel) / p.velocity_time_constant_s
        if not self._on_ground:
            acc = acc + self._cmd_acc
        norm = float(np.linalg.norm(acc))
        if norm > p.max_accel_m_s2:
            acc *= p.max_accel_m_s2 / norm
        if p.accel_time_constant_s > 0.0 and not self._on_ground:
            acc = self._acc_ctrl + (acc - self._acc_ctrl) * min(1.0, h / p.accel_time_constant_s)
        self._acc_ctrl = acc
        if not self._on_ground:
            # the velocity loop trims out drag at the vehicle's own speed; wind is the disturbance
            acc = acc + p.drag_1_s * self._wind
        self._acc = acc
        self._vel = self._vel + acc * h
        self._pos = self._pos + self._vel * h

        # yaw
        if self._on_ground:
            self._yaw_rate = 0.0
        else:
            if self._cmd_yaw is not None:
                rate_cmd = p.yaw_gain_1_s * wrap_angle_rad(self._cmd_yaw - self._yaw)
            else:
                rate_cmd = self._cmd_yaw_rate
            rate_cmd = max(-p.max_yaw_rate_rad_s, min(p.max_yaw_rate_rad_s, rate_cmd))
            alpha = min(1.0, h / p.yaw_time_constant_s)
            self._yaw_rate += alpha * (rate_cmd - self._yaw_rate)
            self._yaw = wrap_angle_rad(self._yaw + self._yaw_rate * h)

        self._t += h
        self._ground_contact()

    def _ground_contact(self) -> None:
        if self._pos[2] <= _GROUND_EPS_M and self._vel[2] <= 0.0:
            self._pos[2] = 0.0
            if not self._on_ground:
                self._vel[:] = 0.0
                self._acc[:] = 0.0
                self._acc_ctrl = np.zeros(3)
                self._yaw_rate = 0.0
            self._on_ground = True
        elif self._pos[2] > _GROUND_EPS_M:
            self._on_ground = False
