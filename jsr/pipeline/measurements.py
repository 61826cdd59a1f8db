"""Measurements of one frame, as structures of arrays (the hot path avoids small objects).

All geometry is in the camera frame of the frame that produced it (x right, y down,
z forward, metres). Planes are ``n . x + d = 0`` with a unit normal ``n`` oriented towards
the camera, so that ``d > 0`` for a plane in front of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PointMeasurements:
    """SIFT keypoints of a frame; ``N`` rows.

    ``pixels``: ``(N, 2)`` undistorted pixel coordinates (u, v).
    ``points``: ``(N, 3)`` camera-frame positions; NaN rows for keypoints without depth.
    ``has_depth``: ``(N,)`` bool; True for a 3D point, False for a 2D point (bearing only).
    ``bearings``: ``(N, 3)`` unit rays through ``pixels`` (used by 2D-to-3D correspondences).
    ``sigma_z``: ``(N,)`` axial depth noise (metres) of 3D points, 0 for 2D points.
    ``descriptors``: ``(N, 128)`` float32 SIFT descriptors.
    """

    pixels: np.ndarray
    points: np.ndarray
    has_depth: np.ndarray
    bearings: np.ndarray
    sigma_z: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.pixels)

    @classmethod
    def empty(cls) -> "PointMeasurements":
        return cls(
            pixels=np.zeros((0, 2)),
            points=np.zeros((0, 3)),
            has_depth=np.zeros(0, dtype=bool),
            bearings=np.zeros((0, 3)),
            sigma_z=np.zeros(0),
            descriptors=np.zeros((0, 128), dtype=np.float32),
        )

    def subset(self, indices: np.ndarray) -> "PointMeasurements":
        """The measurements at ``indices`` (an index array or a boolean mask)."""
        return PointMeasurements(
            self.pixels[indices],
            self.points[indices],
            self.has_depth[indices],
            self.bearings[indices],
            self.sigma_z[indices],
            self.descriptors[indices],
        )


@dataclass
class PlaneMeasurements:
    """Planes extracted from the organized point cloud; ``P`` rows.

    ``normals``: ``(P, 3)`` unit normals towards the camera; ``offsets``: ``(P,)`` d of
    ``n . x + d = 0``; ``centroids``: ``(P, 3)``; ``point_counts``: ``(P,)`` inlier pixels;
    ``fit_rmse``: ``(P,)`` RMS point-to-plane distance in metres; ``label_image``: ``(H, W)``
    int32 plane index per pixel, -1 where no plane.
    """

    normals: np.ndarray
    offsets: np.ndarray
    centroids: np.ndarray
    point_counts: np.ndarray
    fit_rmse: np.ndarray
    label_image: np.ndarray

    def __len__(self) -> int:
        return len(self.normals)

    def mask(self, plane_index: int) -> np.ndarray:
        """``(H, W)`` bool pixel mask of one plane."""
        return self.label_image == plane_index


@dataclass
class Segments:
    """Segments of a frame: one per plane, then depth-discontinuity regions; ``S`` of them.

    ``label_image``: ``(H, W)`` int32 segment index per pixel, -1 where no segment.
    ``plane_index``: ``(S,)`` plane of a plane segment, -1 for a depth segment.
    ``point_indices``: list of ``S`` int arrays, the point measurements inside each segment.
    ``pixel_counts``: ``(S,)`` pixels per segment.
    """

    label_image: np.ndarray
    plane_index: np.ndarray
    point_indices: list[np.ndarray] = field(default_factory=list)
    pixel_counts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.plane_index)

    def mask(self, segment_index: int) -> np.ndarray:
        """``(H, W)`` bool pixel mask of one segment."""
        return self.label_image == segment_index

    def segment_of_points(self, num_points: int) -> np.ndarray:
        """``(num_points,)`` segment index of every point measurement, -1 if in none."""
        owner = np.full(num_points, -1, dtype=np.int64)
        for segment_index, indices in enumerate(self.point_indices):
            owner[indices] = segment_index
        return owner


@dataclass
class FrameMeasurements:
    """Everything the front-end extracts from one frame."""

    frame_index: int
    timestamp: float
    points: PointMeasurements
    planes: PlaneMeasurements
    segments: Segments
    timings_ms: dict[str, float] = field(default_factory=dict)
