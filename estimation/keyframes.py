"""Keyframe selection by motion and parallax instead of a fixed frame skip.

Frame-to-frame VO adds the error of every step; measuring each frame against a *keyframe*
and switching keyframes only when needed keeps the error from growing while the camera is
still (no new keyframe, no drift at rest) and gives the motion estimators enough parallax.

A new keyframe is taken when any of these holds:

* the median image motion of the tracked points since the keyframe exceeds ``max_parallax_px``
  (enough baseline; the essential matrix needs it, PnP loses points near the border);
* fewer than ``min_tracked_fraction`` of the keyframe's points are still tracked as inliers,
  or fewer than ``min_tracked`` in absolute terms;
* the tracked points cover less than ``min_tracked_fraction`` of the image area they covered in
  the keyframe (the scene receding: its points bunch together and leave the rest of the image
  without corners, while every one of them is still tracked);
* the camera moved more than ``max_baseline_ratio`` times the median scene depth (or more
  than ``max_translation_m``), or turned more than ``max_rotation_rad``;
* ``max_interval`` frames have passed (bounds the age of the map).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from estimation.motion import median, rotation_angle_rad

__all__ = ["KeyframeDecision", "KeyframePolicy"]


@dataclass(frozen=True, slots=True)
class KeyframeDecision:
    """Whether to start a new keyframe, and why (``reason`` is empty when not)."""

    new_keyframe: bool
    reason: str = ""


@dataclass(frozen=True, slots=True)
class KeyframePolicy:
    """Thresholds of the keyframe decision (see the module docstring)."""

    max_parallax_px: float = 25.0
    min_tracked_fraction: float = 0.7
    min_tracked: int = 40
    max_baseline_ratio: float = 0.2
    max_translation_m: float = 10.0
    max_rotation_rad: float = 0.35
    max_interval: int = 30

    def decide(
        self,
        parallax_px: npt.NDArray[np.floating] | float,
        n_tracked: int,
        n_keyframe_points: int,
        T_cur_kf: npt.NDArray[np.float64],
        frames_since_keyframe: int,
        scene_depth_m: float = float("inf"),
        covered_fraction: float = 1.0,
    ) -> KeyframeDecision:
        """Apply the policy.

        Args:
            parallax_px: per-point image displacement since the keyframe (or its median).
            n_tracked: inlier tracks of keyframe points in the current frame.
            n_keyframe_points: points the keyframe started with.
            T_cur_kf: motion from the keyframe to the current camera (4x4).
            frames_since_keyframe: frames processed since the keyframe.
            scene_depth_m: median depth of the keyframe's points (for the baseline ratio).
            covered_fraction: the image area the tracked points cover over the area they
                covered in the keyframe (``FrontEnd.covered_fraction``).
        """
        par = (
            median(np.asarray(parallax_px).reshape(-1))
            if np.ndim(parallax_px) and np.size(parallax_px)
            else float(np.asarray(parallax_px).sum() if np.size(parallax_px) else 0.0)
        )
        if par > self.max_parallax_px:
            return KeyframeDecision(True, f"parallax {par:.1f} px")
        if n_tracked < self.min_tracked:
            return KeyframeDecision(True, f"{n_tracked} tracked < {self.min_tracked}")
        if n_keyframe_points and n_tracked < self.min_tracked_fraction * n_keyframe_points:
            return KeyframeDecision(True, f"{n_tracked}/{n_keyframe_points} tracked")
        if covered_fraction < self.min_tracked_fraction:
            return KeyframeDecision(True, f"{covered_fraction:.2f} of the area covered")
        dist = float(np.linalg.norm(T_cur_kf[:3, 3]))
        if dist > self.max_translation_m or dist > self.max_baseline_ratio * scene_depth_m:
            return KeyframeDecision(True, f"moved {dist:.2f} m")
        ang = rotation_angle_rad(T_cur_kf[:3, :3])
        if ang > self.max_rotation_rad:
            return KeyframeDecision(True, f"turned {np.degrees(ang):.1f} deg")
        if frames_since_keyframe >= self.max_interval:
            return KeyframeDecision(True, f"{frames_since_keyframe} frames")
        return KeyframeDecision(False)
