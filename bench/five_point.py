"""Benchmark of the compiled 5-point RANSAC (``estimation.five_point.find_essential``) beside
OpenCV's ``findEssentialMat`` (RANSAC, the same confidence and threshold) on the calls
``rgbd-essential`` makes on the real RGB-D sequences, one core.

Every essential-matrix RANSAC of an ``rgbd-essential`` run (native resolution, started at the
first ground-truth pose) is recorded; then both run on the recorded calls, interleaved, ``--rounds``
times. Prints per sequence: the calls, ms per call of each (CPU time, median of the rounds), the
ratio, and how many calls give OpenCV's inlier set exactly (and the largest difference of the
matrices, up to sign, where the sets agree).

Run: .venv/bin/python bench/five_point.py [--only tum_rpy,7scenes] [--rounds 5] [--cpu N]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import estimation.essential as essential  # noqa: E402
from bench._host import pin_one_cpu  # noqa: E402
from estimation.five_point import find_essential  # noqa: E402
from estimation.pipeline import run_vo, warm_up  # noqa: E402
from flightkit.datasets.registry import open_sequence  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEQUENCES = {
    "tum_rpy": "tum_fr1rpy_000_199",
    "7scenes": "sevenscenes_tsdf50",
    "tum_case1": "tum_fr1xyz_pairs/case_1",
    "tum_case2": "tum_fr1xyz_pairs/case_2",
}

Call = tuple[np.ndarray, np.ndarray, np.ndarray, float, float]


def record(folder: str) -> list[Call]:
    """The RANSAC calls of one ``rgbd-essential`` run (the run itself uses OpenCV here)."""
    calls: list[Call] = []

    def opencv(px_ref: Any, px_cur: Any, K: Any, threshold_px: float = 1.0, confidence: float = 0.999) -> Any:
        calls.append((px_ref.copy(), px_cur.copy(), np.array(K), threshold_px, confidence))
        E, mask = cv2.findEssentialMat(px_ref, px_cur, K, method=cv2.RANSAC, prob=confidence, threshold=threshold_px)
        return (None if E is None else E[:3]), (np.zeros(len(px_ref), bool) if mask is None else mask.ravel() > 0)

    compiled = essential.find_essential
    essential.find_essential = opencv
    try:
        run_vo(open_sequence(DATA / folder), "rgbd-essential", init_from_groundtruth=True)
    finally:
        essential.find_essential = compiled
    return calls


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=",".join(SEQUENCES), help="comma-separated sequence keys")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--cpu", type=int, help="the CPU to pin the process to (default: the last one)")
    args = ap.parse_args()
    pin_one_cpu(args.cpu)
    cv2.setNumThreads(1)
    warm_up("rgbd-essential")
    print(f"OpenCV {cv2.__version__}, one thread, one CPU; median of {args.rounds} interleaved rounds")
    print(
        f"{'sequence':10} {'calls':>5} {'OpenCV ms':>9} {'compiled ms':>11} {'ratio':>6} {'same inliers':>12} "
        f"{'max |dE|':>9}"
    )
    for key in args.only.split(","):
        calls = record(SEQUENCES[key])
        if not calls:
            print(f"{key:10} {0:5d}  (no RANSAC call: the prediction explained every frame)")
            continue
        t_cv: list[float] = []
        t_new: list[float] = []
        for _ in range(args.rounds):
            c = time.thread_time()
            ref = [cv2.findEssentialMat(a, b, K, method=cv2.RANSAC, prob=p, threshold=t) for a, b, K, t, p in calls]
            t_cv.append(time.thread_time() - c)
            c = time.thread_time()
            got = [find_essential(a, b, K, t, p) for a, b, K, t, p in calls]
            t_new.append(time.thread_time() - c)
        same, dE = 0, 0.0
        for (E_cv, m_cv), (E, m) in zip(ref, got, strict=True):
            if E_cv is None or E is None or not np.array_equal(m, m_cv.ravel() > 0):
                continue
            same += 1
            dE = max(dE, min(float(np.abs(E - E_cv[:3]).max()), float(np.abs(E + E_cv[:3]).max())))
        a, b = 1e3 * float(np.median(t_cv)) / len(calls), 1e3 * float(np.median(t_new)) / len(calls)
        print(f"{key:10} {len(calls):5d} {a:9.3f} {b:11.3f} {a / b:6.2f} {same:6d} of {len(calls):3d} {dE:9.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
