"""Correspondences between a frame and a map, and how well a pose explains them.

A frame is registered to a map from three kinds of correspondences (paper, Section 2.2):

* 3D-3D points: a camera-frame point ``p`` and a map landmark ``q``; distance ``|T p - q|``;
* 2D-3D points: a bearing ray ``b`` of a keypoint without depth and a map landmark ``X``;
  distance from ``T^-1 X`` (the landmark in the camera) to the ray, and the landmark must be
  in front of the camera;
* planes: ``[n, d]`` in the camera and ``[m, e]`` in the map; the frame plane moved into the
  map must have a normal within ``ransac.plane_inlier_angle_degrees`` of ``m`` and an offset
  within ``ransac.plane_inlier_distance`` of ``e``.

Point thresholds follow the paper, ``sigma = max(noise.min_inlier_threshold,
noise.inlier_sigmas * sigma_Z(Z))`` with ``sigma_Z = noise.sigma_z_coefficient * Z^2``, ``Z``
the depth of the 3D measurement or, for 2D-3D pairs, of the landmark moved into the camera.

Counting rule. Every correspondence counts as one match, a plane pair included (a plane is
one measurement of the frame even though it summarises many pixels), so
``num_matches = A + B + C``. RANSAC is not run when ``num_matches < ransac.min_matches``.
The registration succeeds when ``num_inliers / num_matches >= ransac.min_inlier_ratio`` and
``num_inliers >= max(3, ransac.min_inliers, ceil(ransac.min_matches * ransac.min_inlier_ratio))``.
The paper's 10 matches at 0.4 alone would accept 4 inliers, one more than a minimal sample:
on real data that happens by chance (a lost object map "found" on four 2D points of the
kitchen, 1.2 m off, in kitchen_box120), hence ``ransac.min_inliers`` (8).

The registration itself (RANSAC and least squares) is :mod:`jsr.pipeline.registration`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from jsr.config import NoiseConfig, RansacConfig
from jsr.geometry import inlier_threshold


_ID_FIELDS = {
    "point3d": ("frame_point_ids", "landmark_ids"),
    "point2d": ("frame_point_ids_2d", "landmark_ids_2d"),
    "plane": ("frame_plane_ids", "landmark_plane_ids"),
}


def _array(values: np.ndarray | None, columns: int) -> np.ndarray:
    if values is None:
        return np.zeros((0, columns))
    return np.asarray(values, dtype=float).reshape(-1, columns)


@dataclass
class Correspondences:
    """Matches between frame measurements and map landmarks, one row per match.

    ``frame_points`` ``(A, 3)`` camera-frame 3D points and ``map_points`` ``(A, 3)`` their
    landmarks; ``point_depths`` ``(A,)`` camera depth of the 3D points (defaults to their z).
    ``frame_bearings`` ``(B, 3)`` unit rays of 2D points and ``map_points_2d`` ``(B, 3)``.
    ``frame_planes`` ``(C, 4)`` ``[n, d]`` in the camera and ``map_planes`` ``(C, 4)`` in the map.
    The optional id arrays (frame measurement indices, landmark ids) are not used here and are
    carried through :meth:`subset` unchanged, so that callers can map inliers back.
    ``focal_length`` (pixels), when given, switches the final least squares to image-space
    residuals (see :func:`~jsr.pipeline.pose_refinement.refine_pose_image_space`).
    """

    frame_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    map_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    frame_bearings: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    map_points_2d: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    frame_planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    map_planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    point_depths: np.ndarray | None = None
    frame_point_ids: np.ndarray | None = None
    landmark_ids: np.ndarray | None = None
    frame_point_ids_2d: np.ndarray | None = None
    landmark_ids_2d: np.ndarray | None = None
    frame_plane_ids: np.ndarray | None = None
    landmark_plane_ids: np.ndarray | None = None
    focal_length: float | None = None

    def __post_init__(self) -> None:
        self.frame_points = _array(self.frame_points, 3)
        self.map_points = _array(self.map_points, 3)
        self.frame_bearings = _array(self.frame_bearings, 3)
        self.map_points_2d = _array(self.map_points_2d, 3)
        self.frame_planes = _array(self.frame_planes, 4)
        self.map_planes = _array(self.map_planes, 4)
        pairs = [
            ("frame_points", "map_points"),
            ("frame_bearings", "map_points_2d"),
            ("frame_planes", "map_planes"),
        ]
        for a, b in pairs:
            if len(getattr(self, a)) != len(getattr(self, b)):
                raise ValueError(f"Correspondences: {a} and {b} differ in length")
        if self.point_depths is None:
            self.point_depths = self.frame_points[:, 2].copy()
        else:
            self.point_depths = np.asarray(self.point_depths, dtype=float).reshape(-1)
            if len(self.point_depths) != self.num_point3d:
                raise ValueError("Correspondences: point_depths must have one value per 3D point")
        sizes = {"point3d": self.num_point3d, "point2d": self.num_point2d, "plane": self.num_plane}
        for kind, names in _ID_FIELDS.items():
            for name in names:
                values = getattr(self, name)
                if values is not None:
                    values = np.asarray(values)
                    if len(values) != sizes[kind]:
                        raise ValueError(f"Correspondences: {name} must have {sizes[kind]} rows")
                    setattr(self, name, values)

    @property
    def num_point3d(self) -> int:
        return len(self.frame_points)

    @property
    def num_point2d(self) -> int:
        return len(self.frame_bearings)

    @property
    def num_plane(self) -> int:
        return len(self.frame_planes)

    @property
    def num_matches(self) -> int:
        """All correspondences; a plane pair counts as one match."""
        return self.num_point3d + self.num_point2d + self.num_plane

    def subset(
        self,
        point3d: np.ndarray | None = None,
        point2d: np.ndarray | None = None,
        plane: np.ndarray | None = None,
    ) -> "Correspondences":
        """The correspondences selected by index arrays or masks (None keeps all of a kind)."""

        def pick(values: np.ndarray | None, selection: np.ndarray | None) -> np.ndarray | None:
            if values is None or selection is None:
                return values
            return values[selection]

        return Correspondences(
            frame_points=pick(self.frame_points, point3d),
            map_points=pick(self.map_points, point3d),
            frame_bearings=pick(self.frame_bearings, point2d),
            map_points_2d=pick(self.map_points_2d, point2d),
            frame_planes=pick(self.frame_planes, plane),
            map_planes=pick(self.map_planes, plane),
            point_depths=pick(self.point_depths, point3d),
            frame_point_ids=pick(self.frame_point_ids, point3d),
            landmark_ids=pick(self.landmark_ids, point3d),
            frame_point_ids_2d=pick(self.frame_point_ids_2d, point2d),
            landmark_ids_2d=pick(self.landmark_ids_2d, point2d),
            frame_plane_ids=pick(self.frame_plane_ids, plane),
            landmark_plane_ids=pick(self.landmark_plane_ids, plane),
            focal_length=self.focal_length,
        )


@dataclass
class RegistrationResult:
    """Outcome of :func:`~jsr.pipeline.registration.register` (or
    :func:`~jsr.pipeline.registration.evaluate_pose`).

    ``transformation``: ``T_map_cam``. On failure it is the best pose found (or the initial
    guess / identity when RANSAC did not run) and must not be trusted; ``reason`` says why
    (on a success it is empty, except for
    :func:`~jsr.pipeline.registration.surface_pose_result`).
    ``fitness`` is ``num_inliers / num_matches``; ``rmse`` the RMS distance of the inlier 3D
    point pairs in metres (0.0 when there are none); ``iterations`` the minimal samples drawn
    (an initial guess is scored in addition to them).
    """

    transformation: np.ndarray
    success: bool
    inliers_point3d: np.ndarray
    inliers_point2d: np.ndarray
    inliers_plane: np.ndarray
    num_matches: int
    num_inliers: int
    fitness: float
    rmse: float
    iterations: int
    reason: str = ""
    time_ms: float = 0.0
    correspondences: Correspondences | None = field(default=None, repr=False)


# --------------------------------------------------------------------------------------
# Residuals and inlier tests
# --------------------------------------------------------------------------------------


def point3d_thresholds(corr: Correspondences, noise_cfg: NoiseConfig) -> np.ndarray:
    """``(A,)`` inlier thresholds of the 3D-3D pairs from the depth of the frame points."""
    return depth_thresholds(corr.point_depths, noise_cfg)


def depth_thresholds(depth: np.ndarray, noise_cfg: NoiseConfig) -> np.ndarray:
    """Inlier thresholds (m) of points at ``depth`` (m, any shape): the paper's
    ``max(noise.min_inlier_threshold, noise.inlier_sigmas * sigma_Z(Z))``."""
    return inlier_threshold(
        np.abs(depth),
        coefficient=noise_cfg.sigma_z_coefficient,
        sigma_multiple=noise_cfg.inlier_sigmas,
        minimum=noise_cfg.min_inlier_threshold,
    )


def point3d_residuals(transform: np.ndarray, corr: Correspondences) -> np.ndarray:
    """``(A,)`` distances ``|T p - q|`` in metres."""
    moved = corr.frame_points @ transform[:3, :3].T + transform[:3, 3]
    return np.linalg.norm(moved - corr.map_points, axis=1)


def point2d_residuals(
    transform: np.ndarray, corr: Correspondences
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the 2D-3D pairs: ``(distance to the ray, landmark depth z, distance along the ray)``.

    The landmark is moved into the camera, ``T^-1 X``; each output is ``(B,)``.
    """
    camera = (corr.map_points_2d - transform[:3, 3]) @ transform[:3, :3]
    bearings = unit_rows(corr.frame_bearings)
    along = np.einsum("bi,bi->b", camera, bearings)
    distance = np.linalg.norm(camera - along[:, None] * bearings, axis=1)
    return distance, camera[:, 2], along


def plane_residuals(transform: np.ndarray, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """For the plane pairs: ``(normal angle in radians, |offset difference| in metres)``."""
    normals = unit_rows(corr.frame_planes[:, :3]) @ transform[:3, :3].T
    offsets = corr.frame_planes[:, 3] - normals @ transform[:3, 3]
    cosine = np.einsum("ci,ci->c", normals, unit_rows(corr.map_planes[:, :3]))
    return np.arccos(np.clip(cosine, -1.0, 1.0)), np.abs(offsets - corr.map_planes[:, 3])


def point_inliers(transform: np.ndarray, corr: Correspondences, noise_cfg: NoiseConfig) -> np.ndarray:
    """``(A,)`` bool: 3D-3D pairs closer than their depth-dependent threshold under ``T``."""
    return point3d_residuals(transform, corr) < point3d_thresholds(corr, noise_cfg)


def point2d_inliers(transform: np.ndarray, corr: Correspondences, noise_cfg: NoiseConfig) -> np.ndarray:
    """``(B,)`` bool: landmarks in front of the camera and close to their bearing ray."""
    distance, depth, along = point2d_residuals(transform, corr)
    return (along > 0) & (depth > 0) & (distance < depth_thresholds(depth, noise_cfg))


def plane_inliers(transform: np.ndarray, corr: Correspondences, ransac_cfg: RansacConfig) -> np.ndarray:
    """``(C,)`` bool: plane pairs within the angle and offset thresholds under ``T``."""
    angle, offset = plane_residuals(transform, corr)
    return (angle < np.deg2rad(ransac_cfg.plane_inlier_angle_degrees)) & (
        offset < ransac_cfg.plane_inlier_distance
    )


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    """``(N, k)`` rows scaled to unit length (zero rows stay zero)."""
    norm = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.where(norm > 0, norm, 1.0)


def min_inliers(ransac_cfg: RansacConfig) -> int:
    """Fewest inliers a successful registration needs (see the module docstring)."""
    return max(3, ransac_cfg.min_inliers, math.ceil(ransac_cfg.min_matches * ransac_cfg.min_inlier_ratio - 1e-9))


__all__ = [
    "Correspondences",
    "RegistrationResult",
    "depth_thresholds",
    "min_inliers",
    "plane_inliers",
    "plane_residuals",
    "point2d_inliers",
    "point2d_residuals",
    "point3d_residuals",
    "point3d_thresholds",
    "point_inliers",
    "unit_rows",
]
