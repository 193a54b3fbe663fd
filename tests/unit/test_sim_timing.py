"""The simulated lab's injected timing and mounting errors, judged by the calibration estimators.

The lab patterns (circle, rectangle, lawnmower) are flown with rotation excitation
(:func:`flightkit.sim.calibration_flight.calibration_motion`); the camera's stamps are late and
drift, the mocap stamps on arrival, and the camera is mounted off the configured place. Every
estimate has an exact answer: offset within 1 ms, drift within 20 ppm, hand-eye within 2 mm and
0.2 deg, and a refusal on a pure-translation flight.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flightkit.calibration import estimate_hand_eye, estimate_time_offset, transform_difference
from flightkit.config import load_config
from flightkit.errors import CalibrationError, ConfigError
from flightkit.frames import Transform
from flightkit.sim.calibration_flight import calibration_motion, simulate_streams
from flightkit.sim.timing_errors import PoseDelay, SimTimingErrors
from trajectories.patterns import Circle, Lawnmower, Rectangle

TRUE_MOUNT = Transform.from_xyz_euler_deg([0.085, -0.004, -0.017], "xz", [133.0, 91.5])

PATTERNS = {
    "circle": Circle(radius_m=1.0, period_s=20.0, laps=3, height_m=1.5),
    "rectangle": Rectangle([(-1, -1), (1, -1), (1, 1), (-1, 1)], 1.5, speed_m_s=0.3, turn_s=3.0),
    "lawnmower": Lawnmower((-1, -1), (2, 2), 0.5, 1.5, speed_m_s=0.3, turn_s=2.0),
}


def test_timing_errors_default_to_none_in_config() -> None:
    sim = load_config().sim
    assert (sim.camera_time_offset_ms, sim.camera_drift_ppm, sim.mocap_latency_ms) == (0.0, 0.0, 0.0)
    assert sim.true_T_body_camera is None
    cfg = load_config(table={"sim": {"camera_time_offset_ms": 40, "mocap_latency_ms": 12.5,
                                     "true_T_body_camera": {"translation_m": [0.1, 0, 0]}}})
    assert cfg.sim.camera_time_offset_ms == 40.0
    assert cfg.sim.true_T_body_camera.to_transform().translation[0] == 0.1
    with pytest.raises(ConfigError, match="sim.mocap_latency_ms"):
        load_config(table={"sim": {"mocap_latency_ms": -1.0}})


def test_camera_stamps_are_late_and_drift_exactly() -> None:
    err = SimTimingErrors(camera_time_offset_s=0.025, camera_drift_ppm=200.0, mocap_latency_s=0.01)
    start = 1_000_000_000_000
    assert err.camera_stamp_ns(start, start) == start + 25_000_000
    assert err.camera_stamp_ns(start + 10**10, start) == start + 10**10 + 25_000_000 + 2_000_000
    assert err.expected_offset_s(start + 10**10, start) == pytest.approx(0.025 + 0.002)  # the mocap stamps capture
    assert not SimTimingErrors().any and err.any


def test_pose_delay_hands_out_the_pose_of_latency_ago() -> None:
    delay = PoseDelay(0.02)

    def pose(t: float) -> Transform:
        return Transform(Rotation.from_rotvec([0.0, 0.0, 0.5 * t]), np.array([t, 0.0, 0.0]))

    out = [delay(i / 120.0, pose(i / 120.0)) for i in range(50)]
    assert out[0].almost_equal(pose(0.0))
    assert out[40].almost_equal(pose(40 / 120.0 - 0.02), tol_m=1e-12, tol_rad=1e-12)


@pytest.fixture(scope="module", params=sorted(PATTERNS))
def flight(request: pytest.FixtureRequest):
    err = SimTimingErrors(camera_time_offset_s=0.073, camera_drift_ppm=180.0, mocap_latency_s=0.031)
    return request.param, simulate_streams(
        calibration_motion(PATTERNS[request.param]), 60.0, errors=err, T_body_camera=TRUE_MOUNT,
        camera_noise_deg=0.005, mocap_noise_m=0.0002, mocap_noise_rad=math.radians(0.005), seed=4,
    )


def test_offset_drift_and_mount_on_the_lab_patterns(flight) -> None:
    name, st = flight
    est = estimate_time_offset(st.mocap, st.camera)
    expected = st.errors.expected_offset_s(est.ref_ns, st.start_ns)
    assert est.offset_s == pytest.approx(expected, abs=1e-3), name
    assert est.drift_ppm == pytest.approx(180.0, abs=20.0), name
    assert est.drift_uncertainty_ppm < 10.0, name  # the bound is met by a margin, not by luck
    he = estimate_hand_eye(st.mocap, st.camera, camera_to_body_ns=est.camera_to_mocap_ns)
    dm, ddeg = transform_difference(he.T_body_camera, TRUE_MOUNT)
    assert dm < 0.002 and ddeg < 0.2, (name, dm, ddeg)


def test_a_pure_translation_flight_is_refused() -> None:
    st = simulate_streams(
        calibration_motion(PATTERNS["circle"], rock_deg=(0, 0, 0), follow_yaw=False), 20.0,
        errors=SimTimingErrors(0.05, 0.0, 0.0), T_body_camera=TRUE_MOUNT,
    )
    with pytest.raises(CalibrationError, match="too little rotation to tell"):
        estimate_time_offset(st.mocap, st.camera)
    with pytest.raises(CalibrationError, match="too little rotation to tell"):
        estimate_hand_eye(st.mocap, st.camera)

