"""Synthetic VO sequences for the benchmark: the lab patterns seen by the simulated camera.

The patterns and the sequences are built by ``flightkit.apps.sequences``; this module names
them for the bench tables and pre-renders them, so the rendering cost (about 25 ms per view at
320x240, two views per frame with stereo) is paid once and not counted in the VO timings.

    from bench._synthetic import SYNTHETIC, prerendered
    seq = prerendered("circle", size=(320, 240))     # SimSequence with every frame cached
"""

from __future__ import annotations

from typing import Any

from flightkit.apps.sequences import SYNTHETIC_PATTERNS, synthetic_sequence
from flightkit.sim.sequence import SimSequence

__all__ = ["METHODS", "RATE_HZ", "SYNTHETIC", "prerendered"]

SYNTHETIC: dict[str, str] = {f"sim_{name}": name for name in SYNTHETIC_PATTERNS}
"""Bench/test key -> lab pattern name."""

METHODS = ["rgbd-pnp", "rgbd-essential", "rgbd-kabsch"]
METHODS += ["stereo", "stereo@exact", "stereo@ransac", "stereo@drop", "flow"]
"""Every method runs on the synthetic sequences: they carry colour, depth and a stereo pair."""

RATE_HZ = 15.0


def prerendered(
    pattern: str, size: tuple[int, int] = (320, 240), rate_hz: float = RATE_HZ, **kwargs: Any
) -> SimSequence:
    """A synthetic sequence of ``pattern`` with every frame rendered now and kept in memory (without
    colour: about 0.3 MB per frame at 320x240); ``kwargs`` go to ``synthetic_sequence``."""
    return synthetic_sequence(pattern, size=size, rate_hz=rate_hz, color=False, prerender=True, **kwargs)
