"""Procedural textures of the synthetic scene and their mip levels."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class TextureStyle:
    """Parameters of :func:`make_texture` (hue/saturation/value ranges in [0, 1])."""

    hue: tuple[float, float]
    saturation: tuple[float, float]
    value: tuple[float, float]
    shapes_per_texel: float  # shape density
    radius: tuple[float, float]  # shape radius range in texels (log-uniform)
    contrast: float  # how far shape colours stray from the base colour (0..1)
    hue_spread: float  # hue range of the shapes around the base hue
    noise: float  # amplitude of the luminance noise


_STYLES = {
    "floor": TextureStyle((0.04, 0.12), (0.3, 0.55), (0.45, 0.65), 1 / 420, (2.0, 14.0), 0.45, 0.08, 0.22),
    "wall": TextureStyle((0.0, 1.0), (0.1, 0.3), (0.65, 0.85), 1 / 520, (2.0, 16.0), 0.45, 0.15, 0.16),
    "ceiling": TextureStyle((0.0, 1.0), (0.0, 0.12), (0.75, 0.88), 1 / 700, (2.0, 10.0), 0.3, 0.1, 0.12),
    "wood": TextureStyle((0.05, 0.1), (0.35, 0.65), (0.4, 0.65), 1 / 380, (2.0, 12.0), 0.45, 0.05, 0.25),
    "furniture": TextureStyle((0.0, 1.0), (0.25, 0.6), (0.5, 0.85), 1 / 360, (2.0, 14.0), 0.6, 0.2, 0.18),
    "object": TextureStyle((0.0, 1.0), (0.6, 0.95), (0.65, 0.95), 1 / 170, (2.5, 16.0), 1.0, 0.5, 0.15),
}


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV (each in [0, 1], hue wraps) to ``(N, 3)`` RGB in [0, 1]."""
    h = np.mod(np.asarray(h, dtype=float), 1.0) * 6.0
    s = np.clip(np.asarray(s, dtype=float), 0.0, 1.0)
    v = np.clip(np.asarray(v, dtype=float), 0.0, 1.0)
    channel = np.stack([np.mod(5.0 + h, 6.0), np.mod(3.0 + h, 6.0), np.mod(1.0 + h, 6.0)], axis=-1)
    ramp = np.clip(np.minimum(channel, 4.0 - channel), 0.0, 1.0)
    return v[..., None] * (1.0 - s[..., None] * ramp)


def _noise(rng: np.random.Generator, height: int, width: int, cell: float) -> np.ndarray:
    """Smooth value noise, about unit variance, with features ``cell`` texels apart."""
    grid = rng.standard_normal((max(2, math.ceil(height / cell) + 1), max(2, math.ceil(width / cell) + 1)))
    return cv2.resize(grid.astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)


_ALPHABET = "ABCDEFGHKMNPRSTUVWXYZ2345789&#%@"


def make_texture(rng: np.random.Generator, height: int, width: int, style: str) -> np.ndarray:
    """A procedural ``(height, width, 3)`` uint8 RGB texture: two-colour blotches and
    multi-scale noise under a few hundred random shapes, lines and letters."""
    look = _STYLES[style]
    base_hue = rng.uniform(*look.hue)
    base = _hsv_to_rgb(
        np.array([base_hue, base_hue + rng.uniform(-0.1, 0.1)]),
        rng.uniform(*look.saturation, 2),
        rng.uniform(*look.value, 2) * np.array([1.0, rng.uniform(0.7, 1.0)]),
    )
    blend = np.clip(0.5 + 0.6 * _noise(rng, height, width, 64.0), 0.0, 1.0)[:, :, None]
    image = base[0] * (1.0 - blend) + base[1] * blend
    luminance = look.noise * (0.6 * _noise(rng, height, width, 24.0) + 0.35 * _noise(rng, height, width, 8.0))
    image = image * (1.0 + luminance[:, :, None])
    image = np.ascontiguousarray((np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8))

    count = int(height * width * look.shapes_per_texel) + 3
    kinds = rng.integers(0, 7, count)
    centres = rng.uniform((0, 0), (width, height), (count, 2))
    radii = np.exp(rng.uniform(math.log(look.radius[0]), math.log(look.radius[1]), count))
    angles = rng.uniform(0.0, math.pi, count)
    aspects = rng.uniform(0.3, 1.0, count)
    thickness = rng.integers(1, 4, count)
    letters = rng.integers(0, len(_ALPHABET), count)
    vertices = rng.uniform(-1.0, 1.0, (count, 3, 2))
    # Shape colours: around the base colour, darker or lighter by up to ``contrast``.
    base_value = float(base.max(axis=1).mean())
    lighter = rng.random(count) < 0.5
    values = np.where(
        lighter,
        base_value + rng.uniform(0.3, 1.0, count) * look.contrast * (1.0 - base_value),
        base_value - rng.uniform(0.4, 1.0, count) * look.contrast * base_value,
    )
    colours = _hsv_to_rgb(
        base_hue + rng.uniform(-look.hue_spread, look.hue_spread, count),
        rng.uniform(look.saturation[0], min(1.0, look.saturation[1] + 0.2), count),
        values,
    ) * 255.0
    for i in range(count):
        colour = (float(colours[i, 0]), float(colours[i, 1]), float(colours[i, 2]))
        cx, cy, r = float(centres[i, 0]), float(centres[i, 1]), float(radii[i])
        centre = (int(cx), int(cy))
        kind = kinds[i]
        if kind == 0:
            cv2.circle(image, centre, int(r), colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.circle(image, centre, int(r), colour, int(thickness[i]), cv2.LINE_AA)
        elif kind == 2:
            box = cv2.boxPoints(((cx, cy), (2 * r, 2 * r * aspects[i]), math.degrees(angles[i])))
            cv2.fillPoly(image, [np.round(box).astype(np.int32)], colour, cv2.LINE_AA)
        elif kind == 3:
            dx, dy = 2.5 * r * math.cos(angles[i]), 2.5 * r * math.sin(angles[i])
            ends = (int(cx - dx), int(cy - dy)), (int(cx + dx), int(cy + dy))
            cv2.line(image, *ends, colour, int(thickness[i]), cv2.LINE_AA)
        elif kind == 4:
            cv2.fillPoly(image, [np.round(vertices[i] * r * 1.5 + (cx, cy)).astype(np.int32)], colour, cv2.LINE_AA)
        elif kind == 5:
            axes = (int(r), max(1, int(r * aspects[i])))
            cv2.ellipse(image, centre, axes, math.degrees(angles[i]), 0, 360, colour, -1, cv2.LINE_AA)
        else:
            origin = (int(cx - r), int(cy + r))
            scale = max(0.3, r / 10.0)
            font = cv2.FONT_HERSHEY_SIMPLEX
            cv2.putText(image, _ALPHABET[letters[i]], origin, font, scale, colour, int(thickness[i]), cv2.LINE_AA)
    return cv2.GaussianBlur(image, (0, 0), 0.6)


def half_size(tile: np.ndarray) -> np.ndarray:
    """The next mip level of a texture tile (area average, at least 2x2)."""
    size = (max(2, math.ceil(tile.shape[1] / 2)), max(2, math.ceil(tile.shape[0] / 2)))
    return cv2.resize(tile, size, interpolation=cv2.INTER_AREA)
