"""Flight logs and summaries.

A flight log is a CSV file with one row per control cycle (:class:`LogRow`): time, phase, lap,
the reference, the mocap pose, the setpoint sent and the supervisor's action. Metadata (plan,
vehicle, controller) is a JSON comment on the first line and each fault a ``# fault {...}``
comment line, so the file opens in any spreadsheet or ``numpy.genfromtxt(comments="#")`` and is
read back with :func:`read_flight_log`.

:class:`FlightSummary` is what a flight returns: per-phase RMS and max tracking error,
duration, loop rate and faults; ``to_dict()`` gives the JSON summary.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from flightkit.errors import DatasetError, FlightkitError
from flightkit.frames import Vec3Tuple
from flightkit.link.base import VelocitySetpoint
from trajectories.base import Reference
from trajectories.supervisor import Action, Fault

__all__ = [
    "COLUMNS",
    "LATENCY_STAGES",
    "FlightLog",
    "FlightLogData",
    "FlightSummary",
    "LogRow",
    "PhaseStats",
    "read_flight_log",
]

LATENCY_STAGES = ("capture_to_bus", "bus_to_runner", "runner_to_setpoint")
"""The stages of a mocap sample's way to the setpoint computed from it: its capture stamp to the
bus (or to its arrival here, for a source in this process), the bus to this process, and its
arrival to the setpoint leaving (its age at the cycle plus the cycle)."""

COLUMNS = (
    "t_s", "stamp_ns", "phase", "lap", "action",
    "ref_x_m", "ref_y_m", "ref_z_m", "ref_yaw_rad", "ref_vx_m_s", "ref_vy_m_s", "ref_vz_m_s",
    "pos_x_m", "pos_y_m", "pos_z_m", "yaw_rad", "mocap_age_s",
    "sp_frame", "sp_vx_m_s", "sp_vy_m_s", "sp_vz_m_s", "sp_yaw_rad", "sp_yaw_rate_rad_s",
    "err_m", "cycle_s",
    "capture_to_bus_s", "bus_to_runner_s", "runner_to_setpoint_s",
)  # fmt: skip
_MAGIC = "# flightkit flight log v1 "


@dataclass(frozen=True, slots=True)
class LogRow:
    """One control cycle, as logged (:data:`trajectories.flightlog.COLUMNS`).

    Attributes:
        t_s: flight time. stamp_ns: clock time. phase / lap / action: what the cycle did.
        ref: the reference it tracked. pos_m / yaw_rad: the measured pose (world; None / NaN
        without one). mocap_age_s: age of that pose (-1 without one). setpoint: what was sent
        (or would have been, on a phase that only watches). err_m: tracking error (NaN when
        not measured). cycle_s / cycle_cpu_s: wall and CPU time of the cycle. stages_s: the
        pose's latency per :data:`~trajectories.flightlog.LATENCY_STAGES` stage (NaN when not known).
    """

    t_s: float
    stamp_ns: int
    phase: str
    lap: int
    action: Action
    ref: Reference
    pos_m: Vec3Tuple | None
    yaw_rad: float
    mocap_age_s: float
    setpoint: VelocitySetpoint
    err_m: float
    cycle_s: float
    cycle_cpu_s: float
    stages_s: tuple[float, float, float] = (math.nan, math.nan, math.nan)

    def values(self) -> tuple[object, ...]:
        """The row in :data:`~trajectories.flightlog.COLUMNS` order."""
        p = self.pos_m or (math.nan, math.nan, math.nan)
        sp = self.setpoint
        return (
            round(self.t_s, 6),
            self.stamp_ns,
            self.phase,
            self.ref.lap,
            self.action.name,
            *self.ref.pos_m,
            self.ref.yaw_rad,
            *self.ref.vel_m_s,
            *p,
            self.yaw_rad,
            self.mocap_age_s,
            sp.frame.value,
            *sp.vel_m_s,
            sp.yaw_rad if sp.yaw_rad is not None else math.nan,
            sp.yaw_rate_rad_s if sp.yaw_rate_rad_s is not None else math.nan,
            self.err_m,
            self.cycle_s,
            *self.stages_s,
        )


@dataclass(slots=True)
class PhaseStats:
    """Tracking statistics of one phase (accumulated online).

    Attributes:
        name: phase name ("takeoff", "hold", "pattern", ...).
        duration_s: time spent in the phase.
        samples: control cycles with a valid tracking error.
        rms_error_m / max_error_m: 3-D position error against the reference.
    """

    name: str
    duration_s: float = 0.0
    samples: int = 0
    sum_sq_m2: float = 0.0
    max_error_m: float = 0.0

    @property
    def rms_error_m(self) -> float:
        return math.sqrt(self.sum_sq_m2 / self.samples) if self.samples else math.nan

    def add(self, err_m: float) -> None:
        self.samples += 1
        self.sum_sq_m2 += err_m * err_m
        if err_m > self.max_error_m:
            self.max_error_m = err_m

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "duration_s": round(self.duration_s, 3),
            "samples": self.samples,
            "rms_error_m": _r(self.rms_error_m),
            "max_error_m": _r(self.max_error_m),
        }


def _r(x: float, nd: int = 4) -> float | None:
    return None if math.isnan(x) else round(x, nd)


@dataclass(slots=True)
class FlightSummary:
    """The end-of-flight summary.

    Attributes:
        plan: plan name.
        outcome: "completed", "landed_early" (a fault ended the pattern but we landed),
            "autopilot_landing" (handed to the autopilot's LAND), "released" (the pilot took
            over), "stopped" (link lost) or "failed" (an error before take-off).
        duration_s: flight time from the first command to the end.
        phases: statistics per phase, in flight order (repeated phases are merged by name).
        faults: every fault, in order of detection.
        laps_completed: laps of the pattern flown to the end.
        loop_rate_hz: control cycles per second inside the phases; cycle_p50_ms / cycle_p99_ms:
            wall time per cycle (from reading the pose to handing the setpoint to the link); cycle_cpu_p50_ms /
            cycle_cpu_p99_ms: the loop thread's CPU time per cycle, i.e. the same without the
            time spent waiting for the GIL, the scheduler or a hypervisor that took the CPU.
        latency_p50_ms / latency_p99_ms: from a mocap sample reaching this process to the setpoint
            computed from it leaving (the sample's age at the cycle plus the cycle), per cycle.
        stage_latency_ms: (p50, p99) per :data:`LATENCY_STAGES` stage with samples, and ``total``
            (capture stamp to setpoint).
        log_path: the flight log file (None when not logging).
        companion_loss: what the autopilot would have done had flightkit stopped (the preflight's
            one line, from its failsafe parameters; empty when not checked).
    """

    plan: str
    outcome: str = "completed"
    duration_s: float = 0.0
    phases: list[PhaseStats] = field(default_factory=list)
    faults: list[Fault] = field(default_factory=list)
    laps_completed: int = 0
    loop_rate_hz: float = math.nan
    cycle_p50_ms: float = math.nan
    cycle_p99_ms: float = math.nan
    cycle_cpu_p50_ms: float = math.nan
    cycle_cpu_p99_ms: float = math.nan
    latency_p50_ms: float = math.nan
    latency_p99_ms: float = math.nan
    stage_latency_ms: dict[str, tuple[float, float]] = field(default_factory=dict)
    log_path: str | None = None
    companion_loss: str = ""

    def phase(self, name: str) -> PhaseStats:
        """The stats of phase ``name`` (KeyError if it was not flown)."""
        for p in self.phases:
            if p.name == name:
                return p
        raise KeyError(f"phase {name!r} was not flown (phases: {', '.join(p.name for p in self.phases)})")

    @property
    def ok(self) -> bool:
        return self.outcome == "completed" and not self.faults

    def to_dict(self) -> dict[str, Any]:
        return {
            "plan": self.plan,
            "outcome": self.outcome,
            "duration_s": round(self.duration_s, 3),
            "laps_completed": self.laps_completed,
            "loop_rate_hz": _r(self.loop_rate_hz, 1),
            "cycle_p50_ms": _r(self.cycle_p50_ms, 4),
            "cycle_p99_ms": _r(self.cycle_p99_ms, 4),
            "cycle_cpu_p50_ms": _r(self.cycle_cpu_p50_ms, 4),
            "cycle_cpu_p99_ms": _r(self.cycle_cpu_p99_ms, 4),
            "latency_p50_ms": _r(self.latency_p50_ms, 3),
            "latency_p99_ms": _r(self.latency_p99_ms, 3),
            "stage_latency_ms": {k: {"p50": _r(v[0], 3), "p99": _r(v[1], 3)} for k, v in self.stage_latency_ms.items()},
            "phases": [p.to_dict() for p in self.phases],
            "faults": [f.to_dict() for f in self.faults],
            "log_path": self.log_path,
            "companion_loss": self.companion_loss,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def format_table(self) -> str:
        """A plain-text table for terminals."""
        lines = [
            f"flight {self.plan!r}: {self.outcome}, {self.duration_s:.1f} s, "
            f"{self.laps_completed} lap(s), loop {self.loop_rate_hz:.0f} Hz "
            f"(cycle p50 {self.cycle_p50_ms:.3f} ms, p99 {self.cycle_p99_ms:.3f} ms)"
        ]
        if not math.isnan(self.latency_p50_ms):
            lines.append(
                f"  mocap sample to setpoint: p50 {self.latency_p50_ms:.1f} ms, p99 {self.latency_p99_ms:.1f} ms"
            )
        if self.stage_latency_ms:
            stages = self.stage_latency_ms.items()
            lines.append("  latency per stage, p50 / p99 ms: " + ", ".join(
                f"{name} {p50:.1f} / {p99:.1f}" for name, (p50, p99) in stages
            ))
        lines.append(f"  {'phase':<10} {'time s':>8} {'RMS err m':>10} {'max err m':>10}")
        for p in self.phases:
            lines.append(f"  {p.name:<10} {p.duration_s:>8.1f} {p.rms_error_m:>10.4f} {p.max_error_m:>10.4f}")
        if self.faults:
            lines.append("  faults:")
            lines.extend(f"    t={f.time_s:7.2f} s  {f.kind.value:<18} {f.message}" for f in self.faults)
        else:
            lines.append("  faults: none")
        if self.companion_loss:
            lines.append(f"  {self.companion_loss}")
        if self.log_path:
            lines.append(f"  log: {self.log_path}")
        return "\n".join(lines)


class FlightLog:
    """Writes the per-cycle CSV log. Rows are buffered in memory and flushed every second of rows.

    Args:
        path: file to create (its folder is created); refuses to overwrite an existing file.
        meta: JSON-serialisable metadata written on the first line.
    """

    def __init__(self, path: str | Path, meta: dict[str, Any] | None = None, flush_every: int = 200) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fh: TextIO = self.path.open("x", encoding="utf-8", newline="")
        except FileExistsError:
            raise FlightkitError(
                f"flight log {self.path} exists; give another --log path or remove the old log"
            ) from None
        except OSError as exc:
            raise FlightkitError(f"cannot create flight log {self.path}: {exc.strerror}; check the folder") from exc
        self._fh.write(_MAGIC + json.dumps(meta or {}) + "\n")
        self._fh.write(",".join(COLUMNS) + "\n")
        self._buf = io.StringIO()
        self._rows = 0
        self._flush_every = flush_every

    def row(self, values: tuple[Any, ...]) -> None:
        """Append one row (values in :data:`COLUMNS` order); returns immediately."""
        self._buf.write(",".join(_fmt(v) for v in values))
        self._buf.write("\n")
        self._rows += 1
        if self._rows % self._flush_every == 0:
            self.flush()

    def fault(self, fault: Fault) -> None:
        self._buf.write("# fault " + json.dumps(fault.to_dict()) + "\n")

    def flush(self) -> None:
        if self._fh.closed:
            return
        self._fh.write(self._buf.getvalue())
        self._buf = io.StringIO()
        self._fh.flush()

    def close(self, summary: FlightSummary | None = None) -> None:
        if self._fh.closed:
            return
        if summary is not None:
            self._buf.write("# summary " + json.dumps(summary.to_dict()) + "\n")
        self.flush()
        self._fh.close()

    @property
    def rows(self) -> int:
        return self._rows


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.6g}" if abs(v) >= 1e4 else f"{v:.6f}"
    return str(v)


@dataclass(frozen=True, slots=True)
class FlightLogData:
    """A flight log read back.

    Attributes:
        meta: the metadata line.
        columns: numeric columns by name (shape (N,)); ``phase``, ``action`` and ``sp_frame`` are strings.
        faults: fault records (dicts as written).
        summary: the summary written at the end (empty if the flight did not finish cleanly).
    """

    meta: dict[str, Any]
    columns: dict[str, npt.NDArray[Any]]
    faults: list[dict[str, Any]]
    summary: dict[str, Any]

    def __getitem__(self, name: str) -> npt.NDArray[Any]:
        return self.columns[name]

    def __len__(self) -> int:
        return len(self.columns["t_s"])


_STR_COLS = {"phase", "action", "sp_frame"}


def read_flight_log(path: str | Path) -> FlightLogData:
    """Read a flight log written by :class:`FlightLog`.

    Raises:
        FileNotFoundError: no such file. DatasetError: not a flightkit flight log, or a malformed one.
    """
    meta: dict[str, Any] = {}
    faults: list[dict[str, Any]] = []
    summary: dict[str, Any] = {}
    rows: list[list[str]] = []
    header: list[str] = []
    with Path(path).open(encoding="utf-8") as fh:
        first = fh.readline()
        if not first.startswith(_MAGIC):
            raise DatasetError(
                f"{path} is not a flightkit flight log (first line {first[:40]!r}); "
                "give a log written by flightkit fly or sim (--log)"
            )
        try:
            meta = json.loads(first[len(_MAGIC) :])
            for line in fh:
                if line.startswith("# fault "):
                    faults.append(json.loads(line[8:]))
                elif line.startswith("# summary "):
                    summary = json.loads(line[10:])
                elif not header:
                    header = line.rstrip("\n").split(",")
                elif line.strip():
                    rows.append(line.rstrip("\n").split(","))
        except ValueError as exc:  # json.JSONDecodeError
            raise DatasetError(f"{path}: a metadata line is not valid JSON ({exc}); is the log truncated?") from exc
    cols: dict[str, npt.NDArray[Any]] = {}
    try:
        for i, name in enumerate(header):
            vals = [r[i] for r in rows]
            cols[name] = np.array(vals, dtype=object if name in _STR_COLS else np.float64)
    except (ValueError, IndexError) as exc:
        raise DatasetError(f"{path}: a row does not match the header ({exc}); is the log truncated?") from exc
    return FlightLogData(meta, cols, faults, summary)
