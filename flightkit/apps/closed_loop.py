"""Flying on the estimate: the simulated lab's autopilot fuses live VO instead of mocap.

:func:`fly_closed_loop` wires the whole loop in one process, over the same interfaces a lab uses:

1. the simulated lab (:class:`~flightkit.sim.lab.SimLab`) with its estimator set to fuse
   external vision (PX4: ``EKF2_EV_CTRL`` position + yaw, ``EKF2_HGT_REF`` vision; ArduPilot:
   ``VISO_TYPE`` and the ``EK3_SRC1_*`` sources = ExternalNav);
2. one bus session carrying the simulated mocap (published in the mocap frame, used **only to
   score** the flight and to give the VO its start pose) and the simulated camera (colour +
   depth), both from :class:`~flightkit.sim.publish.SimLabPublishers`;
3. :class:`~estimation.live.LiveVo` on those frames, publishing ``<ns>/odometry/<method>`` and
   feeding ``send_vision_pose`` over the real MAVLink link; it starts once the vehicle is
   airborne (the camera sits below the body's origin and cannot see the floor standing on it);
4. the flight runner flying the plan with :class:`~flightkit.mocap.telemetry_source.TelemetryPoseSource`
   as its position feedback (the autopilot's own, VO-fused estimate) and the controller in
   ``local_ned`` output mode.

After landing it scores the flight against mocap: tracking error of the pattern (reference vs
where mocap saw the vehicle), VO drift (position and yaw), how far the autopilot's estimate
departed from the truth, VO frame counts and the vision message rate; it writes TUM files of
the VO estimate and of mocap and a top-view PNG. ``flightkit demo --closed-loop`` calls it::

    cfg, plan = load_config("examples/lab_sim.toml"), load_plan("examples/circle.toml")
    report = asyncio.run(fly_closed_loop(cfg, plan, "out/closed_loop"))
    print(report.format())
"""

from __future__ import annotations

import asyncio
import bisect
import dataclasses
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, Clock, SimClock
from flightkit.config import Autopilot, LabConfig, LinkBackend
from flightkit.errors import DatasetError
from flightkit.frames import Transform, angle_diff_rad
from flightkit.link.base import ExternalPoseKind

if TYPE_CHECKING:
    from flightkit.datasets.trajectory import Trajectory

__all__ = ["ClosedLoopReport", "fly_closed_loop", "vision_fusion_params"]

logger = logging.getLogger(__name__)

_AIRBORNE_M = 0.3


def vision_fusion_params(autopilot: Autopilot) -> dict[str, float]:
    """Autopilot parameters that make the estimator fuse external vision position and yaw."""
    if autopilot is Autopilot.PX4:
        # EKF2_EV_CTRL bits: 0 horizontal position, 1 vertical position, 3 yaw; height from vision
        return {"EKF2_EV_CTRL": 11.0, "EKF2_HGT_REF": 3.0}
    return {"VISO_TYPE": 1.0, "EK3_SRC1_POSXY": 6.0, "EK3_SRC1_POSZ": 6.0, "EK3_SRC1_YAW": 6.0}


@dataclass(slots=True)
class ClosedLoopReport:
    """What a closed-loop flight measured (positions in metres, world frame).

    Attributes:
        autopilot, method: what flew and which VO fed it.
        outcome: the flight summary's outcome (``completed`` when it went to plan).
        tracking_rms_m, tracking_max_m: pattern phase, reference vs the mocap position.
        tracking_est_rms_m: pattern phase, reference vs the autopilot's estimate (what the
            controller saw).
        vo_final_err_m, vo_max_err_m, vo_rms_err_m: VO body position vs mocap while airborne.
        vo_final_yaw_err_deg, vo_max_yaw_err_deg: VO heading vs mocap.
        vo_path_m: distance flown while the VO estimated (for drift per metre).
        ap_final_err_m, ap_max_err_m: the autopilot's position estimate vs the truth, from
            the moment it fused vision (it follows the VO, drift included).
        ap_vs_vo_rms_m: RMS distance between the autopilot's estimate and the newest VO
            estimate while fusing (small: the autopilot flies on the VO).
        fusion_events: the simulator's ``vision`` events (``"fusing"``, ``"stopped"``).
        vo: LiveVo counters. files: what was written (name -> path).
        summary: the runner's flight summary.
    """

    autopilot: str
    method: str
    outcome: str = "failed"
    laps: int = 0
    duration_s: float = math.nan
    tracking_rms_m: float = math.nan
    tracking_max_m: float = math.nan
    tracking_est_rms_m: float = math.nan
    vo_final_err_m: float = math.nan
    vo_max_err_m: float = math.nan
    vo_rms_err_m: float = math.nan
    vo_final_yaw_err_deg: float = math.nan
    vo_max_yaw_err_deg: float = math.nan
    vo_path_m: float = math.nan
    ap_final_err_m: float = math.nan
    ap_max_err_m: float = math.nan
    ap_vs_vo_rms_m: float = math.nan
    fusion_events: list[str] = field(default_factory=list)
    vo: Any = None
    files: dict[str, str] = field(default_factory=dict)
    summary: Any = None
    camera: str = ""

    @property
    def fused_vision(self) -> bool:
        """The autopilot reported fusing vision during the flight."""
        return "fusing" in self.fusion_events

    @property
    def ok(self) -> bool:
        """The flight completed without faults and the autopilot fused vision."""
        faults = getattr(self.summary, "faults", [])
        return self.outcome == "completed" and not faults and self.fused_vision

    @property
    def drift_pct(self) -> float:
        """Final VO position error as a percentage of the distance flown."""
        return 100.0 * self.vo_final_err_m / self.vo_path_m if self.vo_path_m > 0 else math.nan

    def format(self) -> str:
        """A printable multi-line summary."""
        vo = self.vo
        lines = [
            f"closed loop: {self.autopilot} flying on {self.method} VO ({self.camera}); "
            f"outcome {self.outcome}, {self.laps} lap(s), {self.duration_s:.1f} s",
            f"  tracking vs mocap (pattern):   RMS {self.tracking_rms_m:.3f} m, "
            f"max {self.tracking_max_m:.3f} m "
            f"(vs the autopilot's estimate: RMS {self.tracking_est_rms_m:.3f} m)",
            f"  VO drift vs mocap:             final {self.vo_final_err_m:.3f} m "
            f"({self.drift_pct:.2f} % of {self.vo_path_m:.1f} m), max {self.vo_max_err_m:.3f} m, "
            f"RMS {self.vo_rms_err_m:.3f} m; yaw final {self.vo_final_yaw_err_deg:.2f} deg, "
            f"max {self.vo_max_yaw_err_deg:.2f} deg",
            f"  autopilot estimate vs truth:   final {self.ap_final_err_m:.3f} m, "
            f"max {self.ap_max_err_m:.3f} m "
            f"(vs the VO: RMS {self.ap_vs_vo_rms_m:.3f} m; "
            f"vision fusion: {', '.join(self.fusion_events) or 'never'})",
        ]
        if vo is not None:
            lines.append(f"  {vo.format()}")
        faults = getattr(self.summary, "faults", [])
        for f in faults:
            lines.append(f"  fault at t={f.time_s:.1f} s: {f.kind.value}: {f.message}")
        for name, path in self.files.items():
            lines.append(f"  {name}: {path}")
        lines.append("  result: " + ("OK" if self.ok else "NOT OK"))
        return "\n".join(lines)


# ----------------------------------------------------------------------------- helpers


class _PoseHistory:
    """Mocap poses by stamp, for the VO's start pose and for scoring (thread-safe: the VO
    thread looks poses up while the event loop adds them)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.stamps_ns: list[int] = []
        self.poses: list[Transform] = []

    def add(self, stamp_ns: int, T: Transform) -> None:  # noqa: N803
        with self._lock:
            if not self.stamps_ns or stamp_ns > self.stamps_ns[-1]:
                self.stamps_ns.append(int(stamp_ns))
                self.poses.append(T)

    def at(self, stamp_ns: int, max_gap_ns: int = 50_000_000) -> Transform | None:
        """The pose at ``stamp_ns`` (position interpolated between neighbours), or None when
        no pose lies within ``max_gap_ns``."""
        with self._lock:
            s = self.stamps_ns
            if not s:
                return None
            i = bisect.bisect_left(s, stamp_ns)
            if i == 0 or i == len(s):
                j = 0 if i == 0 else len(s) - 1
                return self.poses[j] if abs(s[j] - stamp_ns) <= max_gap_ns else None
            a, b = s[i - 1], s[i]
            Ta, Tb = self.poses[i - 1], self.poses[i]  # noqa: N806
        if b - a > 2 * max_gap_ns:
            return None
        w = (stamp_ns - a) / (b - a)
        near = Ta if w < 0.5 else Tb
        return Transform(near.rotation, (1 - w) * Ta.translation + w * Tb.translation)

    def trajectory(self) -> Trajectory:
        from flightkit.datasets.trajectory import Trajectory

        return Trajectory.from_transforms(self.stamps_ns, self.poses, name="mocap")


def _rms(x: npt.NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else math.nan


def _plot(
    path: Path,
    ref_xy: npt.NDArray[np.float64],
    mocap_xy: npt.NDArray[np.float64],
    vo_xy: npt.NDArray[np.float64],
    title: str,
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 6.0))
    try:
        if len(ref_xy):
            ax.plot(ref_xy[:, 0], ref_xy[:, 1], "k--", lw=1.0, label="reference")
        if len(mocap_xy):
            ax.plot(mocap_xy[:, 0], mocap_xy[:, 1], color="tab:blue", lw=1.2, label="mocap (flown)")
        if len(vo_xy):
            ax.plot(
                vo_xy[:, 0], vo_xy[:, 1], color="tab:orange", lw=1.0, label="VO estimate (fed to autopilot)"
            )
        ax.set_aspect("equal")
        ax.set_xlabel("x [m] (world, east)")
        ax.set_ylabel("y [m] (world, north)")
        ax.set_title(title, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)
    return path


# ----------------------------------------------------------------------------- the flight


async def fly_closed_loop(
    lab_cfg: LabConfig,
    plan: Any,
    out_dir: str | Path,
    *,
    speed: float = 1.0,
    autopilot: Autopilot | str | None = None,
    backend: LinkBackend | str | None = None,
    method: str = "rgbd-pnp",
    width_px: int | None = 320,
    height_px: int | None = 240,
    camera_rate_hz: float | None = 15.0,
    vision_rate_hz: float = 30.0,
    kind: ExternalPoseKind = ExternalPoseKind.VISION_POSITION_ESTIMATE,
    vo_start_height_m: float = 0.5,
    clock: Clock | None = None,
    progress: Callable[[str], None] | None = print,
    on_status: Callable[[Any], None] | None = None,
) -> ClosedLoopReport:
    """Fly ``plan`` in the simulated lab with the autopilot fusing live VO; blocks until landed.

    Args:
        lab_cfg: the lab (``vehicle``, ``link.backend``, ``mocap`` body and calibration,
            ``bus``, ``camera`` extrinsics and intrinsics, ``sim``).
        plan: a :class:`trajectories.plan.Plan`; its controller is switched to ``local_ned``.
        out_dir: where the flight log, the TUM files and the plot go (created).
        speed: simulated seconds per wall second at most; the lab slows down when the host
            cannot render or estimate a frame within half a frame period of simulated time.
        autopilot / backend: override the config's.
        method: VO method (one that uses depth).
        width_px, height_px, camera_rate_hz: camera overrides (None keeps the config's);
            320x240 at 15 Hz keeps real time on two cores.
        vision_rate_hz: most vision messages per second (<= 50).
        kind: VISION_POSITION_ESTIMATE or ODOMETRY.
        vo_start_height_m: the VO starts (from the mocap pose) once mocap sees the body this high.
        clock: defaults to ``SimClock(speed)``.
        progress: called with one line per step (None: quiet).
        on_status: the runner's live status callback.

    Returns:
        The report (``report.ok`` says whether it went to plan).

    Raises:
        SafetyAbort: a preflight check failed. LinkError / BusError: the set-up failed.
    """
    from estimation.live import LiveVo
    from estimation.live_config import LiveVoConfig
    from flightkit.bus.keys import Keys
    from flightkit.bus.session import open_session
    from flightkit.bus.streams import CameraStreamSelection
    from flightkit.frames import WorldFrames
    from flightkit.link import open_link
    from flightkit.mocap.bus_source import BusMocapSource
    from flightkit.mocap.telemetry_source import TelemetryPoseSource
    from flightkit.sim.autopilot import AutopilotOptions
    from flightkit.sim.lab import SimEvent, SimLab
    from flightkit.sim.publish import SimLabPublishers
    from trajectories.controller import OutputFrame
    from trajectories.flightlog import read_flight_log
    from trajectories.fly import fly_plan

    say = progress or (lambda _s: None)
    out = Path(out_dir)
    await asyncio.to_thread(out.mkdir, parents=True, exist_ok=True)

    # ---- configuration
    cfg = lab_cfg
    if autopilot is not None:
        cfg = dataclasses.replace(
            cfg, vehicle=dataclasses.replace(cfg.vehicle, autopilot=Autopilot(autopilot))
        )
    if backend is not None:
        cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, backend=LinkBackend(backend)))
    cam = cfg.camera
    cam = dataclasses.replace(
        cam,
        width_px=width_px or cam.width_px,
        height_px=height_px or cam.height_px,
        rate_hz=camera_rate_hz or cam.rate_hz,
    )
    cfg = dataclasses.replace(cfg, camera=cam, sim=dataclasses.replace(cfg.sim, speed=float(speed)))
    ap = cfg.vehicle.autopilot
    plan = plan.with_lab_defaults(cfg)
    plan = plan.with_changes(
        controller=dataclasses.replace(plan.controller, output_frame=OutputFrame.LOCAL_NED)
    )
    # the simulated onboard computer keeps up with the camera: rendering a frame and estimating
    # it take at most half a frame period of simulated time each, however loaded the host is
    frame_budget_s = 0.5 / cam.rate_hz
    live_cfg = LiveVoConfig(method=method, vision_rate_hz=vision_rate_hz, kind=kind, compute_budget_s=frame_budget_s)
    keys = Keys(cfg.vehicle.namespace)
    body = cfg.mocap.body
    clock = clock or SimClock(float(speed), max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
    report = ClosedLoopReport(
        ap.value, method, camera=f"{cam.width_px}x{cam.height_px} at {cam.rate_hz:g} Hz"
    )

    # ---- the lab
    lab = SimLab(
        cfg,
        url="udpin:127.0.0.1:0",
        clock=clock,
        options=AutopilotOptions(params=vision_fusion_params(ap)),
        ready_after_s=0.0,
    )
    fusion: list[tuple[float, str]] = []

    def on_event(e: SimEvent) -> None:
        if e.kind == "vision":
            fusion.append((e.stamp_s, e.detail))

    lab.events.append(on_event)
    lab.start()
    cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, url=lab.client_url))
    say(f"simulated {lab.personality.vehicle_name} on {lab.url}; estimator set to fuse vision ({ap.value})")

    session = open_session(cfg.bus)
    pubs = None
    history = _PoseHistory()
    ap_err: list[tuple[float, float]] = []  # (|autopilot estimate - truth|, |estimate - VO|) while fusing
    log_path = out / "closed_loop_flight.csv"
    try:
        streams = CameraStreamSelection(color=True, depth=True, stereo=False, tf=False)
        pubs = SimLabPublishers(
            lab, cfg, session, camera=True, streams=streams, render_budget_s=frame_budget_s
        ).start()
        say(f"bus: mocap (scoring only) and camera {cam.width_px}x{cam.height_px} at {cam.rate_hz:g} Hz on "
            f"{', '.join(pubs.keys)}")
        mocap = BusMocapSource(session, keys, clock, WorldFrames(cfg.mocap.T_world_mocap.to_transform()))
        link = open_link(cfg.link, ap, clock)
        async with mocap, link:
            feedback = TelemetryPoseSource(link, clock, body)
            vo = LiveVo(
                session,
                keys,
                clock,
                T_body_camera=cam.T_body_camera.to_transform(),
                link=link,
                config=live_cfg,
            )
            async with feedback, vo, asyncio.TaskGroup() as tg:

                async def record_mocap() -> None:
                    async for p in mocap.poses(body):
                        if p.valid:
                            history.add(p.stamp_ns, p.T_world_body)

                async def start_vo() -> None:
                    while True:
                        p = mocap.latest(body)
                        if p is not None and p.valid and p.T_world_body.translation[2] >= vo_start_height_m:
                            break
                        await clock.sleep(0.05)
                    vo.start(lambda stamp_ns: history.at(stamp_ns))
                    say(f"airborne at {p.T_world_body.translation[2]:.2f} m: VO starts from the mocap pose")

                async def watch_estimate() -> None:
                    while True:
                        await clock.sleep(0.1)
                        if lab.autopilot.vision_fusion_active:
                            # vision poses are sent in world coordinates: the fused local frame is the world
                            est = lab.autopilot.estimate_local_enu_m()
                            latest = vo.latest
                            to_vo = (
                                math.nan
                                if latest is None
                                else float(np.linalg.norm(est - latest.T_world_body[:3, 3]))
                            )
                            ap_err.append((float(np.linalg.norm(est - lab.truth().pos_enu_m)), to_vo))

                tasks = [
                    tg.create_task(record_mocap()),
                    tg.create_task(start_vo()),
                    tg.create_task(watch_estimate()),
                ]
                try:
                    summary = await fly_plan(
                        plan,
                        cfg,
                        link=link,
                        mocap=feedback,
                        clock=clock,
                        arm=True,
                        log_path=log_path,
                        on_status=on_status,
                    )
                finally:
                    for t in tasks:
                        t.cancel()
            report.vo = vo.stats()
            vo_est = vo.estimates()
    finally:
        if pubs is not None:
            pubs.stop()
        session.close()
        lab.stop()

    report.summary = summary
    report.outcome = summary.outcome
    report.laps = summary.laps_completed
    report.duration_s = summary.duration_s
    report.fusion_events = [d for _t, d in fusion]
    await asyncio.to_thread(_score, report, history, vo_est, ap_err, log_path, read_flight_log, out, plan)
    return report


def _score(
    report: ClosedLoopReport,
    history: _PoseHistory,
    vo_est: list[tuple[int, Transform]],
    ap_err: list[tuple[float, float]],
    log_path: Path,
    read_flight_log: Callable[[Path], Any],
    out: Path,
    plan: Any,
) -> None:
    from flightkit.datasets.trajectory import Trajectory, write_tum

    report.files["flight log"] = str(log_path)
    mocap_traj = history.trajectory()
    if len(mocap_traj):
        report.files["mocap TUM"] = str(
            write_tum(
                out / "closed_loop_mocap.tum", mocap_traj, header="flightkit closed loop: mocap T_world_body"
            )
        )
    if vo_est:
        vo_traj = Trajectory.from_transforms([s for s, _ in vo_est], [T for _, T in vo_est], name="vo")
        report.files["VO TUM"] = str(
            write_tum(
                out / "closed_loop_vo.tum",
                vo_traj,
                header=f"flightkit closed loop: {report.method} T_world_body",
            )
        )

    # VO vs mocap, while airborne
    errs: list[float] = []
    yaw_errs: list[float] = []
    pos_vo: list[npt.NDArray[np.float64]] = []
    for stamp, T in vo_est:
        gt = history.at(stamp)
        if gt is None or gt.translation[2] < _AIRBORNE_M:
            continue
        errs.append(float(np.linalg.norm(T.translation - gt.translation)))
        yaw_errs.append(abs(math.degrees(angle_diff_rad(T.yaw_rad, gt.yaw_rad))))
        pos_vo.append(gt.translation)
    if errs:
        e = np.asarray(errs)
        report.vo_final_err_m, report.vo_max_err_m, report.vo_rms_err_m = (
            float(e[-1]),
            float(e.max()),
            _rms(e),
        )
        report.vo_final_yaw_err_deg, report.vo_max_yaw_err_deg = yaw_errs[-1], max(yaw_errs)
        p = np.asarray(pos_vo)
        report.vo_path_m = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0
    if ap_err:
        a = np.asarray([x for x, _ in ap_err])
        report.ap_final_err_m, report.ap_max_err_m = float(a[-1]), float(a.max())
        v = np.asarray([y for _, y in ap_err])
        report.ap_vs_vo_rms_m = _rms(v[np.isfinite(v)])

    # tracking: the pattern phase of the flight log, reference vs mocap at each cycle's stamp
    ref_xy = np.zeros((0, 2))
    try:
        log = read_flight_log(log_path)
    except (OSError, DatasetError):
        log = None
    if log is not None and len(log):
        sel = log["phase"] == "pattern"
        stamps = log["stamp_ns"][sel].astype(np.int64)
        ref = np.column_stack([log["ref_x_m"][sel], log["ref_y_m"][sel], log["ref_z_m"][sel]])
        est = np.column_stack([log["pos_x_m"][sel], log["pos_y_m"][sel], log["pos_z_m"][sel]])
        ref_xy = ref[:, :2]
        track: list[float] = []
        for s, r in zip(stamps, ref, strict=True):
            gt = history.at(int(s))
            if gt is not None and np.all(np.isfinite(r)):
                track.append(float(np.linalg.norm(gt.translation - r)))
        if track:
            t = np.asarray(track)
            report.tracking_rms_m, report.tracking_max_m = _rms(t), float(t.max())
        ok = np.all(np.isfinite(ref), axis=1) & np.all(np.isfinite(est), axis=1)
        if np.any(ok):
            report.tracking_est_rms_m = _rms(np.linalg.norm(est[ok] - ref[ok], axis=1))

    mocap_xy = mocap_traj.positions[:, :2] if len(mocap_traj) else np.zeros((0, 2))
    mocap_xy = mocap_xy[mocap_traj.positions[:, 2] >= _AIRBORNE_M] if len(mocap_traj) else mocap_xy
    vo_xy = np.asarray([T.translation[:2] for _, T in vo_est]) if vo_est else np.zeros((0, 2))
    try:
        report.files["plot"] = str(
            _plot(
                out / "closed_loop_topview.png",
                ref_xy,
                mocap_xy,
                vo_xy,
                f"{plan.name}: {report.autopilot} flying on {report.method} VO "
                f"(drift {report.vo_final_err_m:.3f} m, tracking RMS {report.tracking_rms_m:.3f} m)",
            )
        )
    except Exception:  # a plot must not lose the figures
        logger.exception("closed-loop plot failed")
