"""Dataset readers and trajectory files on synthetic data written to tmp_path."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation.pipeline import run_vo
from flightkit.datasets import (
    CameraIntrinsics,
    Trajectory,
    associate,
    associate_trajectories,
    open_sequence,
    read_kitti_poses,
    read_trajectory,
    read_tum,
    write_kitti_poses,
    write_tum,
)
from flightkit.datasets.trajectory import parse_stamp_ns
from flightkit.errors import DatasetError, EstimationError


def _traj(n: int = 20) -> Trajectory:
    t = np.arange(n)
    q = Rotation.from_euler("zyx", np.column_stack([0.1 * t, 0.05 * t, -0.02 * t])).as_quat()
    pos = np.column_stack([0.1 * t, np.sin(t), 0.5 + 0 * t])
    return Trajectory(1_305_031_102_000_000_000 + t * 33_333_333, pos, np.column_stack([q[:, 3], q[:, :3]]), "t")


def test_stamps_parse_exactly_to_nanoseconds() -> None:
    assert parse_stamp_ns("1305031102.2159") == 1_305_031_102_215_900_000
    assert parse_stamp_ns("1.403715278862139940e+09") == 1_403_715_278_862_139_940
    assert parse_stamp_ns("0.104499") == 104_499_000
    with pytest.raises(DatasetError, match="'nan' is not a finite number"):
        parse_stamp_ns("nan")
    with pytest.raises(DatasetError, match="'x1' is not a number"):
        parse_stamp_ns("x1")


def test_tum_and_kitti_files_round_trip(tmp_path: Path) -> None:
    traj = _traj()
    back = read_tum(write_tum(tmp_path / "a.txt", traj))
    assert np.array_equal(back.stamps_ns, traj.stamps_ns)
    assert np.allclose(back.positions, traj.positions, atol=1e-9)
    assert np.allclose(np.abs(np.sum(back.quats_wxyz * traj.quats_wxyz, axis=1)), 1.0)
    k = read_kitti_poses(write_kitti_poses(tmp_path / "k.txt", traj), stamps_ns=traj.stamps_ns)
    assert np.allclose(k.as_matrices(), traj.as_matrices(), atol=1e-8)
    assert read_trajectory(tmp_path / "k.txt").stamps_ns[1] == 1_000_000_000  # index stamps
    assert len(read_trajectory(tmp_path / "a.txt")) == 20


def test_bad_trajectory_files_name_file_and_line(tmp_path: Path) -> None:
    p = tmp_path / "bad.txt"
    p.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad.txt:3: expected 8 values"):
        read_tum(p)
    p.write_text("1.0 0 0 x 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad.txt:1: .*number"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(DatasetError, match="zero quaternion"):
        read_tum(p)
    p.write_text("# nothing\n")
    with pytest.raises(DatasetError, match="holds no poses"):
        read_trajectory(p)
    with pytest.raises(DatasetError, match="does not exist"):
        read_tum(tmp_path / "missing.txt")
    p.write_text(" ".join(["2"] * 12) + "\n")
    with pytest.raises(DatasetError, match="not orthonormal"):
        read_kitti_poses(p)


def test_association_takes_the_nearest_stamp_within_the_limit() -> None:
    a = np.array([0, 100, 200, 300, 400])
    b = np.array([2, 95, 160, 260, 390, 500, 600])
    ia, ib = associate(a, b, 10)
    assert ia.tolist() == [0, 1, 4] and ib.tolist() == [0, 1, 4]
    ia, ib = associate(a, b, 50)
    assert ia.tolist() == [0, 1, 2, 3, 4] and ib.tolist() == [0, 1, 2, 3, 4]
    x, y = associate_trajectories(_traj(), _traj().subset([1, 5, 7]), 0.001)
    assert len(x) == len(y) == 3 and np.array_equal(x.stamps_ns, y.stamps_ns)


def test_interpolation_is_linear_and_slerp() -> None:
    q0 = Rotation.identity().as_quat()
    q1 = Rotation.from_euler("z", 90, degrees=True).as_quat()
    traj = Trajectory(
        np.array([0, 1_000_000_000]),
        np.array([[0.0, 0, 0], [2.0, 4.0, 0]]),
        np.array([[q0[3], *q0[:3]], [q1[3], *q1[:3]]]),
    )
    mid = traj.interpolate([250_000_000])
    assert np.allclose(mid.positions[0], [0.5, 1.0, 0])
    assert mid.rotations[0].magnitude() == pytest.approx(np.radians(22.5))
    with pytest.raises(DatasetError, match="spans"):
        traj.interpolate([2_000_000_000])


def test_trajectory_transforms_compose() -> None:
    from flightkit.frames import Transform

    traj = _traj()
    T = Transform.from_xyz_yaw([1.0, 2.0, 3.0], 0.7)  # noqa: N806
    moved = traj.left_multiplied(T)
    assert moved.transform(4).almost_equal(T @ traj.transform(4), 1e-9, 1e-9)
    X = Transform.from_xyz_euler_deg([0.1, 0, 0], "xyz", [0, 10, 0])  # noqa: N806
    assert traj.right_multiplied(X).transform(3).almost_equal(traj.transform(3) @ X, 1e-9, 1e-9)
    assert traj.relative_to_first().transform(0).almost_equal(Transform(), 1e-9, 1e-9)
    with pytest.raises(DatasetError, match="integers"):
        Trajectory(np.array([0.5]), np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]))


def _write_tum_folder(root: Path, n: int = 6) -> Trajectory:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    rgb_lines, depth_lines = ["# color images"], ["# depth images"]
    for i in range(n):
        t = 100.0 + i / 30
        color = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
        depth = np.full((48, 64), 5000 + 100 * i, dtype=np.uint16)
        depth[0, 0] = 0
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), color)
        cv2.imwrite(str(root / "depth" / f"{t + 0.004:.6f}.png"), depth)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    stamps = np.round((100.0 + np.arange(-3, 3 * n + 3) / 90) * 1e9).astype(np.int64)
    pos = np.column_stack([np.linspace(0, 1, stamps.size), np.zeros(stamps.size), np.ones(stamps.size)])
    gt = Trajectory(stamps, pos, np.tile([1.0, 0, 0, 0], (stamps.size, 1)))
    write_tum(root / "groundtruth.txt", gt)
    return gt


def test_tum_rgbd_folder(tmp_path: Path) -> None:
    root = tmp_path / "rgbd_dataset_freiburg3_synthetic"
    gt = _write_tum_folder(root)
    seq = open_sequence(root)
    assert seq.kind == "tum" and len(seq) == 6
    assert seq.intrinsics.fx == 535.4  # freiburg3 from the folder name
    frames = list(seq.frames())
    f = frames[2]
    assert f.stamp_ns == parse_stamp_ns(f"{100.0 + 2 / 30:.6f}")
    assert f.color_bgr is not None and f.gray.shape == (48, 64)
    assert f.depth_m is not None and f.depth_m[1, 1] == pytest.approx((5000 + 200) / 5000) and f.depth_m[0, 0] == 0
    assert f.T_world_camera is not None
    expected = gt.interpolate([f.stamp_ns]).positions[0]
    assert np.allclose(f.T_world_camera.translation, expected)
    (root / "depth.txt").unlink()
    with pytest.raises(DatasetError, match="lacks depth.txt"):
        open_sequence(root)
    assert len(open_sequence(root, with_depth=False)) == 6


def test_a_tum_folder_that_names_no_sensor_is_a_kinect_and_says_so(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """TUM's default calibration is the Kinect's factory one, with the Kinect's rolling shutter;
    a named sensor or a camera.yaml says nothing."""
    root = tmp_path / "desk_sequence"
    _write_tum_folder(root, n=3)
    with caplog.at_level("WARNING", logger="flightkit.datasets.tum"):
        seq = open_sequence(root)
    assert (seq.intrinsics.fx, seq.intrinsics.cx, seq.intrinsics.readout_s) == (525.0, 319.5, 0.02)
    assert "names no TUM sensor" in caplog.text and "camera.yaml" in caplog.text
    caplog.clear()
    named = tmp_path / "tum_fr2_desk"
    _write_tum_folder(named, n=3)
    with caplog.at_level("WARNING", logger="flightkit.datasets.tum"):
        assert open_sequence(named).intrinsics.fx == pytest.approx(520.908620)
    assert "names no TUM sensor" not in caplog.text


def test_unrecognised_and_incomplete_folders(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not a recognised dataset folder"):
        open_sequence(tmp_path)
    with pytest.raises(DatasetError, match="does not exist"):
        open_sequence(tmp_path / "nope")
    (tmp_path / "k" / "image_0").mkdir(parents=True)
    with pytest.raises(DatasetError, match="KITTI folder .* lacks calib.txt"):
        open_sequence(tmp_path / "k")
    s = tmp_path / "s"
    s.mkdir()
    cv2.imwrite(str(s / "frame-000000.color.png"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(DatasetError, match="7-Scenes folder .* lacks frame-000000.depth.png"):
        open_sequence(s)
    (tmp_path / "x.bin").write_bytes(b"0")
    with pytest.raises(DatasetError, match="unknown type"):
        open_sequence(tmp_path / "x.bin")


def test_video_with_json_calibration(tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (64, 48))
    for i in range(12):
        img = np.zeros((48, 64, 3), np.uint8)
        img[:, :, 1] = 20 * i
        writer.write(img)
    writer.release()
    with pytest.raises(DatasetError, match="lacks a calibration file"):
        open_sequence(video)
    calib = {
        "fx": 50.0,
        "fy": 51.0,
        "cx": 32.0,
        "cy": 24.0,
        "width": 64,
        "height": 48,
        "dist": [0.1, 0, 0, 0],
        "start_stamp_ns": 5_000_000_000,
    }
    (tmp_path / "clip.json").write_text(json.dumps(calib))
    seq = open_sequence(video)
    assert (
        seq.kind == "video"
        and len(seq) == 12
        and seq.intrinsics == CameraIntrinsics(50, 51, 32, 24, 64, 48, (0.1, 0, 0, 0))
    )
    frames = list(seq.frames(1, 10, 4))
    assert [f.index for f in frames] == [1, 5, 9]
    assert frames[1].stamp_ns == 5_000_000_000 + round(5 * 1e9 / 15)
    assert frames[2].color_bgr is not None and abs(int(frames[2].color_bgr[20, 20, 1]) - 180) < 8
    # A plain video has no metric scale: every VO method refuses it in one sentence that says so.
    for method in ("rgbd-pnp", "rgbd-essential", "rgbd-kabsch", "stereo", "flow"):
        with pytest.raises(EstimationError, match="one camera and neither depth images nor a stereo pair"):
            run_vo(seq, method)
    calib["width"] = 640
    (tmp_path / "clip.json").write_text(json.dumps(calib))
    with pytest.raises(DatasetError, match="is 64x48 but"):
        open_sequence(video)
    # (k1, k2, k3) from another tool is not OpenCV's order: refused, not read as (k1, k2, p1)
    calib["width"], calib["dist"] = 64, [0.1, -0.05, 0.01]
    (tmp_path / "clip.json").write_text(json.dumps(calib))
    with pytest.raises(DatasetError, match="has 3 coefficients; OpenCV's model takes 4, 5, 8, 12 or 14"):
        open_sequence(video)


@pytest.mark.parametrize("n", [1, 2, 3, 6, 7, 9, 11, 16])
def test_a_distortion_of_no_opencv_length_is_refused(n: int) -> None:
    with pytest.raises(DatasetError, match=f"has {n} coefficients"):
        CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480, (0.01,) * n)
    with pytest.raises(DatasetError, match="finite"):
        CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480, (0.1, float("nan"), 0.0, 0.0))
    for ok in (0, 4, 5, 8, 12, 14):
        assert len(CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480, (0.01,) * ok).dist) == ok


_HEADER = (
    "builtin_interfaces/Time stamp\n"
    "string frame_id\n"
    "================================================================================\n"
    "MSG: builtin_interfaces/Time\n"
    "int32 sec\n"
    "uint32 nanosec"
)
_IMAGE = (
    "std_msgs/Header header\n"
    "uint32 height\n"
    "uint32 width\n"
    "string encoding\n"
    "uint8 is_bigendian\n"
    "uint32 step\n"
    "uint8[] data\n"
)
_INFO = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\n"
    "float64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi\n"
)
_POSE = "std_msgs/Header header\nPose pose\n"


def _msgdef(body: str, extra: list[tuple[str, str]]) -> str:
    sep = "\n================================================================================\n"
    parts = [body]
    for name, text in extra:
        parts.append(f"MSG: {name}\n{text}")
    return sep.join(parts)


def test_mcap_recording_written_with_mcap_ros2(tmp_path: Path) -> None:
    writer_mod = pytest.importorskip("mcap_ros2.writer")
    header_defs = [
        ("std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id"),
        ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec"),
    ]
    path = tmp_path / "rec.mcap"
    rng = np.random.default_rng(0)
    colors, depths = [], []
    with path.open("wb") as fh:
        w = writer_mod.Writer(fh)
        img_s = w.register_msgdef("sensor_msgs/msg/Image", _msgdef(_IMAGE, header_defs))
        info_s = w.register_msgdef(
            "sensor_msgs/msg/CameraInfo",
            _msgdef(
                _INFO,
                header_defs
                + [
                    (
                        "sensor_msgs/RegionOfInterest",
                        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify",
                    )
                ],
            ),
        )
        pose_s = w.register_msgdef(
            "geometry_msgs/msg/PoseStamped",
            _msgdef(
                _POSE,
                header_defs
                + [
                    ("geometry_msgs/Pose", "Point position\nQuaternion orientation"),
                    ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z"),
                    ("geometry_msgs/Quaternion", "float64 x\nfloat64 y\nfloat64 z\nfloat64 w"),
                ],
            ),
        )
        for i in range(60):  # mocap at 100 Hz
            t = 1_000_000_000 + i * 10_000_000
            hdr = {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "mocap"}
            w.write_message(
                "/uav1/mocap/uav1/pose",
                pose_s,
                {
                    "header": hdr,
                    "pose": {
                        "position": {"x": 0.01 * i, "y": 0.0, "z": 1.0},
                        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    },
                },
                log_time=t,
            )
        for i in range(5):  # camera at 10 Hz, depth 2 ms later, logged out of order
            t = 1_050_000_000 + i * 100_000_000
            hdr = {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "cam"}
            color = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)
            depth = rng.integers(0, 4000, (6, 8), dtype=np.uint16)
            colors.append(color)
            depths.append(depth)
            td = t + 2_000_000
            hdr_d = {"stamp": {"sec": td // 10**9, "nanosec": td % 10**9}, "frame_id": "cam"}
            w.write_message(
                "/uav1/camera/depth/image",
                img_s,
                {
                    "header": hdr_d,
                    "height": 6,
                    "width": 8,
                    "encoding": "16UC1",
                    "is_bigendian": 0,
                    "step": 16,
                    "data": depth.tobytes(),
                },
                log_time=td,
            )
            rgb = color[:, :, ::-1].copy()
            w.write_message(
                "/uav1/camera/color/image",
                img_s,
                {
                    "header": hdr,
                    "height": 6,
                    "width": 8,
                    "encoding": "rgb8",
                    "is_bigendian": 0,
                    "step": 24,
                    "data": rgb.tobytes(),
                },
                log_time=t + 3_000_000,
            )
            if i == 0:
                info = {
                    "header": hdr,
                    "height": 6,
                    "width": 8,
                    "distortion_model": "plumb_bob",
                    "d": [0.1, 0.0, 0.0, 0.0, 0.0],
                    "k": [10.0, 0, 4.0, 0, 11.0, 3.0, 0, 0, 1],
                    "r": [1.0, 0, 0, 0, 1, 0, 0, 0, 1],
                    "p": [10.0, 0, 4.0, 0, 0, 11.0, 3.0, 0, 0, 0, 1, 0],
                    "binning_x": 0,
                    "binning_y": 0,
                    "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
                }
                w.write_message("/uav1/camera/color/camera_info", info_s, info, log_time=t)
        w.finish()
    seq = open_sequence(path)
    assert seq.kind == "mcap" and len(seq) == 5
    assert seq.intrinsics == CameraIntrinsics(10, 11, 4, 3, 8, 6, (0.1, 0, 0, 0, 0))
    frames = list(seq.frames())
    assert [f.stamp_ns for f in frames] == [1_050_000_000 + i * 100_000_000 for i in range(5)]
    for f, c, d in zip(frames, colors, depths, strict=True):
        assert f.color_bgr is not None and np.array_equal(f.color_bgr, c)
        assert f.depth_raw is not None and np.array_equal(f.depth_raw, d) and f.depth_scale_m == 1e-3
        assert f.T_world_camera is not None
        assert f.T_world_camera.translation[0] == pytest.approx(0.01 * (f.stamp_ns - 1_000_000_000) / 10_000_000)
    assert [f.index for f in seq.frames(1, None, 2)] == [1, 3]
    gt = seq.groundtruth()
    assert len(gt) == 60 and gt.positions[39, 0] == pytest.approx(0.39)
