"""Patterns: continuity, speed and acceleration limits, lap closure, yaw continuity and geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flightkit.errors import ConfigError, PlanError
from trajectories.base import Pattern, trapezoid, trapezoid_duration_s
from trajectories.patterns import (
    Circle,
    Hold,
    Land,
    Lawnmower,
    Line,
    Rectangle,
    Takeoff,
    Waypoints,
    YawMode,
    rectangle_corners,
)

DT = 0.01


def sample(p: Pattern, dt: float = DT) -> dict[str, np.ndarray]:
    ts = np.arange(0.0, p.duration_s + dt, dt)
    refs = [p.reference(float(t)) for t in ts]
    return {
        "t": ts,
        "pos": np.array([r.pos_m for r in refs]),
        "vel": np.array([r.vel_m_s for r in refs]),
        "yaw": np.array([r.yaw_rad for r in refs]),
        "rate": np.array([r.yaw_rate_rad_s for r in refs]),
        "lap": np.array([r.lap for r in refs]),
    }


def lab_patterns() -> dict[str, Pattern]:
    return {
        "circle": Circle(radius_m=1.0, period_s=40.0, laps=2, height_m=1.5),
        "circle_cw_tangent": Circle(
            radius_m=0.5, speed_m_s=0.4, laps=3, clockwise=True, yaw_mode=YawMode.TRAVEL
        ),
        "rectangle": Rectangle(rectangle_corners((0, 0), (2, 1)), 1.5, 0.1, 0.2, 5.0, laps=2),
        "rectangle_cw_outward": Rectangle(
            [(0, 0), (0, 1), (2, 1), (2, 0)], 1.0, 0.3, 0.5, 2.0, laps=2, yaw_mode=YawMode.OUTWARD
        ),
        "lawnmower": Lawnmower((-1, -0.5), (2, 1), 0.5, 1.5, 0.1, 0.2, 5.0, laps=2),
        "lawnmower_fixed": Lawnmower(
            (0, 0), (2, 1), 0.5, 1.5, 0.2, 0.2, 5.0, yaw_mode=YawMode.FIXED, fixed_yaw_rad=3.0
        ),
        "waypoints": Waypoints(
            [(0, 0, 1), (1, 0, 1), (1, 1, 1.5), (0, 0, 1)], 0.3, 0.3, 0.0, YawMode.TRAVEL, 2.0
        ),
        "takeoff": Takeoff((0.2, -0.1, 0.0), 1.5, 0.3, 0.5, 1.0),
        "land": Land((0.2, -0.1, 1.5), 0.3),
        "hold": Hold((0.0, 0.0, 1.0), 2.0, 3.0),
    }


@pytest.mark.parametrize("name", list(lab_patterns()))
def test_position_continuous_and_velocity_is_its_derivative(name: str) -> None:
    p = lab_patterns()[name]
    s = sample(p)
    dpos = np.diff(s["pos"], axis=0) / DT
    vmid = 0.5 * (s["vel"][1:] + s["vel"][:-1])
    # trapezoidal rule: mean velocity over a step equals the position change (exact for linear v)
    assert np.max(np.abs(dpos - vmid)) < 2e-3
    dyaw = np.diff(s["yaw"]) / DT
    rmid = 0.5 * (s["rate"][1:] + s["rate"][:-1])
    assert np.max(np.abs(dyaw - rmid)) < 5e-3
    # starts and ends at rest
    assert np.allclose(s["vel"][0], 0.0, atol=1e-9) and np.allclose(s["vel"][-1], 0.0, atol=1e-9)


@pytest.mark.parametrize("name", list(lab_patterns()))
def test_yaw_never_jumps(name: str) -> None:
    s = sample(lab_patterns()[name])
    assert np.max(np.abs(np.diff(s["yaw"]))) < 0.02  # no 2*pi jumps at +-pi


@pytest.mark.parametrize(
    ("pattern", "speed", "accel"),
    [
        (Rectangle(rectangle_corners((0, 0), (2, 1)), 1.5, 0.1, 0.2, 5.0, laps=2), 0.1, 0.2),
        (Lawnmower((-1, -0.5), (2, 1), 0.5, 1.5, 0.1, 0.2, 5.0), 0.1, 0.2),
        (Waypoints([(0, 0, 1), (2, 0, 1), (2, 2, 1)], 0.5, 0.4), 0.5, 0.4),
        (Takeoff((0, 0, 0), 2.0, 0.3, 0.5), 0.3, 0.5),
        (Circle(radius_m=1.0, period_s=10.0, laps=2, accel_m_s2=0.3), 2 * math.pi / 10.0, 0.3),
    ],
)
def test_speed_and_acceleration_limits(pattern: Pattern, speed: float, accel: float) -> None:
    s = sample(pattern, 0.005)
    v = np.linalg.norm(s["vel"], axis=1)
    assert v.max() <= speed + 1e-9
    assert v.max() >= speed * 0.999  # and it reaches the cruise speed
    dv_tangential = np.abs(np.diff(v)) / 0.005
    assert dv_tangential.max() <= accel + 1e-6  # ramps instead of jumps


@pytest.mark.parametrize(
    "name", ["circle", "circle_cw_tangent", "rectangle", "rectangle_cw_outward", "lawnmower"]
)
def test_laps_close(name: str) -> None:
    p = lab_patterns()[name]
    assert p.laps >= 2
    start = p.reference(0.0)
    end = p.reference(p.duration_s)
    assert end.done and not start.done
    assert math.dist(start.pos_m, end.pos_m) < 1e-9
    turns = (end.yaw_rad - start.yaw_rad) / (2 * math.pi)
    assert abs(turns - round(turns)) < 1e-9
    if name.startswith(("circle", "rectangle")):
        assert abs(round(turns)) == p.laps  # one full turn of heading per lap
    s = sample(p)
    assert s["lap"][0] == 0 and s["lap"][-1] == p.laps - 1
    assert np.all(np.diff(s["lap"]) >= 0)
    assert p.duration_s == pytest.approx(p.lap_duration_s * p.laps)


def test_circle_geometry_and_inward_yaw() -> None:
    c = Circle(
        centre_m=(0.5, -0.2), radius_m=1.0, period_s=40.0, laps=2, height_m=1.5, start_angle_rad=math.pi
    )
    r0 = c.reference(0.0)
    assert r0.pos_m == pytest.approx((-0.5, -0.2, 1.5))
    assert r0.yaw_rad == pytest.approx(0.0)  # at (-1, 0) from the centre, looking at it = +x
    s = sample(c, 0.05)
    d = s["pos"][:, :2] - np.array([0.5, -0.2])
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.allclose(s["pos"][:, 2], 1.5)
    # the heading points at the centre all the way round
    to_centre = np.arctan2(-d[:, 1], -d[:, 0])
    err = np.angle(np.exp(1j * (s["yaw"] - to_centre)))
    assert np.max(np.abs(err)) < 1e-9
    # counter-clockwise: yaw increases; cruise speed gives 40 s laps
    assert s["yaw"][-1] - s["yaw"][0] == pytest.approx(4 * math.pi)
    assert c.cruise_speed_m_s == pytest.approx(2 * math.pi / 40.0)
    assert c.duration_s == pytest.approx(80.0 + c.cruise_speed_m_s / c.accel_m_s2)


@pytest.mark.parametrize("mode", list(YawMode))
@pytest.mark.parametrize("clockwise", [False, True])
def test_circle_yaw_modes(mode: YawMode, clockwise: bool) -> None:
    c = Circle(
        radius_m=0.8,
        speed_m_s=0.5,
        laps=1,
        clockwise=clockwise,
        yaw_mode=mode,
        fixed_yaw_rad=2.5,
        start_angle_rad=0.3,
    )
    for t in np.linspace(0.5, c.duration_s - 0.5, 17):
        r = c.reference(float(t))
        th = math.atan2(r.pos_m[1], r.pos_m[0])
        travel = math.atan2(r.vel_m_s[1], r.vel_m_s[0])
        want = {
            YawMode.INWARD: th + math.pi,
            YawMode.OUTWARD: th,
            YawMode.TRAVEL: travel,
            YawMode.FIXED: 2.5,
        }[mode]
        assert math.remainder(r.yaw_rad - want, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
        # clockwise means negative angular velocity about z
        cross = r.pos_m[0] * r.vel_m_s[1] - r.pos_m[1] * r.vel_m_s[0]
        assert (cross < 0) == clockwise


def test_rectangle_yaw_perpendicular_inward_and_turns_in_place() -> None:
    r = Rectangle(rectangle_corners((0, 0), (2, 1)), 1.5, 0.1, 0.2, 5.0, laps=1)
    s = sample(r, 0.02)
    moving = np.linalg.norm(s["vel"], axis=1) > 1e-6
    turning = np.abs(s["rate"]) > 1e-9
    assert not np.any(moving & turning)  # never turns while moving
    for i in np.flatnonzero(moving)[::25]:
        v = s["vel"][i]
        inward_normal = math.atan2(v[1], v[0]) + math.pi / 2  # ccw: the inside is on the left
        assert math.remainder(s["yaw"][i] - inward_normal, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
        # looking inward: the heading points toward the centre's side
        p = s["pos"][i]
        look = np.array([math.cos(s["yaw"][i]), math.sin(s["yaw"][i])])
        assert np.dot(look, -p[:2]) > 0
    # four 90-degree turns of 5 s each per lap
    assert r.duration_s == pytest.approx(6.0 / 0.1 + 4 * 0.1 / 0.2 + 4 * 5.0)
    assert s["yaw"][-1] - s["yaw"][0] == pytest.approx(2 * math.pi)
    peak_rate = (math.pi / 2) * (math.pi / 2) / 5.0
    assert np.max(np.abs(s["rate"])) == pytest.approx(peak_rate, rel=1e-3)


def test_lawnmower_lanes_and_travel_yaw() -> None:
    lm = Lawnmower((-1, -0.5), (2, 1), 0.5, 1.5, 0.1, 0.2, 5.0, return_to_start=False)
    ys = sorted({round(p[1], 9) for p in lm.points_m})
    assert ys == [-0.5, 0.0, 0.5]  # three lanes 0.5 m apart cover 1 m
    xs = {round(p[0], 9) for p in lm.points_m}
    assert xs == {-1.0, 1.0}
    s = sample(lm, 0.02)
    for i in np.flatnonzero(np.linalg.norm(s["vel"], axis=1) > 1e-3)[::20]:
        v = s["vel"][i]
        assert math.remainder(s["yaw"][i] - math.atan2(v[1], v[0]), 2 * math.pi) == pytest.approx(
            0.0, abs=1e-9
        )
    end = lm.reference(lm.duration_s)
    assert end.pos_m == pytest.approx((1.0, 0.5, 1.5))


def test_lawnmower_fixed_yaw_never_turns() -> None:
    lm = lab_patterns()["lawnmower_fixed"]
    s = sample(lm)
    assert np.allclose(s["yaw"], 3.0) and np.allclose(s["rate"], 0.0)


def test_lawnmower_lane_direction_rotates_the_area() -> None:
    lm = Lawnmower((0, 0), (2, 1), 0.5, 1.0, lane_dir_rad=math.pi / 2, return_to_start=False)
    # lanes run along +y, stacked toward -x (to the left of +y)
    assert lm.points_m[1][:2] == pytest.approx((0.0, 2.0))
    assert lm.points_m[2][:2] == pytest.approx((-0.5, 2.0))


def test_takeoff_land_hold_line() -> None:
    to = Takeoff((0.2, -0.1, 0.05), 1.5, 0.3, 0.5, 1.0)
    assert to.reference(0).pos_m == pytest.approx((0.2, -0.1, 0.05))
    assert to.reference(to.duration_s).pos_m == pytest.approx((0.2, -0.1, 1.5))
    assert all(to.reference(t).yaw_rad == 1.0 for t in np.linspace(0, to.duration_s, 9))
    ld = Land((0.0, 0.0, 1.0), 0.2, floor_m=0.0, push_m=0.3)
    assert ld.reference(ld.duration_s).pos_m[2] == pytest.approx(-0.3)
    assert min(ld.reference(t).vel_m_s[2] for t in np.linspace(0, ld.duration_s, 50)) == pytest.approx(-0.2)
    h = Hold((1.0, 2.0, 1.0), 0.5, 4.0)
    assert (
        h.duration_s == 4.0 and h.reference(2.0).pos_m == (1.0, 2.0, 1.0) and h.reference(2.0).yaw_rad == 0.5
    )
    ln = Line((0, 0, 1), (1, 1, 1), 0.2, 0.2, yaw_rad=0.3, end_yaw_rad=-2.0)
    assert ln.reference(ln.duration_s).yaw_rad == pytest.approx(-2.0)
    assert ln.reference(ln.duration_s).pos_m == pytest.approx((1.0, 1.0, 1.0))
    with pytest.raises(PlanError, match="takeoff: height_m: target height 0.5 m is not above"):
        Takeoff((0, 0, 1.0), 0.5)


def test_waypoints_travel_turns_before_each_leg() -> None:
    w = Waypoints(
        [(0, 0, 1), (1, 0, 1), (1, 1, 1)],
        0.3,
        0.3,
        start_yaw_rad=math.pi - 0.1,
        yaw_mode=YawMode.TRAVEL,
        turn_s=2.0,
    )
    r0 = w.reference(0.0)
    assert r0.yaw_rad == pytest.approx(math.pi - 0.1)
    # first a turn to face +x (the shorter way, through pi - 0.1 -> 0 ... wrapped continuously)
    assert w.reference(2.0).yaw_rad == pytest.approx(0.0, abs=1e-9) or w.reference(
        2.0
    ).yaw_rad == pytest.approx(2 * math.pi, abs=1e-9)
    end = w.reference(w.duration_s)
    assert math.remainder(end.yaw_rad - math.pi / 2, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_yaw_crosses_pi_smoothly_over_many_laps() -> None:
    c = Circle(radius_m=0.3, speed_m_s=1.0, laps=10, yaw_mode=YawMode.INWARD)
    s = sample(c, 0.01)
    assert s["yaw"][-1] - s["yaw"][0] == pytest.approx(20 * math.pi)
    assert np.max(np.abs(np.diff(s["yaw"]))) < 0.04


def test_bad_arguments_raise() -> None:
    with pytest.raises(PlanError, match="either period_s or speed_m_s"):
        Circle(period_s=10.0, speed_m_s=1.0)
    with pytest.raises(PlanError, match="circle: radius_m: radius must be positive, got 0.0 m; give a radius > 0") as e:
        Circle(radius_m=0.0, period_s=10.0)
    assert (e.value.pattern, e.value.key, e.value.value) == ("circle", "radius_m", 0.0)
    assert isinstance(e.value, ConfigError)  # a plan's loader maps it to its file and key
    with pytest.raises(PlanError, match="coincide"):
        Rectangle([(0, 0), (0, 0), (1, 1)], 1.0)
    with pytest.raises(PlanError, match="return_to_start"):
        Lawnmower((0, 0), (1, 1), 0.5, 1.0, laps=2, return_to_start=False)
    with pytest.raises(PlanError, match="hold: duration_s"):
        Hold((0, 0, 1), 0.0, 0.0)


@settings(max_examples=200, deadline=None)
@given(
    dist=st.floats(0.001, 20.0),
    speed=st.floats(0.01, 5.0),
    accel=st.floats(0.01, 10.0),
    frac=st.floats(0.0, 1.2),
)
def test_trapezoid_properties(dist: float, speed: float, accel: float, frac: float) -> None:
    total = trapezoid_duration_s(dist, speed, accel)
    s, v = trapezoid(frac * total, dist, speed, accel)
    assert -1e-12 <= s <= dist + 1e-9
    assert 0.0 <= v <= speed + 1e-12
    assert trapezoid(total, dist, speed, accel) == pytest.approx((dist, 0.0), abs=1e-9)
    # the speed never exceeds what the acceleration limit allows from either end
    t = frac * total
    assert v <= accel * min(t, max(total - t, 0.0)) + 1e-9
