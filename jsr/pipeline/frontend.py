"""The front-end: everything measured in one frame (points, planes, segments) with timings.

SIFT runs in a worker thread while the main thread extracts planes: OpenCV releases the GIL
during detection, so on a multi-core machine the two overlap. The depth lookup of the
keypoints and the segmentation follow once both are done.

Timings (milliseconds, wall clock) in ``FrameMeasurements.timings_ms``: ``sift`` (detection
and description, in the worker), ``planes``, ``depth_lookup``, ``segments`` and ``total``
(the whole ``process`` call; less than the sum of the stages when they overlap).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from jsr.config import Config
from jsr.io.camera import CameraIntrinsics
from jsr.io.dataset import Frame
from jsr.pipeline.features import (
    build_point_measurements,
    create_sift,
    detect_detail_keypoints,
    detect_keypoints,
    keep_slanted_within_segments,
    to_grey,
)
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.planes import extract_planes
from jsr.pipeline.segments import build_segments

logger = logging.getLogger(__name__)

STAGES = ("sift", "depth_lookup", "planes", "segments", "frontend_total")


REFERENCE_WIDTH, REFERENCE_HEIGHT = 640, 480  # the resolution the pixel thresholds are given for


def scaled_to_resolution(config: Config, width: int, height: int) -> Config:
    """A copy of ``config`` whose pixel sizes fit a ``width`` x ``height`` image (and without
    half-resolution SIFT below 640 pixels wide).

    Block size, minimum plane and segment sizes are given for 640x480 in the config; an object
    covers the same share of the image at any resolution, so block sides scale with the width
    and pixel counts with the area (a 320x240 frame would otherwise miss every plane below a
    quarter of the image).
    """

    linear = width / REFERENCE_WIDTH
    area = (width * height) / (REFERENCE_WIDTH * REFERENCE_HEIGHT)
    if abs(area - 1.0) < 1e-9:
        return config
    planes = dataclasses.replace(
        config.planes,
        block_size=max(4, int(round(config.planes.block_size * linear))),
        min_plane_pixels=max(16, int(round(config.planes.min_plane_pixels * area))),
    )
    segments = dataclasses.replace(
        config.segments, min_segment_pixels=max(16, int(round(config.segments.min_segment_pixels * area))))
    # SIFT at half resolution is a speed-up for 640x480 and larger; below that it would leave
    # too few keypoints on small objects.
    features = dataclasses.replace(config.features, half_resolution=config.features.half_resolution and linear >= 1.0)
    return dataclasses.replace(config, planes=planes, segments=segments, features=features)


class FrontEnd:
    """Measurement extraction for the frames of one camera.

    ``FrontEnd(config, intrinsics).process(frame)`` returns the frame's
    :class:`~jsr.pipeline.measurements.FrameMeasurements`. ``parallel`` runs SIFT in a worker
    thread concurrently with plane extraction. Call :meth:`close` (or use ``with``) to stop
    the worker.
    """

    def __init__(self, config: Config, intrinsics: CameraIntrinsics, parallel: bool = True):
        self.config = scaled_to_resolution(config, intrinsics.width, intrinsics.height)
        self.intrinsics = intrinsics
        self._sift = create_sift(config.features)
        # full-resolution SIFT for the object boxes (features.object_detail)
        self._detail_sift = create_sift(dataclasses.replace(config.features, max_keypoints=0))
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jsr-sift") if parallel else None

    def __enter__(self) -> "FrontEnd":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Stop the SIFT worker thread (the front-end can still be used, serially)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def _detect(self, color: np.ndarray, detail_boxes) -> tuple[np.ndarray, np.ndarray, float]:
        start = time.perf_counter()
        grey = to_grey(color)
        pixels, descriptors = detect_keypoints(grey, self.config.features, self._sift)
        features = self.config.features
        if detail_boxes and features.half_resolution and features.object_detail:
            detail_pixels, detail_descriptors = detect_detail_keypoints(grey, detail_boxes, self._detail_sift)
            pixels = np.concatenate([pixels, detail_pixels])
            descriptors = np.concatenate([descriptors, detail_descriptors])
        return pixels, descriptors, (time.perf_counter() - start) * 1000.0

    def process(self, frame: Frame, detail_boxes: list[tuple[int, int, int, int]] | None = None) -> FrameMeasurements:
        """Points, planes and segments of ``frame``, with per-stage timings. ``detail_boxes``
        (``x0, y0, x1, y1`` pixels, e.g. where objects were in the previous frame) also get
        the finest-scale SIFT keypoints (``features.object_detail``)."""
        config = self.config
        start = time.perf_counter()
        if self._executor is not None:
            pending = self._executor.submit(self._detect, frame.color, detail_boxes)
        else:
            pending = None
            detected = self._detect(frame.color, detail_boxes)

        planes_start = time.perf_counter()
        planes = extract_planes(frame.depth, self.intrinsics, config.planes, config.noise, config.features.undistort)
        planes_ms = (time.perf_counter() - planes_start) * 1000.0

        pixels, descriptors, sift_ms = pending.result() if pending is not None else detected
        lookup_start = time.perf_counter()
        points = build_point_measurements(pixels, descriptors, frame.depth, self.intrinsics, config.features, config.noise)
        lookup_ms = (time.perf_counter() - lookup_start) * 1000.0

        segments_start = time.perf_counter()
        segments = build_segments(
            planes, frame.depth, points, self.intrinsics, config.segments, config.noise, keypoint_pixels=pixels
        )
        straddling = keep_slanted_within_segments(points, pixels, frame.depth, segments.label_image, config.features,
                                                  config.noise)
        if straddling:
            logger.debug("frame %d: %d slanted keypoints straddle a segment border: 2D points", frame.index,
                         straddling)
        segments_ms = (time.perf_counter() - segments_start) * 1000.0
        total_ms = (time.perf_counter() - start) * 1000.0
        timings = {
            "sift": sift_ms,
            "depth_lookup": lookup_ms,
            "planes": planes_ms,
            "segments": segments_ms,
            "frontend_total": total_ms,
        }
        logger.debug(
            "frame %d: %d points (%d 3D), %d planes, %d segments, %.1f ms",
            frame.index,
            len(points),
            int(points.has_depth.sum()),
            len(planes),
            len(segments),
            total_ms,
        )
        return FrameMeasurements(frame.index, frame.timestamp, points, planes, segments, timings)
