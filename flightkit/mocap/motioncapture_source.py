"""Mocap poses from the ``motioncapture`` library (Vicon, OptiTrack, Qualisys, VRPN, mock, ...).

libmotioncapture's calls block without a timeout (``connect`` to an unreachable server,
``waitForNextFrame`` when the stream stops), so they run on one daemon thread that the
source can abandon: entering waits for the first frame with a timeout, leaving asks the
thread to stop and does not wait for a frame that may never come. ``waitForNextFrame``
releases the GIL while it waits, but ``connect`` does not: for Vicon and Qualisys the
server's TCP port is probed first (with a timeout), so an unreachable server gives a
MocapError instead of a frozen interpreter. A server that accepts TCP but never answers
can still freeze ``connect``.

Per body: ``seq`` counts the frames it appeared in, ``stamp_ns``/``received_s`` come from
the injected clock when the frame arrived (the Python binding exposes neither the systems'
frame time nor their latency, so ``stamp_source`` is ``host``; the source says so once when it
connects, and a bridge records it in the channel metadata), and a body that disappears from a
frame, or comes with NaN, is stored once as
``valid=False`` with its last known pose. Poses are measured in the mocap frame and placed
in the world by :class:`~flightkit.mocap.source.WorldFrameSource`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import socket
import threading
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from flightkit.clock import Clock
from flightkit.errors import MocapError
from flightkit.frames import MOCAP_FRAME_ID, Transform, WorldFrames
from flightkit.mocap.base import MocapSample
from flightkit.mocap.source import WorldFrameSource

__all__ = ["MotionCaptureSource", "mock_rigid_bodies"]

logger = logging.getLogger(__name__)

# TCP servers we can probe before libmotioncapture's connect(), which blocks *holding the
# GIL* (the whole interpreter freezes) when the server does not answer.
_TCP_DEFAULT_PORTS = {"vicon": 801, "qualisys": 22223}


def _probe_tcp(system_type: str, hostname: str, timeout_s: float) -> None:
    default_port = _TCP_DEFAULT_PORTS.get(system_type)
    if default_port is None or not hostname:
        return
    host, sep, port_text = hostname.rpartition(":")
    if not sep or not port_text.isdigit():
        host, port = hostname, default_port
    else:
        port = int(port_text)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise MocapError(
            f"cannot reach the {system_type} server at {host}:{port} ({exc.strerror or exc}); "
            "check mocap.hostname and that the mocap software is streaming"
        ) from exc


def mock_rigid_bodies(bodies: Mapping[str, Transform]) -> str:
    """The ``rigid_bodies`` option of the ``mock`` system for fixed bodies:
    ``"name(x,y,z,qw,qx,qy,qz);..."`` (poses in the mocap frame)."""
    parts = []
    for name, T in bodies.items():
        x, y, z = (float(v) for v in T.translation)
        qw, qx, qy, qz = (float(v) for v in T.quat_wxyz)
        parts.append(f"{name}({x!r},{y!r},{z!r},{qw!r},{qx!r},{qy!r},{qz!r})")
    return ";".join(parts)


class MotionCaptureSource(WorldFrameSource):
    """A :class:`~flightkit.mocap.base.MocapSource` backed by ``motioncapture.connect``.

    Args:
        system_type: ``vicon``, ``optitrack``, ``optitrack_closed_source``, ``qualisys``,
            ``vrpn``, ``nokov``, ``fzmotion``, ``motionanalysis`` or ``mock``.
        clock: stamps frames and runs timeouts.
        hostname: the mocap server (ignored by ``mock``).
        options: extra library options; values are converted to strings.
        frames: where the mocap frame sits in the world (``T_world_mocap`` from config).
        connect_timeout_s: how long entering waits for the first frame (clock time).
        bodies: only report these bodies (None: all).
    """

    def __init__(
        self,
        system_type: str,
        clock: Clock,
        *,
        hostname: str = "",
        options: Mapping[str, Any] | None = None,
        frames: WorldFrames | None = None,
        connect_timeout_s: float = 5.0,
        bodies: Sequence[str] | None = None,
    ) -> None:
        super().__init__(clock, frames or WorldFrames(), name=f"motioncapture {system_type}")
        self.system_type = system_type
        self.hostname = hostname
        self.options = {str(k): str(v) for k, v in (options or {}).items()}
        if hostname:
            self.options.setdefault("hostname", hostname)
        self.connect_timeout_s = connect_timeout_s
        self._only = set(bodies) if bodies else None
        self._stop = threading.Event()
        self._first_frame = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq: dict[str, int] = {}
        self._present: set[str] = set()
        self.frames = 0

    def _describe(self) -> str:
        return f"{self.system_type} at {self.hostname}" if self.hostname else self.system_type

    # -- the blocking thread
    def _run(self) -> None:
        try:
            import motioncapture

            mc = motioncapture.connect(self.system_type, self.options)
            while not self._stop.is_set():
                mc.waitForNextFrame()
                if self._stop.is_set():
                    break
                self._on_frame(mc.rigidBodies)
        except Exception as exc:  # libmotioncapture raises RuntimeError for connection problems
            if not self._stop.is_set():
                logger.error("motioncapture %s stopped: %s", self._describe(), exc)
                self._fail(
                    MocapError(
                        f"motioncapture {self._describe()} failed: {exc}; check system_type, hostname and options"
                    )
                )
                self._first_frame.set()

    def _on_frame(self, rigid_bodies: Mapping[str, Any]) -> None:
        stamp_ns = self.clock.time_ns()
        received_s = self.clock.monotonic_s()
        self.frames += 1
        seen: set[str] = set()
        for name, rb in rigid_bodies.items():
            if self._only is not None and name not in self._only:
                continue
            pos = np.asarray(rb.position, dtype=np.float64)
            q = rb.rotation
            quat_wxyz = np.array([q.w, q.x, q.y, q.z], dtype=np.float64)
            norm = float(np.linalg.norm(quat_wxyz))
            seq = self._seq.get(name, 0) + 1
            self._seq[name] = seq
            T_mocap_body = None  # noqa: N806
            if pos.shape == (3,) and np.all(np.isfinite(pos)) and math.isfinite(norm) and norm > 0.5:
                T_mocap_body = Transform.from_quat_wxyz(pos, quat_wxyz / norm)  # noqa: N806
                seen.add(name)
            self._ingest(MocapSample(stamp_ns, name, MOCAP_FRAME_ID, T_mocap_body, T_mocap_body is not None, seq,
                                     received_s, 0, stamp_ns))
        for name in self._present - seen:
            if name not in rigid_bodies:  # gone from the frame (NaN bodies were stored above)
                self._ingest(MocapSample(stamp_ns, name, MOCAP_FRAME_ID, None, False, self._seq.get(name, 0),
                                         received_s, 0, stamp_ns))
        self._present = seen
        self._first_frame.set()

    # -- lifecycle
    async def _open(self) -> None:
        """Start the thread and wait for the first frame.

        Raises:
            MocapError: no frame within ``connect_timeout_s`` (the thread is abandoned), or
                the library refused the connection.
        """
        await asyncio.to_thread(_probe_tcp, self.system_type, self.hostname, min(2.0, self.connect_timeout_s))
        self._stop = threading.Event()
        self._first_frame = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"motioncapture-{self.system_type}", daemon=True)
        self._thread.start()
        step_s = min(0.01, self.connect_timeout_s)
        waited_s = 0.0
        while not self._first_frame.is_set():
            if waited_s >= self.connect_timeout_s:
                self._stop.set()
                raise MocapError(
                    f"no frame from motioncapture {self._describe()} within {self.connect_timeout_s:g} s; "
                    "is the mocap server running and reachable, and streaming?"
                )
            await self.clock.sleep(step_s)
            waited_s += step_s
        self._store.check_failed()
        logger.info("motioncapture %s streaming, bodies: %s", self._describe(), ", ".join(self.bodies()) or "none")
        logger.info("motioncapture %s: the binding gives no frame time or latency; poses are stamped on arrival",
                    self._describe())

    async def _close(self) -> None:
        """Ask the thread to stop (it exits after its current wait); a stalled
        ``waitForNextFrame`` never returns, so the daemon thread is abandoned after 0.2 s."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread.is_alive():
            await asyncio.to_thread(thread.join, 0.2)

    def __repr__(self) -> str:
        return f"MotionCaptureSource({self._describe()!r}, bodies={list(self.bodies())})"
