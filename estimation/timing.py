"""Per-stage timing of a VO pipeline: the table its per-frame stage times summarise into.

API::

    table = TimingTable.from_stage_ms(result.stage_ms)   # {"features": (N,), ..., "total": (N,)} ms
    table.rows                                 # [StageTiming(name, mean_ms, median_ms, p95_ms, max_ms, count, share)]
    table.to_dict(); table.format()            # JSON-friendly / plain-text table

Stage names are free; the usual ones are :data:`STAGE_FEATURES`, :data:`STAGE_3D`,
:data:`STAGE_MOTION`; ``total`` is the time of the whole frame (so stages that are not
timed show up as ``total`` minus the sum of the stages). The pipeline measures the times.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from flightkit.errors import EstimationError

__all__ = [
    "STAGE_3D",
    "STAGE_FEATURES",
    "STAGE_MOTION",
    "STAGE_TOTAL",
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
    """The summary of per-frame stage times: one row per stage (in first-seen order), total last."""

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
