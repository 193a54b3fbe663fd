"""A fault-injecting relay between two pseudo-terminals, standing in for a radio link.

Two pty pairs are created; each end of the link opens its own slave through a stable
symlink (``path_a`` / ``path_b``), the way udev gives a USB dongle a stable
``/dev/serial/by-id/...`` name. The relay thread copies bytes between the two masters,
frame by frame (frames end at a zero byte), and on the way it can

* drop, duplicate, corrupt (one bit flipped) or delay a frame, and reorder frames (a frame
  held back by a random extra delay is overtaken by later ones);
* throttle each direction to a baud rate (``bits_per_byte`` per byte), like the radio;
* cut the link (:meth:`set_link`: bytes are discarded while down, the ports stay open);
* unplug and replug the ports (:meth:`unplug` / :meth:`replug`: the ptys are destroyed,
  so an end's open port fails like an unplugged USB dongle, and the symlinks point to new
  ptys when they come back).

Faults are drawn from a seeded :class:`random.Random` so a failing run can be repeated.
"""
from __future__ import annotations

import heapq
import itertools
import logging
import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

from flightkit.lifetime import Running

__all__ = ["Faults", "PtyRelay", "RelayStats"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Faults:
    """Per-frame fault probabilities and delays for one direction."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0  # probability that a frame is held back by up to reorder_max_s
    reorder_max_s: float = 0.03
    corrupt: float = 0.0  # probability of one flipped bit
    delay_s: float = 0.0
    jitter_s: float = 0.0


@dataclass(slots=True)
class RelayStats:
    frames: int = 0
    dropped: int = 0
    duplicated: int = 0
    corrupted: int = 0
    reordered: int = 0
    cut: int = 0  # frames lost while the link was down
    overflow: int = 0  # bytes discarded because the receiving end did not read
    bytes_out: int = 0


@dataclass(slots=True)
class _Direction:
    src: int
    dst: int
    faults: Faults
    stats: RelayStats = field(default_factory=RelayStats)
    partial: bytearray = field(default_factory=bytearray)
    line_free_at: float = 0.0
    queue: list[tuple[float, int, bytes]] = field(default_factory=list)


class PtyRelay(Running):
    """Relay between ``path_a`` (e.g. the robot's port) and ``path_b`` (the server's).

    Args:
        directory: where the two symlinks are created.
        a_to_b, b_to_a: faults of each direction (``b_to_a`` defaults to ``a_to_b``).
        baud: throttle each direction to this rate (None: as fast as the ptys go).
        bits_per_byte: 10 for 8N1.
        seed: random seed of the faults.
        names: file names of the two symlinks.
    """

    def __init__(
        self,
        directory: str | Path,
        a_to_b: Faults | None = None,
        b_to_a: Faults | None = None,
        *,
        baud: int | None = None,
        bits_per_byte: int = 10,
        seed: int = 0,
        names: tuple[str, str] = ("robot", "server"),
    ) -> None:
        self.directory = Path(directory)
        self.path_a = str(self.directory / names[0])
        self.path_b = str(self.directory / names[1])
        self._faults = (a_to_b or Faults(), b_to_a or a_to_b or Faults())
        self.byte_time_s = bits_per_byte / baud if baud else 0.0
        self.rng = random.Random(seed)
        self._seq = itertools.count()
        self._lock = threading.Lock()
        self._link_up = True
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fds: list[int] = []
        self._dirs: list[_Direction] = []
        self.stats_a_to_b = RelayStats()
        self.stats_b_to_a = RelayStats()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)

    # ------------------------------------------------------------------ lifetime

    def start(self) -> Self:
        """Create the ptys and symlinks and start relaying; returns immediately."""
        self._plug()
        self._thread = threading.Thread(target=self._run, name="pty-relay", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._poke()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        with self._lock:
            self._unplug_locked()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    # ------------------------------------------------------------------ faults

    def set_faults(self, a_to_b: Faults, b_to_a: Faults | None = None) -> None:
        """Change the faults of both directions (takes effect on the next frame)."""
        with self._lock:
            self._faults = (a_to_b, b_to_a or a_to_b)
            for d, f in zip(self._dirs, self._faults, strict=False):
                d.faults = f

    def set_link(self, up: bool) -> None:
        """Cut (False) or restore (True) the link; frames sent while it is down are lost."""
        with self._lock:
            self._link_up = up

    def unplug(self) -> None:
        """Destroy both ptys (both ends' ports fail) and remove the symlinks."""
        with self._lock:
            self._unplug_locked()
        self._poke()

    def replug(self) -> None:
        """Create fresh ptys behind the same symlinks."""
        self._plug()
        self._poke()

    # ------------------------------------------------------------------ internals

    def _poke(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def _plug(self) -> None:
        with self._lock:
            if self._fds:
                return
            self.directory.mkdir(parents=True, exist_ok=True)
            m_a, s_a = os.openpty()
            m_b, s_b = os.openpty()
            for fd in (s_a, s_b):
                tty.setraw(fd)
            for fd in (m_a, m_b):
                os.set_blocking(fd, False)
            self._fds = [m_a, s_a, m_b, s_b]
            for link, slave in ((self.path_a, s_a), (self.path_b, s_b)):
                tmp = link + ".tmp"
                if os.path.lexists(tmp):
                    os.unlink(tmp)
                os.symlink(os.ttyname(slave), tmp)
                os.replace(tmp, link)
            self._dirs = [
                _Direction(m_a, m_b, self._faults[0], self.stats_a_to_b),
                _Direction(m_b, m_a, self._faults[1], self.stats_b_to_a),
            ]

    def _unplug_locked(self) -> None:
        for link in (self.path_a, self.path_b):
            if os.path.lexists(link):
                os.unlink(link)
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._fds = []
        self._dirs = []

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                dirs = list(self._dirs)
            now = time.monotonic()
            timeout = 0.05
            for d in dirs:
                if d.queue:
                    timeout = min(timeout, max(0.0, d.queue[0][0] - now))
            srcs = [d.src for d in dirs]
            try:
                ready, _, _ = select.select([*srcs, self._wake_r], [], [], timeout)
            except (OSError, ValueError):
                continue  # an fd was closed by unplug() under us
            if self._wake_r in ready:
                os.read(self._wake_r, 4096)
            with self._lock:
                if dirs != self._dirs:
                    continue
                for d in dirs:
                    if d.src in ready:
                        self._read(d)
                    self._deliver(d)

    def _read(self, d: _Direction) -> None:
        try:
            data = os.read(d.src, 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return  # EIO: nobody has the slave open right now
        now = time.monotonic()
        buf = d.partial
        buf += data
        while True:
            z = buf.find(0)
            if z < 0:
                break
            frame = bytes(buf[: z + 1])
            del buf[: z + 1]
            self._inject(d, frame, now)

    def _inject(self, d: _Direction, frame: bytes, now: float) -> None:
        f, st, rng = d.faults, d.stats, self.rng
        st.frames += 1
        if not self._link_up:
            st.cut += 1
            return
        if rng.random() < f.drop:
            st.dropped += 1
            return
        copies = 2 if rng.random() < f.duplicate else 1
        st.duplicated += copies - 1
        for _ in range(copies):
            out = frame
            if rng.random() < f.corrupt:
                b = bytearray(frame)
                b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
                out = bytes(b)
                st.corrupted += 1
            t = now + f.delay_s + (rng.uniform(0.0, f.jitter_s) if f.jitter_s else 0.0)
            if rng.random() < f.reorder:
                t += rng.uniform(0.0, f.reorder_max_s)
                st.reordered += 1
            heapq.heappush(d.queue, (t, next(self._seq), out))

    def _deliver(self, d: _Direction) -> None:
        now = time.monotonic()
        while d.queue and d.queue[0][0] <= now:
            if self.byte_time_s and d.line_free_at > now:
                return
            _, _, data = heapq.heappop(d.queue)
            if not self._link_up:
                d.stats.cut += 1
                continue
            try:
                n = os.write(d.dst, data)
            except BlockingIOError:
                n = 0
            except OSError:
                return
            d.stats.bytes_out += n
            d.stats.overflow += len(data) - n
            if self.byte_time_s:
                d.line_free_at = max(d.line_free_at, now) + len(data) * self.byte_time_s
