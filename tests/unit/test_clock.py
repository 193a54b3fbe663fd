import asyncio
import threading
import time

import pytest

from flightkit.clock import Clock, LockstepClock, SimClock, WallClock


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
    with pytest.raises(ValueError):
        SimClock(0.0)
    with pytest.raises(ValueError):
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
    with pytest.raises(ValueError):
        clock.advance(-1.0)
