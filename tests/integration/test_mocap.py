"""Mocap sources against real backends: libmotioncapture's mock system, the simulated mocap
publisher over real Zenoh sessions on loopback, and forwarding to the simulated autopilot
over a real MAVLink UDP link."""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from flightkit.bus.keys import Keys
from flightkit.bus.pose_msgs import PoseStamped
from flightkit.bus.pubsub import BusSubscriber
from flightkit.bus.session import open_session
from flightkit.clock import LockstepClock, SimClock
from flightkit.config import BusConfig, MocapConfig, MocapSourceKind, TransformConfig
from flightkit.errors import MocapBodyMissing, MocapError
from flightkit.frames import Transform, WorldFrames
from flightkit.mocap import (
    ForwardStats,
    MocapSource,
    MotionCaptureSource,
    forward_to_vehicle,
    mock_rigid_bodies,
    open_mocap,
)
from flightkit.mocap.bus_source import BusMocapSource
from flightkit.sim.mocap import SimMocapPublisher, SimMocapSystem
from tests.conftest import free_tcp_port

pytestmark = pytest.mark.timeout(90)

T_WORLD_MOCAP = Transform.from_xyz_euler_deg([0.5, -0.3, 0.0], "z", [30.0])
T_WORLD_UAV = Transform.from_xyz_euler_deg([1.0, 2.0, 1.5], "xyz", [5.0, -3.0, 120.0])


def wait_until(pred: Callable[[], bool], timeout_s: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    ev = threading.Event()
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        ev.wait(0.005)


# ----------------------------------------------------------------------------- motioncapture (mock)


def test_motioncapture_mock_maps_into_the_world_and_counts_frames() -> None:
    T_mocap_uav = T_WORLD_MOCAP.inverse() @ T_WORLD_UAV
    T_mocap_box = Transform.from_xyz_yaw([3.0, 0.0, 0.2], 0.0)
    clock = SimClock(speed=1.0)

    async def main() -> None:
        src = MotionCaptureSource(
            "mock", clock, options={"rigid_bodies": mock_rigid_bodies({"uav1": T_mocap_uav, "box": T_mocap_box}),
                                    "rate": 200},
            frames=WorldFrames(T_WORLD_MOCAP),
        )
        assert isinstance(src, MocapSource)
        async with src:
            pose = await src.wait_for_body("uav1", timeout_s=2.0)
            # libmotioncapture stores float32: compare at its precision
            assert pose.T_world_body.almost_equal(T_WORLD_UAV, tol_m=1e-5, tol_rad=1e-5)
            assert pose.valid and pose.body == "uav1" and pose.seq >= 1
            assert pose.T_mocap_body is not None  # kept as measured, for bridges and recorders
            assert pose.T_mocap_body.almost_equal(T_mocap_uav, tol_m=1e-5, tol_rad=1e-5)
            assert abs(pose.stamp_ns - clock.time_ns()) < 2_000_000_000
            seqs = []
            async for p in src.poses("uav1"):
                seqs.append(p.seq)
                if len(seqs) == 5:
                    break
            assert seqs == list(range(seqs[0], seqs[0] + 5))
            assert src.bodies() == ("box", "uav1")
            with pytest.raises(MocapBodyMissing) as info:
                await src.wait_for_body("ghost", timeout_s=0.1)
            assert info.value.visible == ("box", "uav1") and "visible bodies: box, uav1" in str(info.value)
        assert src.frames >= 5

    asyncio.run(main())


def test_motioncapture_errors_are_mocap_errors() -> None:
    async def main() -> None:
        with pytest.raises(MocapError, match="motioncapture nosuch failed: Unknown motion capture type"):
            async with MotionCaptureSource("nosuch", SimClock(1.0), connect_timeout_s=2.0):
                pass
        # No Vicon server: libmotioncapture's connect() would freeze the interpreter; the probe refuses.
        port = free_tcp_port()
        with pytest.raises(MocapError, match=f"cannot reach the vicon server at 127.0.0.1:{port}"):
            async with MotionCaptureSource("vicon", SimClock(1.0), hostname=f"127.0.0.1:{port}", connect_timeout_s=0.3):
                pass


    asyncio.run(main())


# ----------------------------------------------------------------------------- bus source + sim publisher


def _pair() -> tuple[object, object]:
    port = free_tcp_port()
    a = open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    b = open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=("tcp/127.0.0.1:0",)))
    return a, b


def test_sim_publisher_sends_the_mocap_frame_and_bus_source_maps_it_to_the_world() -> None:
    clock = SimClock(speed=5.0)
    keys = Keys("uav1")
    a, b = _pair()

    async def main() -> None:
        raw = BusSubscriber(a, keys.mocap_pose("uav1"), maxlen=10_000)
        src = BusMocapSource(a, keys, clock, WorldFrames(T_WORLD_MOCAP))
        system = SimMocapSystem(clock, {"uav1": lambda _t: T_WORLD_UAV}, T_world_mocap=T_WORLD_MOCAP, rate_hz=100.0)
        pub = SimMocapPublisher(b, keys, system)
        async with src, pub:
            pose = await src.wait_for_body("uav1", timeout_s=10.0)
            # the wire carries T_mocap_body, not the world pose
            msg = PoseStamped.decode(raw.get(timeout_s=5.0).payload)
            assert msg.header.frame_id == "mocap"
            assert msg.to_transform().almost_equal(T_WORLD_MOCAP.inverse() @ T_WORLD_UAV, 1e-9, 1e-9)
            assert not msg.to_transform().almost_equal(T_WORLD_UAV, 1e-3, 1e-3)
            # the source maps it back into the world
            assert pose.valid and pose.T_world_body.almost_equal(T_WORLD_UAV, 1e-9, 1e-9)
            assert abs(pose.received_s - clock.monotonic_s()) < 1.0

            # occlusion: NaN on the wire -> valid=False with the last known pose
            system.hide_body("uav1")
            async for p in src.poses("uav1"):
                if not p.valid:
                    assert p.T_world_body.almost_equal(T_WORLD_UAV, 1e-9, 1e-9)
                    break
            with pytest.raises(MocapBodyMissing, match="visible bodies: none"):
                await src.wait_for_body("uav1", timeout_s=0.05)
            system.show_body("uav1")
            assert (await src.wait_for_body("uav1", timeout_s=5.0)).valid

            # dropout: nothing arrives for 1 s of clock time, then the stream resumes
            before = system.frames_published  # counted before the frame goes to the publisher
            system.drop_for(1.0)
            t0, t0_ns = clock.monotonic_s(), clock.time_ns()
            async for p in src.poses("uav1"):
                # the first frame captured after the dropout began (one still in flight from
                # before it can arrive late on a loaded host: its capture stamp tells them apart)
                if p.stamp_ns > t0_ns:
                    break
            assert clock.monotonic_s() - t0 >= 0.9
            assert system.frames_dropped > 0 and system.frames_published > before
            assert src.missed("uav1") == 0  # a dropout is silence, not lost messages
            with pytest.raises(MocapBodyMissing) as info:
                await src.wait_for_body("uav2", timeout_s=0.05)
            assert info.value.visible == ("uav1",)
        raw.close()

    try:
        asyncio.run(main())
    finally:
        b.close()  # type: ignore[attr-defined]
        a.close()  # type: ignore[attr-defined]


def test_sim_mocap_takes_the_next_frame_when_lockstep_time_moves_before_its_sleep() -> None:
    # The test thread's advance lands between the sampler's read of the time and its sleep (a
    # race a busy CI machine hit once): the frame due at the new time must still be taken, without
    # a further advance (a lock-step loop waits for it before advancing).
    period = 1.0 / 120.0
    sampler_reads: list[float] = []

    class RacingClock(LockstepClock):
        fired = False

        def monotonic_s(self) -> float:
            t = super().monotonic_s()
            if threading.current_thread() is not threading.main_thread() and system.frames_published == 2:
                sampler_reads.append(t)
                if not self.fired:  # the second frame is out: the test's advance comes now
                    self.fired = True
                    self.advance(period)
            return t

    clock = RacingClock()
    system = SimMocapSystem(clock, {"uav1": lambda _t: T_WORLD_UAV}, T_world_mocap=T_WORLD_MOCAP, rate_hz=120.0)
    system.start()
    try:
        deadline = time.monotonic() + 5.0
        while system.frames_published < 1 and time.monotonic() < deadline:
            time.sleep(0.001)
        clock.advance(period)  # frame 2 at one period; the clock then moves on to two by itself
        while system.frames_published < 3 and time.monotonic() < deadline:
            time.sleep(0.001)
        assert clock.fired and sampler_reads[0] == pytest.approx(period)  # the race did happen
        assert system.frames_published == 3, "the frame due at two periods was not taken"
        assert clock.monotonic_s() == pytest.approx(2 * period)
    finally:
        system.stop()


def test_sim_mocap_noise_is_seeded_and_has_the_configured_spread() -> None:
    clock = LockstepClock()
    kw = dict(T_world_mocap=T_WORLD_MOCAP, rate_hz=100.0, noise_m=0.01, noise_rad=0.0, seed=3)
    s1 = SimMocapSystem(clock, {"uav1": lambda _t: T_WORLD_UAV}, **kw)  # type: ignore[arg-type]
    s2 = SimMocapSystem(clock, {"uav1": lambda _t: T_WORLD_UAV}, **kw)  # type: ignore[arg-type]
    exact = (T_WORLD_MOCAP.inverse() @ T_WORLD_UAV).translation
    d1 = np.array([s1.measure(T_WORLD_UAV).translation - exact for _ in range(2000)])
    d2 = np.array([s2.measure(T_WORLD_UAV).translation - exact for _ in range(2000)])
    np.testing.assert_array_equal(d1, d2)
    assert 0.009 < float(d1.std()) < 0.011 and abs(float(d1.mean())) < 0.001


def test_a_pose_in_an_unknown_frame_fails_the_source_with_the_frames_name() -> None:
    clock = SimClock(speed=5.0)
    keys = Keys("uav1")
    a, b = _pair()

    async def main() -> None:
        from flightkit.bus.msg_base import Header
        from flightkit.bus.pubsub import BusPublisher

        async with BusMocapSource(a, keys, clock, WorldFrames(T_WORLD_MOCAP)) as src:
            pub = BusPublisher(b, keys.mocap_pose("uav1"), PoseStamped, reliable=True, drop_when_congested=False)
            world = PoseStamped.from_transform(clock.time_ns(), "world", T_WORLD_UAV)
            odom = PoseStamped(Header(clock.time_ns(), "odom"), (0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))
            deadline = time.monotonic() + 10.0
            while src.latest("uav1") is None:  # the subscription needs a moment to match
                assert time.monotonic() < deadline, "no pose arrived"
                pub.publish(world)
                await asyncio.sleep(0.02)
            # a pose already in the world frame is used as it is, and its mocap-frame pose derived
            pose = await src.wait_for_body("uav1", timeout_s=5.0)
            assert pose.T_world_body.almost_equal(T_WORLD_UAV, 1e-9, 1e-9)
            assert pose.T_mocap_body is not None
            assert pose.T_mocap_body.almost_equal(T_WORLD_MOCAP.inverse() @ T_WORLD_UAV, 1e-9, 1e-9)
            pub.publish(odom)
            with pytest.raises(MocapError, match="frame 'odom' cannot be placed in the world"):
                while True:
                    await src.wait_for_body("uav1", timeout_s=1.0)
                    await asyncio.sleep(0.01)
            pub.close()

    try:
        asyncio.run(main())
    finally:
        b.close()  # type: ignore[attr-defined]
        a.close()  # type: ignore[attr-defined]


def test_open_mocap_builds_the_configured_source() -> None:
    port = free_tcp_port()
    bus_cfg = BusConfig(well_known_port=port)
    cfg = MocapConfig(source=MocapSourceKind.BUS, T_world_mocap=TransformConfig(rpy_deg=(0.0, 0.0, 30.0)))
    clock = SimClock(speed=1.0)

    async def main() -> None:
        src = open_mocap(cfg, bus_cfg, Keys("uav1"), clock)
        assert isinstance(src, BusMocapSource)
        assert src.T_world_mocap.almost_equal(Transform.from_xyz_euler_deg([0, 0, 0], "z", [30.0]), 1e-12, 1e-12)
        async with src:
            with pytest.raises(MocapBodyMissing):
                await src.wait_for_body("uav1", timeout_s=0.05)
        mc = open_mocap(
            MocapConfig(source=MocapSourceKind.MOTIONCAPTURE, system_type="mock",
                        options={"rigid_bodies": "cf1(0,0,1,1,0,0,0)"}),
            bus_cfg, Keys("uav1"), clock,
        )
        assert isinstance(mc, MotionCaptureSource)
        async with mc:
            p = await mc.wait_for_body("cf1", timeout_s=2.0)
            assert np.allclose(p.T_world_body.translation, [0.0, 0.0, 1.0])

    asyncio.run(main())


# ----------------------------------------------------------------------------- forwarding to the autopilot


def test_forward_to_vehicle_feeds_the_sim_autopilots_estimator() -> None:
    from flightkit.config import Autopilot, LinkConfig
    from flightkit.link.mavlink import MavlinkLink
    from flightkit.sim.autopilot import AutopilotOptions
    from flightkit.sim.lab import SimLab

    clock = SimClock(speed=5.0)
    keys = Keys("uav1")
    a, b = _pair()
    lab = SimLab(
        autopilot="px4", clock=clock, url="udpin:127.0.0.1:0",
        options=AutopilotOptions(params={"EKF2_EV_CTRL": 15}), start_pos_enu_m=(1.0, 2.0, 0.0),
        start_yaw_rad=0.7, ready_after_s=0.0,
    )

    async def main() -> None:
        link = MavlinkLink(LinkConfig(url=lab.client_url, heartbeat_timeout_s=5.0), Autopilot.PX4, clock)
        stats = ForwardStats()
        system = SimMocapSystem(clock, {"uav1": lab.T_world_body}, T_world_mocap=T_WORLD_MOCAP, rate_hz=120.0)
        async with link, BusMocapSource(a, keys, clock, WorldFrames(T_WORLD_MOCAP)) as src, SimMocapPublisher(
            b, keys, system
        ):
            await src.wait_for_body("uav1", timeout_s=10.0)
            task = asyncio.create_task(forward_to_vehicle(src, link, "uav1", rate_hz=30.0, stats=stats))
            try:
                deadline = clock.monotonic_s() + 20.0
                while not any(e.kind == "vision" and e.detail == "fusing" for e in lab.event_log):
                    assert clock.monotonic_s() < deadline, f"the autopilot never fused vision ({stats})"
                    await clock.sleep(0.1)
                await clock.sleep(1.0)  # let the estimator settle on the fused poses
                # ...and 20 poses forwarded: at 30 Hz that is 0.7 s, but a loaded machine delivers
                # fewer fresh mocap samples per sim second over the bus (repeats are not re-sent)
                while stats.sent < 20:
                    assert clock.monotonic_s() < deadline, f"forwarding stalled ({stats})"
                    await clock.sleep(0.1)
                t = link.telemetry
                # with vision fused, the autopilot's local position is the world position
                assert np.allclose(t.pos_local_enu_m, [1.0, 2.0, 0.0], atol=0.05), t.pos_local_enu_m
                assert math.isclose(t.yaw_local_rad, 0.7, abs_tol=0.05)
            finally:
                task.cancel()
                with pytest.raises(asyncio.CancelledError):
                    await task
        assert stats.sent >= 20 and stats.invalid == 0

    with lab:
        try:
            asyncio.run(main())
        finally:
            b.close()
            a.close()
