"""SimMocapSource: the simulator as a MocapSource, on the lab's clock (real threads, no sleeps)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from flightkit.clock import SimClock
from flightkit.errors import MocapBodyMissing, MocapError
from flightkit.frames import Transform
from flightkit.mocap.base import MocapPose, MocapSource
from flightkit.sim.lab import SimLab
from flightkit.sim.mocap import SimMocapSource

pytestmark = pytest.mark.timeout(60)


def lab_at(pos: tuple[float, float, float], yaw: float = 0.3, speed: float = 5.0) -> SimLab:
    # the lab's autopilot is not started: the mocap only reads the ground truth
    return SimLab(autopilot="px4", clock=SimClock(speed), start_pos_enu_m=pos, start_yaw_rad=yaw)


def test_is_a_mocap_source_and_reports_the_truth() -> None:
    lab = lab_at((0.5, -0.2, 0.0))

    async def go() -> MocapPose:
        async with SimMocapSource(lab, body="uav1", rate_hz=200) as src:
            assert isinstance(src, MocapSource)
            return await src.wait_for_body("uav1", timeout_s=2.0)

    pose = asyncio.run(go())
    assert pose.valid and pose.body == "uav1"
    np.testing.assert_allclose(pose.T_world_body.translation, [0.5, -0.2, 0.0], atol=1e-9)
    assert pose.T_world_body.yaw_rad == pytest.approx(0.3)
    assert pose.received_s <= lab.clock.monotonic_s()


def test_rate_seq_and_stamps_follow_the_lab_clock() -> None:
    lab = lab_at((0.0, 0.0, 0.0), speed=5.0)

    async def go() -> list[MocapPose]:
        async with SimMocapSource(lab, rate_hz=100) as src:
            got: list[MocapPose] = []
            async for p in src.poses("uav1"):
                got.append(p)
                if len(got) == 100:
                    break
            return got

    got = asyncio.run(go())
    seqs = [p.seq for p in got]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    span_s = got[-1].received_s - got[0].received_s
    frames = got[-1].seq - got[0].seq
    assert frames / span_s == pytest.approx(100.0, rel=0.1)  # 100 Hz of lab time, at 5x
    stamps = np.array([p.stamp_ns for p in got]) * 1e-9
    assert (stamps[-1] - stamps[0]) == pytest.approx(span_s, abs=0.02)


def test_calibration_error_and_noise() -> None:
    lab = lab_at((1.0, 0.0, 0.0), yaw=0.0)
    true = Transform.from_xyz_yaw((0.0, 0.0, 0.0), 0.0)
    assumed = Transform.from_xyz_yaw((0.1, 0.0, 0.0), math.pi / 2)  # config believes a rotated mocap frame

    async def go(src: SimMocapSource, n: int) -> list[MocapPose]:
        async with src:
            out: list[MocapPose] = []
            async for p in src.poses("uav1"):
                out.append(p)
                if len(out) == n:
                    return out
        raise AssertionError

    biased = asyncio.run(go(SimMocapSource(lab, T_world_mocap=assumed, true_T_world_mocap=true), 1))[0]
    np.testing.assert_allclose(biased.T_world_body.translation, [0.1, 1.0, 0.0], atol=1e-9)
    noisy = asyncio.run(go(SimMocapSource(lab, rate_hz=500, noise_m=0.01, seed=3), 400))
    xyz = np.array([p.T_world_body.translation for p in noisy])
    assert np.std(xyz[:, 0]) == pytest.approx(0.01, rel=0.2)
    assert np.mean(xyz[:, 0]) == pytest.approx(1.0, abs=0.003)


def test_dropout_and_occlusion() -> None:
    lab = lab_at((0.0, 0.0, 0.0), speed=5.0)

    async def go() -> None:
        async with SimMocapSource(lab, rate_hz=100, static_bodies={"wand": Transform()}) as src:
            first = await src.wait_for_body("uav1", 2.0)
            assert set(src.bodies()) == {"uav1", "wand"}
            src.drop_for(0.5)
            assert src.dropping
            # nothing new while dropping; afterwards frames resume and seq shows the gap
            stream = src.poses("uav1")
            nxt = await asyncio.wait_for(anext(stream), 5.0)
            while nxt.seq <= first.seq + 1:  # a frame already queued before the dropout
                nxt = await asyncio.wait_for(anext(stream), 5.0)
            assert nxt.received_s - first.received_s >= 0.45
            assert nxt.seq - first.seq >= 45  # ~50 frames missed at 100 Hz
            assert src.frames_dropped >= 45
            src.hide_body()
            while (p := await asyncio.wait_for(anext(stream), 5.0)).valid:
                pass
            assert not p.valid and src.latest("uav1") is not None
            with pytest.raises(MocapBodyMissing) as info:
                await src.wait_for_body("uav1", 0.2)
            assert set(info.value.visible) == {"wand"}  # the hidden vehicle is not visible
            src.show_body()
            assert (await src.wait_for_body("uav1", 2.0)).valid
            await stream.aclose()

    asyncio.run(go())


def test_missing_body_names_the_visible_ones() -> None:
    lab = lab_at((0.0, 0.0, 0.0))

    async def go() -> None:
        async with SimMocapSource(lab, body="cf7") as src:
            with pytest.raises(MocapBodyMissing, match=r"'uav1'.*visible bodies: cf7"):
                await src.wait_for_body("uav1", 0.5)

    asyncio.run(go())


def test_bad_arguments_are_refused() -> None:
    lab = lab_at((0.0, 0.0, 0.0))
    with pytest.raises(MocapError, match="rate"):
        SimMocapSource(lab, rate_hz=0.0)
    with pytest.raises(MocapError, match="noise"):
        SimMocapSource(lab, noise_m=-1.0)


def test_a_stale_pose_does_not_satisfy_wait_for_body() -> None:
    """One freshness rule for every source: a valid pose is not enough once the stream is silent."""
    lab = lab_at((0.0, 0.0, 0.0), speed=5.0)

    async def go() -> None:
        async with SimMocapSource(lab, rate_hz=100) as src:
            await src.wait_for_body("uav1", 2.0)
            src.drop_for(5.0)
            await lab.clock.sleep(0.5)
            last = src.latest("uav1")
            assert last is not None and last.valid  # still the newest pose, and valid ...
            with pytest.raises(MocapBodyMissing):  # ... but 0.5 s old: not fresh
                await src.wait_for_body("uav1", 0.3)

    asyncio.run(go())
