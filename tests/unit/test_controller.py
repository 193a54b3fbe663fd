"""The tracking controller: feed-forward + P (+ I with anti-windup), limits, frames and yaw."""

from __future__ import annotations

import dataclasses
import math

import pytest

from flightkit.errors import ConfigError
from flightkit.link.base import SetpointFrame
from flightkit.settings import load_section
from trajectories.base import Reference, with_acceleration
from trajectories.controller import (
    ControllerConfig,
    OutputFrame,
    SetpointKind,
    VelocityController,
    YawControl,
)
from trajectories.patterns import Circle


def ref(pos=(0.0, 0.0, 1.0), vel=(0.0, 0.0, 0.0), yaw=0.0, rate=0.0) -> Reference:
    return Reference(0.0, pos, vel, yaw, rate)


def world(**kw: object) -> VelocityController:
    return VelocityController(ControllerConfig(output_frame=OutputFrame.LOCAL_NED, **kw))  # type: ignore[arg-type]


def test_feedforward_plus_proportional_per_axis_group() -> None:
    c = world(kp_horizontal=2.0, kp_vertical=0.5)
    out = c.step(ref(pos=(1.0, 0.1, 1.2), vel=(0.05, -0.02, 0.01)), (0.9, 0.0, 1.0), 0.0, 0.01)
    assert out.vel_world_m_s == pytest.approx((0.05 + 0.2, -0.02 + 0.2, 0.01 + 0.1))
    assert out.error_m == pytest.approx((0.1, 0.1, 0.2))
    assert out.setpoint.frame is SetpointFrame.WORLD
    assert not out.saturated


def test_p_only_law_ignores_reference_velocity_and_yaw_rate() -> None:
    c = world(feedforward=False, kp_horizontal=1.0)
    out = c.step(ref(pos=(0.0, 0.0, 1.0), vel=(0.5, 0.0, 0.0), rate=0.3), (0.0, 0.0, 1.0), 0.0, 0.01)
    assert out.vel_world_m_s == (0.0, 0.0, 0.0)
    assert out.setpoint.yaw_rate_rad_s == 0.0
    ff = world(feedforward=True).step(ref(vel=(0.5, 0.0, 0.0), rate=0.3), (0.0, 0.0, 1.0), 0.0, 0.01)
    assert ff.vel_world_m_s == pytest.approx((0.5, 0.0, 0.0)) and ff.setpoint.yaw_rate_rad_s == pytest.approx(
        0.3
    )


def test_limits_keep_horizontal_direction_and_clip_vertical() -> None:
    c = world()  # defaults: 1.0 m/s horizontal, 0.4 m/s vertical
    out = c.step(ref(pos=(3.0, 4.0, 3.0)), (0.0, 0.0, 1.0), 0.0, 0.01)
    vx, vy, vz = out.vel_world_m_s
    assert math.hypot(vx, vy) == pytest.approx(1.0)
    assert vy / vx == pytest.approx(4.0 / 3.0)
    assert vz == pytest.approx(0.4)
    assert out.saturated
    down = c.step(ref(pos=(0.0, 0.0, 0.0)), (0.0, 0.0, 2.0), 0.0, 0.01)
    assert down.vel_world_m_s[2] == pytest.approx(-0.4)
    out.setpoint.check_limits(1.0, 0.4, 1.0)  # never above the configured limits


@pytest.mark.parametrize("yaw", [0.0, 0.7, math.pi / 2, -2.5, math.pi])
def test_body_frame_rotates_by_measured_yaw(yaw: float) -> None:
    c = VelocityController(ControllerConfig(output_frame=OutputFrame.BODY))
    out = c.step(ref(pos=(0.0, 0.0, 1.0), vel=(0.3, 0.1, 0.0)), (0.0, 0.0, 1.0), yaw, 0.01)
    bx, by, bz = out.setpoint.vel_m_s
    assert out.setpoint.frame is SetpointFrame.BODY
    # rotating the body command back by the yaw gives the world command
    wx = math.cos(yaw) * bx - math.sin(yaw) * by
    wy = math.sin(yaw) * bx + math.cos(yaw) * by
    assert (wx, wy, bz) == pytest.approx((0.3, 0.1, 0.0))
    assert out.setpoint.yaw_rad is None and out.setpoint.yaw_rate_rad_s is not None


def test_yaw_rate_uses_wrapped_error_and_is_limited() -> None:
    c = world(kp_yaw=2.0, max_yaw_rate_rad_s=1.0)
    # reference 4*pi + 0.1 (two laps later) vs measured -0.1 (wrapped): the error is 0.2, not 4 pi
    out = c.step(ref(yaw=4 * math.pi + 0.1), (0.0, 0.0, 1.0), -0.1, 0.01)
    assert out.yaw_error_rad == pytest.approx(0.2)
    assert out.setpoint.yaw_rate_rad_s == pytest.approx(0.4)
    # across +-pi: reference just below pi, measured just above -pi -> small negative error
    out = c.step(ref(yaw=math.pi - 0.05), (0.0, 0.0, 1.0), -math.pi + 0.05, 0.01)
    assert out.yaw_error_rad == pytest.approx(-0.1)
    big = c.step(ref(yaw=2.0), (0.0, 0.0, 1.0), 0.0, 0.01)
    assert big.setpoint.yaw_rate_rad_s == pytest.approx(1.0)


def test_yaw_setpoint_mode_sends_wrapped_heading() -> None:
    c = world(yaw_control=YawControl.SETPOINT)
    out = c.step(ref(yaw=2 * math.pi + 3.0), (0.0, 0.0, 1.0), 0.0, 0.01)
    assert out.setpoint.yaw_rad == pytest.approx(3.0)
    assert out.setpoint.yaw_rate_rad_s is None
    with pytest.raises(ConfigError, match="body frame"):
        load_section(
            ControllerConfig,
            {"yaw_control": "setpoint", "output_frame": "body"},
            path="p.toml",
            prefix="controller",
        )


def test_integral_removes_steady_bias_and_does_not_wind_up() -> None:
    c = world(kp_horizontal=1.0, ki_horizontal=0.5, integral_limit_m_s=0.2)
    # constant error of 0.1 m for 2 s -> integral contribution 0.5 * 0.1 * 2 = 0.1 m/s
    for _ in range(200):
        c.step(ref(pos=(0.1, 0.0, 1.0)), (0.0, 0.0, 1.0), 0.0, 0.01)
    assert c.integral_m_s[0] == pytest.approx(0.1, rel=1e-6)
    # a long error keeps it at the clamp
    for _ in range(5000):
        c.step(ref(pos=(0.1, 0.0, 1.0)), (0.0, 0.0, 1.0), 0.0, 0.01)
    assert c.integral_m_s[0] == pytest.approx(0.2)
    # while saturated it does not integrate
    c.reset()
    for _ in range(300):
        out = c.step(ref(pos=(5.0, 0.0, 1.0)), (0.0, 0.0, 1.0), 0.0, 0.01)
        assert out.saturated
    assert c.integral_m_s == (0.0, 0.0, 0.0)


def _simulate(feedforward: bool) -> float:
    """First-order velocity-tracking vehicle (tau 0.25 s) on the lab circle; returns RMS error."""
    pat = Circle(radius_m=1.0, period_s=40.0, laps=1, height_m=1.5)
    c = VelocityController(ControllerConfig(output_frame=OutputFrame.LOCAL_NED, feedforward=feedforward))
    dt, tau = 0.01, 0.25
    p = list(pat.reference(0.0).pos_m)
    v = [0.0, 0.0, 0.0]
    errs = []
    t = 0.0
    while t < pat.duration_s:
        r = pat.reference(t)
        out = c.step(r, (p[0], p[1], p[2]), r.yaw_rad, dt)
        for i in range(3):
            v[i] += (out.vel_world_m_s[i] - v[i]) * dt / tau
            p[i] += v[i] * dt
        errs.append(out.error_norm_m**2)
        t += dt
    return math.sqrt(sum(errs) / len(errs))


def test_feedforward_beats_p_only_on_the_circle() -> None:
    rms_ff = _simulate(True)
    rms_p = _simulate(False)
    assert rms_p > 0.1  # the P-only law lags by v/Kp = 0.157 m
    assert rms_ff < rms_p / 5.0


def test_hold_is_zero_velocity_keep_yaw() -> None:
    sp = VelocityController().hold()
    assert sp.vel_m_s == (0.0, 0.0, 0.0) and sp.yaw_rate_rad_s == 0.0 and sp.frame is SetpointFrame.BODY


def test_pva_sends_the_reference_position_and_a_limited_acceleration() -> None:
    c = world(setpoint=SetpointKind.PVA, max_accel_m_s2=1.0)
    r = dataclasses.replace(ref(pos=(1.0, 0.0, 1.5), vel=(0.1, 0.0, 0.0)), accel_m_s2=(3.0, 4.0, 0.0))
    out = c.step(r, (0.9, 0.0, 1.5), 0.0, 0.01)
    assert out.setpoint.pos_m == (1.0, 0.0, 1.5)
    assert out.setpoint.accel_m_s2 == pytest.approx((0.6, 0.8, 0.0))  # 5 m/s^2 cut to 1, direction kept
    assert out.setpoint.vel_m_s == pytest.approx((0.2, 0.0, 0.0))  # feed-forward + the mocap error term
    # the baseline sends a velocity only
    assert world().step(r, (0.9, 0.0, 1.5), 0.0, 0.01).setpoint.pos_m is None


def test_pva_needs_the_local_frame() -> None:
    with pytest.raises(ConfigError, match="position targets are in the autopilot's local frame"):
        load_section(ControllerConfig, {"setpoint": "pva", "output_frame": "body"}, path="plan.toml")


def test_reference_acceleration_is_the_velocity_derivative() -> None:
    circle = Circle(radius_m=1.0, period_s=40.0, laps=1, height_m=1.5)
    r = with_acceleration(circle, circle.reference(10.0))
    omega = 2 * math.pi / 40.0
    assert math.hypot(*r.accel_m_s2[:2]) == pytest.approx(omega**2 * 1.0, rel=1e-3)  # centripetal
    # pointing at the centre
    assert r.accel_m_s2[0] * r.pos_m[0] + r.accel_m_s2[1] * r.pos_m[1] < 0.0
