"""Capture sources over a real loopback Zenoh session into a BusRecorder, and the recorder's MCAP writer.

Each source publishes on one session, a BusRecorder on a second session (connected over TCP
on a free loopback port) writes the MCAP file, and the file's contents are checked.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from capture.bus_recorder import BusRecorder
from capture.export import export_recording
from capture.recorder import Compression, Recorder, StreamSample
from capture.sources.mocap import MocapBridge
from capture.sources.opencv import OpenCVCameraPublisher
from capture.sources.replay import DatasetReplayPublisher, McapReplayPublisher
from flightkit.bus.image_msgs import CameraInfo, CompressedImage, Image
from flightkit.bus.keys import Keys
from flightkit.bus.msg_base import Header, schema_text
from flightkit.bus.pose_msgs import PoseStamped, TFMessage, TransformStamped
from flightkit.bus.session import open_session
from flightkit.clock import SimClock, WallClock
from flightkit.config import BusConfig
from flightkit.datasets import open_sequence, read_tum
from flightkit.datasets.mcap_metadata import with_metadata
from flightkit.datasets.mcap_reader import RecordingReader
from flightkit.datasets.mcap_writer import FastMcapWriter
from flightkit.datasets.tum import read_tum_camera_yaml
from flightkit.frames import Transform, WorldFrames
from flightkit.mocap.bus_source import BusMocapSource
from flightkit.mocap.motioncapture_source import MotionCaptureSource, mock_rigid_bodies
from tests.conftest import free_tcp_port, wait

T0_NS = 1_700_000_000_000_000_000






def messages(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> [(publish_time, payload)] in log-time order."""
    out: dict[str, list[tuple[int, bytes]]] = {}
    with path.open("rb") as fh:
        for _s, ch, m in make_reader(fh).iter_messages(log_time_order=True):
            out.setdefault(ch.topic, []).append((m.publish_time, bytes(m.data)))
    return out


def schemas(path: Path) -> dict[str, str]:
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    return {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}


# --------------------------------------------------------------------------- a small lab recording


def write_lab_recording(path: Path, frames: int = 12, w: int = 64, h: int = 48) -> None:
    """Colour (rgb8) + depth (16UC1 mm) + camera_info at 20 Hz, mocap at 100 Hz, tf once."""
    rng = np.random.default_rng(3)
    rec = Recorder(path, schema_text, compression=Compression.ZSTD, chunk_size=64 << 10)
    seq: dict[str, int] = {}

    def put(topic: str, msgtype: str, payload: bytes, stamp: int, reliable: bool = True) -> None:
        seq[topic] = seq.get(topic, 0) + 1
        rec.offer(StreamSample(topic, msgtype, payload, seq[topic], stamp, stamp + 1000, reliable))

    events: list[tuple[int, int]] = [(T0_NS + i * 10_000_000, 0) for i in range(frames * 5 + 3)]
    events += [(T0_NS + 5_000_000 + i * 50_000_000, 1) for i in range(frames)]
    for stamp, kind in sorted(events):
        if kind == 0:
            t = (stamp - T0_NS) * 1e-9
            pose = Transform.from_xyz_yaw([math.cos(t), math.sin(t), 1.5], t + 0.3)
            put(
                "uav1/mocap/uav1/pose",
                PoseStamped.TYPE,
                bytes(PoseStamped.from_transform(stamp, "mocap", pose).encode()),
                stamp,
            )
            continue
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        depth = rng.integers(300, 9000, (h, w), dtype=np.uint16)
        depth[0, :5] = 0
        hdr = Header(stamp, "uav1/camera_color_optical")
        put(
            "uav1/camera/color/image",
            Image.TYPE,
            bytes(Image.from_array(hdr, rgb, "rgb8").encode()),
            stamp,
            False,
        )
        put(
            "uav1/camera/depth/image",
            Image.TYPE,
            bytes(Image.from_array(hdr, depth, "16UC1").encode()),
            stamp,
            False,
        )
        info_msg = CameraInfo.from_intrinsics(
            hdr, w, h, 60.0, 61.0, 31.5, 23.5, d=(0.01, -0.02, 0.0, 0.0, 0.003)
        )
        put("uav1/camera/color/camera_info", CameraInfo.TYPE, bytes(info_msg.encode()), stamp)
        put("uav1/camera/depth/camera_info", CameraInfo.TYPE, bytes(info_msg.encode()), stamp)
    tf = TFMessage((TransformStamped.from_transform(T0_NS, "uav1/base_link", "uav1/cam", Transform()),))
    put("uav1/tf", TFMessage.TYPE, bytes(tf.encode()), T0_NS)
    report = rec.close()
    assert report.error == "" and report.dropped == 0


# --------------------------------------------------------------------------- the writer


@pytest.mark.parametrize("compression", ["", "zstd", "lz4"])
def test_fast_writer_files_read_back_everywhere(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "w.mcap"
    rng = np.random.default_rng(1)
    payloads = [bytes(rng.integers(0, 256, int(n), dtype=np.uint8)) for n in rng.integers(0, 5000, 50)]
    with path.open("wb", buffering=0) as fh:
        w = FastMcapWriter(fh, compression)
        w.start("ros2", "test")
        sid = w.register_schema(Image.TYPE, "ros2msg", schema_text(Image.TYPE).encode())
        c1 = w.register_channel("/a", "cdr", sid, {"k": "v"})
        c2 = w.register_channel("/b", "cdr", sid, {})
        w.add_metadata("m1", {"x": "1"})
        for i, p in enumerate(payloads):
            w.add_message(c1 if i % 3 else c2, 1000 - i if i == 7 else 1000 + i, p, 5 + i, i)
            if i % 17 == 16:
                w.flush_chunk()
        w.add_metadata("m2", {"y": "2"})
        w.finish()
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 50 and summary.statistics.chunk_count == 3
        assert summary.statistics.channel_message_counts == {0: 33, 1: 17}
        assert summary.statistics.message_start_time == 1000 - 7
        got = [
            (m.channel_id, m.sequence, m.publish_time, bytes(m.data))
            for _s, _c, m in reader.iter_messages(log_time_order=False)
        ]
        assert sorted(got, key=lambda g: g[1]) == [
            (0 if i % 3 else 1, i, 5 + i, p) for i, p in enumerate(payloads)
        ]
        assert {m.name: m.metadata for m in reader.iter_metadata()} == {"m1": {"x": "1"}, "m2": {"y": "2"}}
        # Indexed reads use the chunk and message indexes.
        only_b = [
            m.sequence
            for _s, _c, m in reader.iter_messages(topics=["/b"], starting_at=1000, ending_before=1020)
        ]
        assert only_b == [i for i in range(0, 20) if i % 3 == 0 and i != 7 and 1000 + i < 1020]
    with AnyReader([path]) as ar:
        assert sorted(c.topic for c in ar.connections) == ["/a", "/b"]
        assert sum(1 for _ in ar.messages()) == 50


# --------------------------------------------------------------------------- OpenCV: video file


def make_video(path: Path, frames: int, w: int = 160, h: int = 120, fps: float = 30.0, **calibration: float) -> None:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened(), "OpenCV cannot write MJPG here"
    for i in range(frames):
        img = np.zeros((h, w, 3), np.uint8)
        img[:, :, 0] = (np.arange(w) * 255 // w).astype(np.uint8)
        img[:, :, 1] = 40 * (i % 6)
        cv2.putText(img, str(i), (10, 80), cv2.FONT_HERSHEY_SIMPLEX, 2.0, (255, 255, 255), 3)
        vw.write(img)
    vw.release()
    path.with_suffix(".json").write_text(
        json.dumps(
            {
                "fx": 150.0,
                "fy": 151.0,
                "cx": 79.5,
                "cy": 59.5,
                "width": w,
                "height": h,
                "dist": [0.1, -0.05, 0.0, 0.0, 0.0],
                **calibration,
            }
        )
    )


def decoded_frames(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        out.append(img)
    cap.release()
    return out


@pytest.mark.parametrize("fmt", ["bgr8", "rgb8", "jpeg"])
def test_video_file_frames_decode(sessions: tuple[object, object], tmp_path: Path, fmt: str) -> None:
    pub_s, rec_s = sessions
    video = tmp_path / "clip.avi"
    make_video(video, 15)
    truth = decoded_frames(video)
    assert len(truth) == 15
    clock = SimClock(speed=1.0)  # 0.5 s of pacing: room for a loaded machine under the upper bound
    out = tmp_path / "video.mcap"
    cam = OpenCVCameraPublisher(
        pub_s, Keys("uav1"), str(video), clock, color_format=fmt, jpeg_quality=0 if fmt == "bgr8" else 95
    )
    with BusRecorder(rec_s, out, ["uav1/**"], compression="none") as rec:
        wait(lambda: cam.has_subscribers, 10, "the recorder to subscribe")
        with cam:
            assert cam.wait_finished(30) == 15
        image_key = "uav1/camera/color/image" + ("/compressed" if fmt == "jpeg" else "")
        rec.wait_for(
            lambda st: (
                image_key in st
                and st[image_key].count >= 15
                and st.get("uav1/camera/color/camera_info") is not None
                and st["uav1/camera/color/camera_info"].count >= 15
            ),
            10,
        )
    msgs = messages(out)
    extra = {"/uav1/camera/color/image/compressed"} if fmt == "rgb8" else set()  # raw + JPEG
    assert set(msgs) == {"/" + image_key, "/uav1/camera/color/camera_info"} | extra
    stamps = []
    for (pub_t, raw), want in zip(msgs["/" + image_key], truth, strict=True):
        if fmt == "jpeg":
            c = CompressedImage.decode(raw)
            assert c.format == "jpeg"
            img = cv2.imdecode(np.asarray(c.data), cv2.IMREAD_COLOR)
            assert np.abs(img.astype(int) - want.astype(int)).mean() < 3.0
            stamps.append(c.header.stamp_ns)
        else:
            m = Image.decode(raw)
            assert m.encoding == fmt and (m.width, m.height) == (160, 120)
            arr = m.array()
            assert np.array_equal(arr if fmt == "bgr8" else arr[:, :, ::-1], want)
            stamps.append(m.header.stamp_ns)
        assert stamps[-1] <= pub_t < stamps[-1] + 10**9  # on the bus (MCAP publish_time) after the grab
    # Stamped from the clock at grab time, paced at the file's 30 fps on the clock: frame n is
    # due n/30 s of clock time after frame 0, never earlier.
    span_s = (stamps[-1] - stamps[0]) * 1e-9
    assert np.all(np.diff(stamps) > 0) and 14 / 30 - 0.005 <= span_s < 3 * 14 / 30
    assert {st.topic: st.capture_stamp for st in RecordingReader(out).streams}["/" + image_key] == "host"  # a file
    info = CameraInfo.decode(msgs["/uav1/camera/color/camera_info"][0][1])
    assert info.k[0] == 150.0 and info.k[4] == 151.0 and info.k[2] == 79.5 and info.d[:2] == (0.1, -0.05)
    # A calibration without a readout: the camera says 0, and the recording reads as a global shutter.
    assert RecordingReader(out).metadata["calibration.color"]["readout_s"] == "0.0"
    assert open_sequence(out).intrinsics.readout_s == 0.0


def test_missing_device_retries_without_raising(
    sessions: tuple[object, object], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    pub_s, _ = sessions
    calib = tmp_path / "cal.json"
    calib.write_text(json.dumps({"fx": 100, "fy": 100, "cx": 80, "cy": 60, "width": 160, "height": 120}))
    clock = SimClock(speed=50.0)
    cam = OpenCVCameraPublisher(
        pub_s, Keys("uav1"), "/dev/video-does-not-exist", clock, calibration=calib, retry_s=0.5
    )
    with caplog.at_level("WARNING", logger="capture.sources.opencv"), cam:
        wait(lambda: "is not available" in caplog.text, 10, "the warning")
        t = clock.monotonic_s()
        wait(lambda: clock.monotonic_s() > t + 2.0, 10, "a few retries")
    assert cam.error is None and cam.published == 0
    assert caplog.text.count("is not available") == 1  # said once, not per retry


# --------------------------------------------------------------------------- replay: MCAP


def test_mcap_replay_gives_identical_payloads(sessions: tuple[object, object], tmp_path: Path) -> None:
    pub_s, rec_s = sessions
    src = tmp_path / "src.mcap"
    write_lab_recording(tmp_path / "plain.mcap")
    # The colour camera recorded with a rolling-shutter readout: the replay serves it again.
    with_metadata(tmp_path / "plain.mcap", src, "calibration.color",
                  {"topic": "uav1/camera/color/camera_info", "readout_s": "0.02"})
    want = messages(src)
    replay = McapReplayPublisher(pub_s, src, SimClock(speed=10.0))
    assert replay.total == sum(len(v) for v in want.values())
    out = tmp_path / "replayed.mcap"
    infos = {"uav1/camera/color/camera_info", "uav1/camera/depth/camera_info"}
    with BusRecorder(rec_s, out, ["uav1/**"], compression="lz4") as rec:
        wait(lambda: replay.has_subscribers, 10, "the recorder to subscribe")
        t0 = time.monotonic()
        with replay:
            assert replay.wait_finished(30) == replay.total
            wall_s = time.monotonic() - t0
            wait(lambda: rec.calibrated == infos, 10, "the calibration records")
        rec.wait_for(lambda st: sum(s.count for s in st.values()) >= replay.total, 10)
    replayed = RecordingReader(out)
    assert replayed.camera_readout_s("/uav1/camera/color/camera_info") == 0.02
    assert "readout_s" not in replayed.metadata["calibration.depth"]  # none recorded, none served
    got = messages(out)
    assert set(got) == set(want)
    for topic in want:
        assert got[topic] == want[topic], topic  # same bytes, same publish stamps, same order
    assert schemas(out) == schemas(src)
    # Paced: 0.62 s of recording at 10x on the clock takes ~62 ms of wall time, not nothing.
    assert wall_s > 0.05


# --------------------------------------------------------------------------- replay: TUM folder round trip


def tum_rows(path: Path) -> list[list[str]]:
    return [ln.split() for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]


def test_tum_folder_round_trips(sessions: tuple[object, object], tmp_path: Path) -> None:
    pub_s, rec_s = sessions
    src = tmp_path / "src.mcap"
    write_lab_recording(tmp_path / "plain.mcap")
    with_metadata(tmp_path / "plain.mcap", src, "calibration.color",
                  {"topic": "uav1/camera/color/camera_info", "readout_s": "0.02"})
    first = tmp_path / "tum1"
    rep1 = export_recording(src, first, "tum")
    assert rep1.images == 12 and rep1.depth_images == 12 and rep1.groundtruth_poses == 63
    assert "Camera.readout_s: 0.02\n" in (first / "camera.yaml").read_text()
    assert read_tum_camera_yaml(first).readout_s == 0.02  # what export writes, the TUM loader reads
    replay = DatasetReplayPublisher(pub_s, Keys("uav1"), first, SimClock(speed=20.0), gt_body="uav1")
    assert replay.main_name == "color" and replay.depth is not None
    out = tmp_path / "replayed.mcap"
    with BusRecorder(rec_s, out, ["uav1/**"], compression="zstd") as rec:
        wait(lambda: replay.has_subscribers, 10, "the recorder to subscribe")
        with replay:
            assert replay.wait_finished(30) == 12
            wait(lambda: "uav1/camera/color/camera_info" in rec.calibrated, 10, "the calibration record")
        assert replay.poses_published == 63
        rec.wait_for(
            lambda st: (
                st.get("uav1/camera/depth/image") is not None
                and st["uav1/camera/depth/image"].count >= 12
                and st["uav1/mocap/uav1/pose"].count >= 63
                and st["uav1/camera/color/image"].count >= 12
            ),
            10,
        )
    second = tmp_path / "tum2"
    rep2 = export_recording(out, second, "tum")
    assert (rep2.images, rep2.depth_images, rep2.groundtruth_poses) == (12, 12, 63)
    for name in ("rgb.txt", "depth.txt", "associations.txt"):
        assert tum_rows(second / name) == tum_rows(first / name), name
    for row in tum_rows(first / "rgb.txt") + tum_rows(first / "depth.txt"):
        a = cv2.imread(str(first / row[1]), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(second / row[1]), cv2.IMREAD_UNCHANGED)
        assert a.dtype == b.dtype and np.array_equal(a, b), row[1]
    g1, g2 = read_tum(first / "groundtruth.txt"), read_tum(second / "groundtruth.txt")
    assert np.array_equal(g1.stamps_ns, g2.stamps_ns)
    assert np.allclose(g1.positions, g2.positions, atol=1e-9) and np.allclose(
        g1.quats_wxyz, g2.quats_wxyz, atol=1e-9
    )
    assert (first / "camera.yaml").read_text().split("\n")[3:] == (second / "camera.yaml").read_text().split(
        "\n"
    )[3:]
    assert open_sequence(out).intrinsics.readout_s == 0.02  # dataset -> bus -> recording


def test_euroc_stereo_replay_publishes_the_rectified_pair(
    sessions: tuple[object, object], tmp_path: Path, shared_data: Path
) -> None:
    from flightkit.datasets import open_sequence

    pub_s, rec_s = sessions
    folder = shared_data / "euroc_v101_static"
    replay = DatasetReplayPublisher(pub_s, Keys("uav1"), folder, SimClock(speed=10.0))
    assert (replay.main_name, replay.main_encoding, replay.depth) == ("left", "mono8", None)
    n = len(replay.seq)
    n_gt = len(replay.gt) if replay.gt is not None else 0
    out = tmp_path / "euroc.mcap"
    with BusRecorder(rec_s, out, ["uav1/**"], compression="zstd") as rec:
        wait(lambda: replay.has_subscribers, 10, "the recorder to subscribe")
        with replay:
            assert replay.wait_finished(30) == n
        rec.wait_for(
            lambda st: st.get("uav1/camera/right/image") is not None
            and st["uav1/camera/right/image"].count >= n
            and st["uav1/mocap/groundtruth/pose"].count >= n_gt,
            10,
        )
    msgs = messages(out)
    assert n == 20 and n_gt > 0 and len(msgs["/uav1/mocap/groundtruth/pose"]) == n_gt
    truth = list(open_sequence(folder).frames())
    for (_t, raw_l), (_t2, raw_r), frame in zip(
        msgs["/uav1/camera/left/image"], msgs["/uav1/camera/right/image"], truth, strict=True
    ):
        left, right = Image.decode(raw_l), Image.decode(raw_r)
        assert left.header.stamp_ns == frame.stamp_ns == right.header.stamp_ns
        assert np.array_equal(left.array(), frame.gray) and np.array_equal(right.array(), frame.right_gray)
    info_r = CameraInfo.decode(msgs["/uav1/camera/right/camera_info"][0][1])
    seq = open_sequence(folder)
    assert info_r.p[3] == pytest.approx(-seq.intrinsics.fx * seq.baseline_m)
    # The replayed recording reads back as a stereo sequence for VO.
    again = open_sequence(out)
    assert len(again) == n and again.baseline_m == pytest.approx(seq.baseline_m)


# --------------------------------------------------------------------------- mocap bridge


def test_mocap_bridge_publishes_mock_system_in_the_mocap_frame(
    sessions: tuple[object, object], tmp_path: Path
) -> None:
    pub_s, rec_s = sessions
    bodies = {
        "rb1": Transform.from_xyz_yaw([1.0, 2.0, 0.5], 0.4),
        "rb2": Transform.from_xyz_yaw([-0.5, 0.25, 1.5], -1.2),
    }
    T_world_mocap = Transform.from_xyz_yaw([0.3, -0.2, 0.0], math.radians(30))  # noqa: N806
    clock = WallClock()
    keys = Keys("uav1")
    out = tmp_path / "mocap.mcap"

    async def run() -> tuple[MocapBridge, dict[str, Transform]]:
        # The source places poses in the world like any flight consumer; the bridge publishes them as
        # the system measured them (nothing undone).
        src = MotionCaptureSource(
            "mock",
            clock,
            options={"rigid_bodies": mock_rigid_bodies(bodies), "rate": "200"},
            frames=WorldFrames(T_world_mocap),
        )
        listener = BusMocapSource(rec_s, keys, clock, WorldFrames(T_world_mocap))
        async with src, listener:
            bridge = MocapBridge(pub_s, keys, src)
            task = asyncio.ensure_future(bridge.run())
            with BusRecorder(rec_s, out, ["uav1/**"], compression="none") as rec:
                deadline = time.monotonic() + 10
                while not all(
                    rec.snapshot().get(f"uav1/mocap/{b}/pose", None) is not None
                    and rec.snapshot()[f"uav1/mocap/{b}/pose"].count >= 20
                    for b in bodies
                ):
                    assert time.monotonic() < deadline, f"bridge published {bridge.per_body}"
                    await asyncio.sleep(0.01)
            seen = {b: (await listener.wait_for_body(b, 5.0)).T_world_body for b in bodies}
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            bridge.close()
            return bridge, seen

    bridge, seen = asyncio.run(run())
    assert bridge.lost_published == 0
    msgs = messages(out)
    assert set(msgs) == {"/uav1/mocap/rb1/pose", "/uav1/mocap/rb2/pose"}
    for body, T in bodies.items():
        rows = msgs[f"/uav1/mocap/{body}/pose"]
        assert len(rows) >= 20
        for pub_t, raw in rows:
            p = PoseStamped.decode(raw)
            assert p.header.frame_id == "mocap" and p.header.stamp_ns <= pub_t  # stamped on arrival, then put
            assert p.to_transform().almost_equal(T, 1e-6, 1e-6)  # the system's own numbers (float32)
        # A bus consumer applying T_world_mocap sees what an in-process consumer sees.
        assert seen[body].almost_equal(T_world_mocap @ T, 1e-6, 1e-6)
    # motioncapture's binding gives no frame time: the recording says the stamps are the host's
    assert {st.capture_stamp for st in RecordingReader(out).streams} == {"host"}


# --------------------------------------------------------------------------- RealSense (hardware)


@pytest.mark.hardware
def test_realsense_publishes_color_and_aligned_depth(sessions: tuple[object, object], tmp_path: Path) -> None:
    from capture.sources.realsense import RealSensePublisher

    pub_s, rec_s = sessions
    out = tmp_path / "rs.mcap"
    cam = RealSensePublisher(pub_s, Keys("uav1"), WallClock(), width_px=640, height_px=480, rate_hz=30)
    with BusRecorder(rec_s, out, ["uav1/**"], compression="none") as rec, cam:
        cam.wait_published(30, 20)
        rec.wait_for(
            lambda st: (
                st.get("uav1/camera/depth/image") is not None and st["uav1/camera/depth/image"].count >= 30
            ),
            10,
        )
    msgs = messages(out)
    depth = Image.decode(msgs["/uav1/camera/depth/image"][-1][1])
    color = Image.decode(msgs["/uav1/camera/color/image"][-1][1])
    assert depth.encoding == "16UC1" and color.encoding == "rgb8"
    assert (depth.width, depth.height) == (color.width, color.height)
    valid = depth.array()[depth.array() > 0]
    assert valid.size > 0 and 100 < np.median(valid) < 10000  # millimetres


# --------------------------------------------------------------------------- CLI


def test_cli_publish_replays_a_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from flightkit.cli.main import main as flightkit_main

    src = tmp_path / "src.mcap"
    write_lab_recording(src, frames=6)
    want = messages(src)
    port = free_tcp_port()
    out = tmp_path / "cli.mcap"
    with open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",))) as rec_s:
        with BusRecorder(rec_s, out, ["uav1/**"], compression="none") as rec:
            rc = flightkit_main(
                [
                    "capture",
                    "publish",
                    f"replay:{src}",
                    "--speed",
                    "inf",
                    "--connect",
                    f"tcp/127.0.0.1:{port}",
                    "--wait-subscribers",
                    "10",
                ]
            )
            assert rc == 0
            total = sum(len(v) for v in want.values())
            rec.wait_for(lambda st: sum(s.count for s in st.values()) >= total, 10)
    assert f"published {total} messages" in capsys.readouterr().out
    assert messages(out) == want


def test_cli_publish_rejects_unknown_sources(capsys: pytest.CaptureFixture[str]) -> None:
    from flightkit.cli.main import main as flightkit_main

    assert flightkit_main(["capture", "publish", "webcam"]) == 2
    assert "camera:0" in capsys.readouterr().err


def test_cli_publish_mocap_bridges_the_configured_system(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from flightkit.cli.main import main as flightkit_main

    lab = tmp_path / "lab.toml"
    lab.write_text(
        '[vehicle]\nnamespace = "lab"\n[mocap]\nsource = "motioncapture"\nsystem_type = "mock"\n'
        '[mocap.options]\nrigid_bodies = "uav7(0.5,0.25,1.0,1,0,0,0)"\nrate = "100"\n'
    )
    port = free_tcp_port()
    out = tmp_path / "mocap.mcap"
    with open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",))) as rec_s:
        with BusRecorder(rec_s, out, ["lab/**"], compression="none") as rec:
            rc = flightkit_main(["capture", "publish", "mocap", "--config", str(lab), "--duration", "0.5",
                                 "--connect", f"tcp/127.0.0.1:{port}"])
            assert rc == 0
            m = __import__("re").search(r"published (\d+) poses", capsys.readouterr().out)
            assert m is not None and int(m.group(1)) > 10
            rec.wait_for(lambda st: "lab/mocap/uav7/pose" in st and st["lab/mocap/uav7/pose"].count >= 5, 10)
    rows = messages(out)["/lab/mocap/uav7/pose"]
    pose = PoseStamped.decode(rows[-1][1])
    assert pose.header.frame_id == "mocap" and pose.position_m == pytest.approx((0.5, 0.25, 1.0))


def test_cli_publish_refuses_to_bridge_the_bus(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from flightkit.cli.main import main as flightkit_main

    assert flightkit_main(["capture", "publish", "mocap"]) == 1  # default mocap.source = "bus"
    assert "already on the bus" in capsys.readouterr().err
