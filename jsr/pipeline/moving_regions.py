"""Moving-region detection, the stage (Caccamo et al. 2017, Section 2.1, and beyond): which
segments of a frame moved relative to the static scene, grouped into regions, and what becomes
of each region: an object seen again (re-identification), a new object map, or a suspect too
poor in 3D points to start one, looked at closer in the next frames.

The cues: segments mostly made of static-map outliers whose outliers agree on one rigid motion
(:mod:`jsr.pipeline.region_motion`), segments in space the static keyframes saw empty
(:mod:`jsr.pipeline.free_space`) and segments whose static landmarks all went missing at once.
"""

from __future__ import annotations

import logging

import numpy as np

from jsr.pipeline.detection import detect_moving_segments, displaced_landmark_groups, merge_adjacent_moving_segments
from jsr.pipeline.free_space import depth_at_map_points
from jsr.pipeline.map_updates import start_object
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.ownership import pixel_box
from jsr.pipeline.region_growth import UNSUPPORTED_STATIC_SHARE, grow
from jsr.pipeline.region_motion import mostly_in_place, not_in_place, rigidly_moved
from jsr.pipeline.correspondences import depth_thresholds
from jsr.pipeline.reidentification import reidentify
from jsr.pipeline.state import DYNAMIC, FrameContext, SceneState
from jsr.pipeline.static_tracking import current_pose, static_inlier_landmarks

logger = logging.getLogger(__name__)

CANDIDATE_DETAIL_FRAMES = 3  # a moving region too poor in 3D points to start a map gets detail keypoints this many frames


def detect_moving_regions(state: SceneState, ctx: FrameContext) -> None:
    """Section 2.1: segments mostly made of static-map outliers are moving regions; beyond the
    paper, also segments in space the static keyframes saw empty and segments whose static
    landmarks all went missing. Each group of touching moving segments is first registered
    against the existing object maps (an object seen again, elsewhere,
    :func:`~jsr.pipeline.reidentification.reidentify`): by features in every group, then by
    surface in the groups left, against the objects still lost; a group none fits starts a new
    object map. Adds to ``ctx.assignment``, ``ctx.suspects`` and the report's objects."""
    if not ctx.registered:
        return  # matched against the previous frame only: outliers say nothing about motion
    config, frame, measurements, report, assignment = state.config, ctx.frame, ctx.measurements, ctx.report, \
        ctx.assignment
    points, segments = measurements.points, measurements.segments
    matched = ctx.static_matched()
    inliers, _ = ctx.static_inliers()
    owned = assignment.point_owner > 0  # measurements already given to an object
    by_outliers = detect_moving_segments(segments, matched, inliers, config.detection, exclude=owned)
    in_place = by_outliers
    by_outliers = not_in_place(state, ctx, by_outliers, inliers, keep_unknown=False)
    in_place = [s for s in in_place if s not in by_outliers]
    violations, consistent = ctx.free_space_counts(state)
    by_outliers = rigidly_moved(state, ctx, by_outliers, inliers)
    turn_degrees = config.detection.in_place_turn_degrees
    if turn_degrees > 0:
        # Segments of outliers that the in-place test found near where they were: it cannot
        # tell the object's own features from a look-alike's, the turn of their outliers can.
        turned_in_place = rigidly_moved(state, ctx, in_place, inliers, min_turn_degrees=turn_degrees)
        by_outliers = sorted(set(by_outliers) | set(turned_in_place))
    by_free_space = free_space_segments(state, measurements, violations, consistent, inliers)
    by_free_space = not_in_place(state, ctx, by_free_space, inliers, keep_unknown=True)
    # The in-place veto, over each group of touching segments and over its outlier and its
    # displaced landmarks together, but only from as many landmarks as detection by
    # outliers needs: a turned object's one or two outliers are often found "in place" on
    # its own new texture (synth_two_sim seed 3), while a static surface whose depth
    # disagrees at its landmarks (a depth edge, redkitchen300 seed 1: 7 of 10 in place) has
    # many. Its displaced landmarks count too: a cylinder that moved 8 cm and turned 35
    # degrees had all 7 outlier landmarks found on look-alikes of its own texture, but 45
    # displaced ones (synth_two seed 3, frame 19; detected 3 frames later without them).
    by_displacement = []
    displaced_in = {}  # segment -> the static landmarks displaced in its group (a candidate's evidence)
    for group, displaced in displaced_landmarks(state, ctx, inliers):
        if not mostly_in_place(state, ctx, group, inliers, config.detection.min_segment_features, also=displaced):
            by_displacement.extend(group)
            displaced_in.update({segment: displaced for segment in group})
    moving = sorted(set(by_outliers) | set(by_free_space) | set(by_displacement))
    moving = [s for s in moving if assignment.segment_owner[s] == 0]
    if not moving:
        return
    groups = merge_adjacent_moving_segments(segments, moving, config.detection.merge_gap_pixels)
    by_id = {outcome.object_map.object_id: outcome for outcome in ctx.outcomes}
    unexplained = []  # (region, its point measurements) that no lost object's features explain
    for index, group in enumerate(groups):
        # a group does not grow into another group of this frame (an object beside it that
        # moved too), nor into what an earlier group grew to
        others = [s for k, other in enumerate(groups) if k != index for s in other]
        others += [s for earlier, _ in unexplained for s in earlier]
        owner = assignment.segment_owner.copy()
        owner[others] = np.where(owner[others] == 0, -1, owner[others])
        group = grow(state, ctx, group, inliers, owner)
        group_points = np.concatenate([segments.point_indices[s] for s in group]).astype(np.int64)
        group_points = group_points[assignment.point_owner[group_points] == 0]
        if moved_as_before(state, ctx, group):
            continue
        if int(points.has_depth[group_points].sum()) < config.detection.min_object_points:
            # a small object carries few half-resolution keypoints: look closer at it in
            # the next frames (features.object_detail) and start it once it has enough
            until = frame.index + CANDIDATE_DETAIL_FRAMES
            state.memory.candidate_boxes.append((pixel_box(np.isin(segments.label_image, group)), until))
            displaced = [displaced_in[s] for s in group if s in displaced_in]
            if displaced:  # its evidence stays for as long
                state.memory.pending_displaced.append((np.unique(np.concatenate(displaced)), until))
            ctx.suspects.extend(group)  # nor does its new place enter the static map
            continue
        if config.objects.reidentify and reidentify(state, ctx, group, group_points, by_id):
            continue
        unexplained.append((group, group_points))
    # Surface alignment costs 0.5-2 s a draw, features milliseconds: a lost object that the
    # features find in one region of the frame is not aligned to the others first
    # (bonn_crowd_people, RANSAC seed 4, frame 20: a lost person map was aligned twice to one
    # region, 2.3 s each, before its landmarks found it in the next region), and every region
    # has its first draw before any has its second (a draw may find the object in the next).
    surfaces_tried = config.objects.reidentify and config.objects.shape_reidentify
    for _ in range(config.objects.shape_attempts if surfaces_tried else 0):
        still_unexplained = []
        for group, group_points in unexplained:
            group_points = group_points[assignment.point_owner[group_points] == 0]
            if not reidentify(state, ctx, group, group_points, by_id, shape_draws=1):
                still_unexplained.append((group, group_points))
        unexplained = still_unexplained
    for group, group_points in unexplained:
        group_points = group_points[assignment.point_owner[group_points] == 0]
        evidence = np.union1d(outlier_landmarks(ctx, group, inliers),
                              np.concatenate([displaced_in.get(s, np.zeros(0, np.int64)) for s in group]))
        object_map = start_object(state, ctx, group, report.T_w_c, evidence_landmarks=evidence)
        if object_map is not None and object_map.confirmed:  # (a candidate is reported once confirmed)
            report.objects_created.append(object_map.object_id)
            report.objects_tracked.append(object_map.object_id)


def outlier_landmarks(ctx: FrameContext, group: list[int], static_inliers: np.ndarray) -> np.ndarray:
    """Sorted ids of the static landmarks matched as outliers by the point measurements of the
    segments ``group`` (``static_inliers`` ``(N,)`` bool)."""
    matched = ctx.static.matched
    point_segment = ctx.measurements.segments.segment_of_points(len(ctx.measurements.points))
    rows = np.isin(point_segment[matched.point_measurements], group) & ~static_inliers[matched.point_measurements]
    return np.unique(matched.point_landmarks[rows])


def moved_as_before(state: SceneState, ctx: FrameContext, group: list[int]) -> bool:
    """Whether the moving region ``group`` continues a motion no rigid map explains: at least
    half of its pixels were dynamic in the previous frame (a person walking on), or belonged to
    a candidate, which its registration in this frame does not explain (not found, or this part
    of it moved otherwise: a person's limb; ``ctx.unexplained``, weighed by
    :mod:`~jsr.pipeline.confirmation`). Such a region is dynamic in this frame
    (``ctx.dynamic``), and starts no map."""
    previous = state.memory.previous_mask
    if previous is None:
        return False
    in_group = np.isin(ctx.measurements.segments.label_image, group)
    before = previous[in_group]
    if not len(before):
        return False
    owners, counts = np.unique(before[before > 0], return_counts=True)
    if not len(owners) or counts.max() < 0.5 * len(before):
        return False
    owner = int(owners[np.argmax(counts)])
    if owner == DYNAMIC:
        ctx.dynamic.extend(group)
        return True
    if not any(m.object_id == owner and not m.confirmed for m in state.object_maps):
        return False
    ctx.unexplained.add(owner)
    ctx.dynamic.extend(group)
    return True


def free_space_segments(state: SceneState, measurements: FrameMeasurements, violations: np.ndarray,
                        consistent: np.ndarray, static_inliers: np.ndarray) -> list[int]:
    """Segments that lie in space the latest static keyframes saw as empty: something moved
    in (an object that jumped to where the static map has no landmarks of it)."""
    config = state.config.objects
    if not state.free_space.enabled:
        return []
    segments = measurements.segments
    moving = (violations >= state.free_space.min_samples()) & (
        violations >= config.free_space_share * (violations + consistent))
    # tiny segments (thin structures, depth edges) are where depth noise looks like motion
    moving &= np.asarray(segments.pixel_counts) >= config.free_space_min_segment_pixels * state.area_scale
    moving &= little_static_support(measurements, static_inliers)
    return np.flatnonzero(moving).tolist()


def displaced_landmarks(state: SceneState, ctx: FrameContext, static_inliers: np.ndarray
                        ) -> list[tuple[list[int], np.ndarray]]:
    """Groups of touching segments whose static landmarks all went missing at once: an
    object that turned or jumped so that its features match nothing (no outliers to detect
    it by), over about where it stood (so that free space says nothing either;
    synth_two_sim seed 3: a cylinder turned 35 degrees, 2 of its 30 features matched).

    The static landmarks that were inliers in the previous frame are projected with the
    frame's camera pose (``static_inliers``: ``(N,)`` bool, this frame's point
    measurements that are inliers of the static registration); one is *displaced* when it is no inlier
    now and the depth measured at its projection moved off its predicted depth by more than
    the inlier threshold since the previous frame (its surface is not there any more;
    :func:`depth_offsets_before`). What changed is the evidence: a registration inlier by
    its pixel alone (``ransac.depth_fallback``) may be centimetres off the depth in every
    frame, by the sensor's or the pose's error, and is no proof of motion while that offset
    holds (set 1 redkitchen_s3_two_jump, frame 72: 11 kitchen landmarks 3-9 cm in front of
    the measured surface in frames 71 and 72 alike started a static candidate that was
    confirmed). Segments, alone or with touching
    ones, with enough of them move (:func:`~jsr.pipeline.detection.displaced_landmark_groups`).
    A static surface that lost its matches to blur keeps its depth; one that a nearer
    static surface hides keeps most of its landmarks elsewhere.
    Measured (December 2026, seed 0): no static segment of redkitchen300, bonn_crowd200 or
    kitchen_box120 with more than 6 displaced landmarks (6 of 6 in redkitchen300's blurred
    frame 179, where 17% of all are: chance 3e-5), objects with 5-37; a box 2.4 m away (set 3
    bonn_s4_two_sim, frame 10) with 7 of 8 (chance 8e-8), which a fixed count of 10 missed.

    Returns ``(group, landmark ids)`` pairs: each group's segments and the static landmarks
    displaced in it."""
    config = state.config.detection
    frame, measurements, static, T_w_c = ctx.frame, ctx.measurements, ctx.static, ctx.T_w_c
    memory = state.memory
    memory.pending_displaced = [(ids, until) for ids, until in memory.pending_displaced if until >= frame.index]
    previous = memory.previous_static_inliers
    if config.displaced_share <= 0 or previous is None:
        return []
    pending = np.concatenate([ids for ids, _ in memory.pending_displaced] or [np.zeros(0, np.int64)])
    previous = np.union1d(previous, pending)
    if not len(previous):
        return []
    landmarks = previous[state.static_map.points.active[previous]]
    camera_points, (u, v), inside, measured = depth_at_map_points(state.static_map.points.positions[landmarks], T_w_c,
                                                                  frame.depth, state.intrinsics)
    with_depth = inside & (measured > 0)
    if not with_depth.any():
        return []
    segments = measurements.segments
    segment = np.full(len(landmarks), -1, dtype=np.int64)
    segment[with_depth] = segments.label_image[v[with_depth], u[with_depth]]
    with_depth &= segment >= 0
    z = camera_points[:, 2]
    threshold = depth_thresholds(z, state.config.noise)
    kept = np.isin(landmarks, static_inlier_landmarks(static))
    before = depth_offsets_before(state, landmarks, ~np.isin(landmarks, pending))
    displaced = with_depth & ~kept & (np.abs(measured - z - before) > threshold)
    projecting = np.bincount(segment[with_depth], minlength=len(segments))
    displaced_count = np.bincount(segment[displaced], minlength=len(segments))
    groups = displaced_landmark_groups(segments, displaced_count, projecting,
                                       little_static_support(measurements, static_inliers), config)
    # seen through: the surface measured behind them (the background an object left, or
    # an object that turned away over its old place)
    seen_through = np.bincount(segment[displaced & (measured > z)], minlength=len(segments))
    for group in groups:
        logger.debug("frame %d: segments %s: %s of %s previous static inliers displaced (%s seen through)",
                     measurements.frame_index, group, displaced_count[group].tolist(),
                     projecting[group].tolist(), seen_through[group].tolist())
    return [(group, landmarks[displaced & np.isin(segment, group)]) for group in groups]


def depth_offsets_before(state: SceneState, landmarks: np.ndarray, judged: np.ndarray) -> np.ndarray:
    """``(L,)`` measured minus predicted depth (m) of the static ``landmarks`` in the previous
    frame (``memory.previous_depth`` at that frame's pose, after any bundle adjustment since),
    for those ``judged`` ``(L,)`` bool; 0 where that depth is unknown, and for
    the others: a landmark already displaced in an earlier frame (``memory.pending_displaced``)
    is judged against its prediction itself."""
    offsets = np.zeros(len(landmarks))
    depth, reports = state.memory.previous_depth, state.reports
    if depth is None or not reports or not reports[-1].tracked or not len(landmarks):
        return offsets
    T_w_previous = current_pose(state.static_map, reports[-1])
    camera_points, _, inside, measured = depth_at_map_points(state.static_map.points.positions[landmarks],
                                                             T_w_previous, depth, state.intrinsics)
    known = inside & (measured > 0) & judged
    offsets[known] = measured[known] - camera_points[known, 2]
    return offsets


def little_static_support(measurements: FrameMeasurements, static_inliers: np.ndarray) -> np.ndarray:
    """``(S,)`` bool: segments at most UNSUPPORTED_STATIC_SHARE of whose 3D point features are
    static inliers (``static_inliers`` ``(N,)`` bool), so that the static map does not show
    them in place (featureless segments included)."""
    points, segments = measurements.points, measurements.segments
    point_segment = segments.segment_of_points(len(points))
    in_segment = point_segment >= 0
    static_support = np.bincount(point_segment[in_segment & static_inliers], minlength=len(segments))
    three_d = np.bincount(point_segment[in_segment & points.has_depth], minlength=len(segments))
    return static_support <= UNSUPPORTED_STATIC_SHARE * np.maximum(three_d, 1)
