"""Options of a synthetic sequence (:class:`SynthOptions`) and their validation."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from jsr.errors import InputError

MOTIONS = ("jump", "smooth", "static")
IMAGE_FORMATS = ("png", "jpg")
MAX_OBJECTS = 6
MIN_WIDTH, MIN_HEIGHT = 32, 24
MAX_SIDE = 4096
MAX_FRAMES = 100_000


@dataclass
class SynthOptions:
    """What :func:`generate_sequence` renders. The defaults are a 640x480, 60-frame sequence."""

    frames: int = 60
    objects: int = 1  # K rigid textured objects (0: static scene)
    motion: str = "jump"  # "jump", "smooth" or "static"
    simultaneous: bool = False  # with objects >= 2: all objects move in the same frames
    width: int = 640
    height: int = 480
    depth_noise: bool = True  # sigma_Z = 1.425e-3 Z^2 m, then quantisation to 1/5000 m
    dropout: float = 0.02  # random fraction of valid depth pixels dropped (plus systematic dropouts)
    seed: int = 0
    fps: float = 30.0
    image_format: str = "png"  # colour format: "png" or "jpg"


def validate_options(options: SynthOptions) -> SynthOptions:
    """Check ``options``; returns a normalised copy or raises :class:`InputError`."""
    if not isinstance(options, SynthOptions):
        raise InputError("options must be a SynthOptions")
    motion = str(options.motion).strip().lower()
    image_format = str(options.image_format).strip().lower().lstrip(".")
    image_format = "jpg" if image_format == "jpeg" else image_format

    def integer(name: str) -> int:
        value = getattr(options, name)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InputError(f"--{name} must be an integer, got {value!r}")
        return int(value)

    frames, objects, width, height, seed = (integer(n) for n in ("frames", "objects", "width", "height", "seed"))
    if not 2 <= frames <= MAX_FRAMES:
        raise InputError(f"--frames must be between 2 and {MAX_FRAMES}, got {frames}")
    if not 0 <= objects <= MAX_OBJECTS:
        raise InputError(f"--objects must be between 0 and {MAX_OBJECTS}, got {objects}")
    if motion not in MOTIONS:
        raise InputError(f"unknown --motion '{options.motion}'; choose one of {', '.join(MOTIONS)}")
    if not (MIN_WIDTH <= width <= MAX_SIDE and MIN_HEIGHT <= height <= MAX_SIDE):
        raise InputError(
            f"resolution {width}x{height} is out of range; use at least {MIN_WIDTH}x{MIN_HEIGHT} "
            f"and at most {MAX_SIDE} pixels a side"
        )
    try:
        dropout = float(options.dropout)
        fps = float(options.fps)
    except (TypeError, ValueError):
        raise InputError("--dropout and fps must be numbers") from None
    if not 0.0 <= dropout < 1.0:
        raise InputError(f"--dropout must be in [0, 1), got {options.dropout}")
    if not (math.isfinite(fps) and 0.0 < fps <= 1000.0):
        raise InputError(f"fps must be in (0, 1000] (timestamps have 6 decimals), got {options.fps}")
    if seed < 0:
        raise InputError(f"--seed must be >= 0, got {seed}")
    if image_format not in IMAGE_FORMATS:
        raise InputError(f"unknown --format '{options.image_format}'; choose png or jpg")
    return replace(
        options,
        frames=frames,
        objects=objects,
        motion=motion,
        simultaneous=bool(options.simultaneous),
        width=width,
        height=height,
        depth_noise=bool(options.depth_noise),
        dropout=dropout,
        seed=seed,
        fps=fps,
        image_format=image_format,
    )
