"""Export an MCAP recording to a TUM RGB-D or EuRoC (ASL) folder.

TUM RGB-D (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    OUT/rgb/<t>.png            colour, 8-bit (PNG)
    OUT/depth/<t>.png          depth, 16-bit PNG, 5000 units per metre, 0 = no data
    OUT/rgb.txt, depth.txt     "timestamp filename" per image, '#' header lines
    OUT/groundtruth.txt        "timestamp tx ty tz qx qy qz qw": the colour camera's optical
                               centre in the world (or mocap) frame, at the mocap stamps
    OUT/associations.txt       "t_rgb rgb/... t_depth depth/..." (TUM associate.py on rgb.txt, depth.txt)
    OUT/associations_gt.txt    "t_rgb rgb/... t_gt tx ty tz qx qy qz qw" (associate.py on rgb.txt, groundtruth.txt)
    OUT/camera.yaml            calibration (OpenCV FileStorage, ORB-SLAM style keys, DepthMapFactor 5000,
                               Camera.readout_s for a rolling shutter)

EuRoC / ASL::

    OUT/mav0/cam0/data/<ns>.png + data.csv + sensor.yaml   left (or colour as gray) camera, T_BS = T_body_camera,
                                                            readout_s for a rolling shutter
    OUT/mav0/cam1/...                                       right camera of a stereo recording
    OUT/mav0/state_groundtruth_estimate0/data.csv           body pose (17 columns as EuRoC)
    OUT/mav0/body.yaml

Timestamps are the header stamps (capture time), written exactly (9 decimals / integer ns).
A camera's rolling-shutter readout (its ``calibration.<camera>`` record) is written only when > 0,
so a global-shutter export is byte for byte what it was before readouts were recorded.
Association follows TUM's ``associate.py`` (:func:`flightkit.datasets.tum.tum_associate`).

Ground truth: the mocap body poses, placed in the **world** frame by the recording's own
``T_world_mocap`` (``frame="world"``, the default), or left in the mocap system's frame
(``frame="mocap"``, as TUM and EuRoC publish theirs); camera poses through the extrinsics,
``T_frame_camera = T_frame_body @ T_body_camera``. ``T_body_camera`` and ``T_world_mocap``
come from the arguments, else from the recording (its ``flightkit calibrate`` record first, whose
time offset also moves the ground truth onto the camera's clock). The recording is read through
:class:`~flightkit.datasets.mcap_reader.RecordingReader`; the folder formats are written by
:mod:`flightkit.datasets.tum` and :mod:`flightkit.datasets.euroc`.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.bus.image_msgs import CameraInfo
from flightkit.calibration.result import METADATA_RECORD, CalibrationResult
from flightkit.datasets.euroc import euroc_sensor_yaml, write_euroc_groundtruth
from flightkit.datasets.mcap_reader import DecodedImage, RecordingReader, decode_image
from flightkit.datasets.trajectory import Trajectory, write_tum
from flightkit.datasets.tum import to_tum_depth, tum_associate, write_tum_camera_yaml
from flightkit.errors import CaptureError, DatasetError
from flightkit.frames import MOCAP_FRAME_ID, WORLD_FRAME_ID, Transform, WorldFrames, quat_wxyz_to_xyzw

__all__ = ["ExportReport", "export_recording", "export_vehicles"]

logger = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]


@dataclass
class ExportReport:
    """What an export wrote.

    Attributes:
        images: main-camera images written; depth_images, right_images likewise.
        groundtruth_poses: rows of the ground-truth file.
        associated_depth: colour frames with a depth partner within ``max_diff_s``.
        associated_groundtruth: frames with a ground-truth pose within ``max_diff_s``.
        frame: the frame the ground truth is written in (``world`` or ``mocap``).
    """

    out_dir: Path
    fmt: str
    camera: str
    images: int = 0
    depth_images: int = 0
    right_images: int = 0
    groundtruth_poses: int = 0
    associated_depth: int = 0
    associated_groundtruth: int = 0
    max_diff_s: float = 0.02
    frame: str = WORLD_FRAME_ID
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        parts = [f"{self.images} {self.camera} images"]
        if self.depth_images:
            parts.append(f"{self.depth_images} depth ({self.associated_depth} associated)")
        if self.right_images:
            parts.append(f"{self.right_images} right")
        parts.append(
            f"{self.groundtruth_poses} ground-truth poses in the {self.frame} frame "
            f"({self.associated_groundtruth} frames matched)"
        )
        return f"{self.fmt} folder {self.out_dir}: " + ", ".join(parts)


@dataclass
class _Plan:
    main: str
    main_topic: str
    depth_topic: str | None
    right_topic: str | None
    infos: dict[str, CameraInfo]
    readouts_s: dict[str, float]  # camera -> rolling-shutter readout, s (0: global shutter)
    T_body_camera: Transform | None  # noqa: N815
    body_traj: Trajectory | None  # in the export frame
    counts: dict[str, int]


def _stamp_text(stamp_ns: int) -> str:
    s, ns = divmod(int(stamp_ns), 1_000_000_000)
    return f"{s}.{ns:09d}"


def _plan(
    rec: RecordingReader,
    fmt: str,
    camera: str | None,
    mocap_body: str | None,
    frames: WorldFrames,
    vehicle: str | None,
) -> _Plan:
    if vehicle is None:
        with_cameras = rec.camera_namespaces()
        if len(with_cameras) > 1:
            raise CaptureError(
                f"{rec.path} holds the cameras of {', '.join(with_cameras)}; export one vehicle (--vehicle) "
                "or all of them, one folder each (export_vehicles, the export command's default)"
            )
    elif vehicle not in rec.namespaces():
        raise CaptureError(f"{rec.path} has no vehicle {vehicle!r}; it has {', '.join(rec.namespaces()) or 'none'}")
    cams = rec.cameras(vehicle)
    images = {name: t["image"] for name, t in cams.items() if "image" in t}
    prefs = ("left", "color", "gray", "image", "infra1") if fmt == "euroc" else ("color", "left", "gray", "image")
    if camera is None:
        camera = next((c for c in prefs if c in images), None) or next(
            (c for c in sorted(images) if c not in ("depth", "right")), None
        )
    if camera is None or camera not in images:
        raise CaptureError(
            f"{rec.path} has no camera image stream{'' if camera is None else f' named {camera!r}'}; "
            f"it has {sorted(images) or 'none'} (topics …/camera/<name>/image)"
        )
    mocap = rec.mocap_topics(vehicle)
    calib = rec.calibration()
    if mocap_body is None and mocap:
        mocap_body = calib.mocap_body if calib.mocap_body in mocap else sorted(mocap)[0]
    if mocap_body is not None and mocap_body not in mocap:
        raise CaptureError(f"{rec.path} has no mocap body {mocap_body!r}; it has {sorted(mocap) or 'none'}")
    infos: dict[str, CameraInfo] = {}
    readouts: dict[str, float] = {}
    for name, t in cams.items():
        if "camera_info" in t and (info := rec.first_camera_info(t["camera_info"])) is not None:
            infos[name] = info
            readouts[name] = rec.camera_readout_s(t["camera_info"])
    body_traj = None
    if mocap_body is not None:
        body_traj = rec.pose_trajectory(mocap[mocap_body], frames, name=f"mocap {mocap_body}")
    return _Plan(
        camera,
        images[camera],
        images.get("depth") if camera != "depth" else None,
        images.get("right") if camera != "right" else None,
        infos,
        readouts,
        calib.T_body_camera,
        body_traj,
        {s.topic: s.count for s in rec.streams},
    )


def _prepare_out(out_dir: Path, allow_overwrite: bool) -> None:
    if out_dir.exists() and any(out_dir.iterdir()):
        if not allow_overwrite:
            raise CaptureError(f"{out_dir} exists and is not empty; choose another folder or pass --force")
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)


_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 1]


def _write_png(path: Path, img: npt.NDArray[Any]) -> None:
    if not cv2.imwrite(str(path), img, _PNG):
        raise CaptureError(f"cannot write {path}; check the disk and permissions")


def export_recording(
    src: str | Path,
    out_dir: str | Path,
    fmt: str,
    *,
    camera: str | None = None,
    mocap_body: str | None = None,
    max_diff_s: float = 0.02,
    T_body_camera: Transform | None = None,  # noqa: N803
    T_world_mocap: Transform | None = None,  # noqa: N803
    frame: str = WORLD_FRAME_ID,
    vehicle: str | None = None,
    allow_overwrite: bool = False,
    progress: ProgressFn | None = None,
    use_calibration: bool = True,
    calibration: CalibrationResult | None = None,
) -> ExportReport:
    """Write ``src`` (an MCAP recording) as a ``tum`` or ``euroc`` folder at ``out_dir``.

    Args:
        frame: ``world`` (the default) or ``mocap``: the frame the ground truth is written in.
        vehicle: the vehicle (bus namespace) whose camera and mocap body to export; needed when
            the recording holds several vehicles' cameras (see :func:`export_vehicles`).
        T_body_camera, T_world_mocap: override the recording's extrinsics and mocap frame.
        use_calibration: apply the recording's ``calibration.time_extrinsics`` record (written by
            ``flightkit calibrate --write REC.mcap``) when it has one: its ``T_body_camera``
            (unless ``T_body_camera`` is given) and its time offset, which moves the ground
            truth onto the camera's clock; EuRoC's ``sensor.yaml`` records the offset.
        calibration: a calibration result (``--calibration FILE.json``) used instead of the
            recording's own record.

    Blocks until done; ``progress(done, total)`` is called as images are written.

    Raises:
        CaptureError: unreadable recording, no camera stream, a non-empty output folder
            without ``allow_overwrite``, or an image that cannot be decoded or written.
        FrameError: a recorded pose in a frame the recording cannot place in the world.
    """
    if fmt not in ("tum", "euroc"):
        raise CaptureError(f"export format {fmt!r} is not known; use tum or euroc")
    if frame not in (WORLD_FRAME_ID, MOCAP_FRAME_ID):
        raise CaptureError(f"ground-truth frame {frame!r} is not known; use world or mocap")
    src, out = Path(src), Path(out_dir)
    if not src.is_file():
        raise CaptureError(f"{src} does not exist; check the path")
    try:
        rec = RecordingReader(src)
        frames = rec.world_frames(T_world_mocap)
        plan = _plan(rec, fmt, camera, mocap_body, frames, vehicle)
        cal = calibration or (rec.measured_calibration() if use_calibration else None)
    except DatasetError as exc:
        raise CaptureError(str(exc)) from exc
    T_bc = T_body_camera or plan.T_body_camera  # noqa: N806
    report = ExportReport(out, fmt, plan.main, max_diff_s=max_diff_s, frame=frame)
    origin = "the given calibration file" if calibration is not None else f"the recording's {METADATA_RECORD} record"
    if cal is not None and T_body_camera is None and cal.T_body_camera is not None:
        T_bc = cal.T_body_camera  # noqa: N806
        report.notes.append(f"T_body_camera from {origin} (flightkit calibrate)")
    if T_bc is None:
        T_bc = Transform()  # noqa: N806
        report.notes.append("no extrinsics in the recording: ground truth is the mocap body pose (T_body_camera = I)")
    if plan.main not in plan.infos:
        raise CaptureError(
            f"{src} lacks camera {plan.main}'s camera_info (…/camera/{plan.main}/camera_info); "
            "calibration files cannot be written without it"
        )
    _prepare_out(out, allow_overwrite)
    second = plan.depth_topic if fmt == "tum" else plan.right_topic
    topics = [t for t in (plan.main_topic, second) if t]
    if fmt == "euroc" and plan.depth_topic:
        report.notes.append("depth is not part of EuRoC and was not exported (use --format tum)")
    total = sum(plan.counts.get(t, 0) for t in topics)
    max_diff_ns = round(max_diff_s * 1e9)
    body_traj = plan.body_traj
    if body_traj is not None and cal is not None and cal.time_offset_ms is not None:
        body_traj = Trajectory(cal.mocap_to_camera_ns(body_traj.stamps_ns), body_traj.positions, body_traj.quats_wxyz,
                               body_traj.name)
        report.notes.append(
            f"ground truth moved onto the camera's clock by the calibrated offset ({cal.time_offset_ms:+.2f} ms, "
            f"drift {cal.drift_ppm or 0.0:+.1f} ppm)"
        )
    if body_traj is not None and frame == MOCAP_FRAME_ID:
        body_traj = body_traj.left_multiplied(frames.T_world_mocap.inverse())
    images = _images(rec, topics)
    if fmt == "tum":
        _export_tum(src, out, plan, images, body_traj, T_bc, max_diff_ns, report, total, progress)
    else:
        _export_euroc(src, out, plan, images, body_traj, T_bc, max_diff_ns, report, total, progress,
                      cal if cal is not None and cal.time_offset_ms is not None else None)
    logger.info("%s", report.summary())
    return report


def export_vehicles(
    src: str | Path, out_dir: str | Path, fmt: str, *, allow_overwrite: bool = False, **options: Any
) -> dict[str, ExportReport]:
    """Export every vehicle of a (fleet) recording with a camera, one folder each: ``OUT/<vehicle>``
    (a one-vehicle recording goes to ``OUT`` itself). ``options`` as :func:`export_recording`.

    Raises:
        CaptureError: as :func:`export_recording`; also when no vehicle has a camera.
    """
    src, out = Path(src), Path(out_dir)
    try:
        vehicles = RecordingReader(src).camera_namespaces()
    except DatasetError as exc:
        raise CaptureError(str(exc)) from exc
    if len(vehicles) <= 1:
        only = vehicles[0] if vehicles else None
        return {only or "": export_recording(src, out, fmt, vehicle=only, allow_overwrite=allow_overwrite, **options)}
    _prepare_out(out, allow_overwrite)
    return {v: export_recording(src, out / v, fmt, vehicle=v, **options) for v in vehicles}


def _images(rec: RecordingReader, topics: list[str]) -> Iterator[tuple[str, DecodedImage]]:
    for m in rec.messages(topics):
        try:
            yield m.topic, decode_image(m.topic, m.data)
        except DatasetError as exc:
            raise CaptureError(str(exc)) from exc


def _export_tum(
    src: Path,
    out: Path,
    plan: _Plan,
    images: Iterator[tuple[str, DecodedImage]],
    body_traj: Trajectory | None,
    T_bc: Transform,  # noqa: N803
    max_diff_ns: int,
    report: ExportReport,
    total: int,
    progress: ProgressFn | None,
) -> None:
    (out / "rgb").mkdir()
    if plan.depth_topic:
        (out / "depth").mkdir()
    rgb: list[tuple[int, str]] = []
    depth: list[tuple[int, str]] = []
    done = 0
    for topic, img in images:
        name = f"{_stamp_text(img.stamp_ns)}.png"
        if topic == plan.main_topic:
            _write_png(out / "rgb" / name, img.bgr())
            rgb.append((img.stamp_ns, f"rgb/{name}"))
        elif topic == plan.depth_topic:
            try:
                _write_png(out / "depth" / name, to_tum_depth(img.array, img.encoding))
            except DatasetError as exc:
                raise CaptureError(str(exc)) from exc
            depth.append((img.stamp_ns, f"depth/{name}"))
        done += 1
        if progress is not None:
            progress(done, total)
    rgb.sort()
    depth.sort()
    report.images, report.depth_images = len(rgb), len(depth)
    head = f"# exported by flightkit from {src.name}\n"
    (out / "rgb.txt").write_text(
        "# color images\n" + head + "# timestamp filename\n" + "".join(f"{_stamp_text(t)} {f}\n" for t, f in rgb)
    )
    if plan.depth_topic:
        (out / "depth.txt").write_text(
            "# depth maps\n" + head + "# timestamp filename\n" + "".join(f"{_stamp_text(t)} {f}\n" for t, f in depth)
        )
    rgb_ns = np.array([t for t, _ in rgb], np.int64)
    if depth:
        ia, ib = tum_associate(rgb_ns, np.array([t for t, _ in depth], np.int64), max_diff_ns)
        report.associated_depth = int(ia.size)
        (out / "associations.txt").write_text(
            "".join(
                f"{_stamp_text(rgb[i][0])} {rgb[i][1]} {_stamp_text(depth[j][0])} {depth[j][1]}\n"
                for i, j in zip(ia, ib, strict=True)
            )
        )
    if body_traj is not None:
        cam = body_traj.right_multiplied(T_bc).renamed("groundtruth")
        write_tum(
            out / "groundtruth.txt",
            cam,
            header=(
                f"ground truth: colour camera (OpenCV) in the {report.frame} frame\n"
                "# timestamp tx ty tz qx qy qz qw"
            ),
        )
        report.groundtruth_poses = len(cam)
        ia, ib = tum_associate(rgb_ns, cam.stamps_ns, max_diff_ns)
        report.associated_groundtruth = int(ia.size)
        q = quat_wxyz_to_xyzw(cam.quats_wxyz)
        (out / "associations_gt.txt").write_text(
            "".join(
                f"{_stamp_text(rgb[i][0])} {rgb[i][1]} {_stamp_text(int(cam.stamps_ns[j]))} "
                + " ".join(f"{v:.9f}" for v in (*cam.positions[j], *q[j]))
                + "\n"
                for i, j in zip(ia, ib, strict=True)
            )
        )
    write_tum_camera_yaml(out / "camera.yaml", plan.infos[plan.main], plan.infos.get("right"),
                          plan.readouts_s.get(plan.main, 0.0))


def _export_euroc(
    src: Path,
    out: Path,
    plan: _Plan,
    images: Iterator[tuple[str, DecodedImage]],
    body_traj: Trajectory | None,
    T_bc: Transform,  # noqa: N803
    max_diff_ns: int,
    report: ExportReport,
    total: int,
    progress: ProgressFn | None,
    timing: CalibrationResult | None,
) -> None:
    mav0 = out / "mav0"
    cams = {plan.main_topic: mav0 / "cam0"}
    if plan.right_topic:
        cams[plan.right_topic] = mav0 / "cam1"
    for d in cams.values():
        (d / "data").mkdir(parents=True)
    rows: dict[str, list[int]] = {t: [] for t in cams}
    done = 0
    for topic, img in images:
        _write_png(cams[topic] / "data" / f"{img.stamp_ns}.png", img.gray())
        rows[topic].append(img.stamp_ns)
        done += 1
        if progress is not None:
            progress(done, total)
    for topic, d in cams.items():
        stamps = sorted(rows[topic])
        (d / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in stamps))
        rate = (
            (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-9) if len(stamps) > 1 and stamps[-1] > stamps[0] else 0.0
        )
        if topic == plan.main_topic:
            T_bs = T_bc  # noqa: N806
            info = plan.infos[plan.main]
            readout_s = plan.readouts_s.get(plan.main, 0.0)
            report.images = len(stamps)
        else:
            info = plan.infos.get("right") or plan.infos[plan.main]
            readout_s = plan.readouts_s.get("right" if "right" in plan.infos else plan.main, 0.0)
            baseline = -info.p[3] / info.p[0] if info.p[0] else 0.0
            T_bs = T_bc @ Transform(translation=np.array([baseline, 0.0, 0.0]))  # noqa: N806
            report.right_images = len(stamps)
        (d / "sensor.yaml").write_text(
            euroc_sensor_yaml(info, T_bs, rate, f"{d.name} exported by flightkit from {src.name}", timing, readout_s)
        )
    (mav0 / "body.yaml").write_text("# Body frame: the mocap rigid body (FLU)\nsensor_type: body\n")
    if body_traj is not None:
        write_euroc_groundtruth(mav0 / "state_groundtruth_estimate0", body_traj)
        report.groundtruth_poses = len(body_traj)
        ia, _ = tum_associate(np.array(sorted(rows[plan.main_topic]), np.int64), body_traj.stamps_ns, max_diff_ns)
        report.associated_groundtruth = int(ia.size)
