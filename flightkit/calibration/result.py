"""A calibration's result: JSON file, and the metadata record a recording carries.

:class:`CalibrationResult` holds what ``flightkit calibrate time`` and ``calibrate handeye``
measure -- the camera's time offset (ms, with its uncertainty) and drift (ppm) against the mocap,
the estimated ``T_body_camera`` with its residuals, and how far it is from the configured one
(metres and degrees). It is written as a JSON document (:meth:`CalibrationResult.write_json`)
and as a recording metadata record (:meth:`CalibrationResult.to_metadata`, a str -> str map
named :data:`METADATA_RECORD`, which :meth:`flightkit.datasets.mcap_reader.RecordingReader.calibration`
returns with the other ``calibration*`` records). Transforms are stored as the recorder stores
its extrinsics: ``{"translation_m": [x, y, z], "quat_xyzw": [x, y, z, w]}``.

Time convention: ``camera stamp - mocap stamp = offset + drift * (t - ref)`` for one instant
(see :mod:`flightkit.calibration.time_offset`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from flightkit.errors import CalibrationError
from flightkit.frames import Transform

__all__ = ["METADATA_RECORD", "SCHEMA", "CalibrationResult", "transform_difference"]

METADATA_RECORD = "calibration.time_extrinsics"
"""Name of the recording metadata record a calibration is stored under."""

SCHEMA = "flightkit.calibration/1"


def _t_to_obj(T: Transform) -> dict[str, list[float]]:  # noqa: N803
    return {"translation_m": [float(v) for v in T.translation], "quat_xyzw": [float(v) for v in T.quat_xyzw]}


def _t_from_obj(obj: Any, what: str) -> Transform:
    try:
        return Transform.from_quat_xyzw(obj["translation_m"], obj["quat_xyzw"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"the calibration's {what} is malformed ({exc}); re-run the calibration", what) from exc


def transform_difference(a: Transform, b: Transform) -> tuple[float, float]:
    """(translation distance in m, rotation angle in deg) between two transforms."""
    return (
        float(math.dist(a.translation, b.translation)),
        math.degrees(float((a.rotation.inv() * b.rotation).magnitude())),
    )


@dataclass(frozen=True, slots=True)
class CalibrationResult:
    """A time and extrinsics calibration (see the module docstring). Absent parts are None.

    Attributes:
        time_offset_ms: camera stamp minus mocap stamp of one instant at ``ref_ns``, ms.
        time_offset_uncertainty_ms: one standard deviation, ms.
        drift_ppm: how much faster the camera clock runs than the mocap's, ppm.
        drift_uncertainty_ppm: one standard deviation, ppm.
        drift_estimated: False when the recording was too short for a drift (then 0).
        ref_ns: mocap time the offset refers to.
        correlation: how well the aligned rotation rates agree (1 = identical).
        T_body_camera: the estimated camera mount (camera OpenCV in body FLU).
        residual_m, residual_deg: RMS residuals of the hand-eye fit.
        pairs: relative motions used by the hand-eye fit.
        configured_T_body_camera: the mount the config (or the recording) said.
        source: what was calibrated (recording path, topics, VO method), free-form strings.
    """

    time_offset_ms: float | None = None
    time_offset_uncertainty_ms: float | None = None
    drift_ppm: float | None = None
    drift_uncertainty_ppm: float | None = None
    drift_estimated: bool = False
    ref_ns: int | None = None
    correlation: float | None = None
    T_body_camera: Transform | None = None
    residual_m: float | None = None
    residual_deg: float | None = None
    pairs: int | None = None
    configured_T_body_camera: Transform | None = None
    source: dict[str, str] = field(default_factory=dict)

    # ------------------------------------------------------------------ derived

    @property
    def difference_to_configured(self) -> tuple[float, float] | None:
        """(m, deg) between the estimated and the configured ``T_body_camera``; None without both."""
        if self.T_body_camera is None or self.configured_T_body_camera is None:
            return None
        return transform_difference(self.T_body_camera, self.configured_T_body_camera)

    def mocap_to_camera_ns(self, stamps_ns: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """Mocap stamps moved onto the camera's clock (int64 ns): ``t + offset + drift * (t - ref)``.

        Raises:
            CalibrationError: the result has no time offset.
        """
        if self.time_offset_ms is None:
            raise CalibrationError("this calibration has no time offset; run 'flightkit calibrate time'", "time offset")
        t = np.asarray(stamps_ns, dtype=np.int64)
        ref = self.ref_ns if self.ref_ns is not None else int(t[0]) if t.size else 0
        shift = self.time_offset_ms * 1e6 + (self.drift_ppm or 0.0) * 1e-6 * (t - ref).astype(np.float64)
        return np.asarray(t + np.round(shift).astype(np.int64), dtype=np.int64)

    def merged(self, other: CalibrationResult) -> CalibrationResult:
        """This result with every part ``other`` has replaced by ``other``'s (e.g. a time result
        plus a hand-eye result)."""
        updates = {
            f.name: getattr(other, f.name)
            for f in dataclasses.fields(other)
            if f.name != "source" and getattr(other, f.name) is not None and f.name != "drift_estimated"
        }
        if other.time_offset_ms is not None:
            updates["drift_estimated"] = other.drift_estimated
        return dataclasses.replace(self, **updates, source={**self.source, **other.source})

    # ------------------------------------------------------------------ JSON

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (the document ``--json`` prints and :meth:`write_json` writes)."""
        out: dict[str, Any] = {"schema": SCHEMA}
        if self.time_offset_ms is not None:
            out["time"] = {
                "offset_ms": self.time_offset_ms,
                "offset_uncertainty_ms": self.time_offset_uncertainty_ms,
                "drift_ppm": self.drift_ppm,
                "drift_uncertainty_ppm": self.drift_uncertainty_ppm,
                "drift_estimated": self.drift_estimated,
                "ref_ns": self.ref_ns,
                "correlation": self.correlation,
                "convention": "camera stamp - mocap stamp = offset + drift * (t - ref)",
            }
        if self.T_body_camera is not None:
            he: dict[str, Any] = {
                "T_body_camera": _t_to_obj(self.T_body_camera),
                "residual_m": self.residual_m,
                "residual_deg": self.residual_deg,
                "pairs": self.pairs,
            }
            diff = self.difference_to_configured
            if diff is not None:
                he["difference_to_configured"] = {"translation_m": diff[0], "rotation_deg": diff[1]}
            out["handeye"] = he
        if self.configured_T_body_camera is not None:
            out["configured_T_body_camera"] = _t_to_obj(self.configured_T_body_camera)
        if self.source:
            out["source"] = dict(self.source)
        return out

    @staticmethod
    def from_dict(data: Any) -> CalibrationResult:
        """The inverse of :meth:`to_dict`.

        Raises:
            CalibrationError: not a calibration document, or a malformed field.
        """
        schema = data.get("schema") if isinstance(data, dict) else None
        if not isinstance(data, dict) or schema != SCHEMA:
            raise CalibrationError(
                f"not a flightkit calibration document (schema {schema!r}, "
                f"expected {SCHEMA!r}); write it with 'flightkit calibrate ... --write'",
                "calibration",
            )
        kw: dict[str, Any] = {}
        try:
            if (t := data.get("time")) is not None:
                kw.update(
                    time_offset_ms=float(t["offset_ms"]),
                    time_offset_uncertainty_ms=_opt_float(t.get("offset_uncertainty_ms")),
                    drift_ppm=_opt_float(t.get("drift_ppm")),
                    drift_uncertainty_ppm=_opt_float(t.get("drift_uncertainty_ppm")),
                    drift_estimated=bool(t.get("drift_estimated", False)),
                    ref_ns=None if t.get("ref_ns") is None else int(t["ref_ns"]),
                    correlation=_opt_float(t.get("correlation")),
                )
            if (h := data.get("handeye")) is not None:
                kw.update(
                    T_body_camera=_t_from_obj(h["T_body_camera"], "T_body_camera"),
                    residual_m=_opt_float(h.get("residual_m")),
                    residual_deg=_opt_float(h.get("residual_deg")),
                    pairs=None if h.get("pairs") is None else int(h["pairs"]),
                )
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"a calibration field is malformed ({exc!r}); re-run the calibration",
                                   "calibration") from exc
        if (c := data.get("configured_T_body_camera")) is not None:
            kw["configured_T_body_camera"] = _t_from_obj(c, "configured_T_body_camera")
        kw["source"] = {str(k): str(v) for k, v in (data.get("source") or {}).items()}
        return CalibrationResult(**kw)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @staticmethod
    def from_json(text: str) -> CalibrationResult:
        """Parse :meth:`to_json` text.

        Raises:
            CalibrationError: not JSON or not a calibration document.
        """
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise CalibrationError(f"a calibration file is not JSON ({exc})", "calibration") from exc
        return CalibrationResult.from_dict(data)

    def write_json(self, path: str | os.PathLike[str]) -> Path:
        """Write the JSON document to ``path`` (replacing it); returns the path."""
        p = Path(path)
        p.write_text(self.to_json() + "\n", encoding="utf-8")
        return p

    @staticmethod
    def read_json(path: str | os.PathLike[str]) -> CalibrationResult:
        """Read a file written by :meth:`write_json`.

        Raises:
            CalibrationError: missing, unreadable or malformed file.
        """
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise CalibrationError(f"cannot read calibration file {path}: {exc.strerror}; check the path",
                                   "calibration") from exc
        return CalibrationResult.from_json(text)

    # ------------------------------------------------------------------ recording metadata

    def to_metadata(self) -> dict[str, str]:
        """The record stored in a recording (str -> str; named :data:`METADATA_RECORD`)."""
        out = {"schema": SCHEMA}
        doc = self.to_dict()
        for key in ("time", "handeye", "configured_T_body_camera", "source"):
            if key in doc:
                out[key] = json.dumps(doc[key], sort_keys=True)
        if self.time_offset_ms is not None:
            out["time_offset_ms"] = repr(self.time_offset_ms)
        if self.T_body_camera is not None:
            out["T_body_camera"] = json.dumps(_t_to_obj(self.T_body_camera))
        return out

    @staticmethod
    def from_metadata(record: dict[str, str]) -> CalibrationResult:
        """The inverse of :meth:`to_metadata`.

        Raises:
            CalibrationError: a malformed record.
        """
        try:
            doc: dict[str, Any] = {"schema": record.get("schema")}
            for key in ("time", "handeye", "configured_T_body_camera", "source"):
                if key in record:
                    doc[key] = json.loads(record[key])
        except ValueError as exc:
            raise CalibrationError(f"the recording's {METADATA_RECORD} record is malformed ({exc})",
                                   "calibration") from exc
        return CalibrationResult.from_dict(doc)


def _opt_float(v: Any) -> float | None:
    return None if v is None else float(v)
