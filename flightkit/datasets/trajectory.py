"""Timestamped pose trajectories and their file formats (TUM, KITTI).

API::

    traj = read_tum("groundtruth.txt")              # "t tx ty tz qx qy qz qw" rows, '#' comments
    traj.stamps_ns      # int64 (N,), nanoseconds (parsed exactly from the decimal text)
    traj.positions      # float64 (N, 3), metres, position of the body/camera in the world
    traj.quats_wxyz     # float64 (N, 4), unit quaternions, orientation of the body/camera
    traj.transforms()   # list[Transform] T_world_x;  traj.as_matrices() -> (N, 4, 4)
    write_tum("est.txt", traj)
    read_kitti_poses("00.txt", stamps_ns=None)      # 3x4 row-major rows; stamps = times.txt or index
    idx_a, idx_b = associate(a.stamps_ns, b.stamps_ns, max_diff_ns=10_000_000)
    a_sync, b_sync = associate_trajectories(a, b, max_diff_s=0.01)
    traj.interpolate(stamps_ns)                     # linear position + slerp orientation

Association follows TUM's ``associate.py`` as implemented in evo (``evo.core.sync``): each pose
of the shorter trajectory is matched with the nearest-in-time pose of the longer one when
the difference is at most ``max_diff``; poses without a partner are dropped.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from flightkit.errors import DatasetError
from flightkit.frames import Transform, quat_wxyz_to_xyzw, quat_xyzw_to_wxyz

__all__ = [
    "Trajectory",
    "associate",
    "associate_trajectories",
    "parse_stamp_ns",
    "read_kitti_poses",
    "read_trajectory",
    "read_tum",
    "write_kitti_poses",
    "write_tum",
]

logger = logging.getLogger(__name__)

_NS_PER_S = 1_000_000_000


def parse_stamp_ns(text: str) -> int:
    """Seconds written in decimal (``"1305031102.2159"``, ``"1.4037e+09"``) -> exact integer ns.

    Raises:
        DatasetError: not a finite decimal number.
    """
    try:
        value = Decimal(text)
    except InvalidOperation as exc:
        raise DatasetError(f"time {text!r} is not a number; write seconds in decimal, e.g. 1305031102.2159") from exc
    if not value.is_finite():
        raise DatasetError(f"time {text!r} is not a finite number; write seconds in decimal, e.g. 1305031102.2159")
    return int((value * _NS_PER_S).to_integral_value())


@dataclass(frozen=True, slots=True, eq=False)
class Trajectory:
    """A sequence of timestamped poses ``T_world_x`` (x: camera or body).

    Attributes:
        stamps_ns: int64 (N,), nanoseconds (any epoch; an index-only file uses 0, 1, 2 ... s).
        positions: float64 (N, 3), metres, position of x in the world frame.
        quats_wxyz: float64 (N, 4), unit quaternions w, x, y, z (normalised on creation).
        name: label for tables and plots.

    The arrays are owned by the trajectory (copied on creation); treat them as read-only.
    """

    stamps_ns: npt.NDArray[np.int64]
    positions: npt.NDArray[np.float64]
    quats_wxyz: npt.NDArray[np.float64]
    name: str = ""

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_ns)
        if stamps.dtype.kind not in "iu":
            raise DatasetError(
                f"trajectory stamps_ns must be integers (nanoseconds), got dtype {stamps.dtype}; "
                "convert seconds with np.round(t_s * 1e9).astype(np.int64)"
            )
        stamps = stamps.astype(np.int64).reshape(-1)
        n = stamps.shape[0]
        pos = np.array(self.positions, dtype=np.float64).reshape(-1, 3) if n else np.zeros((0, 3))
        quat = np.array(self.quats_wxyz, dtype=np.float64).reshape(-1, 4) if n else np.zeros((0, 4))
        if pos.shape != (n, 3) or quat.shape != (n, 4):
            raise DatasetError(
                f"trajectory {self.name!r} has {n} stamps, positions of shape {pos.shape} and "
                f"quaternions of shape {quat.shape}; they must be (N,), (N, 3) and (N, 4)"
            )
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
            raise DatasetError(f"trajectory {self.name!r} holds non-finite positions or quaternions")
        norms = np.linalg.norm(quat, axis=1)
        if n and float(norms.min()) < 1e-6:
            bad = int(np.argmin(norms))
            raise DatasetError(f"trajectory {self.name!r} pose {bad} has a zero quaternion {quat[bad]}")
        quat = quat / norms[:, None]
        object.__setattr__(self, "stamps_ns", stamps)
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "quats_wxyz", quat)

    # ------------------------------------------------------------------ construction
    @staticmethod
    def from_matrices(stamps_ns: npt.ArrayLike, matrices: npt.ArrayLike, name: str = "") -> Trajectory:
        """From (N, 4, 4) or (N, 3, 4) homogeneous matrices ``T_world_x``."""
        m = np.asarray(matrices, dtype=np.float64)
        if m.ndim != 3 or m.shape[1:] not in ((4, 4), (3, 4)):
            raise DatasetError(f"expected (N, 4, 4) or (N, 3, 4) pose matrices, got shape {m.shape}")
        if m.shape[0] == 0:
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)), name)
        quats = quat_xyzw_to_wxyz(Rotation.from_matrix(m[:, :3, :3]).as_quat())
        return Trajectory(np.asarray(stamps_ns, dtype=np.int64), m[:, :3, 3], quats, name)

    @staticmethod
    def from_transforms(
        stamps_ns: npt.ArrayLike, transforms: Iterable[Transform], name: str = ""
    ) -> Trajectory:
        """From a list of :class:`~flightkit.frames.Transform` ``T_world_x``."""
        ts = list(transforms)
        if not ts:
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)), name)
        pos = np.array([t.translation for t in ts])
        quats = np.array([t.quat_wxyz for t in ts])
        return Trajectory(np.asarray(stamps_ns, dtype=np.int64), pos, quats, name)

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    @property
    def stamps_s(self) -> npt.NDArray[np.float64]:
        return self.stamps_ns.astype(np.float64) * 1e-9

    @property
    def rotations(self) -> Rotation:
        """All orientations as one scipy Rotation (R_world_x)."""
        return Rotation.from_quat(quat_wxyz_to_xyzw(self.quats_wxyz))

    def as_matrices(self) -> npt.NDArray[np.float64]:
        """(N, 4, 4) homogeneous matrices ``T_world_x``."""
        out = np.zeros((len(self), 4, 4))
        if len(self):
            out[:, :3, :3] = self.rotations.as_matrix()
        out[:, :3, 3] = self.positions
        out[:, 3, 3] = 1.0
        return out

    def transform(self, i: int) -> Transform:
        """Pose ``i`` as a Transform ``T_world_x``."""
        return Transform.from_quat_wxyz(self.positions[i], self.quats_wxyz[i])

    def transforms(self) -> list[Transform]:
        return [self.transform(i) for i in range(len(self))]

    def subset(self, indices: npt.ArrayLike) -> Trajectory:
        idx = np.asarray(indices, dtype=np.int64)
        return Trajectory(self.stamps_ns[idx], self.positions[idx], self.quats_wxyz[idx], self.name)

    def renamed(self, name: str) -> Trajectory:
        return Trajectory(self.stamps_ns, self.positions, self.quats_wxyz, name)

    def path_length_m(self) -> float:
        """Length of the polyline through the positions."""
        if len(self) < 2:
            return 0.0
        return float(np.sum(np.linalg.norm(np.diff(self.positions, axis=0), axis=1)))

    def duration_s(self) -> float:
        if len(self) < 2:
            return 0.0
        return float(self.stamps_ns[-1] - self.stamps_ns[0]) * 1e-9

    # ------------------------------------------------------------------ transformation
    def left_multiplied(self, T_new_world: Transform | npt.ArrayLike, scale: float = 1.0) -> Trajectory:  # noqa: N803
        """Express the trajectory in another frame: ``T_new_x = T_new_world @ (s * T_world_x)``.

        ``scale`` multiplies the positions first (the Sim(3) alignment of a monocular estimate).
        """
        T = T_new_world if isinstance(T_new_world, Transform) else Transform.from_matrix(T_new_world)  # noqa: N806
        pos = T.rotation.apply(self.positions * scale) + T.translation if len(self) else self.positions
        rot = T.rotation * self.rotations if len(self) else None
        quats = quat_xyzw_to_wxyz(rot.as_quat()) if rot is not None else self.quats_wxyz
        return Trajectory(self.stamps_ns, pos, quats, self.name)

    def right_multiplied(self, T_x_y: Transform) -> Trajectory:  # noqa: N803
        """Change the tracked frame: ``T_world_y = T_world_x @ T_x_y`` for every pose."""
        if not len(self):
            return self
        rot = self.rotations
        pos = rot.apply(T_x_y.translation) + self.positions
        quats = quat_xyzw_to_wxyz((rot * T_x_y.rotation).as_quat())
        return Trajectory(self.stamps_ns, pos, quats, self.name)

    def relative_to_first(self) -> Trajectory:
        """The same motion starting at the identity: ``T_0^-1 @ T_i``."""
        if not len(self):
            return self
        return self.left_multiplied(self.transform(0).inverse())

    def interpolate(self, stamps_ns: npt.ArrayLike) -> Trajectory:
        """Poses at ``stamps_ns`` (linear in position, slerp in orientation).

        Raises:
            DatasetError: a requested stamp lies outside the trajectory's time span, or the
                trajectory's stamps are not strictly increasing.
        """
        query = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if len(self) < 2:
            raise DatasetError(f"cannot interpolate trajectory {self.name!r} with {len(self)} pose(s)")
        if np.any(np.diff(self.stamps_ns) <= 0):
            raise DatasetError(
                f"cannot interpolate trajectory {self.name!r}: its stamps are not strictly increasing"
            )
        lo, hi = int(self.stamps_ns[0]), int(self.stamps_ns[-1])
        if query.size and (int(query.min()) < lo or int(query.max()) > hi):
            raise DatasetError(
                f"cannot interpolate trajectory {self.name!r} at {query.min() * 1e-9:.6f}.."
                f"{query.max() * 1e-9:.6f} s: it spans {lo * 1e-9:.6f}..{hi * 1e-9:.6f} s; "
                "select stamps inside that span first"
            )
        # Work relative to the first stamp so float64 keeps sub-nanosecond resolution.
        t_rel = (self.stamps_ns - lo).astype(np.float64)
        q_rel = (query - lo).astype(np.float64)
        pos = np.column_stack([np.interp(q_rel, t_rel, self.positions[:, k]) for k in range(3)])
        rot = Slerp(t_rel, self.rotations)(q_rel)
        return Trajectory(query, pos, quat_xyzw_to_wxyz(rot.as_quat()), self.name)


# ---------------------------------------------------------------------- association
def associate(
    stamps_a_ns: npt.ArrayLike, stamps_b_ns: npt.ArrayLike, max_diff_ns: int = 10_000_000
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Match two stamp lists by nearest time (evo's ``matching_time_indices`` on the shorter list).

    Each stamp of the list with fewer entries gets the nearest stamp of the other list when
    ``|difference| <= max_diff_ns`` (ties go to the earlier stamp); others are dropped. A stamp
    of the longer list can be matched more than once, as in evo.

    Returns:
        ``(indices_a, indices_b)``, equal length, in the order of the shorter list.
    """
    a = np.asarray(stamps_a_ns, dtype=np.int64).reshape(-1)
    b = np.asarray(stamps_b_ns, dtype=np.int64).reshape(-1)
    if a.size == 0 or b.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    b_longer = b.size > a.size
    short, long_ = (a, b) if b_longer else (b, a)
    idx_short, idx_long = _match_nearest(short, long_, int(max_diff_ns))
    return (idx_short, idx_long) if b_longer else (idx_long, idx_short)


def _match_nearest(
    short: npt.NDArray[np.int64], long_: npt.NDArray[np.int64], max_diff: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    if np.any(np.diff(long_) < 0):
        diffs = np.abs(long_[None, :] - short[:, None])
        best = np.argmin(diffs, axis=1)
        ok = diffs[np.arange(short.size), best] <= max_diff
        return np.nonzero(ok)[0].astype(np.int64), best[ok].astype(np.int64)
    upper = np.searchsorted(long_, short, side="right")
    upper = np.minimum(upper, long_.size - 1)
    lower = upper - 1
    diff_ub = long_[upper] - short
    diff_lb = np.where(lower >= 0, short - long_[np.maximum(lower, 0)], np.iinfo(np.int64).max)
    take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    in_range = (short >= long_[0] - max_diff) & (short <= long_[-1] + max_diff)
    take_ub &= in_range
    take_lb &= in_range
    keep = take_ub | take_lb
    best = np.where(take_ub, upper, lower)
    return np.nonzero(keep)[0].astype(np.int64), best[keep].astype(np.int64)


def associate_trajectories(
    a: Trajectory, b: Trajectory, max_diff_s: float = 0.01
) -> tuple[Trajectory, Trajectory]:
    """Reduce two trajectories to their time-matched poses (see :func:`associate`).

    Raises:
        DatasetError: no pose pair lies within ``max_diff_s``.
    """
    ia, ib = associate(a.stamps_ns, b.stamps_ns, round(max_diff_s * _NS_PER_S))
    if ia.size == 0:
        span_a = f"{a.stamps_ns[0] * 1e-9:.3f}..{a.stamps_ns[-1] * 1e-9:.3f} s" if len(a) else "empty"
        span_b = f"{b.stamps_ns[0] * 1e-9:.3f}..{b.stamps_ns[-1] * 1e-9:.3f} s" if len(b) else "empty"
        raise DatasetError(
            f"no poses of {a.name or 'the first trajectory'} ({span_a}) and "
            f"{b.name or 'the second trajectory'} ({span_b}) are within {max_diff_s} s of each other; "
            "check that both use the same clock or raise the maximum time difference"
        )
    logger.debug("associated %d of %d/%d poses (max diff %.4f s)", ia.size, len(a), len(b), max_diff_s)
    return a.subset(ia), b.subset(ib)


# ---------------------------------------------------------------------- TUM files
def _data_lines(path: Path) -> Iterable[tuple[int, list[str]]]:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError as exc:
        raise DatasetError(f"trajectory file {path} does not exist; check the path") from exc
    except OSError as exc:
        raise DatasetError(f"cannot read trajectory file {path}: {exc.strerror}") from exc
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#") or line.startswith("%"):
            continue
        yield lineno, line.replace(",", " ").split()


def read_tum(path: str | os.PathLike[str], name: str | None = None) -> Trajectory:
    """Read a TUM trajectory file: ``timestamp tx ty tz qx qy qz qw`` per line.

    Comment lines start with ``#``; commas are accepted as separators.

    Raises:
        DatasetError: missing file, or a line that is not 8 numbers (names file and line).
    """
    p = Path(path)
    stamps: list[int] = []
    values: list[list[float]] = []
    for lineno, parts in _data_lines(p):
        if len(parts) != 8:
            raise DatasetError(
                f"{p}:{lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(parts)}; "
                "is this a TUM trajectory file?"
            )
        try:
            stamps.append(parse_stamp_ns(parts[0]))
            values.append([float(v) for v in parts[1:]])
        except (ValueError, DatasetError) as exc:
            raise DatasetError(f"{p}:{lineno}: {exc}; every value must be a number") from exc
    if not stamps:
        raise DatasetError(f"trajectory file {p} holds no poses; is it empty or all comments?")
    arr = np.array(values)
    quats = quat_xyzw_to_wxyz(arr[:, 3:7])
    try:
        return Trajectory(np.array(stamps, dtype=np.int64), arr[:, :3], quats, name or p.stem)
    except DatasetError as exc:
        raise DatasetError(f"{p}: {exc}") from exc


def _format_stamp(stamp_ns: int) -> str:
    sign = "-" if stamp_ns < 0 else ""
    s, ns = divmod(abs(int(stamp_ns)), _NS_PER_S)
    return f"{sign}{s}.{ns:09d}"


def write_tum(path: str | os.PathLike[str], trajectory: Trajectory, header: str | None = None) -> Path:
    """Write a TUM trajectory file (stamps with 9 decimals, exact to the nanosecond).

    Returns:
        The path written.
    """
    p = Path(path)
    lines = [f"# {header}" if header else "# timestamp tx ty tz qx qy qz qw"]
    q_xyzw = quat_wxyz_to_xyzw(trajectory.quats_wxyz)
    for stamp, pos, q in zip(trajectory.stamps_ns, trajectory.positions, q_xyzw, strict=True):
        lines.append(
            f"{_format_stamp(int(stamp))} {pos[0]:.9f} {pos[1]:.9f} {pos[2]:.9f} "
            f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"
        )
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


# ---------------------------------------------------------------------- KITTI files
def read_kitti_times(path: str | os.PathLike[str]) -> npt.NDArray[np.int64]:
    """Read a KITTI ``times.txt`` (one time in seconds per line) into int64 nanoseconds."""
    p = Path(path)
    stamps: list[int] = []
    for lineno, parts in _data_lines(p):
        try:
            stamps.append(parse_stamp_ns(parts[0]))
        except DatasetError as exc:
            raise DatasetError(f"{p}:{lineno}: {exc}; times.txt holds one time in seconds per line") from exc
    return np.array(stamps, dtype=np.int64)


def read_kitti_poses(
    path: str | os.PathLike[str],
    stamps_ns: npt.ArrayLike | None = None,
    times_path: str | os.PathLike[str] | None = None,
    name: str | None = None,
) -> Trajectory:
    """Read a KITTI pose file: 12 numbers per line, the row-major 3x4 matrix ``[R | t]``.

    Stamps come from ``stamps_ns``, else from ``times_path`` (KITTI ``times.txt``), else are the
    line index in seconds (0, 1, 2 ... s) so index-based association pairs line i with line i.

    Raises:
        DatasetError: missing file, a malformed line, or a stamp count that differs from the
            pose count.
    """
    p = Path(path)
    rows: list[list[float]] = []
    for lineno, parts in _data_lines(p):
        if len(parts) != 12:
            raise DatasetError(
                f"{p}:{lineno}: expected 12 values (a row-major 3x4 pose), got {len(parts)}; "
                "is this a KITTI pose file?"
            )
        try:
            rows.append([float(v) for v in parts])
        except ValueError as exc:
            raise DatasetError(f"{p}:{lineno}: {exc}; every value must be a number") from exc
    if not rows:
        raise DatasetError(f"KITTI pose file {p} holds no poses; is it empty?")
    mats = np.array(rows).reshape(-1, 3, 4)
    if stamps_ns is not None:
        stamps = np.asarray(stamps_ns, dtype=np.int64)
    elif times_path is not None:
        stamps = read_kitti_times(times_path)
    else:
        stamps = np.arange(len(rows), dtype=np.int64) * _NS_PER_S
    if stamps.shape[0] != mats.shape[0]:
        raise DatasetError(
            f"{p} has {mats.shape[0]} poses but {stamps.shape[0]} stamps were given"
            f"{f' ({times_path})' if times_path else ''}; use the times file of the same sequence"
        )
    # Rotations in KITTI files are stored with ~7 digits; project them onto SO(3).
    _check_rotations(p, mats[:, :, :3])
    return Trajectory.from_matrices(stamps, mats, name or p.stem)


def _check_rotations(path: Path, rots: npt.NDArray[np.float64]) -> None:
    err = np.abs(np.einsum("nij,nkj->nik", rots, rots) - np.eye(3)).max(axis=(1, 2))
    bad = np.nonzero(err > 1e-2)[0]
    if bad.size:
        raise DatasetError(
            f"{path}: pose {int(bad[0])} has a rotation block that is not orthonormal "
            f"(|R R^T - I| = {err[bad[0]]:.3g}); is the file in KITTI 3x4 row-major format?"
        )


def write_kitti_poses(path: str | os.PathLike[str], trajectory: Trajectory) -> Path:
    """Write a KITTI pose file (12 numbers per line, no stamps)."""
    p = Path(path)
    mats = trajectory.as_matrices()[:, :3, :]
    lines = [" ".join(f"{v:.9e}" for v in m.reshape(-1)) for m in mats]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


def read_trajectory(
    path: str | os.PathLike[str], times_path: str | os.PathLike[str] | None = None
) -> Trajectory:
    """Read a TUM or a KITTI pose file, recognised by the number of values per line (8 or 12).

    Raises:
        DatasetError: unknown format (names the file, the first data line and its value count).
    """
    p = Path(path)
    for lineno, parts in _data_lines(p):
        if len(parts) == 8:
            return read_tum(p)
        if len(parts) == 12:
            return read_kitti_poses(p, times_path=times_path)
        raise DatasetError(
            f"{p}:{lineno}: a line of {len(parts)} values is neither TUM (8: t tx ty tz qx qy qz qw) "
            "nor KITTI (12: row-major 3x4 pose); convert the file to one of them"
        )
    raise DatasetError(f"trajectory file {p} holds no poses; is it empty or all comments?")
