"""Classification of a frame's measurements into the static map and the object maps
(Caccamo et al. 2017, Section 2.3, lines 14-24 of Algorithm 1, for several object maps).

For every point and plane measurement of the frame:

1. if it lies inside a *matching segment* of an object map (a frame segment that the
   segment-based registration matched to that map), it goes to that object;
2. otherwise, if it is an inlier of the object map's frame-based registration or of its
   refined segment-based registration, it goes to that object;
3. otherwise it goes to the static map.

Only registrations that succeeded count: the inliers of a failed frame-based registration,
and the matching segments and inliers of a failed segment-based registration, are ignored.

When several object maps claim one measurement, a matching-segment claim beats an inlier
claim; between claims of the same kind, the object map with more inliers wins (its counted
inliers: the union of the successful frame- and segment-based inlier masks, points plus
planes), and on equal counts the smaller ``object_id``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jsr.pipeline.measurements import Segments

STATIC = 0

_NO_CLAIM = 0
_INLIER_CLAIM = 1
_SEGMENT_CLAIM = 2


@dataclass
class ObjectRegistration:
    """What the multi-group registration produced for one object map.

    ``object_id`` (> 0) names the object map. Frame-based registration (Algorithm 1, lines
    5-6): ``frame_success`` and its inlier masks over the frame's ``N`` point and ``P`` plane
    measurements. Segment-based registration (lines 7-13): ``segment_success``, the frame
    segments matched to the map (``matching_segments``), and the inlier masks after
    prediction-based refinement, as the union over the matching segments.
    """

    object_id: int
    frame_success: bool
    frame_inliers_points: np.ndarray
    frame_inliers_planes: np.ndarray
    segment_success: bool
    matching_segments: list[int] = field(default_factory=list)
    segment_inliers_points: np.ndarray | None = None
    segment_inliers_planes: np.ndarray | None = None


def segment_of_planes(segments: Segments, num_planes: int) -> np.ndarray:
    """``(num_planes,)`` segment index of every plane measurement, -1 if in none."""
    owner = np.full(num_planes, -1, dtype=np.int64)
    plane_index = np.asarray(segments.plane_index, dtype=np.int64)
    has_plane = (plane_index >= 0) & (plane_index < num_planes)
    owner[plane_index[has_plane]] = np.flatnonzero(has_plane)
    return owner


def _bool_mask(values: np.ndarray | None, count: int, name: str) -> np.ndarray:
    if values is None:
        return np.zeros(count, dtype=bool)
    array = np.asarray(values, dtype=bool)
    if array.shape != (count,):
        raise ValueError(f"{name} must have shape ({count},), got {array.shape}")
    return array


def _claims(
    registration: ObjectRegistration, measurement_segment: np.ndarray, frame_inliers, segment_inliers, kind: str
) -> np.ndarray:
    """``(M,)`` claim level of one object map on the measurements of one kind."""
    count = len(measurement_segment)
    inlier = np.zeros(count, dtype=bool)
    if registration.frame_success:
        inlier |= _bool_mask(frame_inliers, count, f"frame_inliers_{kind}")
    in_matching = np.zeros(count, dtype=bool)
    if registration.segment_success:
        inlier |= _bool_mask(segment_inliers, count, f"segment_inliers_{kind}")
        matching = np.asarray(registration.matching_segments, dtype=np.int64)
        if len(matching):
            in_matching = (measurement_segment >= 0) & np.isin(measurement_segment, matching)
    claims = np.full(count, _NO_CLAIM, dtype=np.int64)
    claims[inlier] = _INLIER_CLAIM
    claims[in_matching] = _SEGMENT_CLAIM
    return claims


def _counted_inliers(registration: ObjectRegistration, num_points: int, num_planes: int) -> int:
    points = np.zeros(num_points, dtype=bool)
    planes = np.zeros(num_planes, dtype=bool)
    if registration.frame_success:
        points |= _bool_mask(registration.frame_inliers_points, num_points, "frame_inliers_points")
        planes |= _bool_mask(registration.frame_inliers_planes, num_planes, "frame_inliers_planes")
    if registration.segment_success:
        points |= _bool_mask(registration.segment_inliers_points, num_points, "segment_inliers_points")
        planes |= _bool_mask(registration.segment_inliers_planes, num_planes, "segment_inliers_planes")
    return int(points.sum() + planes.sum())


def _resolve(claims: np.ndarray, rank: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
    """Owner per measurement from ``claims`` ``(R, M)``; ``rank`` ``(R,)`` breaks ties (higher wins)."""
    if claims.shape[0] == 0:
        return np.full(claims.shape[1], STATIC, dtype=np.int64)
    num_registrations = claims.shape[0]
    score = np.where(claims > _NO_CLAIM, claims * num_registrations + rank[:, None], -1)
    best = np.argmax(score, axis=0)
    claimed = score[best, np.arange(claims.shape[1])] >= 0
    return np.where(claimed, object_ids[best], STATIC).astype(np.int64)


def classify_measurements(
    num_points: int,
    num_planes: int,
    point_segment: np.ndarray,
    plane_segment: np.ndarray,
    registrations: list[ObjectRegistration],
) -> tuple[np.ndarray, np.ndarray]:
    """Owner of every point and plane measurement: ``(point_owner (N,), plane_owner (P,))``,
    0 for the static map, else the ``object_id`` of an object map (see the module docstring
    for the rules and priorities).

    ``point_segment`` ``(N,)`` / ``plane_segment`` ``(P,)``: segment index of every
    measurement, -1 for none (see :meth:`Segments.segment_of_points`,
    :func:`segment_of_planes`).
    """
    point_segment = np.asarray(point_segment, dtype=np.int64)
    plane_segment = np.asarray(plane_segment, dtype=np.int64)
    if point_segment.shape != (num_points,):
        raise ValueError(f"point_segment must have shape ({num_points},), got {point_segment.shape}")
    if plane_segment.shape != (num_planes,):
        raise ValueError(f"plane_segment must have shape ({num_planes},), got {plane_segment.shape}")
    object_ids = np.array([int(r.object_id) for r in registrations], dtype=np.int64)
    if np.any(object_ids <= STATIC):
        raise ValueError(f"object ids must be positive, got {object_ids.tolist()}")
    if len(np.unique(object_ids)) != len(object_ids):
        raise ValueError(f"object ids must be unique, got {object_ids.tolist()}")

    # Tie-break rank: more counted inliers first, then the smaller object id.
    inlier_counts = np.array([_counted_inliers(r, num_points, num_planes) for r in registrations], dtype=np.int64)
    order = np.lexsort((object_ids, -inlier_counts))  # best first
    rank = np.empty(len(registrations), dtype=np.int64)
    rank[order] = np.arange(len(registrations))[::-1]

    point_claims = np.array(
        [
            _claims(r, point_segment, r.frame_inliers_points, r.segment_inliers_points, "points")
            for r in registrations
        ],
        dtype=np.int64,
    ).reshape(len(registrations), num_points)
    plane_claims = np.array(
        [
            _claims(r, plane_segment, r.frame_inliers_planes, r.segment_inliers_planes, "planes")
            for r in registrations
        ],
        dtype=np.int64,
    ).reshape(len(registrations), num_planes)
    return _resolve(point_claims, rank, object_ids), _resolve(plane_claims, rank, object_ids)
