"""The reference mapping server: robots, tracks and wall segments on a 2D map.

One :class:`~.transport.SerialTransport` (one thread) per port, each running a
:class:`~.endpoints.ServerEndpoint`, so several robots can report over several dongles (or
share one radio channel, told apart by their robot id). The server keeps each robot's
latest pose, its track and its segments, writes every event to a JSON-lines log, saves a
PNG map, and sends navigation orders (reliably, in order) to a robot by id or name.

Everything here is in map units (see :mod:`.mapframe`); the server never needs to know the
world frame.
"""
from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Self

from flightkit.clock import Clock, WallClock
from flightkit.errors import ProtocolError
from flightkit.lifetime import Running

from .endpoints import ServerEndpoint
from .events import Connected, Delivered, LinkLost, PeerGoodbye, PoseReceived, SegmentReceived
from .link_session import SessionConfig
from .messages import MsgType, NavOrder, PoseUpdate, Segment
from .transport import PortLost, PortOpened, SerialTransport, TransportEvent

__all__ = ["MapServer", "OrderLine", "RobotState", "parse_orders"]

logger = logging.getLogger(__name__)


@dataclass(slots=True)
class RobotState:
    """What the server knows about one robot (map units)."""

    robot_id: int
    port: str
    name: str = ""
    online: bool = False
    pose: PoseUpdate | None = None
    last_seen_s: float = math.nan
    poses: int = 0
    track: list[tuple[float, float]] = field(default_factory=list)
    segments: list[Segment] = field(default_factory=list)
    orders_sent: int = 0
    orders_acked: int = 0
    reconnects: int = 0

    @property
    def label(self) -> str:
        return f"{self.name or '?'}#{self.robot_id}"


@dataclass(frozen=True, slots=True)
class OrderLine:
    """One navigation order from a file or the command line."""

    robot: str  # id or name
    x: float
    y: float
    z: float = math.nan
    heading_rad: float = math.nan


def parse_orders(text: str, source: str = "<orders>") -> list[OrderLine]:
    """Parse orders, one per line: ``ROBOT X Y [Z] [HEADING_DEG]`` (``#`` starts a comment).

    Raises:
        ProtocolError: naming the line that cannot be read.
    """
    out: list[OrderLine] = []
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip().replace(",", " ")
        if not line:
            continue
        parts = line.split()
        if not 3 <= len(parts) <= 5:
            raise ProtocolError(
                f"{source}:{n}: cannot read order {raw.strip()!r} ({len(parts)} fields); "
                "write ROBOT X Y [Z] [HEADING_DEG]",
            )
        try:
            nums = [float(v) for v in parts[1:]]
            z = nums[2] if len(nums) > 2 else math.nan
            heading = math.radians(nums[3]) if len(nums) > 3 else math.nan
            out.append(OrderLine(parts[0], nums[0], nums[1], z, heading))
        except ValueError as exc:
            raise ProtocolError(
                f"{source}:{n}: cannot read order {raw.strip()!r} ({exc}); write ROBOT X Y [Z] [HEADING_DEG]"
            ) from exc
    return out


class MapServer(Running):
    """Serve ``ports``; see the module docstring.

    Args:
        ports: serial ports or URLs, one dongle each.
        baud: baud rate of every port.
        clock: protocol timers.
        out_dir: where the log (``mapserver_log.jsonl``) and map (``map.png``) go; None: no log.
        name: the server's name in the handshake.
        session_config: protocol timing.
        max_track_points: per robot; older points are thinned out beyond it.
    """

    def __init__(
        self,
        ports: Sequence[str],
        *,
        baud: int = 115200,
        clock: Clock | None = None,
        out_dir: str | Path | None = None,
        name: str = "mapserver",
        session_config: SessionConfig | None = None,
        max_track_points: int = 200_000,
        link_rate_bps: float | None = None,
    ) -> None:
        if not ports:
            raise ProtocolError("the mapping server needs at least one port; pass --port")
        self.clock: Clock = clock or WallClock()
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.max_track_points = max_track_points
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._robots: dict[tuple[str, int], RobotState] = {}
        self._order_ids = 0
        self._pending_orders: list[OrderLine] = []
        self._log: IO[str] | None = None
        self.endpoints: dict[str, ServerEndpoint] = {}
        self.transports: dict[str, SerialTransport] = {}
        self.port_errors: dict[str, str] = {}
        cfg = session_config or SessionConfig()
        for port in ports:
            ep = ServerEndpoint(name=name, config=cfg)
            self.endpoints[port] = ep
            self.transports[port] = SerialTransport(
                port,
                ep,
                baud=baud,
                clock=self.clock,
                link_rate_bps=link_rate_bps,
                on_event=self._handler(port),
                queue_events=False,
            )

    # ------------------------------------------------------------------ lifetime

    def start(self) -> Self:
        """Open the log and start every port; returns immediately."""
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._log = (self.out_dir / "mapserver_log.jsonl").open("a", encoding="utf-8")
        for t in self.transports.values():
            t.start()
        return self

    def stop(self) -> None:
        for t in self.transports.values():
            t.stop()
        with self._lock:
            if self._log is not None:
                self._log.close()
                self._log = None

    # ------------------------------------------------------------------ queries

    def robots(self) -> list[RobotState]:
        """A snapshot of every robot seen (copies; safe to keep)."""
        with self._lock:
            return [
                RobotState(
                    r.robot_id,
                    r.port,
                    r.name,
                    r.online,
                    r.pose,
                    r.last_seen_s,
                    r.poses,
                    list(r.track),
                    list(r.segments),
                    r.orders_sent,
                    r.orders_acked,
                    r.reconnects,
                )
                for r in self._robots.values()
            ]

    def wait_for(self, predicate: Callable[[list[RobotState]], bool], timeout_s: float) -> list[RobotState]:
        """Block until ``predicate(robots)`` holds; returns that snapshot.

        Raises:
            ProtocolError: when it did not hold within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                snap = self.robots()
                if predicate(snap):
                    return snap
                left = deadline - time.monotonic()
                if left <= 0:
                    names = ", ".join(r.label for r in snap) or "none"
                    raise ProtocolError(
                        f"mapping server: condition not met within {timeout_s:.1f} s (robots seen: {names}); "
                        "check the robots' ports, ids and baud rates"
                    )
                self._cond.wait(min(left, 0.1))

    # ------------------------------------------------------------------ orders

    def send_order(
        self, robot: int | str, x: float, y: float, z: float = math.nan, heading_rad: float = math.nan
    ) -> int:
        """Queue a navigation order (map units) for reliable delivery; returns its order id.

        ``robot`` is an id or a name. An order for a robot id not yet seen is queued on
        every port and delivered once it connects.

        Raises:
            ProtocolError: for a robot name that no connected robot has.
        """
        with self._lock:
            ports = self._ports_of(robot)
            self._order_ids += 1
            order = NavOrder(self._order_ids, x, y, z, heading_rad)
            for port, rid in ports:

                def send(ep: ServerEndpoint, rid: int = rid) -> int:
                    return ep.session(rid).send_nav_order(order)

                self.transports[port].call(send)
                state = self._robot(port, rid)
                state.orders_sent += 1
            self._write_log(
                {"event": "order", "robot": str(robot), "order_id": order.order_id, "x": x, "y": y}
            )
            return order.order_id

    def queue_orders(self, orders: Sequence[OrderLine]) -> None:
        """Send orders now where the robot is known, later (on connection) otherwise."""
        for o in orders:
            try:
                self.send_order(o.robot, o.x, o.y, o.z, o.heading_rad)
            except ProtocolError:
                with self._lock:
                    self._pending_orders.append(o)

    def _ports_of(self, robot: int | str) -> list[tuple[str, int]]:
        if isinstance(robot, str) and robot.isdigit():
            robot = int(robot)
        if isinstance(robot, int):
            known = [k for k in self._robots if k[1] == robot]
            return known or [(p, robot) for p in self.transports]
        named = [k for k, r in self._robots.items() if r.name == robot]
        if not named:
            seen = ", ".join(r.label for r in self._robots.values()) or "none"
            raise ProtocolError(
                f"no robot named {robot!r} has connected (seen: {seen}); use its id or wait for it"
            )
        return named

    # ------------------------------------------------------------------ events

    def _robot(self, port: str, robot_id: int) -> RobotState:
        key = (port, robot_id)
        st = self._robots.get(key)
        if st is None:
            st = self._robots[key] = RobotState(robot_id, port)
        return st

    def _handler(self, port: str) -> Callable[[TransportEvent], None]:
        def handle(ev: TransportEvent) -> None:
            with self._cond:
                self._on_event(port, ev)
                self._cond.notify_all()

        return handle

    def _on_event(self, port: str, ev: TransportEvent) -> None:
        now = self.clock.monotonic_s()
        if isinstance(ev, PoseReceived):
            st = self._robot(port, ev.robot_id)
            p = ev.pose
            st.pose, st.last_seen_s = p, now
            st.poses += 1
            st.track.append((p.x, p.y))
            if len(st.track) > self.max_track_points:
                st.track = st.track[::2]
            self._write_log(
                {
                    "event": "pose",
                    "robot": st.label,
                    "t_us": p.stamp_us,
                    "x": p.x,
                    "y": p.y,
                    "z": p.z,
                    "heading_rad": p.heading_rad,
                    "quality": p.quality,
                }
            )
        elif isinstance(ev, SegmentReceived):
            st = self._robot(port, ev.robot_id)
            st.segments.append(ev.segment)
            s = ev.segment
            self._write_log(
                {"event": "segment", "robot": st.label, "x0": s.x0, "y0": s.y0, "x1": s.x1, "y1": s.y1}
            )
        elif isinstance(ev, Delivered):
            st = self._robot(port, ev.robot_id)
            if ev.msg_type is MsgType.NAV_ORDER:
                st.orders_acked += 1
                self._write_log({"event": "order_acked", "robot": st.label, "seq": ev.seq})
        elif isinstance(ev, Connected):
            st = self._robot(port, ev.robot_id)
            st.reconnects += 1 if st.name else 0
            st.name, st.online, st.last_seen_s = ev.peer_name, True, now
            logger.info("robot %s connected on %s", st.label, port)
            self._write_log({"event": "connected", "robot": st.label, "port": port, "resumed": ev.resumed})
            self._flush_pending()
        elif isinstance(ev, LinkLost | PeerGoodbye):
            st = self._robot(port, ev.robot_id)
            st.online = False
            why = "link lost" if isinstance(ev, LinkLost) else f"goodbye ({ev.reason.name.lower()})"
            logger.info("robot %s offline: %s", st.label, why)
            self._write_log({"event": "offline", "robot": st.label, "why": why})
        elif isinstance(ev, PortLost):
            self.port_errors[port] = ev.message
            self._write_log({"event": "port_lost", "port": port, "message": ev.message})
        elif isinstance(ev, PortOpened):
            self.port_errors.pop(port, None)
            self._write_log({"event": "port_open", "port": port})

    def _flush_pending(self) -> None:
        pending, self._pending_orders = self._pending_orders, []
        self.queue_orders(pending)

    def _write_log(self, record: dict[str, object]) -> None:
        if self._log is None:
            return
        record = {"t_ns": self.clock.time_ns(), **record}
        self._log.write(json.dumps(record) + "\n")

    # ------------------------------------------------------------------ map

    def save_map(self, path: str | Path | None = None, *, title: str = "flightkit map") -> Path:
        """Draw tracks, robots (with heading) and segments into a PNG; returns its path.

        Raises:
            ProtocolError: when no path is given and the server has no ``out_dir``.
        """
        if path is None:
            if self.out_dir is None:
                raise ProtocolError("save_map needs a path when the server has no out_dir")
            path = self.out_dir / "map.png"
        return draw_map(self.robots(), Path(path), title=title)


def draw_map(robots: Sequence[RobotState], path: Path, *, title: str = "flightkit map") -> Path:
    """Render robots to a PNG (matplotlib, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    try:
        colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        for i, r in enumerate(sorted(robots, key=lambda r: r.robot_id)):
            c = colors[i % len(colors)]
            if r.track:
                xs, ys = zip(*r.track, strict=True)
                ax.plot(xs, ys, "-", color=c, lw=1.2, alpha=0.8, label=f"{r.label} track ({r.poses} poses)")
            for s in r.segments:
                ax.plot([s.x0, s.x1], [s.y0, s.y1], "-", color="k", lw=3, solid_capstyle="round")
            if r.pose is not None:
                p = r.pose
                ax.plot([p.x], [p.y], "o", color=c, ms=9, mec="k")
                scale = _arrow_scale(r.track)
                ax.annotate(
                    "",
                    xy=(p.x + scale * math.cos(p.heading_rad), p.y + scale * math.sin(p.heading_rad)),
                    xytext=(p.x, p.y),
                    arrowprops={"arrowstyle": "->", "color": c, "lw": 2},
                )
                ax.annotate(r.label, (p.x, p.y), textcoords="offset points", xytext=(8, 8), color=c)
        if any(r.segments for r in robots):
            ax.plot([], [], "-", color="k", lw=3, label="wall segments")
        # Never zoom in below half a map unit around the data: a hovering robot is a dot, not noise.
        pts = [xy for r in robots for xy in r.track] + [
            (x, y) for r in robots for s in r.segments for x, y in ((s.x0, s.y0), (s.x1, s.y1))
        ]
        if pts:
            xs_all, ys_all = zip(*pts, strict=True)
            cx, cy = (min(xs_all) + max(xs_all)) / 2, (min(ys_all) + max(ys_all)) / 2
            half = max(max(xs_all) - min(xs_all), max(ys_all) - min(ys_all), 1.0) / 2 * 1.15
            ax.set_xlim(cx - half, cx + half)
            ax.set_ylim(cy - half, cy + half)
        ax.set_aspect("equal", adjustable="box")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("map x")
        ax.set_ylabel("map y")
        ax.set_title(title)
        if robots:
            ax.legend(loc="best", fontsize=8)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path)
    finally:
        plt.close(fig)
    return path


def _arrow_scale(track: list[tuple[float, float]]) -> float:
    if len(track) < 2:
        return 0.3
    xs = [p[0] for p in track]
    ys = [p[1] for p in track]
    span = max(max(xs) - min(xs), max(ys) - min(ys))
    return max(span * 0.06, 1e-3)
