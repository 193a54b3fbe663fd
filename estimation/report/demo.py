"""One call that reports a whole trajectory to a mapping server over a pty pair.

Used by ``flightkit demo`` at the end of a flight: the poses travel the real path (framing,
session, paced serial transport, pseudo-terminals, mapping server) and the server's map is
saved as a PNG.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from flightkit.errors import ProtocolError
from flightkit.frames import Transform

from .mapframe import MapFrame
from .mapserver import MapServer
from .relay import PtyRelay
from .reporter import PoseSample, Reporter

__all__ = ["report_trajectory_over_pty"]

logger = logging.getLogger(__name__)


def _as_samples(poses: Any) -> list[PoseSample]:
    if hasattr(poses, "stamps_ns") and hasattr(poses, "transform"):  # a datasets Trajectory
        return [PoseSample(int(poses.stamps_ns[i]), poses.transform(i)) for i in range(len(poses))]
    out: list[PoseSample] = []
    for p in poses:
        if isinstance(p, PoseSample):
            out.append(p)
        elif hasattr(p, "T_world_body") and hasattr(p, "stamp_ns"):  # MocapPose and friends
            out.append(PoseSample(int(p.stamp_ns), p.T_world_body, 255 if getattr(p, "valid", True) else 0))
        else:
            stamp_ns, T = p
            if not isinstance(T, Transform):
                raise ProtocolError(
                    f"pose {p!r} is not (stamp_ns, Transform); pass PoseSample or MocapPose objects"
                )
            out.append(PoseSample(int(stamp_ns), T))
    return out


def report_trajectory_over_pty(
    poses: Iterable[Any],
    out_dir: str | Path,
    *,
    segments_world_m: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
    rate_hz: float = 20.0,
    speed: float = 10.0,
    baud: int = 115200,
    map_frame: MapFrame | None = None,
    name: str = "uav1",
    timeout_s: float = 30.0,
) -> Path:
    """Report ``poses`` to a mapping server through a pty pair; returns the map PNG path.

    Args:
        poses: PoseSample, MocapPose, (stamp_ns, Transform) tuples, or a Trajectory.
        out_dir: the server writes ``map.png`` and ``mapserver_log.jsonl`` here.
        segments_world_m: wall segments ((x0, y0), (x1, y1)) in world metres to report too.
        rate_hz: pose updates per second of flight time.
        speed: replay this many times faster than the flight (the line must keep up:
            ``rate_hz * speed`` should stay below ~300 at 115200 baud).
        baud: the simulated line's baud rate (the transports pace their writes to it).
        map_frame: world -> map frame (default identity, metres).
        timeout_s: give up waiting for the server after this long.

    Raises:
        ProtocolError: when the server did not receive the trajectory in time.
    """
    samples = _as_samples(poses)
    if not samples:
        raise ProtocolError("no poses to report; the trajectory is empty")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    period_ns = int(1e9 / rate_hz)
    picked = [samples[0]]
    for s in samples[1:]:
        if s.stamp_ns - picked[-1].stamp_ns >= period_ns:
            picked.append(s)
    if picked[-1] is not samples[-1]:
        picked.append(samples[-1])
    with tempfile.TemporaryDirectory(prefix="flightkit-pty-") as tmp:
        with PtyRelay(tmp) as relay, MapServer([relay.path_b], baud=baud, out_dir=out) as server:
            with Reporter(relay.path_a, name=name, baud=baud, map_frame=map_frame) as rep:
                rep.wait_connected(timeout_s)
                for a, b in segments_world_m:
                    rep.report_segment(a, b)
                wall_period_s = 1.0 / (rate_hz * speed)
                t_next = time.monotonic()
                for s in picked:
                    rep.report_pose(s)
                    t_next += wall_period_s
                    time.sleep(max(0.0, t_next - time.monotonic()))
                last_us = rep.map_frame.pose_update(picked[-1].stamp_ns, picked[-1].T_world_body).stamp_us
                server.wait_for(
                    lambda rs: (
                        any(r.pose is not None and r.pose.stamp_us == last_us for r in rs)
                        and all(len(r.segments) == len(segments_world_m) for r in rs)
                    ),
                    timeout_s,
                )
                robots = server.robots()
            png = server.save_map(title=f"{name}: {robots[0].poses} pose updates over a {baud}-baud pty pair")
    logger.info("map of %d poses saved to %s", len(picked), png)
    return png
