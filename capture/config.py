"""The ``[capture]`` section of a lab config: what the camera publishers send, how the recorder writes.

Example ``lab.toml``::

    [capture]
    stereo = true            # also publish the rectified pair (left/right, mono8)
    compression = "zstd"     # default for `flightkit record`
    topics = ["uav1/**"]     # what `flightkit record` subscribes to by default

Validated with ``lab_cfg.section("capture", CaptureConfig)``; every key is optional.
"""

from __future__ import annotations

from dataclasses import dataclass

from flightkit.bus.streams import CameraStreamSelection
from flightkit.settings import setting

__all__ = ["CaptureConfig"]


@dataclass(frozen=True, slots=True)
class CaptureConfig:
    """Capture settings (publishers and recorder)."""

    color: bool = setting(True, help="publish the colour image (rgb8) and its camera_info")
    depth: bool = setting(True, help="publish 16-bit depth in millimetres (16UC1) and its camera_info")
    stereo: bool = setting(False, help="publish the rectified stereo pair (left/right mono8) and camera_info")
    tf: bool = setting(True, help="publish the camera extrinsics and ground-truth camera poses on <ns>/tf")
    jpeg_quality: int = setting(0, min=0, max=100, help="also publish colour as JPEG CompressedImage (0 = off)")
    compression: str = setting("zstd", help="recorder chunk compression: zstd, lz4 or none")
    topics: tuple[str, ...] = setting((), help="key expressions `flightkit record` subscribes to (default <ns>/**)")
    chunk_size_mb: float = setting(4.0, min=0.01, max=256.0, help="recorder chunk size")
    chunk_max_age_s: float = setting(0.5, min=0.01, max=60.0, help="close a chunk at least this often")
    queue_limit_mb: float = setting(1024.0, min=1.0, max=65536.0, help="memory the recorder may buffer")

    def streams(self) -> CameraStreamSelection:
        """The publisher switches of this section."""
        return CameraStreamSelection(self.color, self.depth, self.stereo, self.tf, self.jpeg_quality)

    @staticmethod
    def _check(obj: CaptureConfig, path: str, prefix: str) -> None:
        from flightkit.errors import ConfigError

        if obj.compression not in ("zstd", "lz4", "none"):
            raise ConfigError(
                path, f"{prefix}.compression", f"{obj.compression!r} is not allowed", "use zstd, lz4 or none",
                obj.compression,
            )
