"""rgbd-kabsch's prior-guided rigid fit: Kabsch on the 3D-3D pairs the predicted motion explains."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation.motion import invert, make_T, rotation_angle_rad
from estimation.pipeline import KabschOptions, VoOptions
from estimation.rigid import _kabsch_masked, ransac_rigid, rigid_from_prior, umeyama
from flightkit.errors import EstimationError


def pairs(n: int = 200, noise_m: float = 0.002, seed: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(1.0, 4.0, n)]
    T = make_T(Rotation.from_euler("xyz", [1.0, -2.0, 1.5], degrees=True).as_matrix(), [0.03, -0.01, 0.02])
    Y = X @ T[:3, :3].T + T[:3, 3] + rng.normal(0, noise_m, X.shape)
    return X, Y, T


def test_kabsch_equals_umeyama_reflections_included() -> None:
    """The compiled Kabsch of the refits equals the checked least squares, on the points of a
    mask (the others are far off and must not count)."""
    rng = np.random.default_rng(0)
    for i in range(100):
        P = rng.normal(size=(int(rng.integers(3, 300)), 3))
        R = Rotation.random(random_state=i).as_matrix()
        Q = P @ R.T + rng.normal(size=3) + rng.normal(0, 0.05, P.shape)
        if i % 2:
            Q[:, 2] = -Q[:, 2]  # the best orthogonal fit is a reflection: both must return a rotation
        R_u, t_u, _ = umeyama(P, Q)
        mask = np.r_[np.ones(len(P), dtype=bool), np.zeros(5, dtype=bool)]
        outliers = rng.normal(0.0, 50.0, (5, 3))
        R_k, t_k = _kabsch_masked(np.r_[P, outliers], np.r_[Q, -outliers], mask)
        np.testing.assert_allclose(R_k, R_u, rtol=0, atol=1e-10)
        np.testing.assert_allclose(t_k, t_u, rtol=0, atol=1e-10)
        assert np.linalg.det(R_k) > 0


def test_rigid_from_prior_gives_ransacs_answer_from_a_near_prediction() -> None:
    X, Y, T = pairs()
    out = np.random.default_rng(1).permutation(len(X))[:5]
    Y[out] += 0.3  # 2.5 % outliers, as the RGB-D tracks here
    # Constant velocity predicts a little off: 5 mm and 0.2 degrees.
    guess = make_T(Rotation.from_rotvec([0.0, 0.0035, 0.0]).as_matrix(), [0.005, 0.0, 0.0]) @ T
    prior = rigid_from_prior(X, Y, guess, threshold_m=0.01, gate_m=0.02, min_fraction=0.9, min_inliers=12)
    full = ransac_rigid(X, Y, threshold_m=0.01, min_inliers=12, rng=np.random.default_rng(0))
    assert prior is not None and prior.ok and full.ok
    np.testing.assert_array_equal(prior.inliers, full.inliers)
    assert not prior.inliers[out].any()
    np.testing.assert_allclose(prior.T_cur_ref, full.T_cur_ref, atol=1e-12)
    dT = invert(T) @ prior.T_cur_ref
    assert np.linalg.norm(dT[:3, 3]) < 0.001 and rotation_angle_rad(dT[:3, :3]) < np.radians(0.05)


def test_rigid_from_prior_declines_when_the_prediction_does_not_explain_the_pairs() -> None:
    X, Y, T = pairs()
    # A turn the prediction missed (3 degrees): most pairs lie beyond the gate -> RANSAC's turn.
    missed = make_T(Rotation.from_euler("y", 3.0, degrees=True).as_matrix(), [0.0, 0.0, 0.0]) @ T
    assert rigid_from_prior(X, Y, missed, threshold_m=0.01, gate_m=0.02, min_fraction=0.9) is None
    # Too many outliers for the required fraction, even with the exact prediction.
    Y2 = Y.copy()
    Y2[:40] += 0.3
    assert rigid_from_prior(X, Y2, T, threshold_m=0.01, gate_m=0.02, min_fraction=0.9) is None
    m = rigid_from_prior(X, Y2, T, threshold_m=0.01, gate_m=0.02, min_fraction=0.75)
    assert m is not None and not m.inliers[:40].any() and m.inliers[40:].all()
    # Too few pairs at all.
    assert rigid_from_prior(X[:10], Y[:10], T, threshold_m=0.01, gate_m=0.02, min_inliers=12) is None


def test_vo_options_reject_bad_kabsch_prior_values() -> None:
    VoOptions(estimator=KabschOptions(prior_gate=0.0))  # off is fine
    for bad in ({"prior_gate": -1.0}, {"prior_min_fraction": 0.0}):
        with pytest.raises(EstimationError, match="prior_gate"):
            KabschOptions(**bad)
