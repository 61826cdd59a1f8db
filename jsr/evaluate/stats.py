"""Plain-number helpers of the metrics: JSON-safe floats, ratios and matrices, rotation
angles, root mean squares."""

from __future__ import annotations

import math

import numpy as np


def number(value: float) -> float | None:
    """A JSON-safe float: NaN and infinities become ``None``."""
    value = float(value)
    return value if math.isfinite(value) else None


def ratio(numerator: float, denominator: float) -> float | None:
    """``numerator / denominator``, or ``None`` when the denominator is not positive."""
    return float(numerator) / float(denominator) if denominator > 0 else None


def matrix(transform: np.ndarray) -> list[list[float]]:
    """A matrix (e.g. a 4x4 transform) as nested lists of floats."""
    return [[float(value) for value in row] for row in np.asarray(transform, dtype=float)]


def angle_degrees(rotations: np.ndarray) -> np.ndarray:
    """Rotation angles in degrees of ``(N, 3, 3)`` rotations, accurate also near 0 and 180 degrees.

    ``atan2(sin, cos)`` with ``sin`` from the skew-symmetric part and ``cos`` from the trace;
    ``arccos`` of the trace alone loses half the digits for small angles (~1e-6 degree noise).
    """
    rotations = np.asarray(rotations, dtype=float)
    skew = rotations - np.swapaxes(rotations, -1, -2)
    sine = 0.5 * np.linalg.norm(np.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1), axis=-1)
    cosine = 0.5 * (np.trace(rotations, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sine, cosine))


def rms(values: np.ndarray) -> float:
    """Root mean square of ``(N,)`` values; NaN when there are none."""
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else math.nan
