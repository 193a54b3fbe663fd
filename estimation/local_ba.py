"""Local bundle adjustment over the last keyframes (``VoOptions.ba_window``): the keyframe poses
and the points they share refined on reprojection and disparity (``estimation.bundle``)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from estimation.motion import invert

__all__ = ["LocalBundleWindow"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


class LocalBundleWindow:
    """The last ``size`` keyframes: their poses, observations (ids, undistorted pixels,
    disparities at ``baseline_m``) and the points (world frame) they see.

    Args:
        size: keyframes in the window.
        K: camera matrix.
        fx: focal length, px.
        baseline_m: the (real or virtual) stereo baseline of the disparities.
    """

    def __init__(self, size: int, K: F64, fx: float, baseline_m: float) -> None:
        self.size = size
        self.K = K
        self.fx = fx
        self.baseline_m = baseline_m
        self.window: list[tuple[F64, I64, F64, F64]] = []
        self.landmarks: dict[int, F64] = {}

    def add_keyframe(self, T_world_kf: F64, ids: I64, und_px: F64, X_kf: F64) -> None:
        """Add a keyframe (its points ``X_kf`` in its camera frame, seen at ``und_px``)."""
        disp = self.fx * self.baseline_m / X_kf[:, 2]
        self.window.append((T_world_kf.copy(), ids.copy(), und_px, disp))
        Xw = X_kf @ T_world_kf[:3, :3].T + T_world_kf[:3, 3]
        for i, lid in enumerate(ids.tolist()):
            if lid not in self.landmarks:
                self.landmarks[lid] = Xw[i]
        if len(self.window) > self.size:
            self.window.pop(0)
            alive = set(np.concatenate([w[1] for w in self.window]).tolist())
            self.landmarks = {k: v for k, v in self.landmarks.items() if k in alive}

    def run(self, ids: I64, X_kf: F64, min_depth_m: float) -> tuple[F64, F64] | None:
        """Adjust the window; returns the newest keyframe's refined pose and its points ``X_kf``
        (ids ``ids``) moved to the refined estimates, or None when nothing was adjusted."""
        from estimation.bundle import bundle_adjust  # scipy: loaded when BA is on

        if len(self.window) < 2:
            return None
        poses = np.stack([w[0] for w in self.window])
        lids = np.array(sorted(self.landmarks), dtype=np.int64)
        if len(lids) < 10:
            return None
        pos = {lid: i for i, lid in enumerate(lids.tolist())}
        cams, pts, uv, dd = [], [], [], []
        for c, (_, kids, und, disp) in enumerate(self.window):
            for j, lid in enumerate(kids.tolist()):
                if lid in pos:
                    cams.append(c)
                    pts.append(pos[lid])
                    uv.append(und[j])
                    dd.append(disp[j])
        cams_a, pts_a, uv_a, d_a = np.array(cams), np.array(pts), np.array(uv), np.array(dd)
        # Only points seen from two or more keyframes constrain the poses.
        seen = np.bincount(pts_a, minlength=len(lids))
        multi = seen >= 2
        if np.count_nonzero(multi) < 10:
            return None
        remap = np.cumsum(multi) - 1
        keep_obs = multi[pts_a]
        lids = lids[multi]
        P = np.stack([self.landmarks[int(k)] for k in lids])
        res = bundle_adjust(
            poses,
            P,
            cams_a[keep_obs],
            remap[pts_a[keep_obs]],
            uv_a[keep_obs],
            self.K,
            n_fixed=1,
            disparity_px=d_a[keep_obs],
            baseline_m=self.baseline_m,
        )
        if res is None:
            return None
        new_poses, new_P = res
        for i, lid in enumerate(lids.tolist()):
            self.landmarks[lid] = new_P[i]
        self.window = [(new_poses[c], *w[1:]) for c, w in enumerate(self.window)]
        T_new: F64 = new_poses[-1].copy()
        T_kf_world = invert(T_new)
        # Points the adjustment refined come from the landmarks; the others (seen by the newest
        # keyframe alone) keep their place in its camera frame and move with it in the world.
        adjusted = set(lids.tolist())
        Xw = np.stack([self.landmarks[int(k)] if int(k) in adjusted else np.full(3, np.nan) for k in ids])
        Xk = Xw @ T_kf_world[:3, :3].T + T_kf_world[:3, 3]
        good = np.isfinite(Xk).all(axis=1) & (Xk[:, 2] > min_depth_m)
        Xk = np.where(good[:, None], Xk, X_kf)
        Xw_new = Xk @ T_new[:3, :3].T + T_new[:3, 3]
        for i, lid in enumerate(ids.tolist()):
            if lid not in adjusted:
                self.landmarks[lid] = Xw_new[i]
        return T_new, Xk
