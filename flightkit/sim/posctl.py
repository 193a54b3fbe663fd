"""The firmware's position controller as the simulated autopilot runs it (ArduCopter's ``AC_PosControl``).

A real autopilot does not hand a velocity setpoint straight to its attitude loops: it first
turns it into a smooth kinematic target, limited in acceleration and jerk, and then tracks
that target with position and velocity feedback and an acceleration feed-forward. Those
limits are what make a vehicle lag a velocity-only stream (issue 19: ArduCopter moved 2.32 m
for 1 m/s held 3 s). This module holds that shaping:

* :class:`PosCtlLimits`: the limits and gains, read from the firmware's parameters
  (``WPNAV_ACCEL``, ``WPNAV_ACCEL_Z``, ``PSC_JERK_XY``, ``PSC_JERK_Z``, ``PSC_POSXY_P``,
  ``PSC_POSZ_P``; docs/sim.md says where each default comes from).
* :class:`VelocityShaper`: a velocity target that follows the commanded velocity with its
  acceleration limited in norm (horizontal) or magnitude (vertical) and its change limited by
  the jerk limit. The velocity error gain is jerk / acceleration, so the acceleration reaches
  its limit as the jerk allows.

The vehicle (:class:`~flightkit.sim.dynamics.QuadDynamics`) is then told the shaped velocity
and its acceleration as feed-forward. Pure float arithmetic on numpy vectors, ENU, metres and
seconds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["PosCtlLimits", "VelocityShaper"]


@dataclass(frozen=True, slots=True)
class PosCtlLimits:
    """Limits and gains of the firmware's position controller.

    Attributes:
        accel_xy_m_s2: horizontal acceleration limit of the kinematic target.
        accel_z_m_s2: vertical acceleration limit of the kinematic target.
        jerk_xy_m_s3: horizontal jerk limit.
        jerk_z_m_s3: vertical jerk limit.
        pos_xy_p_1_s: horizontal position error gain (position targets).
        pos_z_p_1_s: vertical position error gain (position targets).
    """

    accel_xy_m_s2: float
    accel_z_m_s2: float
    jerk_xy_m_s3: float
    jerk_z_m_s3: float
    pos_xy_p_1_s: float
    pos_z_p_1_s: float

    @staticmethod
    def from_ardupilot_params(params: Mapping[str, float]) -> PosCtlLimits:
        """The limits from ArduCopter's parameters (``WPNAV_ACCEL*`` in cm/s², ``PSC_JERK_*`` in m/s³)."""
        return PosCtlLimits(
            accel_xy_m_s2=params["WPNAV_ACCEL"] / 100.0,
            accel_z_m_s2=params["WPNAV_ACCEL_Z"] / 100.0,
            jerk_xy_m_s3=params["PSC_JERK_XY"],
            jerk_z_m_s3=params["PSC_JERK_Z"],
            pos_xy_p_1_s=params["PSC_POSXY_P"],
            pos_z_p_1_s=params["PSC_POSZ_P"],
        )


def _shape(
    v_cmd: npt.NDArray[np.float64],
    v_t: npt.NDArray[np.float64],
    a_t: npt.NDArray[np.float64],
    accel_max: float,
    jerk_max: float,
    dt_s: float,
) -> None:
    """One step of the velocity target ``v_t`` (with acceleration ``a_t``) toward ``v_cmd``, in place.

    The wanted acceleration is ``(jerk / accel) * (v_cmd - v_t)``, limited in norm to
    ``accel_max``; the acceleration moves toward it by at most ``jerk_max * dt_s``. Near the
    commanded velocity the acceleration is also capped so it can come back to zero within the
    jerk limit without passing the command.
    """
    gain = jerk_max / accel_max
    err = v_cmd - v_t
    want = gain * err
    # stop accelerating in time: with jerk J, an acceleration a needs a^2 / (2 J) of velocity to unwind
    err_norm = float(np.linalg.norm(err))
    cap = min(accel_max, math.sqrt(2.0 * jerk_max * err_norm))
    norm = float(np.linalg.norm(want))
    if norm > cap:
        want *= cap / norm
    step = want - a_t
    step_norm = float(np.linalg.norm(step))
    max_step = jerk_max * dt_s
    if step_norm > max_step:
        step *= max_step / step_norm
    a_t += step
    v_t += a_t * dt_s


class VelocityShaper:
    """The firmware's velocity target: follows the command within acceleration and jerk limits.

    Horizontal (x, y) and vertical (z) are shaped separately, each with its own limits.
    """

    def __init__(self) -> None:
        self.vel_m_s = np.zeros(3)
        self.accel_m_s2 = np.zeros(3)

    def reset(self, vel_m_s: npt.ArrayLike = (0.0, 0.0, 0.0)) -> None:
        """Start again from ``vel_m_s`` at zero acceleration (on the ground, or on a mode change)."""
        self.vel_m_s = np.array(vel_m_s, dtype=np.float64).reshape(3)
        self.accel_m_s2 = np.zeros(3)

    def step(
        self, vel_cmd_m_s: npt.NDArray[np.float64], limits: PosCtlLimits, dt_s: float
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Advance by ``dt_s`` toward ``vel_cmd_m_s``; the shaped (velocity, acceleration)."""
        if dt_s > 0.0:
            v_xy, a_xy = self.vel_m_s[:2].copy(), self.accel_m_s2[:2].copy()
            _shape(vel_cmd_m_s[:2], v_xy, a_xy, limits.accel_xy_m_s2, limits.jerk_xy_m_s3, dt_s)
            v_z, a_z = self.vel_m_s[2:].copy(), self.accel_m_s2[2:].copy()
            _shape(vel_cmd_m_s[2:], v_z, a_z, limits.accel_z_m_s2, limits.jerk_z_m_s3, dt_s)
            self.vel_m_s = np.concatenate([v_xy, v_z])
            self.accel_m_s2 = np.concatenate([a_xy, a_z])
        return self.vel_m_s.copy(), self.accel_m_s2.copy()
