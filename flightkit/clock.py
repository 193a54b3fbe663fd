"""One clock interface for every loop in flightkit.

Loops never call ``time.time``/``asyncio.sleep`` directly; they take a :class:`Clock`, so the
same code runs on wall time on a real vehicle, on accelerated simulated time in tests and
demos, and in lock-step under a test that advances time explicitly.

* :class:`WallClock`: real time.
* :class:`SimClock`: simulated time running ``speed`` times faster than real time
  (``speed=1`` for demos, 5-20 for tests of whole flights); optionally slowed down rather
  than jumping when the host stalls the process (``max_wall_step_s``).
* :class:`LockstepClock`: time moves only when :meth:`LockstepClock.advance` is called;
  sleepers (coroutines and threads) wake exactly at their deadlines.

Two notions of time are offered: ``monotonic_s()`` for loop timing, and ``time_ns()`` for
stamps that are recorded (nanoseconds since the Unix epoch).
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import itertools
import threading
import time
from collections.abc import Iterator
from typing import Protocol, runtime_checkable

from flightkit.errors import SimError

STAMP_DEVICE = "device"
"""A capture stamp that is the device's own capture time (frame metadata, buffer time, mocap frame time)."""
STAMP_HOST = "host"
"""A capture stamp that is the host's time when the driver handed the sample over (the device gives none)."""
STAMP_SOURCES = ("", STAMP_DEVICE, STAMP_HOST)
"""Bus attachment code -> stamp source (``""``: not said, e.g. a foreign or older publisher)."""

__all__ = [
    "LATE_SLEEPER_LEAD_S",
    "LATE_SLEEPER_PATIENCE_WALL_S",
    "STAMP_DEVICE",
    "STAMP_HOST",
    "STAMP_SOURCES",
    "ONE_PROCESS_WALL_STEP_S",
    "Clock",
    "LockstepClock",
    "SimClock",
    "WallClock",
    "sleep_until",
]

#: The stall limit (``SimClock(max_wall_step_s=...)``) for a simulated lab whose clients share its
#: clock in one process: 30 ms of wall time, 0.15 s of simulated time at 5x (below the 0.2 s
#: mocap age at which a flight holds). Normal reads of the clock in a running lab are a few
#: milliseconds apart (the autopilot ticks every 2-5 ms).
ONE_PROCESS_WALL_STEP_S = 0.03

#: How far a stall-limited clock runs past the deadline of a sleeper that has not woken yet
#: (simulated seconds): a quarter of the 0.2 s mocap age at which a flight holds.
LATE_SLEEPER_LEAD_S = 0.05

#: How long (wall seconds) a stall-limited clock holds for one late sleeper before it lets time
#: go on without it (a sleeper whose event loop is blocked would otherwise stop the lab).
LATE_SLEEPER_PATIENCE_WALL_S = 0.5


@runtime_checkable
class Clock(Protocol):
    """Time source used by every loop."""

    @property
    def speed(self) -> float:
        """Simulated seconds per wall-clock second (1.0 for wall time; ``inf`` for lock-step)."""
        ...

    def monotonic_s(self) -> float:
        """Monotonic time in seconds (arbitrary origin); for loop timing."""
        ...

    def time_ns(self) -> int:
        """Nanoseconds since the Unix epoch; for recorded stamps."""
        ...

    async def sleep(self, duration_s: float) -> None:
        """Suspend the calling coroutine for ``duration_s`` of this clock's time."""
        ...

    def sleep_blocking(self, duration_s: float) -> None:
        """Block the calling thread for ``duration_s`` of this clock's time."""
        ...

    def busy(self, budget_s: float) -> contextlib.AbstractContextManager[None]:
        """Work (rendering a frame, estimating one) that takes at most ``budget_s`` of this
        clock's time however long the host takes: a simulated clock waits for it."""
        ...


class WallClock:
    """Real time."""

    @property
    def speed(self) -> float:
        return 1.0

    def monotonic_s(self) -> float:
        return time.monotonic()

    def time_ns(self) -> int:
        return time.time_ns()

    async def sleep(self, duration_s: float) -> None:
        await asyncio.sleep(max(0.0, duration_s))

    def sleep_blocking(self, duration_s: float) -> None:
        time.sleep(max(0.0, duration_s))

    def busy(self, budget_s: float) -> contextlib.AbstractContextManager[None]:
        """Real work takes what it takes: no effect on wall time."""
        return contextlib.nullcontext()

    def __repr__(self) -> str:
        return "WallClock()"


class SimClock:
    """Simulated time running ``speed`` times faster than real time.

    Args:
        speed: simulated seconds per wall second (> 0).
        start_ns: the epoch time (ns) that simulated time starts at; defaults to now.
        max_wall_step_s: if set, simulated time advances by at most this much wall time
            (times ``speed``) between two reads of the clock. Use it when everything that
            shares the clock runs in one process (flight tests, the closed-loop demo): when the host stalls
            the process (a 2-core VM whose hypervisor takes the CPU away for 0.3 s has been
            seen), a clock that follows the wall clock would jump by 0.3 s x ``speed`` at once
            and every deadline in the lab (heartbeat, mocap age) would expire together,
            although nothing went wrong in the simulated world. With the limit the lab slows
            down for the stall instead, as a simulator's real-time factor drops when its host
            cannot keep up. Sleeps then wait on simulated time in wall slices of at most half
            the limit, so an idle process loses no time. Leave it off (the default) when
            another process runs its own clock at the same speed and compares stamps with it.
            A stall-limited clock also waits for late sleepers: a thread or coroutine
            whose sleep deadline has passed but which the host has not run yet (a starved
            thread on a loaded 2-core machine) holds time at ``late_lead_s`` past its
            deadline until it wakes, for at most ``LATE_SLEEPER_PATIENCE_WALL_S`` of wall
            time. A starved mocap publisher or setpoint stream then slows the lab down
            instead of letting the rest of it see stale data.
        late_lead_s: with ``max_wall_step_s``, how far (simulated seconds) time may run past
            the deadline of a sleeper that has not woken yet.
    """

    def __init__(
        self,
        speed: float = 1.0,
        start_ns: int | None = None,
        max_wall_step_s: float | None = None,
        late_lead_s: float = LATE_SLEEPER_LEAD_S,
    ) -> None:
        if not speed > 0.0 or speed == float("inf"):
            raise SimError(
                f"SimClock speed must be a positive finite number, got {speed}; use e.g. 1.0 (real time) or 10.0",
            )
        if max_wall_step_s is not None and not 0.0 < max_wall_step_s < float("inf"):
            raise SimError(
                f"SimClock max_wall_step_s must be a positive number of seconds, got {max_wall_step_s}; "
                "give a finite step > 0 or None"
            )
        if not 0.0 < late_lead_s < float("inf"):
            raise SimError(
                f"SimClock late_lead_s must be a positive number of seconds, got {late_lead_s}; give a finite lead > 0"
            )
        self._speed = float(speed)
        self._wall0 = time.monotonic()
        self._start_ns = time.time_ns() if start_ns is None else int(start_ns)
        self._max_wall_step_s = max_wall_step_s
        # the stall-limited clock: simulated seconds so far and the wall time they were read at
        self._lock = threading.Lock()
        self._sim_s = 0.0
        self._wall_read = self._wall0
        # sleepers of the stall-limited clock, earliest deadline first (finished ones are dropped lazily)
        self._late_lead_s = float(late_lead_s)
        self._sleepers: list[tuple[float, int, _Sleeper]] = []
        self._seq = itertools.count()
        self.late_sleeper_holds = 0
        """Times a late sleeper held time back (stall-limited clock; a diagnostic)."""
        self.late_sleepers_abandoned = 0
        """Late sleepers that did not wake within the patience and were left behind."""

    @property
    def speed(self) -> float:
        return self._speed

    @property
    def max_wall_step_s(self) -> float | None:
        """The stall limit (wall seconds), or None when time follows the wall clock exactly."""
        return self._max_wall_step_s

    def monotonic_s(self) -> float:
        if self._max_wall_step_s is None:
            return (time.monotonic() - self._wall0) * self._speed
        with self._lock:
            wall = time.monotonic()
            step = min(wall - self._wall_read, self._max_wall_step_s)
            self._wall_read = wall
            if step > 0.0:
                target = self._sim_s + step * self._speed
                hold = self._hold_for_late_sleeper(target, wall)
                self._sim_s = max(self._sim_s, min(target, hold))
            return self._sim_s

    def _hold_for_late_sleeper(self, target_s: float, wall_s: float) -> float:
        """The time that the earliest late sleeper lets the clock reach (``inf`` if none). Under the lock."""
        heap = self._sleepers
        while heap:
            deadline_s, _, sleeper = heap[0]
            if sleeper.done:
                heapq.heappop(heap)
                continue
            hold_s = deadline_s + self._late_lead_s
            if hold_s >= target_s:
                return hold_s
            if sleeper.held_since_wall_s is None:
                sleeper.held_since_wall_s = wall_s
                self.late_sleeper_holds += 1
            elif wall_s - sleeper.held_since_wall_s > LATE_SLEEPER_PATIENCE_WALL_S:
                heapq.heappop(heap)
                self.late_sleepers_abandoned += 1
                continue
            return hold_s
        return float("inf")

    def _sleeper(self, deadline_s: float) -> _Sleeper:
        sleeper = _Sleeper()
        with self._lock:
            heapq.heappush(self._sleepers, (deadline_s, next(self._seq), sleeper))
        return sleeper

    def time_ns(self) -> int:
        return self._start_ns + int(self.monotonic_s() * 1e9)

    async def sleep(self, duration_s: float) -> None:
        if self._max_wall_step_s is None:
            await asyncio.sleep(max(0.0, duration_s) / self._speed)
            return
        remaining = max(0.0, duration_s)
        deadline = self.monotonic_s() + remaining
        sleeper = self._sleeper(deadline)
        try:
            while True:  # at least one pass, so sleep(0) still yields to the event loop
                await asyncio.sleep(min(remaining / self._speed, 0.5 * self._max_wall_step_s))
                remaining = deadline - self.monotonic_s()
                if remaining <= 0.0:
                    return
        finally:
            sleeper.done = True

    def sleep_blocking(self, duration_s: float) -> None:
        if self._max_wall_step_s is None:
            time.sleep(max(0.0, duration_s) / self._speed)
            return
        remaining = max(0.0, duration_s)
        deadline = self.monotonic_s() + remaining
        sleeper = self._sleeper(deadline)
        try:
            while True:
                time.sleep(min(remaining / self._speed, 0.5 * self._max_wall_step_s))
                remaining = deadline - self.monotonic_s()
                if remaining <= 0.0:
                    return
        finally:
            sleeper.done = True

    @contextlib.contextmanager
    def busy(self, budget_s: float) -> Iterator[None]:
        """On a stall-limited clock, hold time at ``budget_s`` past now until the block ends (for
        at most ``LATE_SLEEPER_PATIENCE_WALL_S`` of wall time): the simulated computer keeps up
        whatever the host's load. No effect when time follows the wall clock exactly."""
        if self._max_wall_step_s is None:
            yield
            return
        sleeper = self._sleeper(self.monotonic_s() + max(0.0, budget_s) - self._late_lead_s)
        try:
            yield
        finally:
            sleeper.done = True

    def __repr__(self) -> str:
        limit = "" if self._max_wall_step_s is None else f", max_wall_step_s={self._max_wall_step_s:g}"
        return f"SimClock(speed={self._speed:g}{limit})"


class _Sleeper:
    """One sleep on a stall-limited :class:`SimClock`."""

    __slots__ = ("done", "held_since_wall_s")

    def __init__(self) -> None:
        self.done = False
        self.held_since_wall_s: float | None = None


class LockstepClock:
    """Time that advances only when :meth:`advance` is called.

    Coroutines (from any event loop) and threads may sleep on it; :meth:`advance` wakes
    each sleeper whose deadline has been reached, in deadline order. Use it to drive a loop
    deterministically: ``clock.advance(0.01)`` is one 10 ms tick.
    """

    def __init__(self, start_ns: int = 1_700_000_000_000_000_000) -> None:
        self._start_ns = int(start_ns)
        self._now_s = 0.0
        self._cond = threading.Condition()
        self._seq = itertools.count()
        # heap of (deadline_s, seq, loop, future) for coroutine sleepers
        self._waiters: list[tuple[float, int, asyncio.AbstractEventLoop, asyncio.Future[None]]] = []

    @property
    def speed(self) -> float:
        return float("inf")

    def monotonic_s(self) -> float:
        with self._cond:
            return self._now_s

    def time_ns(self) -> int:
        return self._start_ns + int(self.monotonic_s() * 1e9)

    async def sleep(self, duration_s: float) -> None:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        with self._cond:
            deadline = self._now_s + max(0.0, duration_s)
            if deadline <= self._now_s:
                fut.set_result(None)
            else:
                heapq.heappush(self._waiters, (deadline, next(self._seq), loop, fut))
        await fut

    def sleep_blocking(self, duration_s: float) -> None:
        with self._cond:
            deadline = self._now_s + max(0.0, duration_s)
            self._cond.wait_for(lambda: self._now_s >= deadline)

    def busy(self, budget_s: float) -> contextlib.AbstractContextManager[None]:
        """Time moves only when advanced: work takes no time."""
        return contextlib.nullcontext()

    def wait_until(self, deadline_s: float, timeout_wall_s: float) -> bool:
        """Block until time reaches ``deadline_s`` (True) or ``timeout_wall_s`` of wall time
        passed (False): a thread that must also watch something else (a stop event) waits
        in such slices, as time moves only when another thread advances it."""
        with self._cond:
            return self._cond.wait_for(lambda: self._now_s >= deadline_s, timeout=timeout_wall_s)

    @property
    def pending_sleepers(self) -> int:
        """Coroutines currently sleeping on this clock."""
        with self._cond:
            return len(self._waiters)

    def advance(self, duration_s: float) -> None:
        """Move time forward by ``duration_s`` and wake every sleeper that is due."""
        if duration_s < 0.0:
            raise SimError(f"time cannot go backwards (advance by {duration_s} s); advance by 0 or more")
        with self._cond:
            self._now_s += duration_s
            due: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
            while self._waiters and self._waiters[0][0] <= self._now_s:
                _, _, loop, fut = heapq.heappop(self._waiters)
                due.append((loop, fut))
            self._cond.notify_all()
        for loop, fut in due:
            if not loop.is_closed():
                loop.call_soon_threadsafe(_resolve, fut)

    def __repr__(self) -> str:
        return f"LockstepClock(t={self._now_s:.6f}s)"


#: A deadline counts as reached within this much (simulated seconds): the rounding of summed
#: clock steps (a lock-step test advancing 0.01 s a thousand times) must not miss one.
DUE_TOLERANCE_S = 1e-6


def sleep_until(clock: Clock, deadline_s: float, stop: threading.Event, slice_wall_s: float = 0.05) -> bool:
    """Sleep a thread on ``clock`` until its ``monotonic_s()`` reaches ``deadline_s``.

    Returns True at the deadline, False as soon as ``stop`` is set: the wait goes in slices of
    at most ``slice_wall_s`` of wall time, so a thread that is told to stop leaves within a
    slice, on a wall, a simulated or a lock-step clock (where time moves only when a test
    advances it and a plain ``sleep_blocking`` would wait for that).
    """
    while not stop.is_set():
        left = deadline_s - clock.monotonic_s()
        if left <= DUE_TOLERANCE_S:
            return True
        if isinstance(clock, LockstepClock):
            clock.wait_until(deadline_s - DUE_TOLERANCE_S / 2, slice_wall_s)
        else:
            clock.sleep_blocking(min(left - DUE_TOLERANCE_S / 2, slice_wall_s * clock.speed))
    return False


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)
