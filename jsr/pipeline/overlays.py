"""Per-frame overlays of the front-end's measurements, for looking at what it extracted.

``render_overlay`` draws two panels side by side (``(H, 2W, 3)`` uint8 RGB):

* left: the colour image with the planes as translucent colours (outlined), keypoints with
  depth (3D points) as green circles and keypoints without depth (2D points) as red ones;
* right: the segments in distinct colours with white boundaries (unsegmented pixels dark),
  keypoints as small dots.

``write_frame_overlays`` runs the front-end on frames of a sequence and writes
``<out_dir>/<frame name>.png`` for each (atomically), for ``jsr frames SEQ --out DIR``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from jsr.config import Config
from jsr.errors import OutputError
from jsr.io.atomic import atomic_path
from jsr.io.dataset import Frame, RGBDSequence
from jsr.pipeline.frontend import FrontEnd
from jsr.pipeline.measurements import FrameMeasurements

logger = logging.getLogger(__name__)

GREEN = (40, 220, 40)
RED = (240, 40, 40)
WHITE = (255, 255, 255)


def label_colours(count: int, seed: int = 0) -> np.ndarray:
    """``(count, 3)`` uint8 RGB colours, well spread in hue (golden-ratio steps), deterministic."""
    if count <= 0:
        return np.zeros((0, 3), dtype=np.uint8)
    rng = np.random.default_rng(seed)
    hues = (np.arange(count) * 0.618033988749895 + rng.random()) % 1.0
    saturation = 0.55 + 0.45 * ((np.arange(count) * 7) % 3) / 2.0
    value = 0.75 + 0.25 * ((np.arange(count) * 5) % 2)
    hsv = np.stack([hues * 180.0, saturation * 255.0, value * 255.0], axis=-1).astype(np.uint8)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]


def label_boundaries(labels: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels whose right or lower neighbour carries another label."""
    edges = np.zeros(labels.shape, dtype=bool)
    horizontal = labels[:, 1:] != labels[:, :-1]
    vertical = labels[1:, :] != labels[:-1, :]
    edges[:, :-1] |= horizontal
    edges[:, 1:] |= horizontal
    edges[:-1, :] |= vertical
    edges[1:, :] |= vertical
    return edges


def _paint_labels(base: np.ndarray, labels: np.ndarray, colours: np.ndarray, alpha: float) -> np.ndarray:
    """Blend ``colours[label]`` into ``base`` where ``labels >= 0``."""
    out = base.astype(np.float32)
    mask = labels >= 0
    if mask.any() and len(colours):
        out[mask] = (1.0 - alpha) * out[mask] + alpha * colours[labels[mask] % len(colours)].astype(np.float32)
    return np.clip(out, 0, 255).astype(np.uint8)


def _draw_keypoints(image: np.ndarray, pixels: np.ndarray, has_depth: np.ndarray, radius: int) -> None:
    for (u, v), with_depth in zip(np.rint(pixels).astype(int).tolist(), has_depth.tolist()):
        colour = GREEN if with_depth else RED
        if radius <= 1:
            cv2.circle(image, (u, v), 1, colour, -1, lineType=cv2.LINE_AA)
        else:
            cv2.circle(image, (u, v), radius, colour, 1, lineType=cv2.LINE_AA)


def _caption(image: np.ndarray, text: str) -> None:
    cv2.putText(image, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, WHITE, 1, cv2.LINE_AA)


def render_overlay(
    frame: Frame, measurements: FrameMeasurements, keypoint_pixels: np.ndarray | None = None
) -> np.ndarray:
    """Two panels ``(H, 2W, 3)`` uint8 RGB: planes and keypoints | segments.

    Keypoints are drawn at ``keypoint_pixels`` (raw image positions) when given, else at
    ``measurements.points.pixels`` (undistorted positions; a few pixels off near the image
    corners of a distorted camera).
    """
    colour = np.asarray(frame.color, dtype=np.uint8)
    if colour.ndim == 2:
        colour = np.repeat(colour[:, :, None], 3, axis=2)
    points = measurements.points
    planes = measurements.planes
    segments = measurements.segments
    pixels = points.pixels if keypoint_pixels is None else keypoint_pixels

    left = _paint_labels(colour, planes.label_image, label_colours(len(planes), seed=1), 0.5)
    left[label_boundaries(planes.label_image) & (planes.label_image >= 0)] = WHITE
    _draw_keypoints(left, pixels, points.has_depth, radius=3)
    _caption(
        left,
        f"frame {frame.index}: {len(planes)} planes, {int(points.has_depth.sum())} 3D / "
        f"{int((~points.has_depth).sum())} 2D points",
    )

    grey = cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY)
    dim = (np.repeat(grey[:, :, None], 3, axis=2) * 0.35).astype(np.uint8)
    right = _paint_labels(dim, segments.label_image, label_colours(max(len(segments), 1), seed=2), 0.75)
    right[label_boundaries(segments.label_image)] = WHITE
    _draw_keypoints(right, pixels, points.has_depth, radius=1)
    planar = int((segments.plane_index >= 0).sum())
    _caption(right, f"{len(segments)} segments ({planar} planes, {len(segments) - planar} depth)")
    return np.ascontiguousarray(np.concatenate([left, right], axis=1))


def write_frame_overlays(
    sequence: RGBDSequence,
    config: Config,
    out_dir: Path,
    frame_indices: Iterable[int] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[Path]:
    """Run the front-end on frames of ``sequence`` and write ``out_dir/<frame name>.png``.

    ``frame_indices``: positions in the sequence (default: every frame). ``progress`` is
    called as ``progress(done, total)`` after each written frame. Each PNG is written
    atomically. Returns the written paths in order.
    """
    out_dir = Path(out_dir)
    indices = list(range(len(sequence))) if frame_indices is None else [int(i) for i in frame_indices]
    written: list[Path] = []
    with FrontEnd(config, sequence.intrinsics) as frontend:
        for done, index in enumerate(indices, start=1):
            frame = sequence[index]
            measurements = frontend.process(frame)
            image = render_overlay(frame, measurements, keypoint_pixels=_raw_pixels(measurements, sequence, config))
            path = out_dir / f"{frame.name}.png"
            try:
                with atomic_path(path) as temporary:
                    if not cv2.imwrite(str(temporary), np.ascontiguousarray(image[:, :, ::-1])):
                        raise OutputError(f"cannot write overlay {path}")
            except OSError as error:
                raise OutputError(f"cannot write overlay {path}: {error.strerror or error}") from None
            written.append(path)
            logger.debug("overlay %s: %s", path, {k: round(v, 1) for k, v in measurements.timings_ms.items()})
            if progress is not None:
                progress(done, len(indices))
    return written


def _raw_pixels(measurements: FrameMeasurements, sequence: RGBDSequence, config: Config) -> np.ndarray | None:
    """Raw (distorted) keypoint positions for drawing on the raw image."""
    intrinsics = sequence.intrinsics
    pixels = measurements.points.pixels
    if not (config.features.undistort and intrinsics.has_distortion) or len(pixels) == 0:
        return None
    normalised = np.column_stack(
        [(pixels[:, 0] - intrinsics.cx) / intrinsics.fx, (pixels[:, 1] - intrinsics.cy) / intrinsics.fy, np.ones(len(pixels))]
    )
    projected, _ = cv2.projectPoints(
        normalised.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intrinsics.matrix, intrinsics.distortion_coefficients
    )
    return projected.reshape(-1, 2)
