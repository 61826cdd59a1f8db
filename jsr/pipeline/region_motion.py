"""How a moving region moved: the rigid motion that its static-map outliers agree on, the
tests that tell a real motion from a pose error or look-alike texture (a small motion of a
surface seen there before, the outliers still found in place) and the memory that confirms a
turn over frames.

Caccamo et al. 2017 take a segment with many outliers as moving; beyond the paper, the outliers
must agree on one rigid motion relative to the static scene (``detection.require_rigid_motion``).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from jsr.config import Config
from jsr.geometry import invert_transform, rotation_angle, transform_points
from jsr.pipeline.detection import merge_adjacent_moving_segments
from jsr.pipeline.matching import guided_match
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.registration import register
from jsr.pipeline.state import DetectionMemory, FrameContext, SceneState

logger = logging.getLogger(__name__)

# two frames' rotations fitted to 5-15 points each differ by a few degrees (synth_two seed 3: 3.2)
TURN_MEMORY_DEGREES_FACTOR = 2
IN_PLACE_TURN_INLIER_FACTOR = 2  # overruling the in-place veto by one frame's rigid turn takes this many times the usual agreeing outliers (two frames: see detection.in_place_turn_memory_frames)


def rigidly_moved(state: SceneState, ctx: FrameContext, candidates: list[int], static_inliers: np.ndarray,
                  min_turn_degrees: float | None = None) -> list[int]:
    """The candidate segments whose static-map outliers agree on one rigid motion
    (``detection.require_rigid_motion``), grouped as touching regions. With
    ``min_turn_degrees``, only motions turning the region by at least that much count. A
    region whose motion awaits confirmation goes to ``ctx.suspects``.

    An object that moved carries its old landmarks along: their matches are outliers of the
    camera pose but inliers of one other rigid transformation. Outliers from view-dependent
    appearance (specular highlights) or repeated texture agree on nothing.
    """
    if not candidates:
        return candidates
    config, measurements, static = state.config, ctx.measurements, ctx.static
    if not config.detection.require_rigid_motion:
        return candidates if min_turn_degrees is None else []
    segments = measurements.segments
    matched = static.matched
    three_d = matched.is_3d
    point_segment = segments.segment_of_points(len(measurements.points))
    fitted_pairs = three_d & ~static_inliers[matched.point_measurements]  # the motion is fitted to the outliers
    confirmed: list[int] = []
    for group in merge_adjacent_moving_segments(segments, candidates, config.detection.merge_gap_pixels):
        in_group = fitted_pairs & np.isin(point_segment[matched.point_measurements], group)
        rows = np.flatnonzero(in_group[three_d])  # 3D pairs come first in the correspondences
        if len(rows) < config.detection.min_segment_features:
            continue
        subset = matched.correspondences.subset(point3d=rows, point2d=np.zeros(0, dtype=np.int64),
                                                plane=np.zeros(0, dtype=np.int64))
        usual_inliers = max(config.detection.min_segment_features, config.ransac.min_inliers)
        # a motion is remembered (and held back) from min_segment_features agreeing outliers; one
        # frame alone decides it with the usual (an in-place turn: twice the usual), two frames
        # with the same motion with min_segment_features each
        memory = config.detection.in_place_turn_memory_frames > 0
        ransac = dataclasses.replace(config.ransac, min_matches=config.detection.min_segment_features,
                                     min_inliers=config.detection.min_segment_features
                                     if memory or min_turn_degrees is not None else usual_inliers,
                                     min_inlier_ratio=0.5)
        motion = register(subset, ransac, config.noise, state.streams.objects)
        if not motion.success:
            continue
        # The region's motion relative to the static scene, seen from the camera: a small one
        # is the camera pose's own error over part of the image, not an object that moved.
        relative = np.linalg.inv(static.result.transformation) @ motion.transformation
        moved = np.linalg.norm(relative[:3, 3])
        turned = np.degrees(rotation_angle(relative[:3, :3]))
        logger.debug("frame %d: segments %s moved %.3f m, %.1f deg (%d of %d outliers agree)",
                     measurements.frame_index, group, moved, turned, motion.num_inliers, len(rows))
        detection = config.detection
        if not (moved >= detection.min_motion or turned >= detection.min_motion_degrees):
            continue
        if min_turn_degrees is not None and turned < min_turn_degrees:
            continue
        if moved < detection.free_space_veto_motion and seen_static(state, ctx, group):
            # A small motion of a region whose surface is where the static keyframes saw
            # one: on real data, a camera pose that is off over part of the image.
            logger.debug("frame %d: segments %s: surface seen there before", measurements.frame_index, group)
            continue
        needed = usual_inliers if min_turn_degrees is None else IN_PLACE_TURN_INLIER_FACTOR * usual_inliers
        if motion.num_inliers < needed:
            # too few agreeing outliers to decide alone (an object turned so that few of its
            # features match): the same motion in a recent frame confirms it
            seen = memory and turn_seen_before(config, state.memory, measurements, group,
                                               static.result.transformation, motion.transformation)
            if not seen:
                # not confirmed (yet): its new place stays out of the static map meanwhile
                ctx.suspects.extend(group)
                continue
        confirmed.extend(group)
    return sorted(confirmed)


def turn_seen_before(config: Config, memory: DetectionMemory, measurements: FrameMeasurements, group: list[int],
                     T_w_c: np.ndarray, T_w_old: np.ndarray) -> bool:
    """Whether a motion of the region ``group`` (its camera-frame points go to their old
    place by ``T_w_old``; ``T_w_c`` is the camera pose) with too few agreeing outliers to
    decide alone -- an in-place turn, or a jump that turned the object so that few of its
    features still match -- was also found in one of the last
    ``detection.in_place_turn_memory_frames`` frames. Same motion: it takes the region's
    centroid to within ``detection.min_motion`` of the same old place, and the rotations
    differ by at most ``TURN_MEMORY_DEGREES_FACTOR`` times ``detection.min_motion_degrees``
    (each is fitted to as few as ``detection.min_segment_features`` points, and two such
    frames together hold the usual agreeing outliers). An object that moved and came to
    rest gives the same motion in every frame; look-alikes and a person walking give a
    different one each time. The motion is remembered either way (``memory.recent_turns``) (in the world frame of this
    frame: a later bundle adjustment moves it by millimetres). Memory counts frame indices."""
    centroid = region_centroid(measurements, group, T_w_c)
    if centroid is None:
        return False
    motion = T_w_old @ invert_transform(T_w_c)  # world, new place -> old place
    detection = config.detection
    frame_index = measurements.frame_index
    memory_frames = detection.in_place_turn_memory_frames
    memory.recent_turns = [turn for turn in memory.recent_turns if frame_index - turn[0] <= memory_frames]
    old_place = transform_points(motion, centroid[None])[0]
    seen = False
    for earlier_frame, earlier_motion in memory.recent_turns:
        if earlier_frame == frame_index:
            continue
        earlier_old_place = transform_points(earlier_motion, centroid[None])[0]
        difference = np.degrees(rotation_angle(earlier_motion[:3, :3].T @ motion[:3, :3]))
        if np.linalg.norm(old_place - earlier_old_place) <= detection.min_motion \
                and difference <= TURN_MEMORY_DEGREES_FACTOR * detection.min_motion_degrees:
            seen = True
            break
    memory.recent_turns.append((frame_index, motion))
    logger.debug("frame %d: segments %s: in-place turn %s in an earlier frame", frame_index, group,
                 "also seen" if seen else "not seen")
    return seen


def seen_static(state: SceneState, ctx: FrameContext, group: list[int]) -> bool:
    """Whether most sampled pixels of the segments ``group`` lie where the latest static
    keyframes saw a surface (free-space test; False when too few pixels could be tested)."""
    if not state.free_space.enabled:
        return False
    violations, consistent = ctx.free_space_counts(state)
    return bool(state.free_space.seen_before(violations[group].sum(), consistent[group].sum()))


def outliers_in_place(state: SceneState, ctx: FrameContext, segment: int | list[int], static_inliers: np.ndarray,
                      also: np.ndarray | None = None) -> tuple[int, int]:
    """``(found, total)``: of the static landmarks matched as outliers in ``segment`` (one
    segment or a list of them), together with the static landmark ids ``also``, how many
    are still where the static map has them. Each is projected with the camera pose and
    looked for among the frame's keypoints near its projection (guided matching). A
    landmark found there has not moved (its outlier match went to a look-alike, such as the
    next cabinet door); one on an object that moved, even one that turned in place, is not
    found: its spot looks different now."""
    measurements, matched, config = ctx.measurements, ctx.static.matched, state.config
    point_segment = measurements.segments.segment_of_points(len(measurements.points))
    outlier = ~static_inliers[matched.point_measurements]
    rows = np.flatnonzero(outlier & np.isin(point_segment[matched.point_measurements], segment))
    landmarks = np.unique(matched.point_landmarks[rows])
    if also is not None:
        landmarks = np.union1d(landmarks, np.asarray(also, dtype=np.int64))
    if not len(landmarks):
        return 0, 0
    points = measurements.points
    static_points = state.static_map.points
    found = guided_match(points.pixels, points.descriptors, static_points.positions[landmarks],
                         static_points.descriptors[landmarks], ctx.T_w_c, state.intrinsics,
                         config.matching.guided_radius_px, config.matching.ratio_test,
                         config.matching.max_descriptor_distance)
    if len(found):
        # a landmark lying where the latest static keyframes saw empty space is a phantom
        # (what it was on moved away), not evidence of a surface still in place
        phantom = state.free_space.in_free_space(state.static_map.keyframes,
                                                 static_points.positions[landmarks[found[:, 1]]])
        if phantom.any():
            logger.debug("frame %d: segment %s: %d of the outlier landmarks found in place lie in free space",
                         measurements.frame_index, segment, int(phantom.sum()))
        found = found[~phantom]
    return len(found), len(landmarks)


def not_in_place(state: SceneState, ctx: FrameContext, candidates: list[int], static_inliers: np.ndarray,
                 keep_unknown: bool) -> list[int]:
    """The candidate segments fewer than half of whose outlier landmarks are still in place
    (:func:`outliers_in_place`); ``keep_unknown`` keeps segments without outlier landmarks."""
    return [segment for segment in candidates
            if not mostly_in_place(state, ctx, segment, static_inliers, 1, unknown=not keep_unknown)]


def mostly_in_place(state: SceneState, ctx: FrameContext, segment: int | list[int], static_inliers: np.ndarray,
                    min_landmarks: int, unknown: bool = False, also: np.ndarray | None = None) -> bool:
    """Whether at least half of the segment's outlier landmarks (and of the landmarks
    ``also``) are still in place, judged from at least ``min_landmarks`` of them (fewer:
    ``unknown``)."""
    found, total = outliers_in_place(state, ctx, segment, static_inliers, also)
    if total < min_landmarks:
        return unknown
    if found >= 0.5 * total:
        logger.debug("frame %d: segment %s: %d of %d outlier landmarks are still in place",
                     ctx.frame.index, segment, found, total)
        return True
    return False


def region_centroid(measurements: FrameMeasurements, segment_ids: list[int], T_w_c: np.ndarray) -> np.ndarray | None:
    """``(3,)`` world-frame centroid of the 3D point measurements in the segments
    ``segment_ids`` (camera pose ``T_w_c``), or None when none of them has depth."""
    points = measurements.points
    indices = np.concatenate([measurements.segments.point_indices[s] for s in segment_ids]).astype(np.int64)
    indices = indices[points.has_depth[indices]]
    return transform_points(T_w_c, points.points[indices]).mean(axis=0) if len(indices) else None
