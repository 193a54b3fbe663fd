"""One clock interface for every loop in flightkit.

Loops never call ``time.time``/``asyncio.sleep`` directly; they take a :class:`Clock`, so the
same code runs on wall time on a real vehicle, on accelerated simulated time in tests and
demos, and in lock-step under a test that advances time explicitly.

* :class:`WallClock`: real time.
* :class:`SimClock`: simulated time running ``speed`` times faster than real time
  (``speed=1`` for demos, 5-20 for tests of whole flights).
* :class:`LockstepClock`: time moves only when :meth:`LockstepClock.advance` is called;
  sleepers (coroutines and threads) wake exactly at their deadlines.

Two notions of time are offered: ``monotonic_s()`` for loop timing, and ``time_ns()`` for
stamps that are recorded (nanoseconds since the Unix epoch).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "LockstepClock", "SimClock", "WallClock"]


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

    def __repr__(self) -> str:
        return "WallClock()"


class SimClock:
    """Simulated time running ``speed`` times faster than real time.

    Args:
        speed: simulated seconds per wall second (> 0).
        start_ns: the epoch time (ns) that simulated time starts at; defaults to now.
    """

    def __init__(self, speed: float = 1.0, start_ns: int | None = None) -> None:
        if not speed > 0.0 or speed == float("inf"):
            raise ValueError(f"SimClock speed must be a positive finite number, got {speed}")
        self._speed = float(speed)
        self._wall0 = time.monotonic()
        self._start_ns = time.time_ns() if start_ns is None else int(start_ns)

    @property
    def speed(self) -> float:
        return self._speed

    def monotonic_s(self) -> float:
        return (time.monotonic() - self._wall0) * self._speed

    def time_ns(self) -> int:
        return self._start_ns + int(self.monotonic_s() * 1e9)

    async def sleep(self, duration_s: float) -> None:
        await asyncio.sleep(max(0.0, duration_s) / self._speed)

    def sleep_blocking(self, duration_s: float) -> None:
        time.sleep(max(0.0, duration_s) / self._speed)

    def __repr__(self) -> str:
        return f"SimClock(speed={self._speed:g})"


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

    @property
    def pending_sleepers(self) -> int:
        """Coroutines currently sleeping on this clock."""
        with self._cond:
            return len(self._waiters)

    def advance(self, duration_s: float) -> None:
        """Move time forward by ``duration_s`` and wake every sleeper that is due."""
        if duration_s < 0.0:
            raise ValueError(f"time cannot go backwards (advance by {duration_s})")
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


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)
