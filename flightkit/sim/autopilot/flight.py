"""Flight behaviour of the simulated autopilot: modes, failsafes, what the vehicle is told to do, ground and estimator.

Each control tick the server calls :meth:`_AutopilotFlight._update_modes` (setpoint loss,
take-off/landing/RTL progress, auto-disarm), :meth:`_AutopilotFlight._command_dynamics`
(turns the mode and setpoints into a velocity/yaw command for the
:class:`~flightkit.sim.dynamics.QuadDynamics`), and the ground-state and estimator updates
(external vision fusion). Arming and disarming live here too, as the modes use them.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.frames import ned_to_enu, wrap_angle_rad, yaw_ned_to_enu
from flightkit.link.base import FlightMode, LandedState
from flightkit.sim.autopilot.core import _NEEDS_POSITION_ARDUPILOT, _AutopilotCore, _rot_z, _Setpoint
from flightkit.sim.dynamics import MotorState
from flightkit.sim.personality import (
    LossAction,
)

mav = mavlink2  # enums and message classes


_HOLD_LIKE = frozenset(
    {
        FlightMode.POSCTL,
        FlightMode.HOLD,
        FlightMode.LOITER,
        FlightMode.BRAKE,
        FlightMode.ALTCTL,
        FlightMode.STABILIZED,
        FlightMode.MANUAL,
    }
)


# ArduCopter's GCS failsafe action per FS_GCS_ENABLE (its events.cpp): 1 RTL, 2 RTL outside AUTO,
# 3 SmartRTL or RTL, 4 SmartRTL or LAND, 5 LAND, 6 DO_LAND_START or RTL, 7 BRAKE or LAND. The
# simulator records no SmartRTL path and flies no mission, so 3 and 6 return (RTL) and 4 lands.
_GCS_FAILSAFE_MODES = {
    1: FlightMode.RTL,
    2: FlightMode.RTL,
    3: FlightMode.RTL,
    4: FlightMode.LAND,
    5: FlightMode.LAND,
    6: FlightMode.RTL,
    7: FlightMode.BRAKE,
}
_LAND_PAUSE_S = 4.0  # ArduCopter's failsafe LAND holds position this long before descending


class _AutopilotFlight(_AutopilotCore):
    """Modes, control, ground state and estimator (the firmware's flight logic)."""

    def _set_mode(self, mode: FlightMode, why: str = "") -> None:
        if mode is self._mode:
            return
        old = self._mode
        self._mode = mode
        self._hold_target = None
        self._hold_yaw = None
        self._landing = mode is self.personality.land_mode
        self._rtl_phase = "climb" if mode is self.personality.rtl_mode else ""
        if mode is not self.personality.takeoff_mode:
            self._takeoff_alt_local_m = None
        if mode is not self.personality.setpoint_mode:
            self._guided_target = None
        self._failsafe = why == "failsafe"
        self._land_pause_until_s = -math.inf
        self._event("mode", f"{old.value} -> {mode.value}{' (' + why + ')' if why else ''}")
        self._send_heartbeat(self.clock.monotonic_s())

    def _loss_timeout_s(self) -> float:
        return self._params[self.personality.loss_timeout_param]

    def _offboard_signal_ok(self, now: float) -> bool:
        """PX4: a setpoint stream has run for stream_required_s and is still alive."""
        sp, start = self._setpoint, self._stream_start_s
        if sp is None or start is None:
            return False
        fresh = now - sp.received_s <= min(self.personality.stream_max_gap_s, self._loss_timeout_s())
        return fresh and sp.received_s - start >= self.personality.stream_required_s - 1e-6

    def _update_modes(self, now: float) -> None:
        p = self.personality
        if not self._armed:
            return
        if p.loss_action is LossAction.FAILSAFE_MODE and self._mode is p.setpoint_mode:
            sp = self._setpoint
            if sp is None or now - sp.received_s > self._loss_timeout_s():
                action = int(self._params.get("COM_OBL_RC_ACT", 0))
                target = {
                    0: FlightMode.POSCTL,
                    1: FlightMode.ALTCTL,
                    2: FlightMode.STABILIZED,
                    3: FlightMode.RTL,
                    4: FlightMode.LAND,
                    5: FlightMode.HOLD,
                }.get(action, FlightMode.HOLD)
                self._failsafe = True
                self._statustext(p.text("offboard_lost"), mav.MAV_SEVERITY_CRITICAL)
                self._set_mode(target, "failsafe")
                self._event("failsafe", "offboard signal lost")
        self._check_gcs_failsafe(now)
        if not self._armed:
            return
        # auto-disarm on the ground
        if self.dynamics.on_ground:
            if self._touchdown_s is not None:
                delay = self._disarm_after_land_s()
                if delay >= 0 and now - self._touchdown_s >= delay:
                    self._disarm(now, p.text("auto_disarm_land"), "landed")
            elif not self._was_airborne:
                delay = self._disarm_preflight_s()
                if delay > 0 and now - self._armed_at_s >= delay and self._takeoff_alt_local_m is None:
                    self._disarm(now, p.text("auto_disarm_preflight"), "preflight timeout")

    def _check_gcs_failsafe(self, now: float) -> None:
        """ArduCopter's GCS failsafe: ``FS_GCS_TIMEOUT`` after the last HEARTBEAT from system
        ``MAV_GCS_SYSID`` (once one was heard), act on ``FS_GCS_ENABLE``; disarm if landed."""
        enable = int(self._params.get("FS_GCS_ENABLE", 0))
        seen = self._gcs_seen_s
        if enable == 0 or seen is None or self._gcs_failsafe:
            return
        if now - seen <= self._params["FS_GCS_TIMEOUT"]:
            return
        self._gcs_failsafe = True
        self._statustext(self.personality.text("gcs_lost"), mav.MAV_SEVERITY_CRITICAL)
        self._event("failsafe", "GCS heartbeat lost")
        if self.dynamics.on_ground:
            self._disarm(now, self.personality.text("auto_disarm_land"), "GCS failsafe on the ground")
            return
        target = _GCS_FAILSAFE_MODES.get(enable, FlightMode.LAND)
        self._set_mode(target, "failsafe")
        if target is FlightMode.LAND:
            self._land_pause_until_s = now + _LAND_PAUSE_S

    def _disarm_after_land_s(self) -> float:
        p = self.personality
        if "COM_DISARM_LAND" in self._params:
            return self._params["COM_DISARM_LAND"]
        if self._mode in (p.land_mode, p.rtl_mode):
            return p.disarm_after_land_s
        return self._params.get("DISARM_DELAY", p.disarm_after_land_s)

    def _disarm_preflight_s(self) -> float:
        if "COM_DISARM_PRFLT" in self._params:
            return self._params["COM_DISARM_PRFLT"]
        return self._params.get("DISARM_DELAY", self.personality.disarm_preflight_s)

    def _hold_command(self, now: float) -> tuple[npt.NDArray[np.float64], float | None, float | None]:
        """Brake, then hold the position where the vehicle stopped (local ENU velocity)."""
        est = self._est_pos_local()
        if self.dynamics.on_ground and not self._landing:
            return np.zeros(3), None, 0.0
        if self._hold_target is None:
            if float(np.linalg.norm(self._est_vel_local())) > 0.15:
                return np.zeros(3), None, 0.0
            self._hold_target = est.copy()
            self._hold_yaw = self._est_yaw_local()
        return self._goto(self._hold_target, 2.0, 1.0), self._hold_yaw, None

    def _goto(
        self, target_local: npt.NDArray[np.float64], max_xy: float, max_z: float
    ) -> npt.NDArray[np.float64]:
        err = target_local - self._est_pos_local()
        v = 1.2 * err
        vh = math.hypot(v[0], v[1])
        if vh > max_xy:
            v[:2] *= max_xy / vh
        v[2] = max(-max_z, min(max_z, v[2]))
        return v

    def _command_dynamics(self, now: float) -> None:
        p = self.personality
        if not self._armed:
            self._shaper_last_s = None
            return
        vel_local = np.zeros(3)
        accel_local: npt.NDArray[np.float64] | None = None  # set: a kinematic target, not shaped
        yaw_local: float | None = None
        yaw_rate: float | None = 0.0
        mode = self._mode

        if self._takeoff_alt_local_m is not None:
            est = self._est_pos_local()
            climb = self._params.get("MPC_TKO_SPEED", self._params.get("WPNAV_SPEED_UP", 250.0) / 100.0)
            if self._hold_target is None:
                self._hold_target = est.copy()
                self._hold_yaw = self._est_yaw_local()
            spooling = self.dynamics.on_ground and now - self._takeoff_cmd_s < p.takeoff_spool_s
            if spooling:
                yaw_local, yaw_rate = self._hold_yaw, None
            elif (
                self.dynamics.motor_state()[0] is MotorState.SPINUP
                or est[2] < self._takeoff_alt_local_m - 0.05
            ):
                vel_local = self._goto(
                    np.array([self._hold_target[0], self._hold_target[1], est[2]]), 1.0, 0.0
                )
                vel_local[2] = self._climb_speed(self._takeoff_alt_local_m - est[2], climb)
                yaw_local, yaw_rate = self._hold_yaw, None
            else:
                self._hold_target = np.array(
                    [self._hold_target[0], self._hold_target[1], self._takeoff_alt_local_m]
                )
                self._takeoff_alt_local_m = None
                self._event("takeoff", "complete")
                if p.takeoff_mode is not None and mode is p.takeoff_mode:
                    self._set_mode(p.hold_mode, "takeoff complete")
                    return
        elif mode is p.land_mode or (mode is p.rtl_mode and self._rtl_phase == "land"):
            est = self._est_pos_local()
            if self._hold_target is None:
                self._hold_target = est.copy()
                self._hold_yaw = self._est_yaw_local()
            vel_local = self._goto(np.array([self._hold_target[0], self._hold_target[1], est[2]]), 1.0, 0.0)
            vel_local[2] = 0.0 if now < self._land_pause_until_s else -self._land_speed()
            yaw_local, yaw_rate = self._hold_yaw, None
        elif mode is p.rtl_mode:
            vel_local, yaw_local, yaw_rate = self._rtl_command()
        elif mode is p.setpoint_mode:
            vel_local, yaw_local, yaw_rate, accel_local = self._setpoint_command(now)
        elif mode in _HOLD_LIKE:
            vel_local, yaw_local, yaw_rate = self._hold_command(now)

        vel_local, accel_local = self._position_controller(now, vel_local, accel_local)
        vel_world = self._est_to_world_vec(vel_local)
        accel_world = None if accel_local is None else self._est_to_world_vec(accel_local)
        yaw_world = None
        if yaw_local is not None:
            yaw_world = wrap_angle_rad(yaw_local - self._yaw_bias + self.options.heading_offset_rad)
        self.dynamics.command(
            vel_world,
            yaw_rad=yaw_world,
            yaw_rate_rad_s=None if yaw_world is not None else yaw_rate,
            accel_enu_m_s2=accel_world,
        )

    def _climb_speed(self, remaining_m: float, climb_m_s: float) -> float:
        """Take-off climb speed with ``remaining_m`` to go: the firmware's position controller
        (ArduCopter: square-root profile within WPNAV_ACCEL_Z), else a proportional slow-down."""
        limits = self.personality.posctl_limits
        if limits is None:
            return max(0.3, min(climb_m_s, 1.5 * remaining_m))
        accel_z = limits(self._params).accel_z_m_s2
        cap = min(climb_m_s, self.personality.takeoff_climb_max_m_s)
        return min(cap, math.sqrt(2.0 * accel_z * max(remaining_m, 0.0)))

    def _position_controller(
        self,
        now: float,
        vel_local: npt.NDArray[np.float64],
        accel_local: npt.NDArray[np.float64] | None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64] | None]:
        """The firmware's kinematic shaping of the velocity command (ArduCopter's AC_PosControl:
        acceleration and jerk limits), unless the command is already a kinematic target."""
        make_limits = self.personality.posctl_limits
        last, self._shaper_last_s = self._shaper_last_s, now
        if make_limits is None:
            return vel_local, accel_local
        if accel_local is not None:  # a position/velocity/acceleration target: followed as it is
            self._shaper.reset(vel_local)
            self._shaper.accel_m_s2 = accel_local.copy()
            return vel_local, accel_local
        if self.dynamics.on_ground and vel_local[2] <= 0.0:
            self._shaper.reset()
            return vel_local, None
        dt = 0.0 if last is None else max(0.0, now - last)
        return self._shaper.step(vel_local, make_limits(self._params), dt)

    def _land_speed(self) -> float:
        if "MPC_LAND_SPEED" in self._params:
            return self._params["MPC_LAND_SPEED"]
        if "LAND_SPEED" in self._params:
            return self._params["LAND_SPEED"] / 100.0
        return self.personality.land_speed_m_s

    def _rtl_command(self) -> tuple[npt.NDArray[np.float64], float | None, float | None]:
        est = self._est_pos_local()
        alt = self._params.get("RTL_RETURN_ALT", self._params.get("RTL_ALT", 1500.0) / 100.0)
        if self._hold_yaw is None:
            self._hold_yaw = self._est_yaw_local()
        if self._rtl_phase == "climb":
            if est[2] >= alt - 0.1 or self.dynamics.on_ground:
                self._rtl_phase = "return"
                self._statustext(self.personality.text("rtl", alt=max(alt, est[2])))
            target = np.array([est[0], est[1], max(alt, est[2])])
            return self._goto(target, 0.5, 2.0), self._hold_yaw, None
        if self._rtl_phase == "return":
            target = np.array([self._home_local_enu[0], self._home_local_enu[1], max(alt, est[2] - 0.0)])
            if math.hypot(est[0] - target[0], est[1] - target[1]) < 0.2:
                self._rtl_phase = "land"
                self._landing = True
                self._hold_target = None
            return self._goto(target, 3.0, 1.0), self._hold_yaw, None
        return np.zeros(3), self._hold_yaw, None

    def _setpoint_command(
        self, now: float
    ) -> tuple[npt.NDArray[np.float64], float | None, float | None, npt.NDArray[np.float64] | None]:
        """(velocity, yaw, yaw rate, acceleration) from the current setpoint; the acceleration is
        not None when the setpoint is a kinematic target (position with velocity or acceleration)."""
        p = self.personality
        if p.loss_action is LossAction.FAILSAFE_MODE:
            sp = self._setpoint
            if sp is None:
                return (*self._hold_command(now), None)
        else:
            sp = self._guided_target
            if sp is None:
                return (*self._hold_command(now), None)
            if sp.pos_local_enu_m is None and now - sp.received_s > self._loss_timeout_s():
                # GUID_TIMEOUT: stop, brake, hover in GUIDED
                self._guided_target = None
                self._hold_target = None
                self._statustext(p.text("offboard_lost"), mav.MAV_SEVERITY_WARNING)
                self._event("failsafe", "velocity command timeout, braking")
                return (*self._hold_command(now), None)
        self._hold_target = None
        accel: npt.NDArray[np.float64] | None = None
        if sp.pos_local_enu_m is not None and (
            sp.accel_local_enu_m_s2 is not None or (sp.vel_local_enu_m_s is not None and p.posctl_limits)
        ):
            vel, accel = self._kinematic_target(now, sp)
        elif sp.pos_local_enu_m is not None:
            vel = self._goto(sp.pos_local_enu_m, 3.0, 1.5)
            if sp.vel_local_enu_m_s is not None:
                vel = vel + sp.vel_local_enu_m_s
        else:
            assert sp.vel_local_enu_m_s is not None
            vel = sp.vel_local_enu_m_s.copy()
        if sp.yaw_local_enu_rad is not None:
            return vel, sp.yaw_local_enu_rad, None, accel
        if sp.yaw_rate_enu_rad_s is not None:
            return vel, None, sp.yaw_rate_enu_rad_s, accel
        # yaw not commanded: hold the current heading
        if self._hold_yaw is None:
            self._hold_yaw = self._est_yaw_local()
        return vel, self._hold_yaw, None, accel

    def _kinematic_target(
        self, now: float, sp: _Setpoint
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Velocity command and acceleration feed-forward for a position + velocity (+ acceleration)
        target: the target advances with its velocity and acceleration between messages (as
        ArduCopter's guided mode does; for GUID_TIMEOUT, then it stops there), and the position
        error feeds back with the position gain."""
        assert sp.pos_local_enu_m is not None
        vel = np.zeros(3) if sp.vel_local_enu_m_s is None else sp.vel_local_enu_m_s
        acc = np.zeros(3) if sp.accel_local_enu_m_s2 is None else sp.accel_local_enu_m_s2
        age = max(0.0, now - sp.received_s)
        timeout = self._loss_timeout_s()
        if age > timeout:
            pos_t = sp.pos_local_enu_m + vel * timeout + 0.5 * acc * timeout**2
            vel_t, acc_t = np.zeros(3), np.zeros(3)
        else:
            pos_t = sp.pos_local_enu_m + vel * age + 0.5 * acc * age**2
            vel_t, acc_t = vel + acc * age, acc.copy()
        make_limits = self.personality.posctl_limits
        if make_limits is None:
            kp_xy = kp_z = 1.2
        else:
            limits = make_limits(self._params)
            kp_xy, kp_z = limits.pos_xy_p_1_s, limits.pos_z_p_1_s
        err = pos_t - self._est_pos_local()
        return vel_t + np.array([kp_xy * err[0], kp_xy * err[1], kp_z * err[2]]), acc_t

    def _update_ground_state(self, now: float) -> None:
        on_ground = self.dynamics.on_ground
        if not on_ground and self._armed:
            if not self._was_airborne:
                self._was_airborne = True
                self._statustext(self.personality.text("takeoff_detected"))
                self._event("airborne", "")
            self._touchdown_s = None
        elif on_ground and self._was_airborne and self._touchdown_s is None:
            self._touchdown_s = now
            self._was_airborne = False
            self._takeoff_alt_local_m = None
            self._statustext(self.personality.text("landed"))
            self._event("landed", "")

    def _landed_state(self) -> LandedState:
        if self.dynamics.on_ground:
            return LandedState.ON_GROUND
        if self._takeoff_alt_local_m is not None:
            return LandedState.TAKEOFF
        if self._landing or (self._mode is self.personality.rtl_mode and self._rtl_phase == "land"):
            return LandedState.LANDING
        return LandedState.IN_AIR

    def _ev_pos_enabled(self) -> bool:
        if "EKF2_EV_CTRL" in self._params:
            return int(self._params["EKF2_EV_CTRL"]) & 1 == 1
        return self._params.get("VISO_TYPE", 0) > 0 and int(self._params.get("EK3_SRC1_POSXY", 3)) == 6

    def _ev_yaw_enabled(self) -> bool:
        if "EKF2_EV_CTRL" in self._params:
            return int(self._params["EKF2_EV_CTRL"]) & 8 == 8
        return self._params.get("VISO_TYPE", 0) > 0 and int(self._params.get("EK3_SRC1_YAW", 1)) == 6

    def _update_estimator(self, now: float) -> None:
        active = self._ev_pos_enabled() and now - self._ev_last_s < 1.0
        if active != self._ev_active:
            self._ev_active = active
            self._statustext(self.personality.text("ev_fusion_on" if active else "ev_fusion_off"))
            self._event("vision", "fusing" if active else "stopped")
        if not self._ev_active:
            wander_world = self.dynamics.sensed_pos_enu_m() - self.dynamics.pos_enu_m
            self._est_bias = _rot_z(self._yaw_bias) @ self._world_to_local_vec(wander_world)

    def _fuse_vision(self, now: float, pos_ned: npt.NDArray[np.float64], yaw_ned: float | None) -> None:
        if not np.all(np.isfinite(pos_ned)):
            return
        self._ev_last_s = now
        if not self._ev_pos_enabled():
            return
        gain = 0.3
        meas_local = ned_to_enu(pos_ned)
        if not self._ev_active:
            gain = 1.0  # first measurement: the estimate jumps onto the vision frame
        est = self._est_pos_local()
        self._est_bias = self._est_bias + gain * (meas_local - est)
        if yaw_ned is not None and math.isfinite(yaw_ned) and self._ev_yaw_enabled():
            # align the estimator's frame with the vision frame; keep the position estimate continuous
            meas_yaw = yaw_ned_to_enu(yaw_ned)
            before = self._est_pos_local()
            self._yaw_bias = wrap_angle_rad(
                self._yaw_bias + gain * wrap_angle_rad(meas_yaw - self._est_yaw_local())
            )
            self._est_bias = self._est_bias + (before - self._est_pos_local())

    def _arming_refusal(self, now: float) -> str | None:
        p = self.personality
        if not self._ready(now):
            if p.loss_action is LossAction.FAILSAFE_MODE or self._mode in _NEEDS_POSITION_ARDUPILOT:
                return p.text("not_ready")
        if p.stream_required_s > 0.0 and self._mode is p.setpoint_mode and not self._offboard_signal_ok(now):
            return p.text("no_offboard")
        return None

    def _arm(self, now: float) -> None:
        self._armed = True
        self._armed_at_s = now
        self._touchdown_s = None
        self._was_airborne = not self.dynamics.on_ground
        self._hold_target = None
        self._hold_yaw = None
        self._home_local_enu = self._est_pos_local().copy()
        self._home_yaw_local = self._est_yaw_local()
        self.dynamics.set_armed(True)
        self._statustext(self.personality.text("armed"))
        self._event("armed", self._mode.value)
        self._send_heartbeat(now)

    def _disarm(self, now: float, text: str, why: str) -> None:
        self._armed = False
        self._touchdown_s = None
        self._was_airborne = False
        self._takeoff_alt_local_m = None
        self._guided_target = None
        self.dynamics.set_armed(False)
        self._statustext(text)
        self._event("disarmed", why)
        self._send_heartbeat(now)

    def _start_takeoff(self, alt_local_m: float) -> None:
        self._takeoff_alt_local_m = alt_local_m
        self._takeoff_cmd_s = self.clock.monotonic_s()
        self._hold_target = None
