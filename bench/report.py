"""Benchmark of the pose-reporting protocol over a real pty pair.

Prints, for 57600 and 115200 baud: bytes per pose update, framing overhead, pose updates
per second achieved (offered as fast as possible; the sending transport paces its writes
to the baud rate at 10 bits per byte, because a pty has no baud limit of its own, just as
a UART drains at the baud rate; the relay injects faults but does not pace again), and
end-to-end latency p50/p99 at 50 updates/s on a clean link and with 10% of frames
dropped, plus a count of reliable segments lost under 10% drops (goal: 0).

Run: .venv/bin/python bench/report.py [--seconds 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time

from estimation.report.endpoints import RobotEndpoint, ServerEndpoint
from estimation.report.events import PoseReceived, SegmentReceived
from estimation.report.messages import PoseUpdate, Segment, encode_pose
from estimation.report.protocol import Frame, encode_frame
from estimation.report.relay import Faults, PtyRelay
from estimation.report.transport import SerialTransport


def _pose(stamp_us: int) -> PoseUpdate:
    return PoseUpdate(stamp_us, 1.25, -3.5, 1.5, 0.7, 200)


def run_case(
    baud: int, faults: Faults, seconds: float, offer_hz: float | None, segments: int = 0
) -> dict[str, float]:
    received: list[tuple[float, int]] = []
    segs: list[float] = []
    lock = threading.Lock()

    def on_server(ev: object) -> None:
        if isinstance(ev, PoseReceived):
            with lock:
                received.append((time.monotonic(), ev.pose.stamp_us))
        elif isinstance(ev, SegmentReceived):
            segs.append(ev.segment.x0)

    with tempfile.TemporaryDirectory() as tmp, PtyRelay(tmp, faults, seed=7) as relay:
        server = SerialTransport(
            relay.path_b, ServerEndpoint(), baud=baud, on_event=on_server, queue_events=False
        )
        robot_ep = RobotEndpoint(1, "bench")
        robot = SerialTransport(relay.path_a, robot_ep, baud=baud, queue_events=False)
        with server, robot:
            deadline = time.monotonic() + 5
            while not robot.call(lambda e: e.session.established):
                if time.monotonic() > deadline:
                    raise RuntimeError("no handshake")
                time.sleep(0.005)
            for i in range(segments):
                robot.call(lambda e, i=i: e.session.send_segment(Segment(float(i), 0, 0, 0)))
            t0 = time.monotonic()
            period = 1.0 / offer_hz if offer_hz else 0.0
            n = 0
            while time.monotonic() - t0 < seconds:
                stamp = int(time.monotonic() * 1e6)
                robot.call(lambda e, s=stamp: e.session.send_pose(_pose(s)))
                n += 1
                if period:
                    time.sleep(max(0.0, t0 + n * period - time.monotonic()))
                else:
                    time.sleep(0.0005)
            t_end = time.monotonic()
            deadline = time.monotonic() + 30
            while robot.call(lambda e: e.session.unacked) and time.monotonic() < deadline:
                time.sleep(0.01)
            stats = robot_ep.session.stats
    with lock:
        window = [r for r in received if r[0] <= t_end]
    lat_ms = sorted((t - s / 1e6) * 1e3 for t, s in window)
    out = {
        "updates_per_s": len(window) / seconds,
        "p50_ms": statistics.median(lat_ms) if lat_ms else float("nan"),
        "p99_ms": lat_ms[int(0.99 * (len(lat_ms) - 1))] if lat_ms else float("nan"),
        "retransmissions": stats.retransmissions,
    }
    if segments:
        out["segments_lost"] = segments - len(segs)
        out["segments_in_order"] = float(segs == [float(i) for i in range(segments)])
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args()
    payload = encode_pose(_pose(1_700_000_000_000_000))
    wire = encode_frame(Frame(3, 1, 1234, 4321, payload))
    print(
        f"pose update: {len(payload)} payload bytes, {len(wire)} bytes on the wire, "
        f"framing overhead {100 * (1 - len(payload) / len(wire)):.1f}% "
        "(6 header + 2 CRC + 1 COBS + 1 delimiter)"
    )
    print()
    print(
        f"{'baud':>7} {'link':>9} {'offered':>9} {'theory/s':>9} {'got/s':>7} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'retx':>5} {'seg lost':>8}"
    )
    for baud in (57600, 115200):
        theory = baud / 10 / len(wire)
        for label, faults in (("clean", Faults()), ("10% drop", Faults(drop=0.1))):
            r = run_case(baud, faults, args.seconds, None)
            print(
                f"{baud:>7} {label:>9} {'max':>9} {theory:>9.0f} {r['updates_per_s']:>7.0f} "
                f"{r['p50_ms']:>7.1f} "
                f"{r['p99_ms']:>7.1f} {r['retransmissions']:>5.0f} {'-':>8}"
            )
            r = run_case(baud, faults, args.seconds, 50.0, segments=300)
            print(
                f"{baud:>7} {label:>9} {'50/s':>9} {theory:>9.0f} {r['updates_per_s']:>7.0f} "
                f"{r['p50_ms']:>7.1f} "
                f"{r['p99_ms']:>7.1f} {r['retransmissions']:>5.0f} {r['segments_lost']:>8.0f}"
                + ("" if r["segments_in_order"] else "  OUT OF ORDER")
            )


if __name__ == "__main__":
    main()
