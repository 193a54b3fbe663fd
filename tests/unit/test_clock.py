import asyncio
import threading
import time

import pytest

from flightkit.clock import (
    LATE_SLEEPER_LEAD_S,
    LATE_SLEEPER_PATIENCE_WALL_S,
    Clock,
    LockstepClock,
    SimClock,
    WallClock,
    sleep_until,
)
from flightkit.errors import SimError


def test_clocks_satisfy_protocol() -> None:
    for clock in (WallClock(), SimClock(5.0), LockstepClock()):
        assert isinstance(clock, Clock)


def test_sim_clock_runs_faster_than_wall() -> None:
    clock = SimClock(speed=50.0)
    wall0, sim0 = time.monotonic(), clock.monotonic_s()
    asyncio.run(clock.sleep(1.0))  # one simulated second = 20 ms of wall time
    wall_elapsed, sim_elapsed = time.monotonic() - wall0, clock.monotonic_s() - sim0
    assert sim_elapsed >= 1.0
    assert wall_elapsed < 0.5
    assert clock.time_ns() > 1_600_000_000 * 10**9


def test_sim_clock_rejects_bad_speed() -> None:
    with pytest.raises(SimError, match="speed"):
        SimClock(0.0)
    with pytest.raises(SimError, match="speed"):
        SimClock(float("inf"))


def test_lockstep_wakes_sleepers_in_deadline_order() -> None:
    clock = LockstepClock()
    woke: list[tuple[str, float]] = []

    async def sleeper(name: str, dt: float) -> None:
        await clock.sleep(dt)
        woke.append((name, clock.monotonic_s()))

    async def main() -> None:
        tasks = [asyncio.create_task(sleeper("b", 0.2)), asyncio.create_task(sleeper("a", 0.1))]
        while clock.pending_sleepers < 2:  # noqa: ASYNC110 - yield until both tasks sleep on the clock
            await asyncio.sleep(0)
        clock.advance(0.05)
        await asyncio.sleep(0)
        assert woke == []
        clock.advance(0.05)
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert [w[0] for w in woke] == ["a"]
        clock.advance(0.1)
        await asyncio.gather(*tasks)

    asyncio.run(main())
    assert [w[0] for w in woke] == ["a", "b"]
    assert woke[1][1] == pytest.approx(0.2)


def test_lockstep_blocking_sleep_from_thread() -> None:
    clock = LockstepClock()
    done = threading.Event()

    def worker() -> None:
        clock.sleep_blocking(1.0)
        done.set()

    t = threading.Thread(target=worker)
    t.start()
    clock.advance(0.5)
    assert not done.wait(0.05)
    clock.advance(0.5)
    assert done.wait(2.0)
    t.join()
    with pytest.raises(SimError, match="backwards"):
        clock.advance(-1.0)


@pytest.mark.parametrize("make_clock", [LockstepClock, lambda: SimClock(speed=0.01)], ids=["lockstep", "sim"])
def test_sleep_until_leaves_when_told_to_stop(make_clock) -> None:  # type: ignore[no-untyped-def]
    # A lock-step clock that nobody advances (or a very slow simulated one) must not keep a
    # thread that is told to stop: its join would otherwise wait for time that never comes.
    clock = make_clock()
    stop = threading.Event()
    result: list[bool] = []
    t = threading.Thread(target=lambda: result.append(sleep_until(clock, clock.monotonic_s() + 60.0, stop)))
    t.start()
    t.join(0.1)
    assert t.is_alive()  # still waiting for its deadline
    t0 = time.monotonic()
    stop.set()
    t.join(2.0)
    assert not t.is_alive() and result == [False]
    assert time.monotonic() - t0 < 0.5  # within a few 50 ms slices


def test_sleep_until_returns_at_the_lockstep_deadline() -> None:
    clock = LockstepClock()
    stop = threading.Event()
    result: list[bool] = []
    t = threading.Thread(target=lambda: result.append(sleep_until(clock, 1.0, stop)))
    t.start()
    for _ in range(100):  # 100 steps of 0.01 s sum to 1 - 1e-16: within the due tolerance
        clock.advance(0.01)
    t.join(2.0)
    assert result == [True]
    assert sleep_until(clock, 0.5, stop)  # a deadline already passed returns at once


class _FakeWall:
    """Stands in for ``time.monotonic`` so a host stall can be staged without waiting for one."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def test_stall_limited_sim_clock_slows_down_instead_of_jumping(monkeypatch: pytest.MonkeyPatch) -> None:
    wall = _FakeWall()
    monkeypatch.setattr("flightkit.clock.time.monotonic", wall)
    clock = SimClock(speed=5.0, max_wall_step_s=0.04)
    plain = SimClock(speed=5.0)
    assert clock.monotonic_s() == 0.0 and plain.monotonic_s() == 0.0
    for _ in range(10):  # normal running: reads 5 ms apart follow the wall clock x speed
        wall.now_s += 0.005
        clock.monotonic_s()
    assert clock.monotonic_s() == pytest.approx(0.25)
    wall.now_s += 0.5  # the host takes the process away for half a second
    assert clock.monotonic_s() == pytest.approx(0.25 + 0.04 * 5.0)  # the lab lost 0.46 s of wall time
    assert plain.monotonic_s() == pytest.approx(0.55 * 5.0)  # the plain clock jumped 2.5 s
    wall.now_s += 0.01
    assert clock.monotonic_s() == pytest.approx(0.45 + 0.05)  # and runs at speed again afterwards


@pytest.mark.parametrize("blocking", [False, True])
def test_stall_limited_sleep_waits_until_the_simulated_deadline(blocking: bool) -> None:
    clock = SimClock(speed=50.0, max_wall_step_s=0.004)  # sleeps in 2 ms slices
    wall0, sim0 = time.monotonic(), clock.monotonic_s()
    if blocking:
        clock.sleep_blocking(1.0)
    else:
        asyncio.run(clock.sleep(1.0))
    assert clock.monotonic_s() - sim0 >= 1.0
    assert time.monotonic() - wall0 >= 0.0199  # never sooner than speed allows


def test_stall_limited_clock_waits_for_a_late_sleeper(monkeypatch: pytest.MonkeyPatch) -> None:
    """A sleeper that the host does not run at its deadline holds time back, for a while."""
    wall = _FakeWall()
    monkeypatch.setattr("flightkit.clock.time.monotonic", wall)
    clock = SimClock(speed=5.0, max_wall_step_s=0.04)
    starved = asyncio.new_event_loop()  # a loop that is not run: its sleeper never wakes by itself
    try:
        task = starved.create_task(clock.sleep(0.1))
        starved.run_until_complete(asyncio.sleep(0))  # the sleep starts and registers its deadline
        assert not task.done()
        for _ in range(40):  # 0.2 s of wall time, 1 s of simulated time at 5x without the hold
            wall.now_s += 0.005
            clock.monotonic_s()
        assert clock.monotonic_s() == pytest.approx(0.1 + LATE_SLEEPER_LEAD_S)
        assert clock.late_sleeper_holds == 1
        wall.now_s += LATE_SLEEPER_PATIENCE_WALL_S  # it stays late: time goes on without it
        for _ in range(10):
            wall.now_s += 0.005
            clock.monotonic_s()
        assert clock.late_sleepers_abandoned == 1
        assert clock.monotonic_s() == pytest.approx(0.15 + 0.04 * 5.0 + 0.045 * 5.0)
        task.cancel()
        starved.run_until_complete(asyncio.gather(task, return_exceptions=True))
    finally:
        starved.close()


def test_busy_work_takes_at_most_its_budget_of_simulated_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """Work in ``busy(budget)`` holds a stall-limited clock at the budget until it ends; other
    clocks are unaffected."""
    wall = _FakeWall()
    monkeypatch.setattr("flightkit.clock.time.monotonic", wall)
    clock = SimClock(speed=5.0, max_wall_step_s=0.04)
    with clock.busy(0.03):  # a frame the host takes 0.2 s of wall time (1 s simulated) to render
        for _ in range(40):
            wall.now_s += 0.005
            clock.monotonic_s()
        assert clock.monotonic_s() == pytest.approx(0.03)
    wall.now_s += 0.005
    assert clock.monotonic_s() == pytest.approx(0.03 + 0.025)  # runs on once the work is done
    plain = SimClock(speed=5.0)
    with plain.busy(0.03):
        wall.now_s += 0.2
    assert plain.monotonic_s() == pytest.approx(0.2 * 5.0)  # follows the wall clock
    lockstep = LockstepClock()
    with lockstep.busy(0.03), WallClock().busy(0.03):
        assert lockstep.monotonic_s() == 0.0


def test_stall_limited_clock_is_not_held_by_sleepers_that_woke(monkeypatch: pytest.MonkeyPatch) -> None:
    wall = _FakeWall()
    monkeypatch.setattr("flightkit.clock.time.monotonic", wall)
    monkeypatch.setattr("flightkit.clock.time.sleep", lambda s: setattr(wall, "now_s", wall.now_s + s))
    clock = SimClock(speed=5.0, max_wall_step_s=0.04)
    for _ in range(20):  # a thread ticking at 50 Hz of simulated time
        clock.sleep_blocking(0.02)
    assert clock.monotonic_s() == pytest.approx(0.4, abs=1e-6)
    assert clock.late_sleeper_holds == 0
    wall.now_s += 0.2
    assert clock.monotonic_s() == pytest.approx(0.4 + 0.04 * 5.0)  # only the stall limit applies


def test_stall_limited_sleep_zero_still_yields() -> None:
    clock = SimClock(speed=5.0, max_wall_step_s=0.04)
    ran: list[str] = []

    async def other() -> None:
        ran.append("other")

    async def main() -> None:
        task = asyncio.ensure_future(other())
        await clock.sleep(0.0)
        ran.append("after sleep(0)")
        await task

    asyncio.run(main())
    assert ran == ["other", "after sleep(0)"]


def test_sim_clock_rejects_bad_stall_limit() -> None:
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(SimError, match="max_wall_step_s"):
            SimClock(2.0, max_wall_step_s=bad)
