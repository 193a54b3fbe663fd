"""The simulated camera: textured boxes on a textured floor, rendered by ray casting.

Renders what a pinhole camera at ``T_world_camera`` sees: an RGB image, 16-bit depth in
millimetres (0 = invalid, as RealSense and Kinect drivers report), and a rectified stereo
pair (the right camera offset by the baseline along the camera x axis). Ground truth is
exact: the pose you render from is the pose.

How it works: one ray per pixel (precomputed in the camera frame with z = 1, so the ray
parameter *is* the depth), intersected in numpy with the floor plane and with every box
that can be in view (slab test); each hit gets texture coordinates into one texture atlas
and the size of the pixel's footprint on the surface, and ``cv2.remap`` samples the atlas's
mip levels trilinearly (a pixel averages the texels it covers, as a lens and sensor do), so
distant textures do not alias and the images carry real, trackable corners. Faces get a
fixed shading by their normal so edges are visible.

Camera frame is OpenCV (x right, y down, z forward); world is ENU (z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.frames import Transform

__all__ = ["Box", "PinholeModel", "RenderedFrame", "Scene", "SimCamera", "make_texture"]

_SKY_RGB = np.array([200, 205, 215], dtype=np.uint8)
_FLOOR_TILE_M = 4.0  # the floor texture repeats every 4 m
_TEX_FLOOR_PX = 1024
_TEX_BOX_PX = 512
_MIP_LEVELS = 7  # level 6: 64 texels per pixel (a floor tile 4 m wide seen 60 m away at 320 px)
_LOD_BIAS = 1.5
"""Mip levels finer than log2(texels per pixel): a pyrDown level k is a Gaussian of ~0.6 * 2^k
texels, twice the spread of the box that a pixel of 2^k texels averages. Measured against
5x5 supersampling averaged down (floor views 20-50 deg below the horizon, 320x240): mean
error 1.2-1.6 grey levels at 1.5, 3.2-6.2 at 0 (blurred), 2.3-3.6 point-sampled (aliased)."""


def _u8(image: cv2.typing.MatLike) -> npt.NDArray[np.uint8]:
    """OpenCV's result of an operation on uint8 images, typed as what it is."""
    return cast("npt.NDArray[np.uint8]", image)


def _spread(d2: npt.NDArray[np.float32], d_n: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Square root of a pixel's footprint area on a surface per unit depth and focal length:
    ``|d| sqrt(|d| / |d . n|)`` for rays ``d`` (z = 1) with squared norm ``d2``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.sqrt(d2)
        return np.asarray(norm * np.sqrt(norm / np.abs(d_n)), dtype=np.float32)


def _mip_level(texels_per_px: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Mip level of footprints: log2 of the texels a pixel spans less ``_LOD_BIAS``, at least 0."""
    with np.errstate(divide="ignore"):
        return np.clip(np.log2(texels_per_px) - np.float32(_LOD_BIAS), 0.0, _MIP_LEVELS - 1.0)


@dataclass(frozen=True, slots=True)
class PinholeModel:
    """Pinhole intrinsics of an undistorted (rectified) camera, in pixels."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float

    @staticmethod
    def from_fov(width_px: int, height_px: int, hfov_deg: float = 90.0) -> PinholeModel:
        fx = (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return PinholeModel(width_px, height_px, fx, fx, (width_px - 1) / 2.0, (height_px - 1) / 2.0)

    @property
    def K(self) -> npt.NDArray[np.float64]:
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, slots=True)
class Box:
    """An axis-aligned box in the world frame (metres)."""

    min_xyz_m: tuple[float, float, float]
    max_xyz_m: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class Scene:
    """The simulated lab: a textured floor at z = 0, four textured walls and textured boxes."""

    boxes: tuple[Box, ...]
    seed: int = 0
    room_half_m: float = 5.0
    wall_height_m: float = 3.0

    @staticmethod
    def default_lab(seed: int = 0) -> Scene:
        """A 10 m x 10 m lab with boxes around the flight area (kept clear within 2.5 m of the
        origin so the lab's patterns fly free)."""
        rng = np.random.default_rng(seed)
        boxes: list[Box] = []
        for i in range(14):
            ang = 2.0 * math.pi * i / 14 + rng.uniform(-0.15, 0.15)
            r = rng.uniform(2.6, 4.2)
            cx, cy = r * math.cos(ang), r * math.sin(ang)
            sx, sy = rng.uniform(0.3, 0.9, size=2)
            h = rng.uniform(0.3, 2.2)
            boxes.append(Box((cx - sx / 2, cy - sy / 2, 0.0), (cx + sx / 2, cy + sy / 2, h)))
        return Scene(tuple(boxes), seed)


def make_texture(size_px: int, seed: int) -> npt.NDArray[np.uint8]:
    """A non-repeating, high-contrast RGB texture with corners at many scales."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((size_px, size_px, 3), np.float32)
    for octave, weight in ((8, 1.0), (32, 0.6), (128, 0.35)):
        small = rng.uniform(0, 255, size=(octave, octave, 3)).astype(np.float32)
        acc += weight * cv2.resize(small, (size_px, size_px), interpolation=cv2.INTER_CUBIC)
    acc /= 1.95
    img = np.clip(acc, 0, 255).astype(np.uint8)
    # Sharp blobs and bars give corner features that survive blur and scale changes.
    for _ in range(size_px // 6):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        x, y = (int(v) for v in rng.integers(0, size_px, 2))
        if rng.uniform() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(3, size_px // 24)), c, -1, lineType=cv2.LINE_AA)
        else:
            w, h = (int(v) for v in rng.integers(4, size_px // 16, 2))
            cv2.rectangle(img, (x, y), (x + w, y + h), c, -1)
    return img


@dataclass(frozen=True, slots=True)
class RenderedFrame:
    """One rendered view.

    Attributes:
        color_rgb: (H, W, 3) uint8.
        depth_mm: (H, W) uint16, millimetres along the optical axis, 0 = no surface / too far.
        T_world_camera: the exact pose rendered from.
    """

    color_rgb: npt.NDArray[np.uint8]
    depth_mm: npt.NDArray[np.uint16]
    T_world_camera: Transform


@dataclass
class _Buffers:
    t: npt.NDArray[np.float32]
    map_u: npt.NDArray[np.float32]
    map_v: npt.NDArray[np.float32]
    shade: npt.NDArray[np.float32]
    lod: npt.NDArray[np.float32]  # mip level: log2(texels per pixel) - _LOD_BIAS, 0 at least and for sky


@dataclass
class SimCamera:
    """Renders :class:`Scene` views for one pinhole model.

    Args:
        scene: what to render.
        model: intrinsics (rectified, no distortion).
        baseline_m: stereo baseline (right camera at +baseline along camera x).
        depth_max_m: surfaces further than this get depth 0.
    """

    scene: Scene
    model: PinholeModel
    baseline_m: float = 0.05
    depth_max_m: float = 10.0
    _rays_cam: npt.NDArray[np.float32] = field(init=False, repr=False)
    _mip_atlas: npt.NDArray[np.uint8] = field(init=False, repr=False)
    _mip_x0: npt.NDArray[np.float32] = field(init=False, repr=False)
    _box_lo: npt.NDArray[np.float64] = field(init=False, repr=False)
    _box_hi: npt.NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        m = self.model
        u, v = np.meshgrid(np.arange(m.width_px, dtype=np.float64), np.arange(m.height_px, dtype=np.float64))
        rays = np.stack([(u - m.cx_px) / m.fx_px, (v - m.cy_px) / m.fy_px, np.ones_like(u)], axis=-1)
        self._rays_cam = rays.reshape(-1, 3).astype(np.float32)  # z = 1: the ray parameter is the depth
        # Atlas rows: floor, 4 walls (1024 px each), then one 512-px band per box.
        textures = [make_texture(_TEX_FLOOR_PX, self.scene.seed + 1000 + k) for k in range(5)]
        textures += [
            _u8(cv2.resize(make_texture(_TEX_BOX_PX, self.scene.seed + 1 + i), (_TEX_FLOOR_PX, _TEX_BOX_PX)))
            for i in range(len(self.scene.boxes))
        ]
        atlas = np.ascontiguousarray(np.concatenate(textures, axis=0))
        # Mip levels, each a Gaussian-filtered half of the one before (cv2.pyrDown: texel j of
        # level k sits at texel j * 2^k of level 0), packed side by side into one image so that
        # two remaps (the levels below and above each pixel's) sample them all.
        mips = [atlas]
        for _ in range(_MIP_LEVELS - 1):
            mips.append(_u8(cv2.pyrDown(mips[-1])))
        x0 = np.cumsum([0] + [mip.shape[1] for mip in mips[:-1]])
        packed = np.zeros((atlas.shape[0], int(x0[-1]) + mips[-1].shape[1], 3), np.uint8)
        for mip, x in zip(mips, x0, strict=True):
            packed[: mip.shape[0], x : x + mip.shape[1]] = mip
        self._mip_atlas, self._mip_x0 = packed, x0.astype(np.float32)
        self._box_lo = np.array([b.min_xyz_m for b in self.scene.boxes], dtype=np.float64).reshape(-1, 3)
        self._box_hi = np.array([b.max_xyz_m for b in self.scene.boxes], dtype=np.float64).reshape(-1, 3)

    @staticmethod
    def from_config(camera_cfg: object, scene: Scene | None = None) -> SimCamera:
        """Build from a :class:`flightkit.config.CameraConfig`."""
        from flightkit.config import CameraConfig

        assert isinstance(camera_cfg, CameraConfig)
        fx, fy, cx, cy = camera_cfg.intrinsics()
        model = PinholeModel(camera_cfg.width_px, camera_cfg.height_px, fx, fy, cx, cy)
        return SimCamera(scene or Scene.default_lab(), model, camera_cfg.stereo_baseline_m, camera_cfg.depth_max_m)

    # ------------------------------------------------------------------ rendering

    def _cast(self, T_world_camera: Transform) -> _Buffers:
        """Intersect every pixel ray with the scene; texture coordinates into the atlas."""
        h, w = self.model.height_px, self.model.width_px
        R = T_world_camera.rotation.as_matrix()
        origin = T_world_camera.translation
        d = (self._rays_cam @ R.T.astype(np.float32)).reshape(h, w, 3)  # t = camera depth
        dk = [np.ascontiguousarray(d[..., k]) for k in range(3)]  # planar components are faster
        t_best = np.full((h, w), np.inf, np.float32)
        map_u = np.full((h, w), -1.0, np.float32)
        map_v = np.full((h, w), -1.0, np.float32)
        shade = np.ones((h, w), np.float32)
        lod = np.zeros((h, w), np.float32)
        # A pixel's footprint on a surface at depth t spans t |d| / f metres across the slope and
        # t |d|^2 / (f |d . n|) along it (d the pixel's ray with z = 1 in the camera, n the unit
        # normal); the mip level follows their geometric mean, the square root of the area (the
        # larger one, as plain GPU trilinear filtering takes, blurs surfaces seen at a grazing
        # angle, the floor ahead, into featureless smears).
        d2 = dk[0] * dk[0] + dk[1] * dk[1] + dk[2] * dk[2]
        inv_f = np.float32(1.0 / self.model.fx_px)
        ox, oy, oz = (float(c) for c in origin)

        # Floor z = 0 (seen from above) and the four walls of the room (seen from inside).
        room, wall_h = self.scene.room_half_m, self.scene.wall_height_m
        # (axis, plane value, texture u axis, texture v axis, tile size m, shade, atlas row offset)
        planes = [(2, 0.0, 0, 1, _FLOOR_TILE_M, 1.0, 0)]
        planes += [
            (axis, sign * room, 1 - axis, 2, 2.5, 0.88, _TEX_FLOOR_PX * (1 + k))
            for k, (axis, sign) in enumerate(((0, -1.0), (0, 1.0), (1, -1.0), (1, 1.0)))
        ]
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis, value, ua, va, tile_m, face_shade, row0 in planes:
                t = np.float32(value - origin[axis]) / dk[axis]
                hit = (t > 1e-4) & (t < t_best)
                if axis != 2:  # walls are bounded by the room and the wall height
                    pu = np.float32(origin[ua]) + t * dk[ua]
                    pz = np.float32(oz) + t * dk[2]
                    hit &= (np.abs(pu) <= room) & (pz >= 0.0) & (pz <= wall_h)
                if not hit.any():
                    continue
                th = t[hit]
                pu = origin[ua] + th * dk[ua][hit]
                pv = origin[va] + th * dk[va][hit]
                scale = _TEX_FLOOR_PX / tile_m
                t_best[hit] = th
                map_u[hit] = np.mod(pu * scale, _TEX_FLOOR_PX - 1)
                map_v[hit] = row0 + np.mod(pv * scale, _TEX_FLOOR_PX - 1)
                shade[hit] = face_shade
                lod[hit] = _mip_level(th * inv_f * _spread(d2[hit], dk[axis][hit]) * np.float32(scale))

        # Boxes: slab test restricted to the image rectangle each box projects into.
        K = self.model.K
        for i in range(self._box_lo.shape[0]):
            lo, hi = self._box_lo[i], self._box_hi[i]
            corners = np.array(np.meshgrid(*zip(lo, hi, strict=True))).reshape(3, -1).T
            c_cam = (corners - origin) @ R
            if np.all(c_cam[:, 2] <= 1e-3):
                continue  # entirely behind the camera
            if np.all(c_cam[:, 2] > 1e-3):
                uv = (c_cam @ K.T)[:, :2] / c_cam[:, 2:3]
                u0, v0 = np.floor(uv.min(axis=0)).astype(int)
                u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 1
                u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w), min(v1, h)
                if u0 >= u1 or v0 >= v1:
                    continue  # outside the image
            else:
                u0, v0, u1, v1 = 0, 0, w, h  # straddles the image plane: test every ray
            sub = (slice(v0, v1), slice(u0, u1))
            t1 = []
            t2 = []
            with np.errstate(divide="ignore", invalid="ignore"):
                for k in range(3):
                    inv = 1.0 / dk[k][sub]
                    a = np.float32(lo[k] - origin[k]) * inv
                    b = np.float32(hi[k] - origin[k]) * inv
                    t1.append(np.minimum(a, b))
                    t2.append(np.maximum(a, b))
            t_near = np.maximum(np.maximum(t1[0], t1[1]), t1[2])
            t_far = np.minimum(np.minimum(t2[0], t2[1]), t2[2])
            hit = (t_near <= t_far) & (t_near > 1e-4) & (t_near < t_best[sub])
            if not hit.any():
                continue
            tn = t_near[hit]
            tn_all = t_near[hit]
            # The slab entered last is the face hit.
            face_axis = np.where(t1[0][hit] == tn_all, 0, np.where(t1[1][hit] == tn_all, 1, 2))
            ray = np.stack([dk[k][sub][hit] for k in range(3)], axis=-1)
            p = origin + tn[:, None] * ray
            rows = np.arange(tn.size)
            a_axis = np.where(face_axis == 0, 1, 0)
            b_axis = np.where(face_axis == 2, 1, 2)
            rel = p - lo
            size = hi - lo
            ua_m = rel[rows, a_axis] + size[a_axis] * face_axis
            vb_m = rel[rows, b_axis]
            scale = _TEX_BOX_PX / 1.5
            t_best[sub][hit] = tn
            # Box faces have twice the texels per metre along u as along v: their geometric mean.
            box_density = np.float32(scale * math.sqrt(2.0))
            d_n = ray[rows, face_axis]
            lod[sub][hit] = _mip_level(tn * inv_f * _spread(np.einsum("ij,ij->i", ray, ray), d_n) * box_density)
            map_u[sub][hit] = np.mod(ua_m * scale * 2.0, _TEX_FLOOR_PX - 1)
            map_v[sub][hit] = 5 * _TEX_FLOOR_PX + i * _TEX_BOX_PX + np.mod(vb_m * scale, _TEX_BOX_PX - 1)
            shade[sub][hit] = np.array([0.78, 0.9, 1.0], np.float32)[face_axis]
        return _Buffers(t_best, map_u, map_v, shade, lod)

    def _shade(self, buf: _Buffers) -> npt.NDArray[np.uint8]:
        """Sample the texture at each pixel's hit, filtered to the pixel's footprint.

        A pixel sees a patch of surface, not a point: where that patch spans several texels
        (a textured floor a few metres away), sampling one point would alias (moire whose
        pattern moves at the wrong speed as the camera moves, a bias for every tracker). So
        the atlas is sampled trilinearly: bilinearly in the two mip levels around the pixel's
        ``lod`` (:func:`_mip_level`), blended between them, as a GPU does.
        """
        h, w = self.model.height_px, self.model.width_px
        sky = tuple(int(c) for c in _SKY_RGB)
        sky_px = buf.map_u < 0.0
        below_k = np.minimum(buf.lod.astype(np.int32), _MIP_LEVELS - 2)
        frac = np.ascontiguousarray(buf.lod - below_k, dtype=np.float32)
        # Texel coordinates in the packed atlas: level k's are level 0's / 2^k, shifted to its column.
        scale = np.ldexp(np.float32(1.0), -below_k).astype(np.float32)
        u_below = buf.map_u * scale + self._mip_x0[below_k]
        u_above = buf.map_u * (scale * np.float32(0.5)) + self._mip_x0[below_k + 1]
        v_below = buf.map_v * scale
        v_above = v_below * np.float32(0.5)
        for coord in (u_below, u_above, v_below, v_above):
            np.putmask(coord, sky_px, np.float32(-1.0))  # outside the atlas: the sky colour
        below = cv2.remap(
            self._mip_atlas, u_below, v_below, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=sky
        )
        above = cv2.remap(
            self._mip_atlas, u_above, v_above, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=sky
        )
        img = _u8(cv2.blendLinear(below, above, 1.0 - frac, frac))
        shaded: npt.NDArray[np.float32] = img * buf.shade.reshape(h, w, 1)
        return np.clip(shaded, 0, 255).astype(np.uint8)

    def render(self, T_world_camera: Transform) -> RenderedFrame:
        """RGB + depth from ``T_world_camera`` (camera in OpenCV convention)."""
        buf = self._cast(T_world_camera)
        h, w = self.model.height_px, self.model.width_px
        depth_m = buf.t.reshape(h, w)
        valid = np.isfinite(depth_m) & (depth_m <= self.depth_max_m)
        depth_mm = np.zeros((h, w), np.uint16)
        depth_mm[valid] = np.round(depth_m[valid] * 1000.0).astype(np.uint16)
        return RenderedFrame(self._shade(buf), depth_mm, T_world_camera)

    def render_stereo(self, T_world_left: Transform) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]:
        """Rectified grayscale pair; the right camera sits ``baseline_m`` along the left's x."""
        T_left_right = Transform(translation=np.array([self.baseline_m, 0.0, 0.0]))
        left = _u8(cv2.cvtColor(self._shade(self._cast(T_world_left)), cv2.COLOR_RGB2GRAY))
        right = _u8(cv2.cvtColor(self._shade(self._cast(T_world_left @ T_left_right)), cv2.COLOR_RGB2GRAY))
        return left, right
