"""Export an MCAP recording to a TUM RGB-D or EuRoC (ASL) folder.

TUM RGB-D (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    OUT/rgb/<t>.png            colour, 8-bit (PNG)
    OUT/depth/<t>.png          depth, 16-bit PNG, 5000 units per metre, 0 = no data
    OUT/rgb.txt, depth.txt     "timestamp filename" per image, '#' header lines
    OUT/groundtruth.txt        "timestamp tx ty tz qx qy qz qw": the colour camera's optical
                               centre in the mocap (or world) frame, at the mocap stamps
    OUT/associations.txt       "t_rgb rgb/... t_depth depth/..." (TUM associate.py on rgb.txt, depth.txt)
    OUT/associations_gt.txt    "t_rgb rgb/... t_gt tx ty tz qx qy qz qw" (associate.py on rgb.txt, groundtruth.txt)
    OUT/camera.yaml            calibration (OpenCV FileStorage, ORB-SLAM style keys, DepthMapFactor 5000)

EuRoC / ASL::

    OUT/mav0/cam0/data/<ns>.png + data.csv + sensor.yaml   left (or colour as gray) camera, T_BS = T_body_camera
    OUT/mav0/cam1/...                                       right camera of a stereo recording
    OUT/mav0/state_groundtruth_estimate0/data.csv           body pose (17 columns as EuRoC)
    OUT/mav0/body.yaml

Timestamps are the header stamps (capture time), written exactly (9 decimals / integer ns).
Association follows TUM's ``associate.py``: every pair within ``max_diff_s`` is a candidate;
candidates are taken in order of increasing difference, each stamp used at most once.

Ground truth: the mocap body poses ``T_mocap_body`` become camera poses through the
extrinsics, ``T_frame_camera = T_frame_mocap @ T_mocap_body @ T_body_camera`` where
``T_frame_mocap`` is identity (ground truth in the mocap system's frame, as TUM and EuRoC
publish it) unless a ``T_world_mocap`` is given. ``T_body_camera`` comes from the argument,
else the recording's ``extrinsics`` metadata, else its ``<ns>/tf`` extrinsics.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from mcap.reader import make_reader

from flightkit.bus.msgs import CameraInfo, Image, PoseStamped, TFMessage
from flightkit.datasets.base import CameraIntrinsics
from flightkit.datasets.trajectory import Trajectory, write_tum
from flightkit.errors import BusError, CaptureError
from flightkit.frames import Transform, quat_wxyz_to_xyzw, quat_xyzw_to_wxyz

__all__ = [
    "ExportReport",
    "export_recording",
    "read_tum_calibration",
    "tum_associate",
]

logger = logging.getLogger(__name__)

_CAMERA = re.compile(r"camera/([^/]+)/(image|camera_info)$")
_MOCAP = re.compile(r"mocap/([^/]+)/pose$")
_TF = re.compile(r"(^|/)tf$")
TUM_DEPTH_FACTOR = 5000.0
ProgressFn = Callable[[int, int], None]


@dataclass
class ExportReport:
    """What an export wrote.

    Attributes:
        images: main-camera images written; depth_images, right_images likewise.
        groundtruth_poses: rows of the ground-truth file.
        associated_depth: colour frames with a depth partner within ``max_diff_s``.
        associated_groundtruth: frames with a ground-truth pose within ``max_diff_s``.
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
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        parts = [f"{self.images} {self.camera} images"]
        if self.depth_images:
            parts.append(f"{self.depth_images} depth ({self.associated_depth} associated)")
        if self.right_images:
            parts.append(f"{self.right_images} right")
        parts.append(f"{self.groundtruth_poses} ground-truth poses ({self.associated_groundtruth} frames matched)")
        return f"{self.fmt} folder {self.out_dir}: " + ", ".join(parts)


# --------------------------------------------------------------------------- association


def tum_associate(
    stamps_a_ns: npt.ArrayLike, stamps_b_ns: npt.ArrayLike, max_diff_ns: int, offset_ns: int = 0
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """TUM ``associate.py``: unique pairs ``(i, j)`` with ``|a_i - (b_j + offset)| < max_diff``,
    taken greedily by increasing difference; returned sorted by ``i``."""
    a = np.asarray(stamps_a_ns, dtype=np.int64).reshape(-1)
    b = np.asarray(stamps_b_ns, dtype=np.int64).reshape(-1) + int(offset_ns)
    if a.size == 0 or b.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    lo = np.searchsorted(bs, a - max_diff_ns, side="right")
    hi = np.searchsorted(bs, a + max_diff_ns, side="left")
    counts = hi - lo
    ii = np.repeat(np.arange(a.size), counts)
    starts = np.repeat(lo, counts)
    within = np.arange(ii.size) - np.repeat(np.cumsum(counts) - counts, counts)
    jj_sorted = starts + within
    diffs = np.abs(a[ii] - bs[jj_sorted])
    order = np.lexsort((jj_sorted, ii, diffs))
    used_a = np.zeros(a.size, bool)
    used_b = np.zeros(b.size, bool)
    out_i: list[int] = []
    out_j: list[int] = []
    for k in order:
        i, js = int(ii[k]), int(jj_sorted[k])
        if used_a[i] or used_b[js]:
            continue
        used_a[i] = used_b[js] = True
        out_i.append(i)
        out_j.append(int(order_b[js]))
    idx = np.argsort(out_i)
    return np.asarray(out_i, np.int64)[idx], np.asarray(out_j, np.int64)[idx]


# --------------------------------------------------------------------------- helpers


def _stamp_text(stamp_ns: int) -> str:
    s, ns = divmod(int(stamp_ns), 1_000_000_000)
    return f"{s}.{ns:09d}"


def _transform_from_json(text: str) -> Transform:
    data = json.loads(text)
    return Transform.from_quat_xyzw(data["translation_m"], data["quat_xyzw"])


def _intrinsics(info: CameraInfo) -> CameraIntrinsics:
    k = info.k
    d = tuple(info.d) if any(v != 0.0 for v in info.d) else ()
    return CameraIntrinsics(k[0], k[4], k[2], k[5], info.width, info.height, d)


def read_tum_calibration(folder: str | Path) -> CameraIntrinsics:
    """The intrinsics in an exported TUM folder's ``camera.yaml`` (pass them to ``open_sequence(..., intrinsics=)``).

    Raises:
        CaptureError: the file is missing or incomplete.
    """
    path = Path(folder) / "camera.yaml"
    if not path.is_file():
        raise CaptureError(f"{path} does not exist; export the folder with 'flightkit export --format tum'")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        vals = {
            k: fs.getNode(f"Camera.{k}")
            for k in ("fx", "fy", "cx", "cy", "width", "height", "k1", "k2", "p1", "p2", "k3")
        }
        if any(vals[k].empty() for k in ("fx", "fy", "cx", "cy", "width", "height")):
            raise CaptureError(f"{path} lacks Camera.fx/fy/cx/cy/width/height; re-export the folder")
        dist = tuple(vals[k].real() for k in ("k1", "k2", "p1", "p2", "k3") if not vals[k].empty())
        return CameraIntrinsics(
            vals["fx"].real(),
            vals["fy"].real(),
            vals["cx"].real(),
            vals["cy"].real(),
            int(vals["width"].real()),
            int(vals["height"].real()),
            dist if any(dist) else (),
        )
    finally:
        fs.release()


@dataclass
class _Plan:
    main: str
    main_topic: str
    depth_topic: str | None
    right_topic: str | None
    mocap_topic: str | None
    infos: dict[str, CameraInfo]
    T_body_camera: Transform | None  # noqa: N815
    mocap: Trajectory | None
    counts: dict[str, int]


def _plan(src: Path, fmt: str, camera: str | None, mocap_body: str | None) -> _Plan:
    try:
        fh = src.open("rb")
    except OSError as exc:
        raise CaptureError(f"cannot open {src}: {exc.strerror}; check the path") from exc
    with fh:
        try:
            reader = make_reader(fh)
            summary = reader.get_summary()
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except Exception as exc:
            raise CaptureError(
                f"{src} is not a readable MCAP file ({exc}); if it crashed, run "
                f"'flightkit capture recover {src} -o FIXED.mcap' first"
            ) from exc
        if summary is None:
            raise CaptureError(f"{src} has no summary; run 'flightkit capture recover {src} -o FIXED.mcap' first")
        images: dict[str, str] = {}
        info_topics: dict[str, str] = {}
        mocap: dict[str, str] = {}
        tf_topics: list[str] = []
        for ch in summary.channels.values():
            t = ch.topic.lstrip("/")
            if m := _CAMERA.search(t):
                (images if m.group(2) == "image" else info_topics)[m.group(1)] = ch.topic
            elif m := _MOCAP.search(t):
                mocap[m.group(1)] = ch.topic
            elif _TF.search(t):
                tf_topics.append(ch.topic)
        counts: dict[str, int] = {}
        if summary.statistics is not None:
            by_id = {cid: ch.topic for cid, ch in summary.channels.items()}
            counts = {by_id[c]: n for c, n in summary.statistics.channel_message_counts.items() if c in by_id}
        prefs = ("left", "color", "gray", "image", "infra1") if fmt == "euroc" else ("color", "left", "gray", "image")
        if camera is None:
            camera = next((c for c in prefs if c in images), None) or next(
                (c for c in sorted(images) if c not in ("depth", "right")), None
            )
        if camera is None or camera not in images:
            raise CaptureError(
                f"{src} has no camera image stream{'' if camera is None else f' named {camera!r}'}; "
                f"it has {sorted(images) or 'none'} (topics …/camera/<name>/image)"
            )
        if mocap_body is None and mocap:
            mocap_body = sorted(mocap)[0]
        if mocap_body is not None and mocap_body not in mocap:
            raise CaptureError(f"{src} has no mocap body {mocap_body!r}; it has {sorted(mocap) or 'none'}")
        mocap_topic = mocap.get(mocap_body) if mocap_body else None
        # First pass over the small streams: calibration, extrinsics, mocap.
        wanted = list(info_topics.values()) + tf_topics + ([mocap_topic] if mocap_topic else [])
        infos: dict[str, CameraInfo] = {}
        poses: list[tuple[int, tuple[float, ...], tuple[float, ...]]] = []
        T_bc_tf: Transform | None = None  # noqa: N806
        info_name = {t: n for n, t in info_topics.items()}
        if wanted:
            for _s, ch, msg in reader.iter_messages(topics=wanted, log_time_order=False):
                try:
                    if ch.topic == mocap_topic:
                        p = PoseStamped.decode(msg.data)
                        poses.append((p.header.stamp_ns, p.position_m, p.quat_xyzw))
                    elif ch.topic in info_name:
                        infos.setdefault(info_name[ch.topic], CameraInfo.decode(msg.data))
                    elif T_bc_tf is None:
                        for ts in TFMessage.decode(msg.data).transforms:
                            if ts.header.frame_id.endswith("base_link") and ts.child_frame_id.endswith("_optical"):
                                T_bc_tf = ts.to_transform()  # noqa: N806
                except BusError as exc:
                    raise CaptureError(f"{src}: a message on {ch.topic} cannot be decoded ({exc})") from exc
    T_body_camera = None  # noqa: N806
    if "extrinsics" in metadata and "T_body_camera" in metadata["extrinsics"]:
        T_body_camera = _transform_from_json(metadata["extrinsics"]["T_body_camera"])  # noqa: N806
    elif T_bc_tf is not None:
        T_body_camera = T_bc_tf  # noqa: N806
    traj = None
    if poses:
        poses.sort(key=lambda p: p[0])
        stamps = np.array([p[0] for p in poses], np.int64)
        keep = np.concatenate([[True], np.diff(stamps) > 0])  # drop duplicate stamps
        traj = Trajectory(
            stamps[keep],
            np.array([p[1] for p in poses])[keep],
            quat_xyzw_to_wxyz(np.array([p[2] for p in poses]))[keep],
            f"mocap {mocap_body}",
        )
    return _Plan(
        camera,
        images[camera],
        images.get("depth") if camera != "depth" else None,
        images.get("right") if camera != "right" else None,
        mocap_topic,
        infos,
        T_body_camera,
        traj,
        counts,
    )


def _prepare_out(out_dir: Path, allow_overwrite: bool) -> None:
    if out_dir.exists() and any(out_dir.iterdir()):
        if not allow_overwrite:
            raise CaptureError(f"{out_dir} exists and is not empty; choose another folder or pass --force")
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)


def _decode_image(data: bytes | memoryview, topic: str) -> Image:
    try:
        return Image.decode(data)
    except BusError as exc:
        raise CaptureError(f"an image on {topic} cannot be decoded ({exc})") from exc


def _to_bgr(arr: npt.NDArray[Any], encoding: str) -> npt.NDArray[Any]:
    if encoding == "rgb8":
        return cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    if encoding == "rgba8":
        return cv2.cvtColor(arr, cv2.COLOR_RGBA2BGR)
    if encoding == "bgra8":
        return cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
    return arr


def _to_gray(arr: npt.NDArray[Any], encoding: str) -> npt.NDArray[Any]:
    if arr.ndim == 2:
        return arr if arr.dtype == np.uint8 else cv2.convertScaleAbs(arr, alpha=255.0 / max(1, int(arr.max())))
    return cv2.cvtColor(_to_bgr(arr, encoding), cv2.COLOR_BGR2GRAY)


def _tum_depth(arr: npt.NDArray[Any], encoding: str) -> npt.NDArray[np.uint16]:
    if encoding in ("16UC1", "mono16"):
        scaled = arr.astype(np.float32) * np.float32(TUM_DEPTH_FACTOR / 1000.0)  # mm -> 1/5000 m
    elif encoding == "32FC1":
        scaled = np.nan_to_num(arr.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0) * np.float32(TUM_DEPTH_FACTOR)
    else:
        raise CaptureError(f"depth encoding {encoding!r} cannot be exported; expected 16UC1 (mm) or 32FC1 (m)")
    return np.clip(np.rint(scaled), 0, 65535).astype(np.uint16)


_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 1]


def _write_png(path: Path, img: npt.NDArray[Any]) -> None:
    if not cv2.imwrite(str(path), img, _PNG):
        raise CaptureError(f"cannot write {path}; check the disk and permissions")


# --------------------------------------------------------------------------- export


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
    allow_overwrite: bool = False,
    progress: ProgressFn | None = None,
) -> ExportReport:
    """Write ``src`` (an MCAP recording) as a ``tum`` or ``euroc`` folder at ``out_dir``.

    Blocks until done; ``progress(done, total)`` is called as images are written.

    Raises:
        CaptureError: unreadable recording, no camera stream, a non-empty output folder
            without ``allow_overwrite``, or an image that cannot be decoded or written.
    """
    if fmt not in ("tum", "euroc"):
        raise CaptureError(f"export format {fmt!r} is not known; use tum or euroc")
    src, out = Path(src), Path(out_dir)
    if not src.is_file():
        raise CaptureError(f"{src} does not exist; check the path")
    plan = _plan(src, fmt, camera, mocap_body)
    T_bc = T_body_camera or plan.T_body_camera  # noqa: N806
    report = ExportReport(out, fmt, plan.main, max_diff_s=max_diff_s)
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
    T_fm = T_world_mocap or Transform()  # noqa: N806
    body_traj = plan.mocap.left_multiplied(T_fm) if plan.mocap is not None else None
    if fmt == "tum":
        _export_tum(src, out, plan, topics, body_traj, T_bc, max_diff_ns, report, total, progress)
    else:
        _export_euroc(src, out, plan, topics, body_traj, T_bc, max_diff_ns, report, total, progress)
    logger.info("%s", report.summary())
    return report


def _iter_images(src: Path, topics: list[str]) -> Any:
    with src.open("rb") as fh:
        for _s, ch, msg in make_reader(fh).iter_messages(topics=topics, log_time_order=True):
            yield ch.topic, msg.data


def _export_tum(
    src: Path,
    out: Path,
    plan: _Plan,
    topics: list[str],
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
    for topic, data in _iter_images(src, topics):
        msg = _decode_image(data, topic)
        arr, enc, stamp = msg.array(), msg.encoding, msg.header.stamp_ns
        name = f"{_stamp_text(stamp)}.png"
        if topic == plan.main_topic:
            _write_png(out / "rgb" / name, _to_bgr(arr, enc))
            rgb.append((stamp, f"rgb/{name}"))
        elif topic == plan.depth_topic:
            _write_png(out / "depth" / name, _tum_depth(arr, enc))
            depth.append((stamp, f"depth/{name}"))
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
            header="ground truth: colour camera (OpenCV) in the mocap frame\n# timestamp tx ty tz qx qy qz qw",
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
    _write_tum_yaml(out / "camera.yaml", plan.infos[plan.main], plan.infos.get("right"))


def _write_tum_yaml(path: Path, info: CameraInfo, right: CameraInfo | None) -> None:
    k = info.k
    d = list(info.d) + [0.0] * (5 - len(info.d))
    lines = [
        "%YAML:1.0",
        "---",
        "# Camera calibration (pinhole, OpenCV plumb_bob distortion), exported by flightkit",
        'Camera.type: "PinHole"',
        f"Camera.fx: {k[0]!r}",
        f"Camera.fy: {k[4]!r}",
        f"Camera.cx: {k[2]!r}",
        f"Camera.cy: {k[5]!r}",
        f"Camera.k1: {d[0]!r}",
        f"Camera.k2: {d[1]!r}",
        f"Camera.p1: {d[2]!r}",
        f"Camera.p2: {d[3]!r}",
        f"Camera.k3: {d[4]!r}",
        f"Camera.width: {info.width}",
        f"Camera.height: {info.height}",
        "Camera.RGB: 1",
        f"DepthMapFactor: {TUM_DEPTH_FACTOR!r}",
    ]
    if right is not None and right.p[0]:
        lines.append(f"Camera.bf: {-right.p[3]!r}")
    path.write_text("\n".join(lines) + "\n")


def _sensor_yaml(info: CameraInfo, T_body_camera: Transform, rate_hz: float, comment: str) -> str:  # noqa: N803
    k = info.k
    d = (list(info.d) + [0.0] * 4)[:4]
    T = T_body_camera.as_matrix().reshape(-1)  # noqa: N806
    return (
        "%YAML:1.0\n"
        "# General sensor definitions.\n"
        "sensor_type: camera\n"
        f"comment: {comment}\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [" + ", ".join(repr(float(v)) for v in T) + "]\n\n"
        "# Camera specific definitions.\n"
        f"rate_hz: {rate_hz:.6g}\n"
        f"resolution: [{info.width}, {info.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{k[0]!r}, {k[4]!r}, {k[2]!r}, {k[5]!r}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        "distortion_coefficients: [" + ", ".join(repr(float(v)) for v in d) + "]\n"
    )


def _export_euroc(
    src: Path,
    out: Path,
    plan: _Plan,
    topics: list[str],
    body_traj: Trajectory | None,
    T_bc: Transform,  # noqa: N803
    max_diff_ns: int,
    report: ExportReport,
    total: int,
    progress: ProgressFn | None,
) -> None:
    mav0 = out / "mav0"
    cams = {plan.main_topic: mav0 / "cam0"}
    if plan.right_topic:
        cams[plan.right_topic] = mav0 / "cam1"
    for d in cams.values():
        (d / "data").mkdir(parents=True)
    rows: dict[str, list[int]] = {t: [] for t in cams}
    done = 0
    for topic, data in _iter_images(src, list(cams)):
        msg = _decode_image(data, topic)
        arr = msg.array()
        stamp = msg.header.stamp_ns
        _write_png(cams[topic] / "data" / f"{stamp}.png", _to_gray(arr, msg.encoding))
        rows[topic].append(stamp)
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
            report.images = len(stamps)
        else:
            info = plan.infos.get("right") or plan.infos[plan.main]
            baseline = -info.p[3] / info.p[0] if info.p[0] else 0.0
            T_bs = T_bc @ Transform(translation=np.array([baseline, 0.0, 0.0]))  # noqa: N806
            report.right_images = len(stamps)
        (d / "sensor.yaml").write_text(
            _sensor_yaml(info, T_bs, rate, f"{d.name} exported by flightkit from {src.name}")
        )
    (mav0 / "body.yaml").write_text("# Body frame: the mocap rigid body (FLU)\nsensor_type: body\n")
    if body_traj is not None:
        gt = mav0 / "state_groundtruth_estimate0"
        gt.mkdir()
        t_s = (body_traj.stamps_ns - body_traj.stamps_ns[0]) * 1e-9
        vel = np.gradient(body_traj.positions, t_s, axis=0) if len(body_traj) > 1 else np.zeros((len(body_traj), 3))
        header = (
            "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
            "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
            "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
            "b_a_RS_S_z [m s^-2]\n"
        )
        lines = [
            f"{int(t)}," + ",".join(f"{v:.9f}" for v in (*p, *q, *v)) + ",0,0,0,0,0,0\n"
            for t, p, q, v in zip(body_traj.stamps_ns, body_traj.positions, body_traj.quats_wxyz, vel, strict=True)
        ]
        (gt / "data.csv").write_text(header + "".join(lines))
        (gt / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: visual-inertial\ncomment: mocap body pose exported by flightkit\n"
            "T_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, "
            "0.0, 0.0, 0.0, 1.0]\n"
        )
        report.groundtruth_poses = len(body_traj)
        ia, _ = tum_associate(np.array(sorted(rows[plan.main_topic]), np.int64), body_traj.stamps_ns, max_diff_ns)
        report.associated_groundtruth = int(ia.size)
