"""A test-pattern camera and mocap body: known content at known rates, no renderer cost.

Used by the capture benchmark, the two-process tests and for checking a lab's bus set-up
without a camera: publishes ``<ns>/camera/color/image`` (rgb8), ``<ns>/camera/depth/image``
(16UC1), their camera_info, and ``<ns>/mocap/<body>/pose`` (a 1 m circle). Frames come from
two preallocated buffers whose first row carries the frame number, so publishing costs one
copy per frame and no allocation.

Run it as a process::

    python -m capture.sources.synthetic --connect tcp/127.0.0.1:7447 --duration 10
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import zenoh

from flightkit.bus.keys import Keys
from flightkit.bus.streams import CameraModel, CameraStream, PosePublisher
from flightkit.clock import Clock, WallClock
from flightkit.errors import CaptureError
from flightkit.frames import Transform

__all__ = ["SyntheticPublisher", "main"]

logger = logging.getLogger(__name__)


def circle_pose(t_s: float) -> Transform:
    a = 0.5 * t_s
    return Transform.from_xyz_yaw([math.cos(a), math.sin(a), 1.5], a + math.pi)


def noise_frames(
    width_px: int, height_px: int, count: int = 8, seed: int = 7
) -> list[tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint16]]]:
    """``count`` different (rgb8, 16-bit depth in mm) noise image pairs, the same for a given seed.

    Consecutive frames differ, as a camera's do: with one image repeated, zstd would find
    every frame again inside a 4 MiB chunk and compress far better than real footage allows.
    """
    rng = np.random.default_rng(seed)
    return [
        (
            rng.integers(0, 256, (height_px, width_px, 3), dtype=np.uint8),
            rng.integers(300, 8000, (height_px, width_px), dtype=np.uint16),
        )
        for _ in range(count)
    ]


class SyntheticPublisher:
    """Publish test-pattern images and a circling mocap body.

    Args:
        session: an open Zenoh session.
        keys: the namespace.
        width_px, height_px: image size.
        camera_hz: image rate (0 = no images); mocap_hz: pose rate (0 = no poses).
        depth: also publish 16-bit depth.
        clock: paces the loop (default wall clock).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        *,
        width_px: int = 640,
        height_px: int = 480,
        camera_hz: float = 30.0,
        mocap_hz: float = 240.0,
        depth: bool = True,
        body: str = "uav1",
        clock: Clock | None = None,
    ) -> None:
        self.clock = clock or WallClock()
        self.camera_hz, self.mocap_hz = camera_hz, mocap_hz
        f = width_px / 2.0
        model = CameraModel(width_px, height_px, f, f, (width_px - 1) / 2, (height_px - 1) / 2, (0.0,) * 5)
        self._pool = noise_frames(width_px, height_px)
        self.color = CameraStream(session, keys, "color", model, "rgb8") if camera_hz > 0 else None
        self.depth = CameraStream(session, keys, "depth", model, "16UC1") if camera_hz > 0 and depth else None
        self.pose = PosePublisher(session, keys, body) if mocap_hz > 0 else None
        self.frames = 0
        self.poses = 0

    @property
    def has_subscribers(self) -> bool:
        """Whether every stream has a subscriber right now."""
        streams = [s for s in (self.color, self.depth) if s is not None]
        ok = all(s.has_subscribers for s in streams)
        return ok and (self.pose is None or self.pose.has_subscribers)

    def wait_for_subscribers(self, timeout_s: float) -> None:
        """Block until a subscriber matches every image stream (wall-clock timeout).

        Raises:
            CaptureError: nobody subscribed in time.
        """
        deadline = time.monotonic() + timeout_s
        while not self.has_subscribers:
            if time.monotonic() > deadline:
                raise CaptureError(f"no subscriber within {timeout_s:g} s; is the recorder running and connected?")
            time.sleep(0.01)

    def publish_frame(self) -> None:
        stamp = self.clock.time_ns()
        rgb, depth = self._pool[self.frames % len(self._pool)]
        rgb[0, :8, 0] = np.frombuffer(self.frames.to_bytes(8, "little"), np.uint8)
        if self.color is not None:
            self.color.publish(stamp, rgb)
        if self.depth is not None:
            self.depth.publish(stamp, depth)
        self.frames += 1

    def publish_pose(self) -> None:
        assert self.pose is not None
        self.pose.publish(self.clock.time_ns(), circle_pose(self.clock.monotonic_s()))
        self.poses += 1

    def run(self, duration_s: float | None = None, frames: int | None = None) -> None:
        """Publish on the calling thread until ``duration_s`` of clock time or ``frames`` images."""
        t0 = self.clock.monotonic_s()
        n_cam = n_pose = 0
        cam_dt = 1.0 / self.camera_hz if self.camera_hz > 0 else math.inf
        pose_dt = 1.0 / self.mocap_hz if self.mocap_hz > 0 else math.inf
        while True:
            now = self.clock.monotonic_s() - t0
            if duration_s is not None and now >= duration_s:
                return
            if frames is not None and n_cam >= frames:
                return
            if n_cam * cam_dt <= now:
                self.publish_frame()
                n_cam += 1
            if n_pose * pose_dt <= now:
                self.publish_pose()
                n_pose += 1
            nxt = min(n_cam * cam_dt, n_pose * pose_dt)
            wait = nxt - (self.clock.monotonic_s() - t0)
            if wait > 0:
                self.clock.sleep_blocking(wait)

    def close(self) -> None:
        for s in (self.color, self.depth, self.pose):
            if s is not None:
                s.close()


def main(argv: Sequence[str] | None = None) -> int:
    from flightkit.bus.session import open_session
    from flightkit.config import BusConfig

    ap = argparse.ArgumentParser(prog="python -m capture.sources.synthetic", description=__doc__)
    ap.add_argument("--connect", nargs="*", default=(), help="Zenoh endpoints to connect to")
    ap.add_argument("--listen", nargs="*", default=(), help="Zenoh endpoints to listen on")
    ap.add_argument("--mode", default="peer", choices=("peer", "client"))
    ap.add_argument("--namespace", default="uav1")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--camera-hz", type=float, default=30.0)
    ap.add_argument("--mocap-hz", type=float, default=240.0)
    ap.add_argument("--no-depth", action="store_true")
    ap.add_argument("--duration", type=float, help="seconds to publish")
    ap.add_argument("--frames", type=int, help="images to publish")
    ap.add_argument("--wait-subscribers", type=float, default=10.0, help="seconds to wait for a subscriber first")
    args = ap.parse_args(argv)
    from flightkit.config import BusMode

    cfg = BusConfig(mode=BusMode(args.mode), connect=tuple(args.connect), listen=tuple(args.listen))
    with open_session(cfg) as s:
        pub = SyntheticPublisher(
            s, Keys(args.namespace), width_px=args.width, height_px=args.height, camera_hz=args.camera_hz,
            mocap_hz=args.mocap_hz, depth=not args.no_depth,
        )
        try:
            pub.wait_for_subscribers(args.wait_subscribers)
            pub.run(args.duration, args.frames)
            time.sleep(0.2)  # let the last samples leave before the session closes
        finally:
            pub.close()
        print(f"published {pub.frames} frames and {pub.poses} poses", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
