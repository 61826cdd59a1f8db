"""Association of a frame's measurements with the landmarks of one map.

Used by every map: the static map and the object maps (frame-based registration and the
prediction-based refinement of segment-based registration).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jsr.config import Config
from jsr.io.dataset import Frame
from jsr.pipeline.correspondences import Correspondences, RegistrationResult
from jsr.pipeline.maps import Map
from jsr.pipeline.matching import guided_match, match_descriptors, match_planes
from jsr.pipeline.measurements import FrameMeasurements


@dataclass
class MatchedFrame:
    """Correspondences of a frame's measurements with a map's landmarks."""

    correspondences: Correspondences
    point_measurements: np.ndarray  # (K,) measurement index of each point correspondence, 3D ones first
    point_landmarks: np.ndarray  # (K,) landmark id of each
    is_3d: np.ndarray  # (K,) True for 3D-3D, False for 2D-3D
    plane_measurements: np.ndarray  # (P,)
    plane_landmarks: np.ndarray  # (P,)


def matched_frame_from_pairs(
    measurements: FrameMeasurements,
    target: Map,
    point_pairs: np.ndarray,
    plane_pairs: np.ndarray,
    focal_length: float | None = None,
) -> MatchedFrame:
    """Correspondences from ``(K, 2)`` ``[measurement, landmark id]`` point pairs and ``(P, 2)``
    ``[plane measurement, plane landmark id]`` pairs (3D point pairs are put first)."""
    points, planes = measurements.points, measurements.planes
    point_pairs = np.asarray(point_pairs, dtype=np.int64).reshape(-1, 2)
    plane_pairs = np.asarray(plane_pairs, dtype=np.int64).reshape(-1, 2)
    measurement_ids, matched_landmarks = point_pairs[:, 0], point_pairs[:, 1]
    is_3d = points.has_depth[measurement_ids]
    order = np.argsort(~is_3d, kind="stable")  # 3D correspondences first
    measurement_ids, matched_landmarks, is_3d = measurement_ids[order], matched_landmarks[order], is_3d[order]
    plane_measurements, plane_landmarks = plane_pairs[:, 0], plane_pairs[:, 1]
    three_d, two_d = measurement_ids[is_3d], measurement_ids[~is_3d]
    frame_planes = np.column_stack([planes.normals, planes.offsets]) if len(planes) else np.zeros((0, 4))
    correspondences = Correspondences(
        frame_points=points.points[three_d],
        map_points=target.points.positions[matched_landmarks[is_3d]],
        frame_bearings=points.bearings[two_d],
        map_points_2d=target.points.positions[matched_landmarks[~is_3d]],
        frame_planes=frame_planes[plane_measurements] if len(plane_measurements) else np.zeros((0, 4)),
        map_planes=target.planes.planes[plane_landmarks] if len(plane_landmarks) else np.zeros((0, 4)),
        point_depths=points.points[three_d, 2],
        focal_length=focal_length,
    )
    return MatchedFrame(correspondences, measurement_ids, matched_landmarks, is_3d, plane_measurements, plane_landmarks)


def predicted_plane_pairs(
    measurements: FrameMeasurements, target: Map, T_map_cam_predicted: np.ndarray | None, config: Config,
    plane_measurements: np.ndarray | None = None,
) -> np.ndarray:
    """``(P, 2)`` ``[plane measurement, plane landmark]`` pairs under a predicted ``T_map_cam``
    (none without a prediction); ``plane_measurements`` restricts the frame planes used."""
    planes = measurements.planes
    if T_map_cam_predicted is None or not len(planes) or not len(target.planes):
        return np.zeros((0, 2), dtype=np.int64)
    candidates = np.arange(len(planes)) if plane_measurements is None else np.asarray(plane_measurements, np.int64)
    if not len(candidates):
        return np.zeros((0, 2), dtype=np.int64)
    frame_planes = np.column_stack([planes.normals, planes.offsets])[candidates]
    pairs = match_planes(frame_planes, target.planes.planes, T_map_cam_predicted,
                         config.matching.plane_angle_degrees, config.matching.plane_distance)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    pairs[:, 0] = candidates[pairs[:, 0]]
    return pairs


def match_frame_to_map(
    measurements: FrameMeasurements,
    target: Map,
    landmark_ids: np.ndarray,
    T_map_cam_predicted: np.ndarray | None,
    config: Config,
    focal_length: float | None = None,
    point_measurements: np.ndarray | None = None,
) -> MatchedFrame:
    """Match the measurements of a frame with the landmarks ``landmark_ids`` of ``target``.

    Points by SIFT descriptor (ratio test); planes by geometry under the predicted pose
    (no planes are matched without a prediction). ``point_measurements`` restricts the
    frame's points (e.g. to one segment). ``focal_length`` (pixels) turns on the
    image-space pose refinement of :func:`~jsr.pipeline.registration.register`.
    """
    points = measurements.points
    landmark_ids = np.asarray(landmark_ids, dtype=np.int64)
    candidates = np.arange(len(points)) if point_measurements is None else np.asarray(point_measurements, np.int64)
    pairs = np.zeros((0, 2), dtype=np.int64)
    if len(candidates) and len(landmark_ids):
        found = match_descriptors(points.descriptors[candidates], target.points.descriptors[landmark_ids],
                                  config.matching.ratio_test)
        if len(found):
            pairs = np.column_stack([candidates[found[:, 0]], landmark_ids[found[:, 1]]]).astype(np.int64)
    plane_pairs = predicted_plane_pairs(measurements, target, T_map_cam_predicted, config)
    return matched_frame_from_pairs(measurements, target, pairs, plane_pairs, focal_length)


def match_frame_guided(
    measurements: FrameMeasurements,
    target: Map,
    landmark_ids: np.ndarray,
    T_map_cam_predicted: np.ndarray,
    intrinsics,
    config: Config,
    focal_length: float | None = None,
    point_measurements: np.ndarray | None = None,
    radius_px: float | None = None,
) -> MatchedFrame:
    """Prediction-based matching: every landmark of ``landmark_ids`` is projected with the
    predicted ``T_map_cam`` and matched with the frame keypoints near its projection
    (``radius_px``, default ``matching.guided_radius_px``); planes are matched under the same
    pose. ``point_measurements`` restricts the frame's points (e.g. to one region)."""
    points = measurements.points
    landmark_ids = np.asarray(landmark_ids, dtype=np.int64)
    candidates = np.arange(len(points)) if point_measurements is None else np.asarray(point_measurements, np.int64)
    radius = config.matching.guided_radius_px if radius_px is None else radius_px
    pairs = np.zeros((0, 2), dtype=np.int64)
    if len(candidates) and len(landmark_ids):
        found = guided_match(points.pixels[candidates], points.descriptors[candidates],
                             target.points.positions[landmark_ids], target.points.descriptors[landmark_ids],
                             T_map_cam_predicted, intrinsics, radius, config.matching.ratio_test,
                             config.matching.max_descriptor_distance)
        if len(found):
            pairs = np.column_stack([candidates[found[:, 0]], landmark_ids[found[:, 1]]]).astype(np.int64)
    plane_pairs = predicted_plane_pairs(measurements, target, T_map_cam_predicted, config)
    return matched_frame_from_pairs(measurements, target, pairs, plane_pairs, focal_length)


def inlier_landmarks(matched: MatchedFrame, result: RegistrationResult, num_points: int) -> np.ndarray:
    """``(num_points,)`` landmark id of each point measurement that is a registration inlier, else -1."""
    landmark_of = np.full(num_points, -1, dtype=np.int64)
    inliers = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
    landmark_of[matched.point_measurements[inliers]] = matched.point_landmarks[inliers]
    return landmark_of


def inlier_plane_landmarks(matched: MatchedFrame, result: RegistrationResult, num_planes: int) -> np.ndarray:
    """``(num_planes,)`` landmark id of each plane measurement that is an inlier, else -1."""
    landmark_of = np.full(num_planes, -1, dtype=np.int64)
    inliers = np.asarray(result.inliers_plane, dtype=bool)
    landmark_of[matched.plane_measurements[inliers]] = matched.plane_landmarks[inliers]
    return landmark_of


def sample_colors(frame: Frame, pixels: np.ndarray) -> np.ndarray:
    """``(N, 3)`` uint8 colours of the frame at ``(N, 2)`` pixel positions (nearest pixel)."""
    height, width = frame.color.shape[:2]
    u = np.clip(np.round(pixels[:, 0]).astype(int), 0, width - 1)
    v = np.clip(np.round(pixels[:, 1]).astype(int), 0, height - 1)
    return frame.color[v, u]


def inlier_mask(matched: MatchedFrame | None, result: RegistrationResult | None, num_points: int,
                num_planes: int) -> tuple[np.ndarray, np.ndarray]:
    """``(N,)`` and ``(P,)`` bool: frame point and plane measurements that are inliers of a
    successful registration (all False otherwise)."""
    points = np.zeros(num_points, dtype=bool)
    planes = np.zeros(num_planes, dtype=bool)
    if matched is None or result is None or not result.success:
        return points, planes
    point_inliers = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
    points[matched.point_measurements[point_inliers]] = True
    planes[matched.plane_measurements[np.asarray(result.inliers_plane, dtype=bool)]] = True
    return points, planes
