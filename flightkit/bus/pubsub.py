"""Typed publishers and subscribers on Zenoh, with per-stream sequence numbers.

Every sample a :class:`BusPublisher` sends carries:

* its ROS 2 message type in the Zenoh encoding: ``application/cdr;geometry_msgs/msg/PoseStamped``;
* a 28-byte attachment: magic ``FK01``, ``uint64`` sequence number (1, 2, ... per publisher),
  ``int64`` stamp (ns since the epoch; the message's header stamp) and a random ``uint64``
  stream id that tells two publishers on one key apart (and a restarted publisher from
  the one before it).

A :class:`BusSubscriber` yields :class:`BusSample` ``(key, msgtype, seq, stamp_ns, payload, bus_ns, stamp_source)``
and counts the messages it missed from gaps in each stream's sequence numbers.

Reliability policies (``BusPublisher(reliable=..., drop_when_congested=...)``):

* mocap, tf, odometry, camera_info: ``reliable=True, drop_when_congested=False`` -- Zenoh
  blocks the publisher rather than drop (``CongestionControl.BLOCK``);
* images: ``reliable=False, drop_when_congested=True`` -- best effort, and under pressure
  Zenoh drops frames (``CongestionControl.DROP``) instead of stalling the camera loop; the
  subscriber sees the drops as sequence gaps.

``express=True`` sends each sample at once instead of batching it with others (lower
latency, more packets): use it for mocap and other small, latency-sensitive streams.

Threads and ordering: Zenoh runs subscriber callbacks on its own threads. The subscriber
appends each sample to a bounded queue under a lock and wakes waiting coroutines with
``loop.call_soon_threadsafe``; threads may block in :meth:`BusSubscriber.get`. Within one
subscriber, samples come out in the order they arrived; samples of one publisher on one
key arrive in publication order. Two different subscribers have no common order. When the
queue is full the oldest sample is dropped and counted in :attr:`BusSubscriber.overflowed`.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import secrets
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, NamedTuple, Self, cast

import zenoh

from flightkit.clock import STAMP_DEVICE, STAMP_HOST, STAMP_SOURCES, Clock
from flightkit.errors import BusError

__all__ = [
    "STAMP_DEVICE",
    "STAMP_HOST",
    "STAMP_SOURCES",
    "BusPublisher",
    "BusSample",
    "BusSubscriber",
    "StreamStats",
    "cdr_encoding",
    "msgtype_of",
]

logger = logging.getLogger(__name__)

_MAGIC_V1 = b"FK01"
_ATTACHMENT_V1 = struct.Struct("<4sQqQ")
_MAGIC = b"FK02"
_ATTACHMENT = struct.Struct("<4sQqQqB")
_CDR = "application/cdr"


def cdr_encoding(msgtype: str) -> zenoh.Encoding:
    """The Zenoh encoding that names a CDR payload's ROS 2 type."""
    return zenoh.Encoding(_CDR).with_schema(msgtype)


def msgtype_of(encoding: zenoh.Encoding) -> str:
    """The ROS 2 type named by an encoding (``""`` if it names none)."""
    text = str(encoding)
    _, sep, schema = text.partition(";")
    return schema if sep else ""


class BusSample(NamedTuple):
    """One received message.

    Attributes:
        key: the key expression it was published on.
        msgtype: ROS 2 type name, e.g. ``"sensor_msgs/msg/Image"`` (``""`` if not given).
        seq: per-stream sequence number (-1 when the publisher is not a flightkit one).
        stamp_ns: the capture stamp, ns since the epoch (0 when not given).
        payload: the CDR payload.
        bus_ns: when the publisher put it on the bus, its clock's ns since the epoch (0: not given).
        stamp_source: ``device``, ``host`` or ``""`` (see :data:`STAMP_SOURCES`).
    """

    key: str
    msgtype: str
    seq: int
    stamp_ns: int
    payload: bytes
    bus_ns: int = 0
    stamp_source: str = ""


def _type_name(msgtype: Any) -> str:
    if isinstance(msgtype, str):
        return msgtype
    name = getattr(msgtype, "TYPE", None)
    if not isinstance(name, str):
        raise BusError(
            f"{msgtype!r} is not a message type; pass a message class (flightkit.bus.pose_msgs, image_msgs) "
            "or a type name"
        )
    return name


class BusPublisher:
    """Publish payloads of one message type on one key.

    Args:
        session: an open Zenoh session.
        key: the key expression (no wildcards).
        msgtype: a message class (:mod:`flightkit.bus.pose_msgs`, :mod:`flightkit.bus.image_msgs`)
            or a full ROS 2 type name.
        reliable: ask for reliable delivery (TCP links are reliable anyway).
        drop_when_congested: drop samples instead of blocking when the network or a
            subscriber cannot keep up (images: True; mocap: False).
        express: send each sample at once, without batching (lower latency).
        priority: Zenoh priority; default ``DATA`` (``REAL_TIME`` for urgent control data).
        clock: stamps each sample's bus time (``time_ns`` when put); default the wall clock.
        stamp_source: ``device`` when the capture stamps given are the device's own, ``host``
            when they are the host's time at hand-over (the default).

    ``put``/``publish`` are thread-safe and return immediately, except that with
    ``drop_when_congested=False`` Zenoh may block while its queues are full.

    Raises:
        BusError: when Zenoh refuses the key.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        msgtype: Any,
        *,
        reliable: bool = True,
        drop_when_congested: bool = False,
        express: bool = False,
        priority: zenoh.Priority | None = None,
        clock: Clock | None = None,
        stamp_source: str = STAMP_HOST,
    ) -> None:
        self.key = key
        self.msgtype = _type_name(msgtype)
        self._code = 0
        self.stamp_source = stamp_source
        self._time_ns = clock.time_ns if clock is not None else time.time_ns
        self.stream_id = secrets.randbits(64)
        self._lock = threading.Lock()
        self._seq = 0
        self._encoding = cdr_encoding(self.msgtype)
        try:
            self._pub = session.declare_publisher(
                key,
                encoding=self._encoding,
                congestion_control=(
                    zenoh.CongestionControl.DROP if drop_when_congested else zenoh.CongestionControl.BLOCK
                ),
                reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
                express=express,
                priority=priority,
            )
        except zenoh.ZError as exc:
            raise BusError(f"cannot publish on {key!r}: {exc}; use a key without wildcards such as 'uav1/tf'") from exc
        self._closed = False

    @property
    def stamp_source(self) -> str:
        """``device`` or ``host``: what the capture stamps of this publisher's samples are."""
        return STAMP_SOURCES[self._code]

    @stamp_source.setter
    def stamp_source(self, source: str) -> None:
        if source not in STAMP_SOURCES[1:]:
            raise BusError(f"stamp source {source!r} is not known; use {STAMP_DEVICE} or {STAMP_HOST}")
        self._code = STAMP_SOURCES.index(source)

    @property
    def seq(self) -> int:
        """Sequence number of the last sample sent (0 before the first)."""
        return self._seq

    @property
    def has_subscribers(self) -> bool:
        """Zenoh's matching status for the key.

        In peer mode it can be True a few milliseconds before samples are actually routed
        to a subscriber that was just declared elsewhere; do not use it as a handshake.
        """
        # zenoh's stub says the property is a bool; at run time it is a MatchingStatus.
        status = cast("zenoh.MatchingStatus", self._pub.matching_status)
        return status.matching

    def put(self, payload: bytes | bytearray, stamp_ns: int, bus_ns: int | None = None) -> int:
        """Send one encoded payload with capture stamp ``stamp_ns`` and bus time ``bus_ns``
        (default: the clock's now; a replay passes the recorded one); returns its sequence number.

        ``payload`` is copied by Zenoh before this returns, so a reused buffer may be
        overwritten afterwards.
        """
        with self._lock:
            if self._closed:
                raise BusError(f"publisher on {self.key!r} is closed; create a new one")
            self._seq += 1
            seq = self._seq
            bus = self._time_ns() if bus_ns is None else int(bus_ns)
            attachment = _ATTACHMENT.pack(_MAGIC, seq, int(stamp_ns), self.stream_id, bus, self._code)
            try:
                self._pub.put(payload, attachment=attachment)
            except zenoh.ZError as exc:
                raise BusError(f"publishing on {self.key!r} failed: {exc}") from exc
        return seq

    def publish(self, msg: Any, out: bytearray | None = None) -> int:
        """Encode ``msg`` (an instance of a class in :data:`flightkit.bus.msgs.MESSAGE_TYPES`) and
        send it, stamped with its header stamp. Images encode into ``out`` when given (a reusable buffer)."""
        if getattr(msg, "TYPE", None) != self.msgtype:
            raise BusError(f"publisher on {self.key!r} sends {self.msgtype}, not {type(msg).__name__}")
        payload = msg.encode(out) if out is not None else msg.encode()
        header = getattr(msg, "header", None)
        stamp_ns = header.stamp_ns if header is not None else 0
        return self.put(payload, stamp_ns)

    def close(self) -> None:
        """Undeclare the publisher; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._pub.undeclare()
            except zenoh.ZError:  # the session is already closed
                pass

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"BusPublisher({self.key!r}, {self.msgtype}, seq={self._seq})"


@dataclass(slots=True)
class StreamStats:
    """Counters of one key on a subscriber (all publishers on that key together)."""

    received: int = 0
    missed: int = 0
    last_seq: int = 0


def _parse_sample(sample: zenoh.Sample) -> tuple[BusSample, int]:
    """The sample and its publisher's stream id (0 when not from a BusPublisher)."""
    key = str(sample.key_expr)
    msgtype = msgtype_of(sample.encoding)
    seq, stamp_ns, stream_id, bus_ns, code = -1, 0, 0, 0, 0
    att = sample.attachment
    if att is not None:
        raw = att.to_bytes()
        if len(raw) == _ATTACHMENT.size and raw[:4] == _MAGIC:
            _, seq, stamp_ns, stream_id, bus_ns, code = _ATTACHMENT.unpack(raw)
        elif len(raw) == _ATTACHMENT_V1.size and raw[:4] == _MAGIC_V1:
            _, seq, stamp_ns, stream_id = _ATTACHMENT_V1.unpack(raw)
    source = STAMP_SOURCES[code] if code < len(STAMP_SOURCES) else ""
    return BusSample(key, msgtype, seq, stamp_ns, sample.payload.to_bytes(), bus_ns, source), stream_id


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class BusSubscriber:
    """Receive samples on a key expression (wildcards allowed), counting sequence gaps.

    Use it as an async iterator (``async for s in sub``), with :meth:`recv` (async) or
    :meth:`get` (blocking, for threads); or pass ``callback`` to handle each sample on the
    Zenoh thread yourself (it must be quick and must not block; nothing is queued then).

    Args:
        session: an open Zenoh session.
        key_expr: e.g. ``"uav1/mocap/*/pose"``.
        maxlen: queue length; on overflow the oldest sample is dropped (and counted).
        callback: optional function called with each :class:`BusSample` on a Zenoh thread.

    Raises:
        BusError: when Zenoh refuses the key expression.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        *,
        maxlen: int = 256,
        callback: Callable[[BusSample], None] | None = None,
    ) -> None:
        self.key_expr = key_expr
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._queue: collections.deque[BusSample] = collections.deque()
        self._maxlen = max(1, int(maxlen))
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        self._streams: dict[tuple[str, int], int] = {}  # (key, stream id) -> last seq
        self._stats: dict[str, StreamStats] = {}
        self._callback = callback
        self.overflowed = 0
        self._closed = False
        try:
            self._sub = session.declare_subscriber(key_expr, self._on_sample)
        except zenoh.ZError as exc:
            raise BusError(f"cannot subscribe to {key_expr!r}: {exc}; check the key expression") from exc

    # -- Zenoh thread
    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self._handle(*_parse_sample(sample))
        except Exception:  # never let an exception escape into Zenoh's thread
            logger.exception("subscriber on %s failed to handle a sample", self.key_expr)

    def _handle(self, s: BusSample, stream_id: int) -> None:
        wake: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        with self._lock:
            if self._closed:
                return
            st = self._stats.get(s.key)
            if st is None:
                st = self._stats[s.key] = StreamStats()
            st.received += 1
            if s.seq >= 0:
                last = self._streams.get((s.key, stream_id))
                if last is not None and s.seq > last + 1:
                    st.missed += s.seq - last - 1
                    logger.debug("%s: missed %d message(s) before seq %d", s.key, s.seq - last - 1, s.seq)
                if last is None or s.seq > last:
                    self._streams[(s.key, stream_id)] = s.seq
                st.last_seq = s.seq
            if self._callback is None:
                if len(self._queue) >= self._maxlen:
                    self._queue.popleft()
                    self.overflowed += 1
                self._queue.append(s)
                self._cond.notify_all()
                wake, self._waiters = self._waiters, []
        if self._callback is not None:
            self._callback(s)
        for loop, fut in wake:
            if not loop.is_closed():
                loop.call_soon_threadsafe(_resolve, fut)

    # -- consumers
    def stats(self) -> dict[str, StreamStats]:
        """Per-key counters (a snapshot)."""
        with self._lock:
            return {k: StreamStats(v.received, v.missed, v.last_seq) for k, v in self._stats.items()}

    def missed(self, key: str | None = None) -> int:
        """Messages missed (sequence gaps) on ``key``, or on all keys."""
        with self._lock:
            if key is not None:
                st = self._stats.get(key)
                return st.missed if st else 0
            return sum(v.missed for v in self._stats.values())

    def received(self, key: str | None = None) -> int:
        """Messages received on ``key``, or on all keys."""
        with self._lock:
            if key is not None:
                st = self._stats.get(key)
                return st.received if st else 0
            return sum(v.received for v in self._stats.values())

    def get(self, timeout_s: float) -> BusSample:
        """Block the calling thread until a sample arrives (wall-clock timeout).

        Raises:
            TimeoutError: nothing arrived within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._queue:
                if self._closed:
                    raise BusError(f"subscriber on {self.key_expr!r} is closed")
                left = deadline - time.monotonic()
                if left <= 0 or not self._cond.wait(left):
                    if self._queue:
                        break
                    raise TimeoutError(f"no message on {self.key_expr!r} within {timeout_s:g} s")
            return self._queue.popleft()

    def try_get(self) -> BusSample | None:
        """The oldest queued sample, or None; returns immediately."""
        with self._lock:
            return self._queue.popleft() if self._queue else None

    async def recv(self, timeout_s: float | None = None) -> BusSample:
        """Wait for the next sample (wall-clock timeout; None waits forever).

        Raises:
            TimeoutError: nothing arrived within ``timeout_s``.
        """
        loop = asyncio.get_running_loop()
        while True:
            with self._lock:
                if self._queue:
                    return self._queue.popleft()
                if self._closed:
                    raise BusError(f"subscriber on {self.key_expr!r} is closed")
                fut: asyncio.Future[None] = loop.create_future()
                self._waiters.append((loop, fut))
            try:
                if timeout_s is None:
                    await fut
                else:
                    await asyncio.wait_for(fut, timeout_s)
            except TimeoutError:
                raise TimeoutError(f"no message on {self.key_expr!r} within {timeout_s:g} s") from None
            finally:
                with self._lock:
                    if (loop, fut) in self._waiters:
                        self._waiters.remove((loop, fut))

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> BusSample:
        try:
            return await self.recv()
        except BusError:
            raise StopAsyncIteration from None

    def close(self) -> None:
        """Undeclare the subscriber and wake every waiter; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            wake, self._waiters = self._waiters, []
            self._cond.notify_all()
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass
        for loop, fut in wake:
            if not loop.is_closed():
                loop.call_soon_threadsafe(_resolve, fut)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
