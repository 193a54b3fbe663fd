"""Pyramidal Lucas-Kanade tracking on image pyramids built once per image.

OpenCV's ``calcOpticalFlowPyrLK`` builds both images' pyramids and the first image's derivatives
on every call (its Python binding takes no prebuilt pyramid), which at 640x480 costs more than
tracking a few hundred points. Here an image's :class:`ImagePyramid` is built once and serves every
track from or into it (forward, backward, stereo); :func:`lk_track` runs Bouguet's iteration as
OpenCV does (``estimation._lk_kernel``), so the results agree with OpenCV's to ~1e-4 px.
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from estimation import _lk_kernel
from flightkit.errors import EstimationError

__all__ = ["EPS_PX", "ImagePyramid", "PyramidCache", "lk_track", "pyramid_of"]

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]

MIN_EIG = 1e-4
"""OpenCV's default ``minEigThreshold``: windows flatter than this are not tracked."""

EPS_PX = 0.03
"""LK stops iterating on a level when its step is shorter than this (OpenCV's usual 0.03)."""


@dataclass(frozen=True, eq=False)
class ImagePyramid:
    """An 8-bit image and its Gaussian pyramid (``cv2.pyrDown``), each level padded by reflection.

    Attributes:
        image: level 0 as given (H, W) uint8.
        levels: the number of levels above level 0 that were built.
        pad_px: border added to every level; windows up to ``pad_px - 2`` pixels wide fit.
        flat: all padded levels, one after the other.
        offsets: where each level starts in ``flat``.
        sizes: (levels + 1, 2) width and height of each level before padding.
    """

    image: U8
    levels: int
    pad_px: int
    flat: U8
    offsets: npt.NDArray[np.int64]
    sizes: npt.NDArray[np.int64]

    @classmethod
    def build(cls, image: U8, levels: int = 3, max_win_px: int = 21) -> ImagePyramid:
        """The pyramid of ``image`` with ``levels`` levels above it, for windows up to
        ``max_win_px``; fewer levels when the image gets too small for such a window (as OpenCV)."""
        if image.ndim != 2 or image.dtype != np.uint8:
            raise EstimationError(f"LK tracking needs an 8-bit grey image; got {image.dtype} {image.shape}")
        lay = _layout(image.shape[0], image.shape[1], levels, max_win_px)
        pad = lay.pad_px
        flat = np.empty(lay.flat_len, np.uint8)
        level = image
        for i, (off, end, shape) in enumerate(lay.spans):
            if i:
                level = np.asarray(cv2.pyrDown(level), dtype=np.uint8)
            cv2.copyMakeBorder(level, pad, pad, pad, pad, cv2.BORDER_REFLECT_101, dst=flat[off:end].reshape(shape))
        return cls(image, len(lay.spans) - 1, pad, flat, lay.offsets, lay.sizes)

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.image.shape
        return h, w


@dataclass(frozen=True, eq=False)
class _Layout:
    """Where each padded level of an :class:`ImagePyramid` lies in ``flat`` (one per image size)."""

    pad_px: int
    flat_len: int
    spans: tuple[tuple[int, int, tuple[int, int]], ...]
    """Per level: its start and end in ``flat`` and its padded (rows, columns)."""
    offsets: npt.NDArray[np.int64]
    sizes: npt.NDArray[np.int64]


@functools.lru_cache(maxsize=16)
def _layout(h: int, w: int, levels: int, max_win_px: int) -> _Layout:
    """The layout of the pyramid of an h x w image (:meth:`ImagePyramid.build`): levels above 0
    while ``cv2.pyrDown``'s next level fits the window (as OpenCV), at most ``levels``."""
    pad = max_win_px + 2
    dims = [(w, h)]
    while len(dims) <= levels and _level_above_fits(*dims[-1], max_win_px):
        dims.append(((dims[-1][0] + 1) // 2, (dims[-1][1] + 1) // 2))
    spans, off = [], 0
    for lw, lh in dims:
        end = off + (lw + 2 * pad) * (lh + 2 * pad)
        spans.append((off, end, (lh + 2 * pad, lw + 2 * pad)))
        off = end
    offsets, sizes = np.array([s[0] for s in spans], np.int64), np.array(dims, np.int64)
    return _Layout(pad, off, tuple(spans), offsets, sizes)  # (shared by the pyramids of this size: read only)


class PyramidCache:
    """The pyramids of the last few images, found by the image object itself, so that an image
    tracked from, tracked into and matched in stereo has its pyramid built once. Images are taken
    as not changing after they are first seen (a frame's arrays are not reused in place)."""

    def __init__(self, levels: int, max_win_px: int, size: int = 6) -> None:
        self.levels, self.max_win_px, self.size = levels, max_win_px, size
        self._pyramids: OrderedDict[int, ImagePyramid] = OrderedDict()

    def __call__(self, image: U8 | ImagePyramid) -> ImagePyramid:
        if isinstance(image, ImagePyramid):
            return image
        key = id(image)
        pyr = self._pyramids.get(key)
        if pyr is not None and pyr.image is image:  # (the pyramid holds the image: its id stays its own)
            self._pyramids.move_to_end(key)
            return pyr
        pyr = ImagePyramid.build(image, self.levels, self.max_win_px)
        self._pyramids[key] = pyr
        while len(self._pyramids) > self.size:
            self._pyramids.popitem(last=False)
        return pyr


def pyramid_of(image: U8 | ImagePyramid, levels: int, win_px: int) -> ImagePyramid:
    """``image``'s pyramid with at least ``levels`` levels (or as many as the image allows) for
    windows of ``win_px``: ``image`` itself when it is such a pyramid, else built."""
    if isinstance(image, ImagePyramid):
        w, h = image.sizes[-1]
        if image.pad_px >= win_px + 2 and (image.levels >= levels or not _level_above_fits(w, h, win_px)):
            return image
        image = image.image
    return ImagePyramid.build(image, levels, win_px)


def lk_track(
    prev: ImagePyramid,
    cur: ImagePyramid,
    pts: F32,
    start: F32 | None = None,
    levels: int = 3,
    win_px: int = 21,
    max_iters: int = 20,
    eps_px: float = EPS_PX,
) -> tuple[F32, npt.NDArray[np.bool_]]:
    """Track ``pts`` (N, 2) from ``prev`` into ``cur`` with an LK window of ``win_px`` (odd) over
    ``levels`` pyramid levels above the image, starting at ``start`` (None: where they are).

    Returns:
        ``(pts_cur, ok)``: (N, 2) float32 positions and (N,) bool (False: the window left the image
        or was too flat to track).
    """
    if prev.shape != cur.shape:
        raise EstimationError(f"LK tracking between images of different sizes: {prev.shape} and {cur.shape}")
    if win_px + 2 > min(prev.pad_px, cur.pad_px) or win_px < 3:
        raise EstimationError(
            f"LK window {win_px} px does not fit the pyramids (built for windows up to "
            f"{min(prev.pad_px, cur.pad_px) - 2} px); build them with a larger max_win_px"
        )
    p0 = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 2)
    p1 = np.array(p0 if start is None else start, dtype=np.float32, copy=True).reshape(-1, 2)
    if p1.shape != p0.shape or levels < 0:
        raise EstimationError(
            f"LK tracking got {len(p0)} points with {len(p1)} start positions and {levels} levels; "
            "give one start per point (or None) and levels >= 0"
        )
    ok = np.empty(len(p0), dtype=np.bool_)
    if len(p0):
        n_levels = 1 + min(levels, prev.levels, cur.levels, _levels_for(prev.sizes, win_px))
        _lk_kernel.tracker(win_px)(
            prev.flat,
            prev.offsets,
            prev.pad_px,
            cur.flat,
            cur.offsets,
            cur.pad_px,
            prev.sizes,
            p0,
            p1,
            ok,
            n_levels,
            max_iters,
            eps_px,
            MIN_EIG,
        )
    return p1, ok


def _level_above_fits(w: int, h: int, win_px: int) -> bool:
    """Whether the pyramid level above a w x h one (``cv2.pyrDown``'s size) is larger than the
    window: OpenCV builds no level below that."""
    return (w + 1) // 2 > win_px and (h + 1) // 2 > win_px


def _levels_for(sizes: npt.NDArray[np.int64], win_px: int) -> int:
    """The levels above 0 of ``sizes`` that a window of ``win_px`` can use."""
    n = 0
    while n + 1 < len(sizes) and _level_above_fits(int(sizes[n, 0]), int(sizes[n, 1]), win_px):
        n += 1
    return n
