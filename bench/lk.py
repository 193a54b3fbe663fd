"""Benchmark of our LK tracker on shared pyramids (``estimation.lk``) beside OpenCV's
``calcOpticalFlowPyrLK`` on the LK calls of real runs, one core.

Every LK call of a run (forward tracking, the backward check, sparse stereo) is recorded: an
``rgbd-kabsch`` run on TUM fr1/rpy and 7-Scenes and a ``stereo`` run on KITTI 06, native
resolution. Then both trackers replay the recorded calls, alternating, ``--rounds`` times:
OpenCV with the same window, levels, iterations and start positions (it builds both pyramids and
the first image's derivatives on every call), ours on pyramids built as the pipeline builds them
(once per image, through its ``PyramidCache``). Prints per sequence: the calls and their
median point count, ms per frame of each (CPU time, median of the rounds) with ours split into
pyramids and tracking, OpenCV's over ours, the share of points whose status agrees and the median
and 99th percentile of the position difference where both tracked.

Run: .venv/bin/python bench/lk.py [--only tum_rpy,7scenes,kitti06] [--rounds 5] [--cpu N]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._host import pin_one_cpu  # noqa: E402
from estimation import flow  # noqa: E402
from estimation.lk import EPS_PX, ImagePyramid, PyramidCache, lk_track  # noqa: E402
from estimation.pipeline import run_vo  # noqa: E402
from flightkit.datasets.registry import open_sequence  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEQUENCES = {
    "tum_rpy": ("tum_fr1rpy_000_199", "rgbd-kabsch"),
    "7scenes": ("sevenscenes_tsdf50", "rgbd-kabsch"),
    "kitti06": ("kitti06_stereo", "stereo"),
}


@dataclass(frozen=True, slots=True)
class Call:
    """One recorded LK call: the two images, the points, where they start, and the settings."""

    prev: np.ndarray
    cur: np.ndarray
    pts: np.ndarray
    start: np.ndarray | None
    levels: int
    win_px: int
    max_iters: int
    eps_px: float


def record(name: str, method: str) -> tuple[list[Call], int, int]:
    """The LK calls of one run of ``method`` on ``name``, the frame count, and the pyramid levels
    the run built."""
    calls: list[Call] = []
    built = [0]
    real = flow.lk_track

    def spy(
        prev: ImagePyramid,
        cur: ImagePyramid,
        pts: Any,
        start: Any,
        levels: int,
        win_px: int,
        max_iters: int,
        eps_px: float = EPS_PX,
    ) -> Any:
        built[0] = max(built[0], prev.levels, cur.levels)
        s = None if start is None else np.array(start, np.float32).reshape(-1, 2)
        calls.append(
            Call(prev.image, cur.image, np.array(pts, np.float32).reshape(-1, 2), s, levels, win_px, max_iters, eps_px)
        )
        return real(prev, cur, pts, start, levels, win_px, max_iters, eps_px)

    flow.lk_track = spy  # type: ignore[assignment]
    try:
        res = run_vo(open_sequence(DATA / name), method, init_from_groundtruth=True)
    finally:
        flow.lk_track = real  # type: ignore[assignment]
    return calls, len(res.stage_ms["total"]), built[0]


def run_opencv(calls: list[Call]) -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for c in calls:
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, c.max_iters, c.eps_px)
        start = c.pts if c.start is None else c.start
        p1, st, _ = cv2.calcOpticalFlowPyrLK(  # type: ignore[call-overload]
            c.prev,
            c.cur,
            c.pts.reshape(-1, 1, 2),
            start.reshape(-1, 1, 2).copy(),
            winSize=(c.win_px, c.win_px),
            maxLevel=c.levels,
            criteria=crit,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        out.append((p1.reshape(-1, 2), st.ravel() == 1))
    return out


def run_ours(calls: list[Call], levels: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], float, float]:
    """Our tracker on the calls with the pipeline's pyramid cache; also the CPU seconds spent
    building pyramids and tracking."""
    cache = PyramidCache(levels, max(c.win_px for c in calls))
    out, t_pyr, t_trk = [], 0.0, 0.0
    for c in calls:
        t0 = time.process_time()
        prev, cur = cache(c.prev), cache(c.cur)
        t1 = time.process_time()
        out.append(lk_track(prev, cur, c.pts, c.start, c.levels, c.win_px, c.max_iters, c.eps_px))
        t_pyr, t_trk = t_pyr + t1 - t0, t_trk + time.process_time() - t1
    return out, t_pyr, t_trk


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=",".join(SEQUENCES), help="sequences: " + ",".join(SEQUENCES))
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: the last)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    pin_one_cpu(args.cpu)
    print(f"OpenCV {cv2.__version__}, threads 1, one CPU; ms per frame, CPU time, median of {args.rounds} rounds")
    print(
        f"{'sequence':10s} {'method':12s} {'calls':>5s} {'pts':>5s} {'opencv':>7s} {'ours':>6s} "
        f"{'(pyr':>6s} {'track)':>6s} {'ratio':>6s} {'status =':>9s} {'|d| med px':>10s} {'p99':>7s}"
    )
    for key in args.only.split(","):
        name, method = SEQUENCES[key]
        calls, frames, levels = record(name, method)
        t_cv, t_pyr, t_trk = [], [], []
        for r in range(args.rounds):
            order = ("cv", "ours") if r % 2 == 0 else ("ours", "cv")
            for who in order:
                if who == "cv":
                    t0 = time.process_time()
                    ref = run_opencv(calls)
                    t_cv.append(time.process_time() - t0)
                else:
                    ours, tp, tt = run_ours(calls, levels)
                    t_pyr.append(tp)
                    t_trk.append(tt)
        agree = np.concatenate([a[1] == b[1] for a, b in zip(ref, ours, strict=True)])
        d = np.concatenate([np.linalg.norm(a[0] - b[0], axis=1)[a[1] & b[1]] for a, b in zip(ref, ours, strict=True)])
        ms = 1e3 / frames
        cv_ms, pyr_ms, trk_ms = np.median(t_cv) * ms, np.median(t_pyr) * ms, np.median(t_trk) * ms
        npts = int(np.median([len(c.pts) for c in calls]))
        print(
            f"{key:10s} {method:12s} {len(calls):5d} {npts:5d} {cv_ms:7.2f} {pyr_ms + trk_ms:6.2f} "
            f"{pyr_ms:6.2f} {trk_ms:6.2f} {cv_ms / (pyr_ms + trk_ms):5.1f}x {agree.mean():9.4f} "
            f"{np.median(d):10.1e} {np.percentile(d, 99):7.3f}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
