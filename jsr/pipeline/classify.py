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

When several object maps claim one measurement, an inlier claim beats a matching-segment
claim: a feature that one map's registration explains within the noise is direct evidence,
a segment matched to another map only groups it (a segment that spans two objects standing
together: redkitchen_s3_two_jump, frame 29, a cylinder's segment-based registration took the
box's features in it, and the two maps were merged in the next frame). Between claims of the
same kind, the object map with more inliers wins (its counted inliers: the union of the
successful frame- and segment-based inlier masks, points plus planes), and on equal counts
the smaller ``object_id``. Likewise a map's matching segment is its own only when no other
map's registration has more inliers in it.

Beyond the paper, :func:`classify_frame` completes segments (a segment whose registered
inliers mostly belong to one object goes to that object as a whole), grows objects into the
depth-adjacent segments nothing shows to be static, and splits segments that span an object and
the static scene.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from jsr.pipeline.association import inlier_mask
from jsr.pipeline.measurements import Segments
from jsr.pipeline.object_extent import (extent_hull, largest_spread, pixels_inside_hull, segments_inside_extent,
                                       wider_than)
from jsr.pipeline.object_registration import ObjectTrackingResult
from jsr.pipeline.region_growth import grow
from jsr.pipeline.state import FrameAssignment, FrameContext, SceneState

logger = logging.getLogger(__name__)

STATIC = 0

_NO_CLAIM = 0
_SEGMENT_CLAIM = 1
_INLIER_CLAIM = 2


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
    claims[in_matching] = _SEGMENT_CLAIM
    claims[inlier] = _INLIER_CLAIM
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


def segment_votes(
    point_segment: np.ndarray, num_segments: int, owner: np.ndarray, counted: np.ndarray, num_owners: int
) -> np.ndarray:
    """``(S, num_owners)`` counts of the counted point measurements of each segment per owner.

    ``point_segment`` ``(N,)`` segment of each point (-1: none); ``owner`` ``(N,)`` owner index
    in ``[0, num_owners)``; ``counted`` ``(N,)`` bool.
    """
    keep = counted & (point_segment >= 0)
    votes = np.zeros((num_segments, num_owners), dtype=np.int64)
    np.add.at(votes, (point_segment[keep], owner[keep]), 1)
    return votes


def complete_segments(
    point_segment: np.ndarray,
    num_segments: int,
    point_owner: np.ndarray,
    evidence: np.ndarray,
    object_ids: list[int],
    min_votes: int,
) -> np.ndarray:
    """``(S,)`` owner of every segment: an object id when that object's registration inliers
    outnumber every other map's inliers in the segment (and reach ``min_votes``), else 0.

    ``point_owner`` ``(N,)`` owner after Algorithm 1; ``evidence`` ``(N,)`` bool: points that
    are inliers of the registration of their owner (static or object).
    """
    if not object_ids:
        return np.zeros(num_segments, dtype=np.int64)
    columns = {0: 0} | {object_id: i + 1 for i, object_id in enumerate(object_ids)}
    owner_column = np.array([columns.get(int(o), 0) for o in point_owner], dtype=np.int64)
    votes = segment_votes(point_segment, num_segments, owner_column, evidence, len(columns))
    best_object = 1 + np.argmax(votes[:, 1:], axis=1)
    best_votes = votes[np.arange(num_segments), best_object]
    others = votes.sum(axis=1) - best_votes
    wins = (best_votes >= min_votes) & (best_votes > others)
    ids = np.array([0] + list(object_ids), dtype=np.int64)
    return np.where(wins, ids[best_object], 0)


def classify_frame(state: SceneState, ctx: FrameContext) -> None:
    """Algorithm 1 (lines 14-24) over the frame's object registrations (``ctx.outcomes``),
    then segment completion (``objects.segment_completion``), growth into depth-adjacent
    unsupported segments (``objects.grow_segments``) and the split of segments that span an
    object and the static scene (``objects.split_mixed_segments``): sets ``ctx.assignment``."""
    config, frame, measurements, outcomes = state.config, ctx.frame, ctx.measurements, ctx.outcomes
    points, planes, segments = measurements.points, measurements.planes, measurements.segments
    num_points, num_planes = len(points), len(planes)
    point_segment = segments.segment_of_points(num_points)
    plane_segment = segment_of_planes(segments, num_planes)
    registrations = []
    for outcome in outcomes:
        frame_points, frame_planes = inlier_mask(outcome.frame_matched, outcome.frame_result, num_points,
                                                 num_planes)
        segment_points, segment_planes = inlier_mask(outcome.segment_matched, outcome.segment_result,
                                                     num_points, num_planes)
        registrations.append(ObjectRegistration(
            object_id=outcome.object_map.object_id,
            frame_success=outcome.frame_success,
            frame_inliers_points=frame_points,
            frame_inliers_planes=frame_planes,
            segment_success=outcome.segment_success,
            matching_segments=list(outcome.seed_segments),
            segment_inliers_points=segment_points,
            segment_inliers_planes=segment_planes,
        ))
    point_owner, plane_owner = classify_measurements(num_points, num_planes, point_segment, plane_segment,
                                                     registrations)
    segment_owner = np.zeros(len(segments), dtype=np.int64)
    tracked = [r for r in registrations if r.frame_success or r.segment_success]
    static_inliers, _ = ctx.static_inliers()
    by_id = {o.object_map.object_id: o for o in outcomes if o.success}
    hulls = {object_id: extent_hull(state.surfaces.extent_points(o.object_map))
             for object_id, o in by_id.items()}  # each object's extent, once per frame
    if tracked and config.objects.segment_completion:
        # Evidence: points that are inliers of the registration of the map they were given to.
        evidence = static_inliers & (point_owner == 0)
        for r in tracked:
            evidence |= (point_owner == r.object_id) & (r.frame_inliers_points | r.segment_inliers_points)
        segment_owner = complete_segments(point_segment, len(segments), point_owner, evidence,
                                          [r.object_id for r in tracked], config.detection.min_segment_features)
        for r in tracked:
            own = np.flatnonzero(segment_owner == r.object_id).tolist()
            inside = None if not config.objects.grow_inside_extent else segments_inside_extent(
                segments.label_image, frame.depth, state.intrinsics, by_id[r.object_id].T_o_c, hulls[r.object_id],
                config.noise, len(segments), config.objects.extent_margin, config.objects.extent_share)
            hull = hulls[r.object_id]
            grown = grow(state, ctx, own, static_inliers, segment_owner, inside,
                         by_id[r.object_id].object_map.created_at_frame,
                         object_width=None if hull is None else largest_spread(hull.points))
            segment_owner[[s for s in grown if segment_owner[s] == 0]] = r.object_id
        # Features and planes inside an object's segment go to that object, matched or not:
        # new views of the object grow its map instead of leaking into the static map.
        in_object_segment = (point_segment >= 0) & (segment_owner[np.maximum(point_segment, 0)] > 0)
        point_owner = np.where(in_object_segment, segment_owner[np.maximum(point_segment, 0)], point_owner)
        plane_in_object = (plane_segment >= 0) & (segment_owner[np.maximum(plane_segment, 0)] > 0)
        plane_owner = np.where(plane_in_object, segment_owner[np.maximum(plane_segment, 0)], plane_owner)
    # the seed segments of segment-based registration belong to their object, unless another
    # object's registration has more inliers in the segment
    inliers_in = {r.object_id: np.bincount(point_segment[(point_segment >= 0) & (
        r.frame_inliers_points | r.segment_inliers_points)], minlength=len(segments)) for r in tracked}
    for r in tracked:
        for segment in r.matching_segments if r.segment_success else []:
            if all(inliers_in[o][segment] <= inliers_in[r.object_id][segment] for o in inliers_in):
                segment_owner[segment] = r.object_id
    assignment = FrameAssignment(point_owner.astype(np.int64), plane_owner.astype(np.int64), segment_owner)
    if tracked and config.objects.split_mixed_segments:
        object_inliers = np.zeros(num_points, dtype=bool)
        for r in tracked:
            object_inliers |= r.frame_inliers_points | r.segment_inliers_points
        split_mixed_segments(state, ctx, assignment, static_inliers & ~object_inliers, by_id, hulls)
    ctx.assignment = assignment


def split_mixed_segments(state: SceneState, ctx: FrameContext, assignment: FrameAssignment,
                         static_evidence: np.ndarray, outcomes: dict[int, ObjectTrackingResult], hulls: dict) -> None:
    """Beyond the paper, which takes segments to be parts of one surface: a segment given
    to an object that also holds ``detection.min_segment_features`` static-registration
    inliers (``static_evidence`` ``(N,)``: not inliers of any object), or that is wider than
    the object can be (:func:`wider_than_object`), spans the object and the static scene (a
    box standing on a table, in one depth segment). Its static inliers,
    and its features outside the object's extent (:func:`pixels_inside_hull`), stay static;
    only its pixels inside that extent go into the object's mask; a plane that is such a
    segment stays static (``objects.split_mixed_segments``)."""
    config, frame, measurements = state.config, ctx.frame, ctx.measurements
    segments = measurements.segments
    point_segment = segments.segment_of_points(len(measurements.points))
    owner_of_point = np.where(point_segment >= 0, assignment.segment_owner[np.maximum(point_segment, 0)], 0)
    evidence = static_evidence & (owner_of_point > 0)
    counts = np.bincount(point_segment[evidence], minlength=len(segments)) if evidence.any() else \
        np.zeros(len(segments), dtype=np.int64)
    mixed = (counts >= config.detection.min_segment_features) & (assignment.segment_owner > 0)
    mixed |= wider_than_object(segments.label_image, frame.depth, state.intrinsics, assignment.segment_owner, hulls)
    mixed = np.flatnonzero(mixed)
    if not len(mixed):
        return
    in_mixed = np.isin(point_segment, mixed)
    assignment.point_owner[evidence & in_mixed] = 0
    plane_segment = segment_of_planes(segments, len(measurements.planes))
    assignment.plane_owner[np.isin(plane_segment, mixed)] = 0
    labels = segments.label_image
    not_object = np.zeros(labels.shape, dtype=bool)
    points = measurements.points
    for segment in mixed:
        object_id = int(assignment.segment_owner[segment])
        outcome, hull = outcomes.get(object_id), hulls.get(object_id)
        if outcome is None or hull is None:
            continue
        rows, cols = np.nonzero(labels == segment)
        depth = frame.depth[rows, cols]
        inside = (depth > 0) & pixels_inside_hull(rows, cols, depth, state.intrinsics, outcome.T_o_c, hull,
                                                  config.noise, config.objects.extent_margin)
        not_object[rows[~inside], cols[~inside]] = True
        members = np.flatnonzero((point_segment == segment) & (assignment.point_owner == object_id))
        if len(members):
            member_inside = points.has_depth[members] & pixels_inside_hull(
                points.pixels[members, 1], points.pixels[members, 0], np.nan_to_num(points.points[members, 2]),
                state.intrinsics, outcome.T_o_c, hull, config.noise, config.objects.extent_margin)
            assignment.point_owner[members[~member_inside]] = 0
        logger.debug("frame %d: segment %d is mixed (%d static inliers); %d of %d pixels are object %d",
                     measurements.frame_index, segment, counts[segment], int(inside.sum()), len(rows), object_id)
    assignment.not_object_pixels = not_object


def wider_than_object(label_image: np.ndarray, depth: np.ndarray, intrinsics, segment_owner: np.ndarray,
                      hulls: dict) -> np.ndarray:
    """``(S,)`` bool: segments given to an object (``segment_owner`` ``(S,)``; ``label_image``
    and ``depth`` ``(H, W)``, the frame's) whose surface is more than ``SIZE_FACTOR`` times
    wider than everything known of that object (its extent hull, ``hulls`` by object id; none:
    nothing is known). Such a segment holds more than the object, even where the static
    registration has few inliers to show it: a repetitive carpet, most of whose features match
    look-alikes (redkitchen_s4_two_sim, seed 14, frame 31: a cylinder resting on the floor got
    the whole 40,000-pixel floor segment from a dozen of its landmarks there)."""
    wide = np.zeros(len(segment_owner), dtype=bool)
    for object_id, hull in hulls.items():
        owned = np.flatnonzero(segment_owner == object_id)
        if hull is not None and len(owned):
            wide[owned] = wider_than(label_image, depth, intrinsics, owned, largest_spread(hull.points))
    return wide
