"""Synthetic VO sequences: the simulated camera flown along the lab's flight patterns.

The three lab patterns (as flown by ``examples/*.toml``) come from ``trajectories``; the
simulated camera and the sequence type come from the core (``flightkit.sim.sequence``). This
module joins them, and opens anything ``flightkit vo run`` accepts: a dataset folder, a
recording, or a ``sim:PATTERN[?options]`` spec::

    seq = open_dataset("sim:circle?rate_hz=30&size=640x480")
    seq = synthetic_sequence("rectangle", size=(320, 240), prerender=True)   # frames in memory
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightkit.errors import DatasetError, EstimationError

if TYPE_CHECKING:
    from flightkit.datasets.base import Sequence
    from flightkit.sim.sequence import SimSequence
    from trajectories.base import Pattern

__all__ = [
    "SIM_PREFIX",
    "SYNTHETIC_PATTERNS",
    "SyntheticWindow",
    "lab_pattern",
    "open_dataset",
    "parse_size",
    "parse_sim_spec",
    "synthetic_sequence",
]

SIM_PREFIX = "sim:"


@dataclass(frozen=True, slots=True)
class SyntheticWindow:
    """The part of a lab pattern a synthetic sequence covers by default.

    Attributes:
        start_s: pattern time of the first frame.
        duration_s: seconds of motion rendered.
        what: what happens in the window (for tables and docs).
    """

    start_s: float
    duration_s: float
    what: str


SYNTHETIC_PATTERNS: dict[str, SyntheticWindow] = {
    "circle": SyntheticWindow(0.0, 12.0, "start of a lap of the 1 m circle at 1.5 m, 40 s/lap, looking inward"),
    "rectangle": SyntheticWindow(14.0, 14.0, "end of the first 2 m side, the 90 deg corner turn, start of the next"),
    "lawnmower": SyntheticWindow(15.0, 14.0, "end of the first 2 m lane, turn, 0.5 m shift to the next lane"),
}
"""The three lab patterns, each with a short window of motion that contains what makes it hard
for VO: the speed-up from rest, and the turns in place."""


def lab_pattern(name: str) -> Pattern:
    """The lab's pattern ``name`` (one lap, as flown by ``examples/<name>.toml``): a 1 m circle at
    1.5 m, 40 s per lap, looking inward; a 2 m x 1 m rectangle at 0.1 m/s looking inward with
    5 s turns; a lawnmower over 2 m x 1 m with 0.5 m lanes at 0.1 m/s facing the travel.

    Raises:
        EstimationError: unknown name.
    """
    from trajectories.patterns import Circle, Lawnmower, Rectangle, rectangle_corners

    if name == "circle":
        return Circle(centre_m=(0.0, 0.0), radius_m=1.0, height_m=1.5, period_s=40.0)
    if name == "rectangle":
        return Rectangle(rectangle_corners((0.0, 0.0), (2.0, 1.0)), 1.5, speed_m_s=0.1, accel_m_s2=0.2, turn_s=5.0)
    if name == "lawnmower":
        return Lawnmower((-1.0, -0.5), (2.0, 1.0), 0.5, 1.5, speed_m_s=0.1, accel_m_s2=0.2, turn_s=5.0)
    raise EstimationError(
        f"unknown synthetic pattern {name!r}; use one of {', '.join(SIM_PREFIX + n for n in SYNTHETIC_PATTERNS)}"
    )


def synthetic_sequence(
    pattern: str,
    *,
    size: tuple[int, int] = (320, 240),
    rate_hz: float = 15.0,
    start_s: float | None = None,
    duration_s: float | None = None,
    seed: int = 0,
    noise_std: float = 0.0,
    blur_s: float = 0.0,
    stereo: bool = True,
    color: bool = True,
    cache: bool = False,
    prerender: bool = False,
) -> SimSequence:
    """A :class:`flightkit.sim.sequence.SimSequence` of the simulated lab camera (the default
    mount, 90 degrees HFOV, 5 cm stereo baseline) flown along the lab pattern ``pattern``.

    Args:
        pattern: ``circle``, ``rectangle`` or ``lawnmower``.
        size: rendered image size (width, height).
        rate_hz: frame rate.
        start_s, duration_s: the pattern-time window (default: :data:`SYNTHETIC_PATTERNS`).
        seed: scene layout (box placement and textures) and noise seed.
        noise_std: image noise, grey levels (0 = none).
        blur_s: motion-blur exposure, seconds (0 = none).
        stereo, color, cache: see :class:`~flightkit.sim.sequence.SimSequence`.
        prerender: render every frame now and keep it in memory (implies ``cache``), so a
            benchmark or a test pays the rendering once and not inside its timings; blocks
            while rendering (~50 ms per frame at 320x240 with stereo; ``seq.render_s`` tells).

    Without ``prerender`` returns immediately; frames render when iterated (~25 ms per view
    at 320x240).

    Raises:
        EstimationError: unknown pattern.
    """
    from flightkit.config import CameraConfig
    from flightkit.sim.camera import Scene
    from flightkit.sim.sequence import ImagingOptions, SimSequence, body_poses_along

    path = lab_pattern(pattern)
    window = SYNTHETIC_PATTERNS[pattern]
    start = window.start_s if start_s is None else start_s
    duration = window.duration_s if duration_s is None else duration_s
    duration = min(duration, float(path.duration_s) - start)
    poses = body_poses_along(path, rate_hz, start_s=start, duration_s=duration)
    camera_cfg = CameraConfig(width_px=size[0], height_px=size[1], rate_hz=rate_hz)
    imaging = ImagingOptions(noise_std=noise_std, exposure_s=blur_s, seed=seed)
    seq = SimSequence.from_config(
        camera_cfg,
        poses,
        scene=Scene.default_lab(seed),
        name=f"sim_{pattern}",
        stereo=stereo,
        color=color,
        imaging=imaging,
        cache=cache or prerender,
    )
    if prerender:
        for _ in seq.frames():
            pass
    return seq


def parse_size(text: str) -> tuple[int, int]:
    """``"640x480"`` -> ``(640, 480)``.

    Raises:
        EstimationError: not WIDTHxHEIGHT with positive integers.
    """
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise EstimationError(f"size {text!r} is not WIDTHxHEIGHT; write e.g. 640x480") from exc
    if w <= 0 or h <= 0:
        raise EstimationError(f"size {text!r} must be positive; write e.g. 640x480")
    return w, h


def parse_sim_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """``"sim:circle?rate_hz=30&size=640x480"`` -> ``("circle", {"rate_hz": 30.0, "size": (640, 480)})``.

    Raises:
        EstimationError: not a ``sim:`` spec, or an unknown or malformed option.
    """
    from urllib.parse import parse_qsl

    if not spec.startswith(SIM_PREFIX):
        raise EstimationError(f"{spec!r} is not a synthetic sequence; write e.g. sim:circle")
    name, _, query = spec[len(SIM_PREFIX) :].partition("?")
    floats = {"rate_hz": "rate_hz", "start_s": "start_s", "duration_s": "duration_s", "noise": "noise_std"}
    floats["blur_s"] = "blur_s"
    kwargs: dict[str, Any] = {}
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)):
        try:
            if key in floats:
                kwargs[floats[key]] = float(value)
            elif key == "seed":
                kwargs["seed"] = int(value)
            elif key == "size":
                kwargs["size"] = parse_size(value)
            elif key == "stereo":
                kwargs["stereo"] = value.lower() not in ("0", "false", "no")
            else:
                raise EstimationError(
                    f"unknown option {key!r} in {spec!r}; use rate_hz, size, start_s, duration_s, seed, noise, "
                    "blur_s or stereo"
                )
        except ValueError as exc:
            raise EstimationError(f"option {key}={value!r} in {spec!r} is not a number") from exc
    return name, kwargs


def open_dataset(source: str | Path, vehicle: str | None = None) -> Sequence:
    """Open a dataset folder, recording or ``sim:PATTERN[?options]`` as a ``Sequence``;
    ``vehicle``: which vehicle's camera of a fleet's recording.

    Raises:
        DatasetError: the path is missing or not recognised, or ``vehicle`` is given for
            something other than an MCAP recording.
        EstimationError: a malformed ``sim:`` spec.
    """
    from flightkit.datasets.registry import open_sequence

    is_sim = isinstance(source, str) and source.startswith(SIM_PREFIX)
    if vehicle is not None and (is_sim or Path(source).suffix.lower() != ".mcap"):
        raise DatasetError(f"a vehicle ({vehicle!r}) is chosen in an .mcap recording only; {source} is not one")
    if is_sim:
        assert isinstance(source, str)
        name, kwargs = parse_sim_spec(source)
        return synthetic_sequence(name, **kwargs)
    return open_sequence(Path(source), **({"vehicle": vehicle} if vehicle is not None else {}))
