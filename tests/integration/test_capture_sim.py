"""Record the simulated camera and mocap over Zenoh, read the file back, export it and load the export.

Time is a LockstepClock driven by the test in mocap ticks (1/240 s), so message counts are exact.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from capture.bus_recorder import BusRecorder, recording_metadata
from capture.config import CaptureConfig
from capture.export import export_recording
from flightkit.bus.image_msgs import Image
from flightkit.bus.keys import Keys
from flightkit.bus.pose_msgs import TFMessage
from flightkit.bus.session import open_session
from flightkit.clock import LockstepClock
from flightkit.config import BusConfig, CameraConfig, LabConfig, load_config
from flightkit.datasets import open_sequence, read_tum
from flightkit.datasets.mcap_metadata import with_metadata
from flightkit.datasets.mcap_reader import RecordingReader
from flightkit.datasets.tum import read_tum_camera_yaml
from flightkit.frames import Transform
from flightkit.sim.camera_publisher import SimCameraPublisher
from flightkit.sim.mocap import SimMocapPublisher, SimMocapSystem
from tests.conftest import free_tcp_port, wait

MOCAP_HZ = 240
CAMERA_HZ = 30
SIM_SECONDS = 1.0
T_WORLD_MOCAP = Transform.from_xyz_yaw([0.5, -0.3, 0.0], math.radians(30))


def truth_at(t_s: float) -> Transform:
    """A circle of 1 m radius at 1.5 m, looking inward (yaw rate 0.5 rad/s)."""
    a = 0.5 * t_s
    return Transform.from_xyz_yaw([math.cos(a), math.sin(a), 1.5], a + math.pi)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, LabConfig, int]:
    """One recording shared by the tests of this module: 1 s of sim at 320x240 + stereo."""
    tmp = tmp_path_factory.mktemp("rec")
    port = free_tcp_port()
    pub_s = open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    rec_s = open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",)))
    clock = LockstepClock()
    keys = Keys("uav1")
    x, y, _ = T_WORLD_MOCAP.translation
    lab = load_config(
        table={
            "camera": {"width_px": 320, "height_px": 240},
            "capture": {"stereo": True},
            "mocap": {"T_world_mocap": {"translation_m": [x, y, 0.0], "rpy_deg": [0.0, 0.0, 30.0]}},
        }
    )
    assert lab.mocap.T_world_mocap.to_transform().almost_equal(T_WORLD_MOCAP, 1e-12, 1e-12)
    streams = lab.section("capture", CaptureConfig).streams()
    cam = SimCameraPublisher(pub_s, keys, truth_at, lab.camera, clock, streams=streams)
    system = SimMocapSystem(clock, {"uav1": truth_at}, T_world_mocap=T_WORLD_MOCAP, rate_hz=MOCAP_HZ)
    mocap = SimMocapPublisher(pub_s, keys, system)
    out = tmp / "run.mcap"
    rec = BusRecorder(rec_s, out, ["uav1/**"], compression="zstd", metadata=recording_metadata(lab))
    try:
        wait(lambda: cam.has_subscribers and mocap.has_subscribers, 10, "the recorder to subscribe")
        cam.start()
        mocap.start()
        ticks = int(SIM_SECONDS * MOCAP_HZ)
        for k in range(ticks + 1):
            wait(lambda k=k: mocap.published >= k + 1, 10, f"mocap tick {k}")
            cam.wait_frames(k // (MOCAP_HZ // CAMERA_HZ) + 1, 10)
            if k < ticks:
                clock.advance(1.0 / MOCAP_HZ)
        frames = cam.frames_published
        wait(lambda: len(rec.calibrated) == 4, 10, "the cameras' calibration records")  # before they go away
        mocap.stop()
        cam.stop()
        rec.wait_for(
            lambda st: (
                st.get("uav1/camera/right/image") is not None
                and st["uav1/camera/right/image"].count >= frames
                and st["uav1/mocap/uav1/pose"].count >= ticks + 1
            ),
            15,
        )
        report = rec.stop()
    finally:
        rec.stop()
        rec_s.close()
        pub_s.close()
    assert report.error == ""
    assert report.missed == 0 and report.dropped == 0
    return out, lab, frames


def test_exact_counts_with_mcap(recording: tuple[Path, LabConfig, int]) -> None:
    out, _lab, frames = recording
    assert frames == int(SIM_SECONDS * CAMERA_HZ) + 1
    with out.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert counts["/uav1/mocap/uav1/pose"] == int(SIM_SECONDS * MOCAP_HZ) + 1
    for cam in ("color", "depth", "left", "right"):
        assert counts[f"/uav1/camera/{cam}/image"] == frames
        assert counts[f"/uav1/camera/{cam}/camera_info"] == frames
    assert counts["/uav1/tf"] == frames
    assert {"flightkit", "config", "extrinsics", "calibration", "calibration.color"} <= set(meta)
    assert meta["calibration.color"]["width"] == "320"
    assert summary.channels[next(iter(summary.channels))].message_encoding == "cdr"


def test_rosbags_reads_images_and_poses_equal_truth(recording: tuple[Path, LabConfig, int]) -> None:
    out, lab, frames = recording
    T_body_camera = lab.camera.T_body_camera.to_transform()  # noqa: N806
    with AnyReader([out]) as ar:
        by_topic = {c.topic: c for c in ar.connections}
        assert by_topic["/uav1/camera/color/image"].msgtype == "sensor_msgs/msg/Image"
        n_img = 0
        for conn, _t, raw in ar.messages(connections=[by_topic["/uav1/camera/color/image"]]):
            msg = ar.deserialize(raw, conn.msgtype)
            img = np.asarray(msg.data).reshape(msg.height, msg.width, 3)
            assert msg.encoding == "rgb8" and img.std() > 10
            n_img += 1
        assert n_img == frames
        for conn, _t, raw in ar.messages(connections=[by_topic["/uav1/camera/depth/image"]]):
            msg = ar.deserialize(raw, conn.msgtype)
            depth = np.frombuffer(bytes(msg.data), "<u2").reshape(msg.height, msg.width)
            assert msg.encoding == "16UC1" and 100 < np.median(depth[depth > 0]) < 10000
        clock0 = LockstepClock()  # same epoch as the recording's clock
        n_pose = 0
        for conn, _t, raw in ar.messages(connections=[by_topic["/uav1/mocap/uav1/pose"]]):
            msg = ar.deserialize(raw, conn.msgtype)
            stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            t_s = (stamp_ns - clock0.time_ns()) * 1e-9
            expected = T_WORLD_MOCAP.inverse() @ truth_at(t_s)
            p = msg.pose.position
            q = msg.pose.orientation
            got = Transform.from_quat_xyzw([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
            assert got.almost_equal(expected, 1e-9, 1e-9)
            n_pose += 1
        assert n_pose == int(SIM_SECONDS * MOCAP_HZ) + 1
    # The camera's ground truth on tf is the body truth through the extrinsics, exactly.
    with out.open("rb") as fh:
        for _s, _c, m in make_reader(fh).iter_messages(topics=["/uav1/tf"]):
            tf = TFMessage.decode(m.data)
            gt = next(t for t in tf.transforms if t.child_frame_id.endswith("camera_gt"))
            t_s = (gt.header.stamp_ns - LockstepClock().time_ns()) * 1e-9
            assert gt.to_transform().almost_equal(truth_at(t_s) @ T_body_camera, 1e-9, 1e-9)


def test_recorded_image_matches_a_fresh_render(recording: tuple[Path, LabConfig, int]) -> None:
    out, lab, _ = recording
    from flightkit.sim.camera import SimCamera

    cam = SimCamera.from_config(lab.camera)
    with out.open("rb") as fh:
        _s, _c, m = next(iter(make_reader(fh).iter_messages(topics=["/uav1/camera/color/image"])))
    img = Image.decode(m.data)
    t_s = (img.header.stamp_ns - LockstepClock().time_ns()) * 1e-9
    fresh = cam.render(truth_at(t_s) @ lab.camera.T_body_camera.to_transform())
    assert np.array_equal(img.array(), fresh.color_rgb)


def test_export_tum_follows_the_format_and_loads_back(recording: tuple[Path, LabConfig, int], tmp_path: Path) -> None:
    out, lab, frames = recording
    dst = tmp_path / "tum"
    seen: list[tuple[int, int]] = []
    rep = export_recording(out, dst, "tum", max_diff_s=0.02, progress=lambda d, t: seen.append((d, t)))
    assert rep.images == frames and rep.depth_images == frames and rep.associated_depth == frames
    assert seen[-1] == (2 * frames, 2 * frames)
    # rgb.txt / depth.txt: '#' comments, then "timestamp filename", increasing, files exist.
    for name, folder in (("rgb.txt", "rgb"), ("depth.txt", "depth")):
        rows = [ln.split() for ln in (dst / name).read_text().splitlines() if not ln.startswith("#")]
        assert len(rows) == frames
        stamps = [float(r[0]) for r in rows]
        assert stamps == sorted(stamps)
        assert all(r[1].startswith(folder + "/") and (dst / r[1]).is_file() for r in rows)
    depth_file = dst / (dst / "depth.txt").read_text().splitlines()[-1].split()[1]
    depth = cv2.imread(str(depth_file), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (240, 320)
    # 5000 units per metre: compare with the recorded millimetres.
    with out.open("rb") as fh:
        msgs = list(make_reader(fh).iter_messages(topics=["/uav1/camera/depth/image"]))
    mm = Image.decode(msgs[-1][2].data).array()
    assert np.array_equal(depth.astype(np.int64), np.minimum(mm.astype(np.int64) * 5, 65535))
    # groundtruth.txt is the colour camera's pose in the world frame (the recording's T_world_mocap
    # applied), at the mocap stamps.
    gt = read_tum(dst / "groundtruth.txt")
    assert len(gt) == int(SIM_SECONDS * MOCAP_HZ) + 1
    T_bc = lab.camera.T_body_camera.to_transform()  # noqa: N806
    t0 = LockstepClock().time_ns()
    for i in (0, len(gt) // 2, len(gt) - 1):
        expected = truth_at((int(gt.stamps_ns[i]) - t0) * 1e-9) @ T_bc
        assert gt.transform(i).almost_equal(expected, 1e-8, 1e-8)
    assert "world frame" in (dst / "groundtruth.txt").read_text().splitlines()[0] and rep.frame == "world"
    assoc = (dst / "associations.txt").read_text().splitlines()
    assert len(assoc) == frames and all(len(a.split()) == 4 for a in assoc)
    assert len((dst / "associations_gt.txt").read_text().splitlines()) == frames
    # Loads back as an estimator input, with the exported calibration (read from camera.yaml).
    K = read_tum_camera_yaml(dst)  # noqa: N806
    assert "readout_s" not in (dst / "camera.yaml").read_text() and K.readout_s == 0.0  # global shutter: as before
    fx, fy, cx, cy = lab.camera.intrinsics()
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (fx, fy, cx, cy, 320, 240)
    seq = open_sequence(dst)
    assert seq.intrinsics == K
    assert len(seq) == frames and seq.has_groundtruth()
    frame = next(iter(seq.frames()))
    assert frame.color_bgr is not None and frame.depth_m is not None
    assert frame.T_world_camera is not None
    assert np.allclose(frame.depth_m[frame.depth_m > 0], mm_first_frame(out)[frame.depth_m > 0] / 1000.0, atol=1e-3)


def test_export_in_the_mocap_frame_on_request(recording: tuple[Path, LabConfig, int], tmp_path: Path) -> None:
    out, lab, _frames = recording
    rep = export_recording(out, tmp_path / "tum_mocap", "tum", frame="mocap")
    assert rep.frame == "mocap"
    gt = read_tum(tmp_path / "tum_mocap" / "groundtruth.txt")
    t0 = LockstepClock().time_ns()
    T_bc = lab.camera.T_body_camera.to_transform()  # noqa: N806
    i = len(gt) // 2
    expected = T_WORLD_MOCAP.inverse() @ truth_at((int(gt.stamps_ns[i]) - t0) * 1e-9) @ T_bc
    assert gt.transform(i).almost_equal(expected, 1e-8, 1e-8)


def mm_first_frame(out: Path) -> np.ndarray:
    with out.open("rb") as fh:
        _s, _c, m = next(iter(make_reader(fh).iter_messages(topics=["/uav1/camera/depth/image"])))
    return Image.decode(m.data).array().astype(np.float64)


def test_export_euroc_follows_the_format_and_loads_back(recording: tuple[Path, LabConfig, int], tmp_path: Path) -> None:
    out, lab, frames = recording
    dst = tmp_path / "euroc"
    rep = export_recording(out, dst, "euroc")
    assert rep.images == frames and rep.right_images == frames
    for cam in ("cam0", "cam1"):
        lines = (dst / "mav0" / cam / "data.csv").read_text().splitlines()
        assert lines[0] == "#timestamp [ns],filename"
        for row in lines[1:]:
            stamp, name = row.split(",")
            assert name == f"{int(stamp)}.png" and (dst / "mav0" / cam / "data" / name).is_file()
    gt_lines = (dst / "mav0" / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
    assert gt_lines[0].startswith("#timestamp") and all(len(r.split(",")) == 17 for r in gt_lines[1:])
    assert len(gt_lines) - 1 == int(SIM_SECONDS * MOCAP_HZ) + 1
    assert not any("readout_s" in (dst / "mav0" / c / "sensor.yaml").read_text() for c in ("cam0", "cam1"))
    seq = open_sequence(dst)  # rectified stereo by default: the pair is already rectified
    assert len(seq) == frames and seq.intrinsics.readout_s == 0.0
    assert seq.baseline_m == pytest.approx(lab.camera.stereo_baseline_m, rel=1e-6)
    frame = next(iter(seq.frames()))
    assert frame.right_gray is not None and frame.T_world_camera is not None
    t0 = LockstepClock().time_ns()
    expected = truth_at((frame.stamp_ns - t0) * 1e-9) @ lab.camera.T_body_camera.to_transform()
    assert frame.T_world_camera.almost_equal(expected, 1e-6, 1e-6)
    raw = open_sequence(dst, rectify=False, stereo=False)
    assert len(raw) == frames


def test_mcap_sequence_reads_the_recording_in_the_world_frame(recording: tuple[Path, LabConfig, int]) -> None:
    out, lab, frames = recording
    seq = open_sequence(out)  # frames and extrinsics from the recording's own metadata
    assert len(seq) == frames and seq.depth_intrinsics is not None
    # The simulated camera is a global shutter and says so over the bus.
    assert RecordingReader(out).metadata["calibration.color"]["readout_s"] == "0.0"
    assert seq.intrinsics.readout_s == 0.0 and seq.depth_intrinsics.readout_s == 0.0
    assert seq.baseline_m == pytest.approx(lab.camera.stereo_baseline_m)
    gt = seq.groundtruth()
    t0 = LockstepClock().time_ns()
    i = len(gt) // 3
    expected = truth_at((int(gt.stamps_ns[i]) - t0) * 1e-9) @ lab.camera.T_body_camera.to_transform()
    assert gt.transform(i).almost_equal(expected, 1e-8, 1e-8)


def with_readout(src: Path, dst: Path, readout_s: str, cameras: tuple[str, ...]) -> Path:
    """A copy of ``src`` whose cameras' calibration records give ``readout_s``, as a recorder writes
    them when the cameras answer with one."""
    meta = RecordingReader(src).metadata
    for cam in cameras:
        with_metadata(src, dst, f"calibration.{cam}", {**meta[f"calibration.{cam}"], "readout_s": readout_s},
                      allow_overwrite=True)
        src = dst
    return dst


def test_exports_keep_the_readout_and_load_it_back(recording: tuple[Path, LabConfig, int], tmp_path: Path) -> None:
    out, _lab, frames = recording
    rs = with_readout(out, tmp_path / "rs.mcap", "0.02", ("color", "left", "right"))
    tum = tmp_path / "tum"
    export_recording(rs, tum, "tum")
    assert "Camera.readout_s: 0.02\n" in (tum / "camera.yaml").read_text()
    assert read_tum_camera_yaml(tum).readout_s == 0.02 and open_sequence(tum).intrinsics.readout_s == 0.02
    euroc = tmp_path / "euroc"
    rep = export_recording(rs, euroc, "euroc")
    assert rep.camera == "left" and rep.right_images == frames
    for cam in ("cam0", "cam1"):
        assert "\nreadout_s: 0.02 #" in (euroc / "mav0" / cam / "sensor.yaml").read_text(), cam
    assert open_sequence(euroc).intrinsics.readout_s == 0.02  # rectified: the left camera's rows, same timing
    assert open_sequence(euroc, rectify=False, stereo=False).intrinsics.readout_s == 0.02


def test_vo_run_uses_the_recorded_readout(recording: tuple[Path, LabConfig, int], tmp_path: Path) -> None:
    """`flightkit vo run` on a recording with a readout: the same trajectory as `--readout-ms` on the
    recording without one, and not the global-shutter trajectory."""
    from flightkit.cli.main import main

    out, _lab, _frames = recording
    rs = with_readout(out, tmp_path / "rs.mcap", "0.02", ("color",))
    runs = {"recorded": [str(rs)], "given": [str(out), "--readout-ms", "20"], "global": [str(out)]}
    for name, args in runs.items():
        assert main(["vo", "run", *args, "--method", "rgbd-pnp", "-o", str(tmp_path / f"{name}.txt")]) == 0
    recorded, given, glob = (read_tum(tmp_path / f"{n}.txt") for n in runs)
    assert np.array_equal(recorded.stamps_ns, given.stamps_ns)
    assert np.array_equal(recorded.positions, given.positions) and np.array_equal(recorded.quats_wxyz, given.quats_wxyz)
    assert np.abs(recorded.positions - glob.positions).max() > 1e-4  # the readout moved it (by ~2 mm here)


def test_vo_runs_on_a_recording_cut_between_colour_and_depth(
    recording: tuple[Path, LabConfig, int], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A recording that stopped after the last colour image but before its depth image (or lost
    that depth message) still gives a trajectory: the incomplete frame is skipped and counted."""
    from mcap.writer import Writer

    from estimation.pipeline import run_vo

    out, lab, frames = recording
    cut = tmp_path / "cut.mcap"
    with out.open("rb") as src, cut.open("wb") as dst:
        reader = make_reader(src)
        writer = Writer(dst)
        writer.start(profile="ros2", library="test")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        messages = list(reader.iter_messages(log_time_order=True))
        depth = [i for i, (_s, c, _m) in enumerate(messages) if c.topic == "/uav1/camera/depth/image"]
        for i, (schema, channel, message) in enumerate(messages):
            if i == depth[-1]:
                continue  # the last depth image never made it to the file
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channel_ids:
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_ids.get(channel.schema_id, 0), channel.metadata
                )
            writer.add_message(channel_ids[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()
    seq = open_sequence(cut, T_body_camera=lab.camera.T_body_camera.to_transform())
    assert len(seq) == frames
    with caplog.at_level("WARNING", logger="estimation.pipeline"):
        result = run_vo(seq, "rgbd-pnp", init_from_groundtruth=True)
    assert len(result) == frames - 1
    assert result.stamps_ns[-1] == seq.stamps_ns()[-2]
    assert "skipped 1 of" in caplog.text and "no depth image" in caplog.text


def test_camera_thread_publishes_every_due_frame(sessions: tuple[object, object]) -> None:
    pub_s, _ = sessions
    clock = LockstepClock()
    cfg = CameraConfig(width_px=160, height_px=120, rate_hz=10.0)
    cam = SimCameraPublisher(
        pub_s,
        Keys("uav9"),
        truth_at,
        cfg,
        clock,
        streams=CaptureConfig(depth=False, tf=False).streams(),
    )
    with cam:
        for k in range(1, 6):
            cam.wait_frames(k, 10)
            clock.advance(0.1)
        assert cam.wait_frames(6, 10) == 6
        assert cam.frames_skipped == 0
