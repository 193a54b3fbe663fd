"""Per-stage timing of a VO pipeline: a timer to fill per frame, and the table it summarises into.

API::

    timer = StageTimer()                       # one per run
    for frame in seq.frames():
        with timer.frame():                    # "total" = the whole frame
            with timer.stage("features"):
                ...
            with timer.stage("3d"):
                ...
            with timer.stage("motion"):
                ...
    table = timer.table()                      # TimingTable
    table.rows                                 # [StageTiming(name, mean_ms, median_ms, p95_ms, max_ms, count, share)]
    table.to_dict(); table.format()            # JSON-friendly / plain-text table

Stage names are free; the usual ones are :data:`STAGE_FEATURES`, :data:`STAGE_3D`,
:data:`STAGE_MOTION`; ``total`` is the time of the ``frame()`` block (so stages that are not
timed show up as ``total`` minus the sum of the stages). Times come from
``time.perf_counter_ns`` (monotonic). Not thread-safe: one timer per pipeline thread.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from flightkit.errors import EstimationError

__all__ = [
    "STAGE_3D",
    "STAGE_FEATURES",
    "STAGE_MOTION",
    "STAGE_TOTAL",
    "StageTimer",
    "StageTiming",
    "TimingTable",
]

STAGE_FEATURES = "features"
STAGE_3D = "3d"
STAGE_MOTION = "motion"
STAGE_TOTAL = "total"


@dataclass(frozen=True, slots=True)
class StageTiming:
    """Statistics of one stage over the frames it ran in (milliseconds).

    Attributes:
        share: mean time of this stage as a fraction of the mean total frame time.
    """

    name: str
    mean_ms: float
    median_ms: float
    p95_ms: float
    max_ms: float
    count: int
    share: float


@dataclass(frozen=True, slots=True)
class TimingTable:
    """The summary of a :class:`StageTimer`: one row per stage (in first-seen order), total last."""

    rows: tuple[StageTiming, ...]
    frames: int

    @property
    def total(self) -> StageTiming | None:
        return next((r for r in self.rows if r.name == STAGE_TOTAL), None)

    @property
    def fps(self) -> float:
        """Frames per second the timed work alone would sustain (1000 / mean total ms)."""
        total = self.total
        return 1000.0 / total.mean_ms if total and total.mean_ms > 0 else float("nan")

    @staticmethod
    def from_stage_ms(stage_ms: Mapping[str, npt.ArrayLike], frames: int | None = None) -> TimingTable:
        """Build the table from per-frame millisecond series, e.g. ``VoResult.stage_ms``
        (``{"features": (N,), ..., "total": (N,)}``); empty series are left out."""
        return _table_from_stage_ms(stage_ms, frames)

    def row(self, name: str) -> StageTiming:
        for r in self.rows:
            if r.name == name:
                return r
        raise EstimationError(f"no timing stage {name!r}; stages are {[r.name for r in self.rows]}")

    def to_dict(self) -> dict[str, object]:
        return {
            "frames": self.frames,
            "stages": {
                r.name: {
                    "mean_ms": r.mean_ms,
                    "median_ms": r.median_ms,
                    "p95_ms": r.p95_ms,
                    "max_ms": r.max_ms,
                    "count": r.count,
                    "share": r.share,
                }
                for r in self.rows
            },
        }

    def format(self) -> str:
        """A plain-text table (for logs; the CLI renders the same rows with rich)."""
        head = f"{'stage':<12}{'mean ms':>10}{'median':>10}{'p95':>10}{'max':>10}{'count':>8}{'share':>8}"
        lines = [head, "-" * len(head)]
        for r in self.rows:
            lines.append(
                f"{r.name:<12}{r.mean_ms:>10.2f}{r.median_ms:>10.2f}{r.p95_ms:>10.2f}{r.max_ms:>10.2f}"
                f"{r.count:>8d}{r.share * 100:>7.0f}%"
            )
        return "\n".join(lines)


class StageTimer:
    """Accumulates wall time per named stage and per frame (see the module docstring)."""

    def __init__(self) -> None:
        self._samples: dict[str, list[int]] = {}
        self._frames = 0
        self._in_frame = False
        self._frame_marks: dict[str, int] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name`` (a stage may run several times per frame; they add up
        per frame when inside :meth:`frame`)."""
        if name == STAGE_TOTAL:
            raise EstimationError(f"stage name {STAGE_TOTAL!r} is reserved for frame(); pick another")
        t0 = time.perf_counter_ns()
        try:
            yield
        finally:
            self.add(name, time.perf_counter_ns() - t0)

    @contextmanager
    def frame(self) -> Iterator[None]:
        """Time one frame (the ``total`` row)."""
        if self._in_frame:
            raise EstimationError("StageTimer.frame() blocks cannot nest")
        self._in_frame = True
        self._frame_marks = {k: len(v) for k, v in self._samples.items()}
        t0 = time.perf_counter_ns()
        try:
            yield
        finally:
            self._in_frame = False
            self._merge_frame_samples()
            self._samples.setdefault(STAGE_TOTAL, []).append(time.perf_counter_ns() - t0)
            self._frames += 1

    def _merge_frame_samples(self) -> None:
        # Several runs of one stage within a frame count as one sample (their sum).
        for name, values in self._samples.items():
            start = self._frame_marks.get(name, 0)
            if len(values) - start > 1:
                values[start:] = [sum(values[start:])]

    def add(self, name: str, duration_ns: int) -> None:
        """Record a duration measured elsewhere (e.g. on a worker thread)."""
        self._samples.setdefault(name, []).append(int(duration_ns))

    @property
    def frames(self) -> int:
        return self._frames

    def table(self) -> TimingTable:
        """Summarise everything recorded so far.

        Raises:
            EstimationError: nothing was timed.
        """
        if not self._samples:
            raise EstimationError("no timings recorded; wrap the work in timer.frame()/timer.stage()")
        stage_ms = {k: np.asarray(v, dtype=np.float64) / 1e6 for k, v in self._samples.items()}
        return TimingTable.from_stage_ms(stage_ms, self._frames)


def _table_from_stage_ms(stage_ms: Mapping[str, npt.ArrayLike], frames: int | None = None) -> TimingTable:
    series = {k: np.asarray(v, dtype=np.float64).reshape(-1) for k, v in stage_ms.items()}
    series = {k: v for k, v in series.items() if v.size}
    if not series:
        raise EstimationError("no timings recorded; every stage series is empty")
    total = series.get(STAGE_TOTAL)
    total_mean = float(np.mean(total)) if total is not None else 0.0
    names = [n for n in series if n != STAGE_TOTAL] + ([STAGE_TOTAL] if total is not None else [])
    rows = []
    for name in names:
        ms = series[name]
        mean = float(ms.mean())
        rows.append(
            StageTiming(
                name=name,
                mean_ms=mean,
                median_ms=float(np.median(ms)),
                p95_ms=float(np.percentile(ms, 95)),
                max_ms=float(ms.max()),
                count=int(ms.size),
                share=mean / total_mean if total_mean > 0 else float("nan"),
            )
        )
    if frames is None:
        frames = int(total.size) if total is not None else max(v.size for v in series.values())
    n = frames
    return TimingTable(tuple(rows), n)
