"""QuadDynamics: velocity lag, limits, ground contact, spin-up, yaw, wind, noise, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightkit.errors import SetpointError, SimError
from flightkit.link.base import FlightMode
from flightkit.sim.dynamics import DynamicsParams, MotorState, QuadDynamics
from flightkit.sim.personality import ARDUPILOT, PX4, personality_for, px4_custom_mode


def flying(params: DynamicsParams | None = None, alt_m: float = 2.0) -> QuadDynamics:
    d = QuadDynamics(params or DynamicsParams(spinup_s=0.0, thrust_ramp_s=0.0), pos_enu_m=(0.0, 0.0, alt_m))
    d.set_armed(True)
    return d


def test_velocity_follows_first_order_lag() -> None:
    d = flying(
        DynamicsParams(velocity_time_constant_s=0.5, max_accel_m_s2=100.0, spinup_s=0, thrust_ramp_s=0)
    )
    d.command((1.0, 0.0, 0.0))
    d.step(0.5)  # one time constant
    assert d.vel_enu_m_s[0] == pytest.approx(1.0 - math.exp(-1.0), abs=0.01)
    d.step(3.0)
    assert d.vel_enu_m_s[0] == pytest.approx(1.0, abs=1e-3)


def test_acceleration_is_limited() -> None:
    d = flying(DynamicsParams(velocity_time_constant_s=0.01, max_accel_m_s2=2.0, spinup_s=0, thrust_ramp_s=0))
    d.command((5.0, 0.0, 0.0))
    d.step(1.0)
    assert d.vel_enu_m_s[0] == pytest.approx(2.0, abs=0.05)
    assert np.linalg.norm(d.state().accel_enu_m_s2) <= 2.0 + 1e-9


def test_never_sinks_below_the_floor_and_lands() -> None:
    d = flying(alt_m=0.5)
    d.command((0.0, 0.0, -1.0))
    for _ in range(300):
        d.step(0.01)
        assert d.pos_enu_m[2] >= 0.0
    st = d.state()
    assert st.on_ground and st.pos_enu_m[2] == 0.0 and np.all(st.vel_enu_m_s == 0.0)
    d.command((1.0, 1.0, 0.0))  # no sliding on the floor
    d.step(1.0)
    assert np.allclose(d.pos_enu_m[:2], 0.0)


def test_spinup_and_thrust_ramp_delay_liftoff() -> None:
    d = QuadDynamics(DynamicsParams(spinup_s=1.0, thrust_ramp_s=3.0))
    d.set_armed(True)
    d.command((0.0, 0.0, 1.0))
    d.step(0.5)
    assert d.motor_state()[0] is MotorState.SPINUP and d.on_ground
    d.step(2.0)
    state, frac = d.motor_state()
    assert state is MotorState.RAMP and 0.3 < frac < 0.7 and d.on_ground
    d.step(1.45)
    assert d.on_ground  # 3.95 s after arming
    d.step(0.5)
    assert not d.on_ground and d.pos_enu_m[2] > 0.0


def test_disarmed_in_air_falls() -> None:
    d = flying(alt_m=5.0)
    d.set_armed(False)
    d.step(0.5)
    assert d.pos_enu_m[2] == pytest.approx(5.0 - 0.5 * 9.80665 * 0.25, abs=0.1)
    d.step(2.0)
    assert d.on_ground


def test_yaw_tracks_target_with_rate_limit() -> None:
    p = DynamicsParams(max_yaw_rate_rad_s=1.0, spinup_s=0, thrust_ramp_s=0)
    d = flying(p)
    d.command((0, 0, 0), yaw_rad=math.pi / 2)
    d.step(0.5)
    assert d.yaw_rad <= 0.5 + 1e-6  # at most 1 rad/s
    d.step(3.0)
    assert d.yaw_rad == pytest.approx(math.pi / 2, abs=0.01)
    d.command((0, 0, 0), yaw_rate_rad_s=-0.5)
    d.step(1.0)
    assert d.state().yaw_rate_rad_s == pytest.approx(-0.5, abs=0.01)


def test_yaw_wraps_across_pi() -> None:
    d = QuadDynamics(DynamicsParams(spinup_s=0, thrust_ramp_s=0), pos_enu_m=(0, 0, 1), yaw_rad=3.0)
    d.set_armed(True)
    d.command((0, 0, 0), yaw_rad=-3.0)  # shortest way is through +pi
    d.step(2.0)
    assert d.yaw_rad == pytest.approx(-3.0, abs=0.01)
    assert -math.pi <= d.yaw_rad < math.pi


def test_tilt_follows_acceleration() -> None:
    d = flying(DynamicsParams(velocity_time_constant_s=0.5, spinup_s=0, thrust_ramp_s=0))
    d.command((2.0, 0.0, 0.0))  # facing +x: accelerate forward -> nose down (+pitch in FLU)
    d.step(0.05)
    st = d.state()
    assert st.pitch_rad > 0.1 and abs(st.roll_rad) < 1e-6
    assert st.T_world_body().yaw_rad == pytest.approx(0.0, abs=1e-9)


def test_gust_pushes_and_decays() -> None:
    d = flying()
    d.command((0.0, 0.0, 0.0))
    d.inject_gust((3.0, 0.0, 0.0), duration_s=2.0)
    d.step(1.0)
    assert d.state().wind_enu_m_s[0] == pytest.approx(3.0, abs=0.05)
    d.step(1.5)
    assert d.pos_enu_m[0] > 0.05  # pushed downwind
    assert np.allclose(d.state().wind_enu_m_s, 0.0)
    d.step(5.0)
    assert abs(d.vel_enu_m_s[0]) < 0.01  # the velocity loop recovers once the gust is over


def test_seeded_runs_are_identical_and_noise_has_its_std() -> None:
    def run(seed: int) -> np.ndarray:
        p = DynamicsParams(
            wind_gust_m_s=2.0, gust_interval_s=1.0, pos_noise_m=0.05, seed=seed, spinup_s=0, thrust_ramp_s=0
        )
        d = flying(p)
        d.command((0.5, 0.0, 0.0))
        out = []
        for _ in range(500):
            d.step(0.02)
            out.append(d.sensed_pos_enu_m())
        return np.array(out)

    a, b, c = run(1), run(1), run(2)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    d = flying(DynamicsParams(pos_noise_m=0.05, seed=3))
    samples = np.array([d.sensed_pos_enu_m() for _ in range(4000)]) - d.pos_enu_m
    assert samples.std(axis=0) == pytest.approx([0.05] * 3, rel=0.1)


def test_extrapolated_pose() -> None:
    d = flying()
    d.command((1.0, 0.0, 0.0))
    d.step(3.0)
    st = d.state()
    T = st.T_world_body(0.1)
    assert T.translation[0] == pytest.approx(st.pos_enu_m[0] + 0.1 * st.vel_enu_m_s[0])


def test_invalid_input_is_rejected() -> None:
    with pytest.raises(SimError, match="below the floor"):
        QuadDynamics(pos_enu_m=(0, 0, -1))
    with pytest.raises(SimError, match="velocity_time_constant_s"):
        DynamicsParams(velocity_time_constant_s=0.0)
    d = QuadDynamics()
    with pytest.raises(SetpointError, match="finite"):
        d.command((math.nan, 0, 0))
    with pytest.raises(SimError, match="backwards"):
        d.step(-0.1)


def test_personalities_encode_modes_like_the_firmware() -> None:
    assert PX4.custom_modes[FlightMode.OFFBOARD] == 393216
    assert PX4.custom_modes[FlightMode.POSCTL] == 196608
    assert PX4.custom_modes[FlightMode.HOLD] == 50593792
    assert PX4.custom_modes[FlightMode.LAND] == 100925440
    assert px4_custom_mode(4, 2) == PX4.custom_modes[FlightMode.TAKEOFF]
    assert ARDUPILOT.custom_modes[FlightMode.GUIDED] == 4
    assert ARDUPILOT.custom_modes[FlightMode.LAND] == 9
    assert ARDUPILOT.custom_modes[FlightMode.BRAKE] == 17
    assert ARDUPILOT.mode_of(5) is FlightMode.LOITER
    assert PX4.mode_of(12345) is None
    assert personality_for("ArduPilot") is ARDUPILOT
    with pytest.raises(SimError, match="unknown autopilot"):
        personality_for("betaflight")
