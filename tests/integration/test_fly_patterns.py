"""The three lab plans flown end to end against the simulated lab, on both backends and autopilots.

Each flight is the real plan from ``examples/`` (preflight, arm, take-off, hold, the pattern,
hold, land, disarm) over real UDP to the simulated PX4 / ArduPilot, with the simulated mocap
on the same accelerated clock. Durations are shortened through plan overrides so the file
stays within a couple of minutes: one lap instead of two, short holds, and the rectangle and
lawnmower at 0.25 m/s with 2 s corner turns instead of 0.1 m/s and 5 s (same geometry on
ArduPilot; half length on PX4, see ``PX4_SIZE_M``). The
pymavlink backend flies every pattern on both personalities; the MAVSDK backend (on wall time,
so at 2x and faster still) flies every pattern and both personalities in three flights.

Bounds were set from measured runs with margin (see docs/flying.md for the figures):
pattern RMS 5-10 mm on pymavlink on a quiet machine (18 mm under heavy load), ~30 mm on MAVSDK.

On this shared 2-core machine a 5x-accelerated flight can miss its 0.2 s (sim) mocap deadline
when the mocap thread alone waits ~40 ms of wall time for a core (measured: single-thread gaps of
20-45 ms under load while the process as a whole ran); the supervisor then holds for a cycle, as
it should. Such ``mocap_stale`` holds are
tolerated here; any other fault fails the test.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from flightkit.apps.sim_session import fly_plan_in_sim
from trajectories.controller import OutputFrame, SetpointKind
from trajectories.flightlog import FlightSummary, read_flight_log
from trajectories.plan import Plan, load_plan

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SPEED = 5.0  # the 2-core machine keeps up at 5x (20x starves the loop)
MAVSDK_SPEED = 3.0  # the MAVSDK backend times its stream on the clock but MAVSDK itself runs on wall time

# Quiet machine: pattern RMS 5-10 mm, max 21-54 mm. Under the shared machine's load a stalled
# event loop (0.1 s wall = 0.5 s sim) has given RMS 18 mm and max 88 mm; the bounds allow that.
RMS_BOUND_M = 0.03
MAX_BOUND_M = 0.12

# PX4's goto lags its transit's 0.5 m/s^2 speed ramps: the velocity law (reference velocity plus a
# 1/s position gain) leaves the error of the autopilot's velocity response, which peaks at ~50 mm
# as the speed ramps up and ~35 mm as it ramps down. Measured (2026-11-27): goto RMS 26-29 mm on
# a quiet machine, 30.3 mm with the process throttled to half a core (docs/testing.md); so the goto
# has its own bound, with margin, and take-off and landing (10 and 22 mm) keep the pattern's.
PX4_GOTO_RMS_BOUND_M = 0.04

# The simulated ArduCopter lags a velocity stream as the firmware does (its position controller's
# acceleration and jerk limits, docs/sim.md). Real ArduCopter 4.7 SITL flying the example plans
# (issue 19): take-off RMS 60-70 mm / max 109-131 mm, goto 66-69 / 111-125 mm, patterns RMS
# 13-15 mm, max after the first 2 s 23-46 mm, landing 51-52 mm, lift-off 2.8 s after the take-off
# command, its 0.3 m lift topping out at 0.41 m. The shortened rectangle and lawnmower fly their
# sides 2.5x faster than the real run, and lag errors grow with speed: their bounds are the real
# figures scaled by 2.5 with the same margin.
ARDUPILOT_RMS_BOUND_M = {"circle": 0.03, "rectangle": 0.05, "lawnmower": 0.05}
ARDUPILOT_MAX_BOUND_M = {"circle": 0.12, "rectangle": 0.16, "lawnmower": 0.16}


def rms_bound(name: str, autopilot: str) -> float:
    return ARDUPILOT_RMS_BOUND_M[name] if autopilot == "ardupilot" else RMS_BOUND_M


def max_bound(name: str, autopilot: str) -> float:
    return ARDUPILOT_MAX_BOUND_M[name] if autopilot == "ardupilot" else MAX_BOUND_M


def liftoff_s_and_top_m(log_path: str) -> tuple[float, float]:
    """From the flight log: seconds from the take-off phase's start until the vehicle is 2 cm up,
    and its height where it led the climb reference most (the top of the autopilot's own lift,
    which the runner's climb then catches up with)."""
    log = read_flight_log(log_path)
    sel = log["phase"] == "takeoff"
    t, z, ref_z = (np.asarray(log[k][sel]) for k in ("t_s", "pos_z_m", "ref_z_m"))
    up = np.flatnonzero(z > z[0] + 0.02)
    assert len(up), "the vehicle never left the ground in the take-off phase"
    return float(t[up[0]] - t[0]), float(z[np.argmax(z - ref_z)] - z[0])


def assert_like_arducopter(summary: FlightSummary, with_pattern: bool) -> None:
    """The flight's figures within bands that compare like with like (issue 19; docs/sim.md).

    The real ArduCopter figures came from the runner of then (climb and descent at its 0.3 m/s
    vertical limit) flying the full example plans on the firmware's own EKF pose as mocap. Flown
    that way the simulated ArduPilot reproduces lift-off, top, take-off max, goto and landing
    (``bench/control.py --like-for-like``). This test flies today's runner (climb and descent with
    20 % headroom below 0.4 m/s) on the sim's truth for one lap: where today's runner flies
    differently, the band is the sim's own figure for it (the landing: 16-23 mm, against 43-52 mm
    like for like and 51-52 real). Not matched like for like, so held to bands around the real
    figures as before: the take-off RMS (sim 26-42 mm, real 60-70) and the circle's max after
    2 s (sim 29-36, real 23). The circle's RMS matches over the real run's two laps (14-19 mm
    against 15); one lap, as here, gives 18-25.
    """
    table = summary.format_table()
    liftoff_s, top_m = liftoff_s_and_top_m(summary.log_path or "")
    assert 2.0 <= liftoff_s <= 3.6, (liftoff_s, table)  # real 2.8 s
    assert 0.29 <= top_m <= 0.53, (top_m, table)  # real 0.41 m
    takeoff, goto, land = summary.phase("takeoff"), summary.phase("goto"), summary.phase("land")
    assert 0.018 <= takeoff.rms_error_m <= 0.091, table  # real 60-70 mm, sim 23-55; lag-free sim 12-17
    assert 0.076 <= takeoff.max_error_m <= 0.17, table  # real 109-131 mm; lag-free sim 33-40
    assert 0.032 <= goto.rms_error_m <= 0.090, table  # real 66-69 mm; lag-free sim 27-28
    assert 0.078 <= goto.max_error_m <= 0.163, table  # real 111-125 mm; lag-free sim 50-52
    # today's runner lands with headroom: 16-23 mm, +30 % and a loaded host's margin (the runner of then,
    # like for like: 43-52 mm; real 51-52)
    assert 0.008 <= land.rms_error_m <= 0.045, table
    if with_pattern:
        pat = summary.phase("pattern")
        # one lap 18-25 mm (the hand-over from the goto weighs twice what it does in the real run's
        # two laps: 14-19 mm like for like, real 15); the steady lag is 12 mm
        assert 0.009 <= pat.rms_error_m <= 0.032, table
        r = pattern_rows(summary.log_path or "")
        late = r["err_m"][settled(r["t_s"]) & (r["t_s"] > r["t_s"][0] + 2.0)]
        # real 23 mm; the sim's hand-over from the goto rings longer (30-36 mm quiet, 45 loaded)
        assert 0.010 <= float(np.max(late)) <= 0.06, table

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]


def shortened(name: str) -> Plan:
    """The example plan ``name`` with one lap, 1 s holds and (rectangle, lawnmower) faster sides."""
    plan = load_plan(EXAMPLES / f"{name}.toml")
    settings = dataclasses.replace(plan.settings, hold_before_s=1.0, hold_after_s=1.0)
    pattern = dataclasses.replace(plan.pattern, laps=1)
    if name in ("rectangle", "lawnmower"):
        pattern = dataclasses.replace(pattern, speed_m_s=0.25, turn_s=2.0)
    return plan.with_changes(settings=settings, pattern=pattern)


# PX4 flies the rectangle and the lawnmower at half length (a 1 m x 0.5 m rectangle; three 1 m
# lanes): every corner, turn in place and lane change, in less time. ArduPilot flies them full
# size, as its take-off, goto and landing are held to the real firmware's figures on those plans.
PX4_SIZE_M = {"rectangle": (1.0, 0.5), "lawnmower": (1.0, 1.0)}


def pattern_plan(name: str, autopilot: str) -> Plan:
    """``shortened(name)``, at ``PX4_SIZE_M`` on PX4."""
    plan = shortened(name)
    if autopilot == "px4":
        plan = plan.with_changes(pattern=dataclasses.replace(plan.pattern, size_m=PX4_SIZE_M[name]))
    return plan


def assert_clean(summary: FlightSummary) -> None:
    assert summary.outcome == "completed", summary.format_table()
    unexpected = [f for f in summary.faults if f.kind.value != "mocap_stale"]
    assert not unexpected, summary.format_table()
    assert summary.laps_completed == 1
    assert [p.name for p in summary.phases] == ["takeoff", "hold", "goto", "pattern", "hold_2", "land"]


def pattern_rows(log_path: str) -> dict[str, np.ndarray]:
    log = read_flight_log(log_path)
    sel = (log["phase"] == "pattern") & (log["action"] == "CONTINUE")
    return {k: np.asarray(v[sel]) for k, v in log.columns.items() if k not in ("phase", "action", "sp_frame")}


def settled(t_s: np.ndarray, gap_s: float = 0.1, window_s: float = 1.0) -> np.ndarray:
    """Log rows not within ``window_s`` after a gap of more than ``gap_s`` between control cycles.

    The loop runs at 100 Hz (0.01 s); a gap of 0.1 s is a stale-mocap hold (its rows are not
    CONTINUE) or the loop itself starved on a loaded machine (0.1 s sim is 20 ms wall at 5x), during
    which the autopilot flew the last setpoint. After one the yaw has a lag to make up (kp_yaw
    1/s: 0.3 rad/s for a 0.3 rad lag), which must not be read as turning while moving.
    """
    gaps = np.flatnonzero(np.diff(t_s) > gap_s) + 1
    ok = np.ones(len(t_s), dtype=bool)
    for i in gaps:
        ok &= ~((t_s >= t_s[i]) & (t_s < t_s[i] + window_s))
    return ok


async def fly(
    name: str, autopilot: str, backend: str, speed: float, tmp_path: Path, plan: Plan | None = None
) -> FlightSummary:
    plan = plan or shortened(name)
    return await fly_plan_in_sim(
        plan,
        autopilot=autopilot,
        backend=backend,
        speed=speed,
        log_path=tmp_path / f"{name}-{autopilot}-{backend}.csv",
    )


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_circle_tracks_within_bounds_and_looks_inward(autopilot: str, tmp_path: Path) -> None:
    summary = asyncio.run(fly("circle", autopilot, "pymavlink", SPEED, tmp_path))
    assert_clean(summary)
    # the loop's own figures: CPU time per cycle is part of the wall time per cycle
    assert 0.0 < summary.cycle_cpu_p50_ms <= summary.cycle_p50_ms
    assert 0.0 < summary.cycle_cpu_p99_ms <= summary.cycle_p99_ms
    assert summary.to_dict()["cycle_cpu_p99_ms"] == pytest.approx(summary.cycle_cpu_p99_ms, abs=1e-4)
    # the loop rate counts the time inside the phases (a row per cycle), not the waits between them
    rows = len(read_flight_log(str(tmp_path / f"circle-{autopilot}-pymavlink.csv"))["phase"])
    inside_s = sum(p.duration_s for p in summary.phases)
    assert summary.loop_rate_hz == pytest.approx((rows - len(summary.phases)) / inside_s, rel=1e-6)
    assert summary.loop_rate_hz > 50.0, summary.format_table()  # 100 Hz timer, 120 Hz mocap wakes
    pat = summary.phase("pattern")
    assert 38.0 < pat.duration_s < 45.0  # one 40 s lap (pattern time stands still only while holding)
    assert pat.rms_error_m < RMS_BOUND_M, summary.format_table()
    assert pat.max_error_m < MAX_BOUND_M, summary.format_table()
    if autopilot == "ardupilot":
        # one lap of the real plan: every phase against the real firmware's figures
        assert_like_arducopter(summary, with_pattern=True)
    else:
        # Take-off and landing track within the pattern's bounds, the landing against the
        # floor-clamped reference (its descent keeps headroom below the vertical speed limit); the
        # goto within its own (PX4_GOTO_RMS_BOUND_M).
        for phase in ("takeoff", "goto", "land"):
            rms_bound_m = PX4_GOTO_RMS_BOUND_M if phase == "goto" else RMS_BOUND_M
            assert summary.phase(phase).rms_error_m < rms_bound_m, summary.format_table()
            assert summary.phase(phase).max_error_m < MAX_BOUND_M, summary.format_table()

    # the flown path, from the log: a 1 m circle at 1.5 m, all the way round, facing the centre
    r = pattern_rows(summary.log_path or "")
    x, y, z = r["pos_x_m"], r["pos_y_m"], r["pos_z_m"]
    radius = np.hypot(x, y)
    assert np.all(np.abs(radius - 1.0) < MAX_BOUND_M)
    assert np.all(np.abs(z - 1.5) < MAX_BOUND_M)
    swept = np.unwrap(np.arctan2(y, x))
    assert abs(swept[-1] - swept[0]) > 2 * math.pi - 0.1  # a full lap, counter-clockwise
    assert swept[-1] > swept[0]
    inward = np.arctan2(-y, -x)
    yaw_err = np.angle(np.exp(1j * (r["yaw_rad"] - inward)))
    assert np.max(np.abs(yaw_err)) < math.radians(8.0)


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_rectangle_flies_its_corners_with_turns_in_place(autopilot: str, tmp_path: Path) -> None:
    plan = pattern_plan("rectangle", autopilot)
    summary = asyncio.run(fly("rectangle", autopilot, "pymavlink", SPEED, tmp_path, plan))
    assert_clean(summary)
    pat = summary.phase("pattern")
    assert pat.rms_error_m < rms_bound("rectangle", autopilot), summary.format_table()
    assert pat.max_error_m < max_bound("rectangle", autopilot), summary.format_table()
    if autopilot == "ardupilot":
        assert_like_arducopter(summary, with_pattern=False)

    r = pattern_rows(summary.log_path or "")
    x, y = r["pos_x_m"], r["pos_y_m"]
    # centred on the origin (2 m x 1 m, on PX4 1 m x 0.5 m): every corner visited, nothing flown outside it
    hx, hy = plan.pattern.size_m[0] / 2.0, plan.pattern.size_m[1] / 2.0
    for cx, cy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)):
        assert np.min(np.hypot(x - cx, y - cy)) < 0.05, (cx, cy)
    assert np.all(np.abs(x) < hx + MAX_BOUND_M) and np.all(np.abs(y) < hy + MAX_BOUND_M)
    # the yaw turns only while standing at a corner (speed ~0 while the yaw rate is large), except
    # while the yaw catches up after the control loop missed its ticks (see settled())
    ok = settled(r["t_s"])
    turning = np.abs(r["sp_yaw_rate_rad_s"]) > 0.3
    # Judge at least half of the turning cycles (520-580 of them; a quiet machine leaves all
    # undisturbed, a loaded CI host has left 78 % of all cycles).
    assert np.count_nonzero(turning & ok) > 0.5 * np.count_nonzero(turning) > 0, (
        f"too few undisturbed turning cycles to judge the corners: {np.count_nonzero(turning & ok)} of "
        f"{np.count_nonzero(turning)} ({np.count_nonzero(~ok)} of {len(ok)} cycles within 1 s of a missed tick)"
    )
    speed = np.hypot(r["ref_vx_m_s"], r["ref_vy_m_s"])
    assert np.all(speed[turning & ok] < 0.02)


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_lawnmower_covers_its_lanes(autopilot: str, tmp_path: Path) -> None:
    plan = pattern_plan("lawnmower", autopilot)
    summary = asyncio.run(fly("lawnmower", autopilot, "pymavlink", SPEED, tmp_path, plan))
    assert_clean(summary)
    pat = summary.phase("pattern")
    assert pat.rms_error_m < rms_bound("lawnmower", autopilot), summary.format_table()
    assert pat.max_error_m < max_bound("lawnmower", autopilot), summary.format_table()
    if autopilot == "ardupilot":
        assert_like_arducopter(summary, with_pattern=False)

    r = pattern_rows(summary.log_path or "")
    x, y = r["pos_x_m"], r["pos_y_m"]
    # lanes along x at y = -0.5, 0, 0.5 (0.5 m spacing over a 1 m width), each flown end to end
    # (2 m long, on PX4 1 m)
    lane_m = plan.pattern.size_m[0]
    for lane_y in (-0.5, 0.0, 0.5):
        on_lane = np.abs(y - lane_y) < 0.03
        assert np.ptp(x[on_lane]) > lane_m - 0.1, lane_y


def with_pva(plan: Plan) -> Plan:
    """``plan`` flown with position + velocity + acceleration targets (the autopilot's local frame)."""
    ctl = dataclasses.replace(plan.controller, output_frame=OutputFrame.LOCAL_NED, setpoint=SetpointKind.PVA)
    return plan.with_changes(controller=ctl)


def test_pva_targets_track_tighter_on_the_simulated_ardupilot(tmp_path: Path) -> None:
    """Issue 19's goal on the faithful simulated ArduCopter, one real circle lap: with position,
    velocity and acceleration targets the pattern tracks within 8 mm RMS and 30 mm max after its
    first 2 s, take-off and goto within 30 mm RMS (velocity-only: 18-21 mm, ~36 mm, 22-65 mm,
    37-61 mm; measured with pva: 3.4 mm, ~11 mm, 15-20 mm, 9-10 mm)."""
    summary = asyncio.run(fly("circle", "ardupilot", "pymavlink", SPEED, tmp_path, with_pva(shortened("circle"))))
    assert_clean(summary)
    table = summary.format_table()
    # Judged on the cycles the loop ran on time: right after a host stall the pose is up to 0.2 s
    # old against a moving reference (on the loaded 2-core host one such row alone has read 29 mm
    # on a circle tracked within ~2 mm), which is no tracking error.
    log = read_flight_log(summary.log_path or "")
    for phase, bound_m in (("takeoff", 0.03), ("goto", 0.03), ("pattern", 0.008)):
        # (err > 0: not the autopilot's own lift, watched against the measured height itself)
        sel = (log["phase"] == phase) & (log["action"] == "CONTINUE") & (log["err_m"] > 0.0)
        t, err = np.asarray(log["t_s"][sel]), np.asarray(log["err_m"][sel])
        ok = settled(t)
        assert np.count_nonzero(ok) >= 100, (phase, table)  # at least 1 s of cycles to judge
        assert float(np.sqrt(np.mean(err[ok] ** 2))) < bound_m, (phase, table)
    r = pattern_rows(summary.log_path or "")
    late = r["err_m"][settled(r["t_s"]) & (r["t_s"] > r["t_s"][0] + 2.0)]
    assert float(np.max(late)) < 0.03, table


def shortened_for_mavsdk(name: str) -> Plan:
    """MAVSDK runs on wall time, so its flights run at 3x: a 20 s circle lap, and the rectangle and
    lawnmower with 1 s turns (same speed as above; 0.5 m/s gave 0.13 m max at the rectangle's
    corners through MAVSDK). The rectangle is half size (1 m x 0.5 m) and the lawnmower covers
    1 m x 0.5 m (two 1 m lanes): the corners, the turns, the lane change and the lane ends are
    all there in under half the time."""
    plan = shortened(name)
    settings = dataclasses.replace(plan.settings, hold_before_s=0.5, hold_after_s=0.5)
    if name == "circle":
        pattern = dataclasses.replace(plan.pattern, period_s=20.0)
    else:
        pattern = dataclasses.replace(plan.pattern, turn_s=1.0, size_m=(1.0, 0.5))
    return plan.with_changes(settings=settings, pattern=pattern)


# The patterns through the MAVSDK backend, and both personalities (the pymavlink backend flies all
# six combinations above; test_link_mavsdk.py flies MAVSDK on both personalities too; the circle on
# MAVSDK and PX4 is flown by the fleet test, tests/integration/test_fleet.py, as one of its vehicles).
# The PX4 flight sends position + velocity + acceleration targets (MAVSDK's own setter for them).
@pytest.mark.parametrize(
    ("name", "autopilot"),
    [("rectangle", "ardupilot"), ("lawnmower", "px4")],
)
def test_mavsdk_backend_flies_the_patterns(name: str, autopilot: str, tmp_path: Path) -> None:
    plan = shortened_for_mavsdk(name)
    if autopilot == "px4":  # PX4 OFFBOARD through MAVSDK's position-velocity-acceleration setter
        plan = with_pva(plan)
    summary = asyncio.run(fly(name, autopilot, "mavsdk", MAVSDK_SPEED, tmp_path, plan))
    assert_clean(summary)
    pat = summary.phase("pattern")
    assert pat.rms_error_m < 0.05, summary.format_table()
    assert pat.max_error_m < 0.12, summary.format_table()
    r = pattern_rows(summary.log_path or "")
    x, y = r["pos_x_m"], r["pos_y_m"]
    if name == "circle":
        assert np.all(np.abs(np.hypot(x, y) - 1.0) < 0.1)
        swept = np.unwrap(np.arctan2(y, x))
        assert swept[-1] - swept[0] > 2 * math.pi - 0.15
    elif name == "rectangle":  # 1 m x 0.5 m centred on the origin: every corner visited
        for cx, cy in ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25)):
            assert np.min(np.hypot(x - cx, y - cy)) < 0.08, (cx, cy)
    else:  # two 1 m lanes, each flown end to end
        for lane_y in (-0.25, 0.25):
            assert np.ptp(x[np.abs(y - lane_y) < 0.05]) > 0.85, lane_y
