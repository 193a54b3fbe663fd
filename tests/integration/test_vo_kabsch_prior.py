"""rgbd-kabsch's prior-guided path on a synthetic lab pattern: the same trajectory as RANSAC's.

When the constant-velocity prediction explains the 3D-3D pairs, rgbd-kabsch fits them by
Kabsch without RANSAC (``KabschOptions.prior_gate``); the inlier re-selection that follows
ends on the same inliers as RANSAC's, so the trajectory is the same bit for bit (measured on
7-Scenes, both TUM pairs and the three patterns at 320x240 and 640x480, 2026-11-22).
"""

from __future__ import annotations

import numpy as np

from estimation.frames import FramePreparer
from estimation.pipeline import KabschOptions, Method, Quality, VisualOdometry, VoOptions, run_vo
from flightkit.apps.sequences import synthetic_sequence


def test_prior_guided_rgbd_kabsch_takes_the_prior_path_and_matches_ransac() -> None:
    seq = synthetic_sequence("circle", duration_s=4.0, color=False, prerender=True)
    prep = FramePreparer(seq, Method.RGBD_KABSCH, None)
    vo: VisualOdometry | None = None
    poses, truth = [], []
    for frame in seq.frames():
        pf = prep(frame)
        assert pf.T_world_camera is not None
        truth.append(pf.T_world_camera.as_matrix())
        if vo is None:
            vo = VisualOdometry(
                Method.RGBD_KABSCH,
                prep.intrinsics,
                seq.baseline_m,
                prep.depth_intrinsics,
                seq.T_body_camera,
                pf.T_world_camera,
                VoOptions(),
            )
        poses.append(vo.process(pf.stamp_ns, pf.gray, pf.right_gray, pf.depth_m))
    assert vo is not None
    steps = len(poses) - 1
    # Every step after the first (no velocity yet: RANSAC) took the prior path.
    assert vo.path_counts["kabsch-prior"] == steps - 1 and vo.path_counts["kabsch-ransac"] == 0
    assert all(p.quality is Quality.GOOD for p in poses[1:])
    guided = np.array([p.T_world_camera for p in poses])
    full = run_vo(
        seq,
        "rgbd-kabsch",
        options=VoOptions(estimator=KabschOptions(prior_gate=0.0)),
        init_from_groundtruth=True,
        T_body_camera=seq.T_body_camera,
    )
    np.testing.assert_allclose(guided, full.T_world_camera, rtol=0, atol=1e-9)
    gt = np.array(truth)
    assert np.linalg.norm(guided[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.02
