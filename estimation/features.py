"""Feature front ends: grid-bucketed corners, Shi-Tomasi, ORB and SIFT.

Everything here works on 8-bit grayscale images (``H x W`` uint8) and returns keypoint
positions as ``float32`` arrays of shape (N, 2) in pixels (x right, y down), which is what
the LK tracker (``estimation.lk``) and ``cv2.solvePnPRansac`` take without copies.

* :class:`GridDetector` spreads FAST corners over the image: the image is cut into cells
  and only the strongest few corners of each cell are kept, so a textured corner of the
  image cannot take the whole budget (motion estimates from clustered points are poorly
  conditioned). Cells that already hold tracked points are skipped when topping up. The
  strength is FAST's response, or the Shi-Tomasi score (the corners LK tracks best).
* :class:`DescriptorExtractor` wraps ORB (binary, Hamming) and SIFT (float, L2) and records
  which norm its descriptors need, so matchers cannot pick the wrong one.

Detectors are built once and reused; nothing allocates image-sized buffers per call
except OpenCV's own internals.
"""

from __future__ import annotations

import logging
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
import numpy.typing as npt

from estimation._grid_kernel import count_cells, grid_select, min_eigenvalue_at
from flightkit.errors import EstimationError

__all__ = ["DescriptorExtractor", "Features", "GridDetector", "as_gray", "occupied_cells"]

logger = logging.getLogger(__name__)

Points2 = npt.NDArray[np.float32]
"""Pixel positions, shape (N, 2), float32."""

_RESPONSE = operator.attrgetter("response")


def as_gray(image: npt.NDArray[np.integer[Any] | np.floating[Any]]) -> npt.NDArray[np.uint8]:
    """Return an 8-bit grayscale view/copy of ``image`` (gray, BGR or BGRA)."""
    if image.ndim == 2:
        if image.dtype == np.uint8:
            return cast("npt.NDArray[np.uint8]", image)
        return cast("npt.NDArray[np.uint8]", cv2.convertScaleAbs(image))
    if image.ndim == 3 and image.shape[2] == 3:
        return cast("npt.NDArray[np.uint8]", cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    if image.ndim == 3 and image.shape[2] == 4:
        return cast("npt.NDArray[np.uint8]", cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY))
    raise EstimationError(f"image of shape {image.shape} is not gray, BGR or BGRA; pass an H x W (x 3) array")


class GridDetector:
    """FAST corners kept per grid cell (strongest first), for an even spread.

    Args:
        max_features: total budget of corners.
        cell_px: grid cell size in pixels (cells are square).
        fast_threshold: initial FAST intensity threshold; adapted from call to call so FAST
            returns 2-6 times the budget (threshold 5 is tried at once when it returns
            fewer corners than the budget).
        border_px: corners closer than this to the border are dropped (KLT windows and
            descriptors need a margin).
        score: what ranks the corners of a cell: ``"fast"`` (FAST's response) or
            ``"shi-tomasi"`` (the structure tensor's smaller eigenvalue over 5x5 pixels).
    """

    def __init__(
        self,
        max_features: int = 300,
        cell_px: int = 32,
        fast_threshold: int = 20,
        border_px: int = 8,
        score: str = "fast",
    ) -> None:
        if score not in ("fast", "shi-tomasi"):
            raise EstimationError(f"GridDetector score is {score!r}; use 'fast' or 'shi-tomasi'")
        if max_features < 1:
            raise EstimationError(f"max_features must be >= 1, got {max_features}; ask for some corners")
        if cell_px < 4:
            raise EstimationError(f"cell_px must be >= 4, got {cell_px}; use a cell of 16-64 pixels")
        self.max_features = max_features
        self.cell_px = cell_px
        self.fast_threshold = fast_threshold
        self.border_px = border_px
        self.score = score
        self._threshold = fast_threshold
        self._fast = cv2.FastFeatureDetector.create(threshold=fast_threshold, nonmaxSuppression=True)
        self._fast_low = cv2.FastFeatureDetector.create(threshold=5, nonmaxSuppression=True)

    def detect(
        self,
        gray: npt.NDArray[np.uint8],
        existing: Points2 | None = None,
        budget: int | None = None,
    ) -> Points2:
        """Detect new corners, avoiding cells already occupied by ``existing`` points.

        Args:
            gray: the image.
            existing: points already tracked (N, 2); their cells get no new corners.
            budget: how many new corners at most (default ``max_features``).

        Returns:
            New corner positions (M, 2), float32, M <= budget. Returns immediately.
        """
        h, w = gray.shape[:2]
        budget = self.max_features if budget is None else budget
        if budget <= 0:
            return np.empty((0, 2), np.float32)
        kps = self._fast.detect(gray, None)
        # Keep FAST's output near 3x the budget: enough to choose from per cell, few
        # enough that reading the keypoints back into numpy stays cheap.
        n = len(kps)
        if n > 6 * budget and self._threshold < 80:
            self._threshold += 4
            self._fast.setThreshold(self._threshold)
        elif n < 2 * budget and self._threshold > 6:
            self._threshold = max(6, self._threshold - 4)
            self._fast.setThreshold(self._threshold)
        if n < budget:
            kps = self._fast_low.detect(gray, None)
        if not kps:
            return np.empty((0, 2), np.float32)
        pts = np.asarray(cv2.KeyPoint.convert(kps), np.float32).reshape(-1, 2)
        if self.score == "fast":
            resp = np.fromiter(map(_RESPONSE, kps), dtype=np.float32, count=len(kps))
        else:
            resp = min_eigenvalue_at(gray, pts)
        cs = self.cell_px
        ncx = (w + cs - 1) // cs
        ncy = (h + cs - 1) // cs
        occupied = np.zeros(ncx * ncy, dtype=bool)
        if existing is not None and len(existing):
            ex = np.asarray(existing, np.float32)
            # (np.minimum/np.maximum: np.clip's generic path costs ~10x on a few hundred points)
            ecx = np.minimum(np.maximum((ex[:, 0] // cs).astype(np.int32), 0), ncx - 1)
            ecy = np.minimum(np.maximum((ex[:, 1] // cs).astype(np.int32), 0), ncy - 1)
            occupied[ecy * ncx + ecx] = True
        # Inside the border, in free cells, the strongest few of each cell (one compiled loop).
        chosen = grid_select(pts, resp, occupied, cs, ncx, self.border_px, w, h, budget)
        return np.ascontiguousarray(pts[chosen])


def occupied_cells(px: Points2, cell_px: float) -> int:
    """How many square cells of ``cell_px`` (a grid from the image origin) hold at least one of
    the pixels ``px`` (N, 2); non-finite pixels hold none."""
    return int(count_cells(np.ascontiguousarray(px, dtype=np.float64).reshape(-1, 2), float(cell_px)))


@dataclass(frozen=True, slots=True, eq=False)
class Features:
    """Keypoints with descriptors.

    Attributes:
        pts_px: (N, 2) float32 pixel positions.
        descriptors: (N, D) uint8 (ORB, 32 bytes) or float32 (SIFT, 128).
        norm: the OpenCV norm the descriptors need (``cv2.NORM_HAMMING`` or ``cv2.NORM_L2``).
    """

    pts_px: Points2
    descriptors: npt.NDArray[np.integer[Any] | np.floating[Any]]
    norm: int

    def __len__(self) -> int:
        return len(self.pts_px)


class DescriptorExtractor:
    """ORB or SIFT keypoints + descriptors, with the matching norm attached.

    Args:
        kind: ``"orb"`` (binary, Hamming norm) or ``"sift"`` (float, L2 norm).
        max_features: keypoint budget.
    """

    def __init__(self, kind: str = "orb", max_features: int = 1000) -> None:
        kind = kind.lower()
        self._det: cv2.Feature2D
        if kind == "orb":
            self._det = cv2.ORB.create(nfeatures=max_features, fastThreshold=12)
            self.norm = cv2.NORM_HAMMING
        elif kind == "sift":
            self._det = cv2.SIFT.create(nfeatures=max_features)
            self.norm = cv2.NORM_L2
        else:
            raise EstimationError(f"unknown descriptor kind {kind!r}; use 'orb' or 'sift'")
        self.kind = kind

    def extract(self, gray: npt.NDArray[np.uint8], mask: npt.NDArray[np.uint8] | None = None) -> Features:
        """Detect and describe; returns immediately (ORB ~4 ms, SIFT ~70 ms at 640x480)."""
        kps, desc = self._det.detectAndCompute(gray, mask)
        if desc is None or not kps:
            width = 32 if self.kind == "orb" else 128
            dtype = np.uint8 if self.kind == "orb" else np.float32
            return Features(np.empty((0, 2), np.float32), np.empty((0, width), dtype), self.norm)
        return Features(np.asarray(cv2.KeyPoint.convert(kps), np.float32).reshape(-1, 2), desc, self.norm)

    def compute_at(
        self, gray: npt.NDArray[np.uint8], pts_px: Points2, size_px: float = 31.0
    ) -> tuple[Features, npt.NDArray[np.intp]]:
        """Describe given positions. Returns the features and the indices of ``pts_px`` kept
        (the extractor drops points too close to the border)."""
        kps: Sequence[cv2.KeyPoint] = [
            cv2.KeyPoint(float(x), float(y), size_px, -1, 0, 0, i) for i, (x, y) in enumerate(pts_px)
        ]
        kps, desc = self._det.compute(gray, kps)
        if desc is None or not kps:
            width = 32 if self.kind == "orb" else 128
            dtype = np.uint8 if self.kind == "orb" else np.float32
            return Features(np.empty((0, 2), np.float32), np.empty((0, width), dtype), self.norm), np.empty(
                0, np.intp
            )
        idx = np.array([k.class_id for k in kps], dtype=np.intp)
        return Features(np.ascontiguousarray(pts_px[idx]), desc, self.norm), idx
