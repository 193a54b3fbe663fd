"""Synthetic VO sequences for the benchmark and the tests: the lab patterns seen by the simulated camera.

The three lab patterns (1 m circle at 1.5 m looking inward, 2 m x 1 m rectangle, 2 m x 1 m
lawnmower with 0.5 m lanes, at the lab's speeds) are defined once, in
``flightkit.cli.vo`` (``lab_pattern``, ``SYNTHETIC_PATTERNS``: the CLI is the one place in the
package allowed to import ``trajectories``), and turned into body poses with quadrotor
attitude by ``flightkit.sim.sequence.body_poses_along``. This module adds what a benchmark
or a test suite wants on top: the sequences pre-rendered into memory, so the rendering cost
(about 25 ms per view at 320x240, two views per frame with stereo) is paid once and not
counted in the VO timings.

    from bench._synthetic import SYNTHETIC, prerendered
    seq = prerendered("circle", size=(320, 240))     # SimSequence with every frame cached
"""

from __future__ import annotations

from typing import Any

from flightkit.cli.vo import SYNTHETIC_PATTERNS, lab_pattern, synthetic_sequence
from flightkit.sim.sequence import SimSequence

__all__ = ["METHODS", "RATE_HZ", "SYNTHETIC", "lab_pattern", "prerendered"]

SYNTHETIC: dict[str, str] = {f"sim_{name}": name for name in SYNTHETIC_PATTERNS}
"""Bench/test key -> lab pattern name."""

METHODS = ["rgbd-pnp", "rgbd-essential", "rgbd-kabsch", "stereo", "flow"]
"""Every method runs on the synthetic sequences: they carry colour, depth and a stereo pair."""

RATE_HZ = 15.0


def prerendered(
    pattern: str,
    size: tuple[int, int] = (320, 240),
    rate_hz: float = RATE_HZ,
    **kwargs: Any,
) -> SimSequence:
    """A synthetic sequence of ``pattern`` with every frame rendered now and kept in memory
    (without colour: about 0.3 MB per frame at 320x240). Blocks while rendering (~50 ms per
    frame at 320x240 with stereo; ``seq.render_s`` tells). ``kwargs`` go to
    ``flightkit.cli.vo.synthetic_sequence``."""
    seq: SimSequence = synthetic_sequence(pattern, size=size, rate_hz=rate_hz, color=False, cache=True, **kwargs)
    for _ in seq.frames():
        pass
    return seq
