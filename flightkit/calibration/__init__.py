"""Dataset-grade time and calibration: time offset and drift, hand-eye, host clocks, latency.

Core numerics (numpy/scipy, and cv2 for the board; no IO, no capability package)::

    from flightkit.calibration import estimate_time_offset, estimate_hand_eye
    t = estimate_time_offset(mocap_trajectory, camera_trajectory)    # offset_s, drift_ppm, ...
    he = estimate_hand_eye(mocap_trajectory, camera_trajectory, camera_to_body_ns=t.camera_to_mocap_ns)
    he.T_body_camera, he.residual_m, he.residual_deg

* :mod:`~flightkit.calibration.rates`: body rates from orientations;
* :mod:`~flightkit.calibration.time_offset`: camera-to-mocap offset and drift;
* :mod:`~flightkit.calibration.hand_eye`: ``T_body_camera`` from paired motions;
* :mod:`~flightkit.calibration.board`: ChArUco and AprilTag-grid board poses (``cv2.aruco``);
* :mod:`~flightkit.calibration.clock_sync`: host clock offset from request/response stamps;
* :mod:`~flightkit.calibration.latency`: p50/p99 of the capture-to-setpoint chain, pose prediction,
  a stream's rate/age/jitter against bounds;
* :mod:`~flightkit.calibration.result`: :class:`CalibrationResult`, JSON and recording metadata.

See ``docs/calibration.md``.
"""

from flightkit.calibration.clock_sync import ClockOffsetEstimate, ClockSync, Exchange, estimate_clock_offset
from flightkit.calibration.hand_eye import HandEyeEstimate, estimate_hand_eye, motion_pairs, solve_hand_eye
from flightkit.calibration.latency import (
    LatencyStats,
    StreamHealth,
    latency_stats,
    predict_pose,
    stream_health,
    velocity_from_poses,
)
from flightkit.calibration.rates import AngularRates, angular_rates
from flightkit.calibration.result import METADATA_RECORD, CalibrationResult, transform_difference
from flightkit.calibration.time_offset import TimeOffsetEstimate, estimate_time_offset

__all__ = [
    "METADATA_RECORD",
    "AngularRates",
    "CalibrationResult",
    "ClockOffsetEstimate",
    "ClockSync",
    "Exchange",
    "HandEyeEstimate",
    "LatencyStats",
    "StreamHealth",
    "TimeOffsetEstimate",
    "angular_rates",
    "estimate_clock_offset",
    "estimate_hand_eye",
    "estimate_time_offset",
    "latency_stats",
    "motion_pairs",
    "predict_pose",
    "solve_hand_eye",
    "stream_health",
    "transform_difference",
    "velocity_from_poses",
]
