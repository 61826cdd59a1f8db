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


def _integer(options, name: str) -> int:
    """``options.name`` as an int, or :class:`InputError` naming the option."""
    value = getattr(options, name)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"--{name} must be an integer, got {value!r}")
    return int(value)


def validate_options(options: SynthOptions) -> SynthOptions:
    """Check ``options``; returns a normalised copy or raises :class:`InputError`."""
    if not isinstance(options, SynthOptions):
        raise InputError("options must be a SynthOptions")
    motion = str(options.motion).strip().lower()
    image_format = str(options.image_format).strip().lower().lstrip(".")
    image_format = "jpg" if image_format == "jpeg" else image_format

    frames, objects, width, height, seed = (
        _integer(options, n) for n in ("frames", "objects", "width", "height", "seed")
    )
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


COMPOSITE_PERIOD = 15  # frames between motions in a composite: a real camera needs more frames to see an object


@dataclass
class CompositeOptions:
    """What :func:`jsr.synth.composite.generate_composite` renders into a real background.

    ``frames`` consecutive frames of the TUM-layout sequence ``background`` from ``start``;
    the image size, camera and timestamps are the background's. ``image_format`` None keeps
    the background's colour format. ``period``: frames between the starts of two motions.
    """

    background: str
    frames: int = 60
    start: int = 0
    objects: int = 1
    motion: str = "jump"
    simultaneous: bool = False
    depth_noise: bool = True
    dropout: float = 0.02
    seed: int = 0
    image_format: str | None = None
    period: int = COMPOSITE_PERIOD

    def synth_options(self, width: int = 640, height: int = 480, image_format: str = "png") -> SynthOptions:
        """The :class:`SynthOptions` of the objects, motion and sensor model, for images of
        ``width`` x ``height`` in ``image_format`` (when ``image_format`` here is None)."""
        return SynthOptions(
            frames=self.frames,
            objects=self.objects,
            motion=self.motion,
            simultaneous=self.simultaneous,
            width=width,
            height=height,
            depth_noise=self.depth_noise,
            dropout=self.dropout,
            seed=self.seed,
            image_format=self.image_format or image_format,
        )


def validate_composite_options(options: CompositeOptions) -> CompositeOptions:
    """Check ``options``; returns a normalised copy or raises :class:`InputError`.
    The options it shares with :class:`SynthOptions` are checked as :func:`validate_options` does."""
    if not isinstance(options, CompositeOptions):
        raise InputError("options must be a CompositeOptions")
    shared = validate_options(options.synth_options())
    for name, least in (("start", 0), ("period", 2)):
        if _integer(options, name) < least:
            raise InputError(f"--{name} must be >= {least}, got {getattr(options, name)}")
    if not str(options.background).strip():
        raise InputError("--background needs the folder of a TUM RGB-D sequence")
    return replace(
        options,
        background=str(options.background),
        frames=shared.frames,
        start=_integer(options, "start"),
        objects=shared.objects,
        motion=shared.motion,
        simultaneous=shared.simultaneous,
        depth_noise=shared.depth_noise,
        dropout=shared.dropout,
        seed=shared.seed,
        image_format=None if options.image_format is None else shared.image_format,
        period=_integer(options, "period"),
    )
