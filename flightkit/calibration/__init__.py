"""Dataset-grade time and calibration: time offset and drift, hand-eye, host clocks, latency.

Core numerics (numpy/scipy only; no IO, no capability package)::

    from flightkit.calibration import estimate_time_offset, estimate_hand_eye
    est = estimate_time_offset(mocap_trajectory, camera_trajectory)   # offset_s, drift_ppm, ...
    he = estimate_hand_eye(mocap_trajectory, camera_trajectory, time_offset=est)

See ``docs/calibration.md``.
"""
