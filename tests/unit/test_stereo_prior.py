"""`stereo`'s PnP from the constant-velocity prediction (``PnpOptions.prior_gate_px``).

Once a motion has been measured, the stereo steps the prediction explains are fitted without
RANSAC (SQPnP on the tracks near their predicted position, then the depth polish); the first
step, without a prediction, goes to RANSAC. A textured plane 2.08 m ahead (12 px of disparity
at f = 250 px, B = 0.1 m) slides 2 px a frame: the camera moves 16.7 mm a frame along x.
"""

from __future__ import annotations

import cv2
import numpy as np

from estimation.pipeline import PnpOptions, Quality, VisualOdometry, VoOptions
from flightkit.datasets.base import CameraIntrinsics

W, H, F_PX, B_M, DISP_PX, STEP_PX = 320, 240, 250.0, 0.1, 12, 2
FRAMES = 8


def _run(options: VoOptions) -> tuple[VisualOdometry, np.ndarray]:
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (H + 8, W + 64), dtype=np.uint8), (5, 5), 1.0)
    intr = CameraIntrinsics(F_PX, F_PX, W / 2, H / 2, W, H)
    vo = VisualOdometry("stereo", intr, B_M, options=options)
    positions = []
    for i in range(FRAMES):
        left = np.ascontiguousarray(texture[4 : 4 + H, STEP_PX * i : STEP_PX * i + W])
        right = np.ascontiguousarray(texture[4 : 4 + H, STEP_PX * i + DISP_PX : STEP_PX * i + DISP_PX + W])
        pose = vo.process(i * 50_000_000, left, right)
        assert i == 0 or pose.quality is Quality.GOOD
        positions.append(pose.T_world_camera[:3, 3])
    return vo, np.array(positions)


def test_stereo_fits_the_predicted_steps_without_ransac_and_lands_where_ransac_does() -> None:
    vo, guided = _run(VoOptions())
    steps = FRAMES - 1
    assert vo.path_counts["pnp-ransac"] == 1 and vo.path_counts["pnp-prior"] == steps - 1
    off, ransac = _run(VoOptions(estimator=PnpOptions(prior_gate_px=0.0)))
    assert off.path_counts["pnp-ransac"] == steps and off.path_counts["pnp-prior"] == 0
    step_m = STEP_PX * (F_PX * B_M / DISP_PX) / F_PX
    truth = np.c_[step_m * np.arange(FRAMES), np.zeros(FRAMES), np.zeros(FRAMES)]
    assert np.abs(guided - truth).max() < 1e-3
    assert np.abs(guided - ransac).max() < 5e-4
