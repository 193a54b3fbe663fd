"""The shared state behind every mocap source: latest pose per body, waiters, streams.

Backends receive frames on their own threads (a Zenoh callback, the motioncapture
thread, the simulator's sampler) and the source stores them with :meth:`PoseStore.update`;
coroutines on any event loop read the latest poses, wait for a body, or iterate over new
poses. Hand-over to asyncio goes through ``loop.call_soon_threadsafe``; poses of one body
come out in the order they were stored.

Freshness, one rule for every source: :meth:`PoseStore.wait_for_body` returns a pose that is
valid and was received at most ``fresh_within_s`` of clock time ago.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
from collections.abc import AsyncIterator

from flightkit.clock import Clock
from flightkit.errors import MocapBodyMissing, MocapError
from flightkit.mocap.base import MocapPose

__all__ = ["PoseStore"]

logger = logging.getLogger(__name__)


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class _Listener:
    __slots__ = ("body", "dropped", "fut", "loop", "queue")

    def __init__(self, body: str | None, loop: asyncio.AbstractEventLoop, maxlen: int) -> None:
        self.body = body
        self.loop = loop
        self.queue: collections.deque[MocapPose] = collections.deque(maxlen=maxlen)
        self.fut: asyncio.Future[None] | None = None
        self.dropped = 0


class PoseStore:
    """Thread-safe latest-pose table with async waiting.

    Args:
        clock: time source for timeouts and freshness (so tests can run on simulated time).
        name: the source's name, for messages.
        fresh_within_s: :meth:`wait_for_body` wants a pose received at most this long ago.
        queue_len: poses buffered per :meth:`poses` iterator before the oldest is dropped.
    """

    def __init__(self, clock: Clock, name: str = "mocap", fresh_within_s: float = 0.5, queue_len: int = 512) -> None:
        if not fresh_within_s > 0.0:
            raise MocapError(f"fresh_within_s {fresh_within_s!r} must be positive; use e.g. 0.5 s")
        self.clock = clock
        self.name = name
        self.fresh_within_s = float(fresh_within_s)
        self._lock = threading.Lock()
        self._latest: dict[str, MocapPose] = {}
        self._listeners: list[_Listener] = []
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        self._queue_len = queue_len
        self._error: BaseException | None = None
        self._closed = False

    # -- producer side (any thread)
    def update(self, pose: MocapPose) -> None:
        """Store ``pose`` as the newest of its body and wake whoever waits; thread-safe."""
        wake: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        with self._lock:
            if self._closed:
                return
            self._latest[pose.body] = pose
            for lst in self._listeners:
                if lst.body is None or lst.body == pose.body:
                    if len(lst.queue) == lst.queue.maxlen:
                        lst.dropped += 1
                    lst.queue.append(pose)
                    if lst.fut is not None:
                        wake.append((lst.loop, lst.fut))
                        lst.fut = None
            wake.extend(self._waiters)
            self._waiters = []
        for loop, fut in wake:
            if not loop.is_closed():
                loop.call_soon_threadsafe(_resolve, fut)

    def fail(self, error: BaseException) -> None:
        """Record that the backend died; waiters raise ``error`` (wrapped in MocapError)."""
        with self._lock:
            self._error = error
        self._wake_all()

    def close(self) -> None:
        """Stop accepting poses; iterators end, waiters raise MocapError."""
        with self._lock:
            self._closed = True
        self._wake_all()

    def reopen(self) -> None:
        """Accept poses again after :meth:`close` (a source entered a second time); keeps the
        latest poses, clears a recorded failure."""
        with self._lock:
            self._closed = False
            self._error = None

    def _wake_all(self) -> None:
        with self._lock:
            wake = self._waiters + [(lst.loop, lst.fut) for lst in self._listeners if lst.fut is not None]
            self._waiters = []
            for lst in self._listeners:
                lst.fut = None
        for loop, fut in wake:
            if not loop.is_closed():
                loop.call_soon_threadsafe(_resolve, fut)

    # -- consumer side
    def check_failed(self) -> None:
        """Raise MocapError if the backend failed or the source is closed."""
        if self._closed and self._error is None:
            raise MocapError(f"{self.name} source is closed; open it again with 'async with'")
        if self._error is not None:
            if isinstance(self._error, MocapError):
                raise self._error
            raise MocapError(f"{self.name} source failed: {self._error}") from self._error

    def bodies(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(sorted(self._latest))

    def visible(self) -> tuple[str, ...]:
        """Bodies whose newest pose is valid."""
        with self._lock:
            return tuple(sorted(b for b, p in self._latest.items() if p.valid))

    def latest(self, body: str) -> MocapPose | None:
        with self._lock:
            return self._latest.get(body)

    def _fresh(self, pose: MocapPose | None) -> bool:
        return (
            pose is not None
            and pose.valid
            and self.clock.monotonic_s() - pose.received_s <= self.fresh_within_s
        )

    async def wait_for_body(self, body: str, timeout_s: float) -> MocapPose:
        """Wait (on the store's clock) until ``body`` has a valid pose received at most
        ``fresh_within_s`` ago.

        Raises:
            MocapBodyMissing: none within ``timeout_s``; names the visible bodies.
            MocapError: the backend failed.
        """
        loop = asyncio.get_running_loop()
        timer = asyncio.ensure_future(self.clock.sleep(timeout_s))
        try:
            while True:
                with self._lock:
                    self.check_failed()
                    pose = self._latest.get(body)
                    if pose is not None and self._fresh(pose):
                        return pose
                    fut: asyncio.Future[None] = loop.create_future()
                    self._waiters.append((loop, fut))
                if timer.done():
                    break
                await asyncio.wait((fut, timer), return_when=asyncio.FIRST_COMPLETED)
                if timer.done() and not fut.done():
                    with self._lock:
                        if (loop, fut) in self._waiters:
                            self._waiters.remove((loop, fut))
                    pose = self.latest(body)
                    if pose is not None and self._fresh(pose):
                        return pose
                    break
        finally:
            timer.cancel()
        raise MocapBodyMissing(body, self.visible())

    async def poses(self, body: str | None = None) -> AsyncIterator[MocapPose]:
        """Every new pose (of ``body``, or of all bodies) from now on, in arrival order.

        Ends with MocapError when the backend fails or the source closes.
        """
        loop = asyncio.get_running_loop()
        lst = _Listener(body, loop, self._queue_len)
        with self._lock:
            self._listeners.append(lst)
        try:
            while True:
                with self._lock:
                    if lst.queue:
                        pose = lst.queue.popleft()
                    else:
                        if self._closed and self._error is None:
                            return
                        self.check_failed()
                        pose = None
                        fut: asyncio.Future[None] = loop.create_future()
                        lst.fut = fut
                if pose is not None:
                    yield pose
                else:
                    await fut
        finally:
            with self._lock:
                if lst in self._listeners:
                    self._listeners.remove(lst)
            if lst.dropped:
                logger.debug("%s: a slow reader of %s dropped %d poses", self.name, body or "all bodies", lst.dropped)
