"""The simulated camera and mocap publish with the injected timing errors and mount, on the bus."""

from __future__ import annotations

import math

import numpy as np

from capture.bus_recorder import BusRecorder
from flightkit.bus.keys import Keys
from flightkit.bus.session import open_session
from flightkit.clock import LockstepClock
from flightkit.config import BusConfig, CameraConfig
from flightkit.datasets.mcap_reader import RecordingReader, header_stamp_ns
from flightkit.frames import Transform
from flightkit.sim.camera_publisher import SimCameraPublisher
from flightkit.sim.mocap import SimMocapPublisher, SimMocapSystem
from flightkit.sim.timing_errors import SimTimingErrors
from tests.conftest import free_tcp_port, wait

MOCAP_HZ, CAMERA_HZ = 120, 10


def truth_at(t_s: float) -> Transform:
    a = 0.5 * t_s
    return Transform.from_xyz_yaw([math.cos(a), math.sin(a), 1.5], a + math.pi)


def test_camera_stamps_late_and_drifting_and_mocap_stamped_at_capture_with_the_bus_time(tmp_path) -> None:
    port = free_tcp_port()
    pub_s = open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    rec_s = open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",)))
    clock = LockstepClock()
    t0_ns = clock.time_ns()
    keys = Keys("uav1")
    timing = SimTimingErrors(camera_time_offset_s=0.04, camera_drift_ppm=500.0, mocap_latency_s=0.025)
    mount = Transform.from_xyz_euler_deg([0.1, 0.0, 0.0], "xz", [130.0, 90.0])
    cam = SimCameraPublisher(pub_s, keys, truth_at, CameraConfig(width_px=160, height_px=120, rate_hz=CAMERA_HZ),
                             clock, timing=timing, true_T_body_camera=mount)
    system = SimMocapSystem(clock, {"uav1": truth_at}, rate_hz=MOCAP_HZ, latency_s=timing.mocap_latency_s)
    mocap = SimMocapPublisher(pub_s, keys, system)
    out = tmp_path / "run.mcap"
    rec = BusRecorder(rec_s, out, ["uav1/**"], compression="none")
    try:
        wait(lambda: cam.has_subscribers and mocap.has_subscribers, 10, "the recorder to subscribe")
        cam.start()
        mocap.start()
        ticks = MOCAP_HZ
        for k in range(ticks + 1):
            wait(lambda k=k: mocap.published >= k + 1, 10, f"mocap tick {k}")
            cam.wait_frames(k // (MOCAP_HZ // CAMERA_HZ) + 1, 10)
            if k < ticks:
                clock.advance(1.0 / MOCAP_HZ)
        frames = cam.frames_published
        mocap.stop()
        cam.stop()
        rec.wait_for(lambda st: st.get("uav1/camera/color/image") is not None
                     and st["uav1/camera/color/image"].count >= frames
                     and st["uav1/mocap/uav1/pose"].count >= ticks + 1, 15)
        rec.stop()
    finally:
        rec.stop()
        rec_s.close()
        pub_s.close()
    reader = RecordingReader(out)
    stamps = [header_stamp_ns(m.data) for m in reader.messages(["/uav1/camera/color/image"])]
    true_ns = t0_ns + np.round(np.arange(len(stamps)) / CAMERA_HZ * 1e9).astype(np.int64)
    want = [timing.camera_stamp_ns(int(t), t0_ns) for t in true_ns]
    assert np.max(np.abs(np.array(stamps) - np.array(want))) <= 1_000  # ns: the lock-step clock's rounding
    assert abs(stamps[-1] - true_ns[-1] - (40_000_000 + 500_000)) <= 1_000  # 40 ms late, plus 500 ppm of 1 s
    gt = reader.pose_trajectory("/uav1/mocap/uav1/pose")
    late = gt.transform(len(gt) - 1)  # on the bus at 1 s, captured (and stamped) at 0.975 s
    assert late.almost_equal(truth_at(1.0 - 0.025), tol_m=1e-6, tol_rad=1e-6)
    assert abs(gt.stamps_ns[-1] - (t0_ns + 1_000_000_000 - 25_000_000)) <= 1_000
    # both times recorded: the capture stamp in the header, the bus time as MCAP publish_time
    pose_msgs = list(reader.messages(["/uav1/mocap/uav1/pose"]))
    bus_minus_capture = np.array([m.publish_time_ns - header_stamp_ns(m.data) for m in pose_msgs])
    assert len(pose_msgs) == MOCAP_HZ + 1 and np.all(np.abs(bus_minus_capture - 25_000_000) <= 1_000)
    images = list(reader.messages(["/uav1/camera/color/image"]))
    bus_ns = np.array([m.publish_time_ns for m in images])
    assert np.all(np.abs(bus_ns - true_ns) <= 1_000)  # on the bus at the true exposure time
    assert {s.capture_stamp for s in reader.streams} == {"device"}  # images, camera_info, poses and tf
    assert cam.last_T_world_camera.almost_equal(truth_at(1.0) @ mount, tol_m=1e-9, tol_rad=1e-9)
