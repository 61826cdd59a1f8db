"""Map updates (Caccamo et al. 2017, Section 2.4): the first frame starts the static map (and an
object map from a given mask), a moving region starts an object map, and every map whose
registration succeeded takes a keyframe of its own measurements when its view is new.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from jsr.config import Config
from jsr.pipeline.association import (MatchedFrame, inlier_landmarks, inlier_plane_landmarks, sample_colors)
from jsr.pipeline.classify import segment_of_planes
from jsr.pipeline.dense_alignment import depth_surface, disagreement, frame_samples, keyframes_target
from jsr.pipeline.loop_closure import find_loop
from jsr.pipeline.maps import Candidacy, Keyframe, ObjectMap
from jsr.pipeline.measurements import FrameMeasurements, PointMeasurements
from jsr.pipeline.object_registration import ObjectTrackingResult
from jsr.pipeline.ownership import ownership_image
from jsr.pipeline.correspondences import RegistrationResult
from jsr.pipeline.state import MAX_OBJECT_ID, FrameAssignment, FrameContext, SceneState
from jsr.pipeline.static_hygiene import holding_back, without_dynamic, without_suspects
from jsr.pipeline.vlad import VladVocabulary

logger = logging.getLogger(__name__)


def initialise(state: SceneState, ctx: FrameContext, init_object_mask: np.ndarray | None) -> None:
    """The first frame with enough 3D points defines the world frame and the static map
    (and object map 1 from the segments inside ``init_object_mask`` ``(H, W)`` bool, when
    given): sets ``ctx.assignment`` and the report's pose."""
    frame, measurements, report = ctx.frame, ctx.measurements, ctx.report
    points, planes = measurements.points, measurements.planes
    assignment = ctx.assignment = FrameAssignment.all_static(measurements)
    if int(points.has_depth.sum()) < state.config.ransac.min_matches:
        report.reason = "too few 3D points to start the map"
        return
    pose = np.eye(4)
    if init_object_mask is not None:
        object_segments = segments_in_mask(measurements, init_object_mask)
        if object_segments:
            object_map = start_object(state, ctx, object_segments, pose, candidate=False)
            if object_map is not None:
                report.objects_created.append(object_map.object_id)
                report.objects_tracked.append(object_map.object_id)
            else:
                logger.warning("the initial object mask covers too few 3D features on frame %d (an object map "
                               "needs %d); no object map started: give a larger mask or box", frame.index,
                               min(state.config.detection.min_object_points, state.config.ransac.min_matches))
        else:
            logger.warning("the initial object mask covers no segment of frame %d; no object map started",
                           frame.index)
    static_points = np.flatnonzero(assignment.point_owner == 0)
    static_planes = np.flatnonzero(assignment.plane_owner == 0)
    state.static_map.add_keyframe(
        frame.index, frame.timestamp, pose, points, static_points, np.full(len(static_points), -1),
        sample_colors(frame, points.pixels[static_points]), planes, static_planes,
        np.full(len(static_planes), -1),
    )
    report.tracked, report.T_w_c, report.new_keyframe = True, pose, True
    state.camera.last_pose = pose
    state.camera.previous = (measurements, pose)
    remember_depth(state, ctx)


def segments_in_mask(measurements: FrameMeasurements, mask: np.ndarray) -> list[int]:
    """Segments with at least half of their pixels inside ``mask`` ``(H, W)`` bool."""
    labels = measurements.segments.label_image
    if mask.shape != labels.shape:
        raise ValueError(f"initial object mask is {mask.shape[1]}x{mask.shape[0]} but frames are "
                         f"{labels.shape[1]}x{labels.shape[0]}")
    inside = np.bincount(labels[mask & (labels >= 0)], minlength=len(measurements.segments))
    total = np.maximum(np.asarray(measurements.segments.pixel_counts), 1)
    return np.flatnonzero(inside >= 0.5 * total).tolist()


def start_object(state: SceneState, ctx: FrameContext, segment_ids: list[int], T_w_c: np.ndarray,
                 candidate: bool = True, evidence_landmarks: np.ndarray | None = None) -> ObjectMap | None:
    """A new object map from the segments ``segment_ids`` of the frame (their features no
    object has), its frame this camera frame (pose ``T_w_c``); None when they hold too few 3D
    points or no id is left. ``ctx.assignment`` gives them to it. ``candidate``: it must be
    confirmed over the next frames (:mod:`~jsr.pipeline.confirmation`; not with
    ``detection.confirm_frames`` 0) before it is an object; ``evidence_landmarks``: the static
    landmarks that showed it moved (its outliers, those displaced in it), tested again then."""
    frame, measurements, assignment = ctx.frame, ctx.measurements, ctx.assignment
    points, planes = measurements.points, measurements.planes
    points_in, planes_in = features_in_segments(measurements, segment_ids)
    point_ids = np.flatnonzero(points_in & (assignment.point_owner == 0) & points.has_depth)
    plane_ids = np.flatnonzero(planes_in & (assignment.plane_owner == 0))
    if len(point_ids) < min(state.config.detection.min_object_points, state.config.ransac.min_matches):
        return None
    if state.next_object_id > MAX_OBJECT_ID:
        logger.warning("frame %d: %d object maps already; no more are started (masks hold ids up to %d)",
                       frame.index, MAX_OBJECT_ID, MAX_OBJECT_ID)
        return None
    object_id = state.next_object_id  # ids are never reused, also after merges
    state.next_object_id += 1
    on_probation = candidate and state.config.detection.confirm_frames > 0
    candidacy = None
    if on_probation:
        candidacy = Candidacy(frame.index, np.zeros(0, np.int64) if evidence_landmarks is None else evidence_landmarks)
    object_map = ObjectMap(object_id, frame.index, candidacy)
    keyframe = object_map.add_keyframe(
        frame.index, frame.timestamp, np.eye(4), points, point_ids, np.full(len(point_ids), -1),
        sample_colors(frame, points.pixels[point_ids]), planes, plane_ids, np.full(len(plane_ids), -1))
    assignment.point_owner[point_ids] = object_id
    assignment.plane_owner[plane_ids] = object_id
    assignment.segment_owner[segment_ids] = object_id
    state.object_maps.append(object_map)
    ensure_vocabulary(state, measurements)
    index_segments(state, object_map, keyframe, measurements, segment_ids)
    object_map.last_T_o_c = np.eye(4)
    object_map.last_T_w_o = np.array(T_w_c, dtype=float)
    object_map.record_pose(frame.index, frame.timestamp, object_map.last_T_w_o)
    object_map.frames_tracked = 1
    logger.info("frame %d: %s %d detected (%d segments, %d points, %d planes)", frame.index,
                "candidate" if on_probation else "object", object_id, len(segment_ids), len(point_ids), len(plane_ids))
    return object_map


def index_segments(state: SceneState, object_map: ObjectMap, keyframe: Keyframe, measurements: FrameMeasurements,
                   segment_ids) -> None:
    """Store the VLAD and landmark ids of every segment an object keyframe received."""
    if state.vocabulary is None:
        return
    landmark_of = np.full(len(measurements.points), -1, dtype=np.int64)
    landmark_of[keyframe.point_measurements] = keyframe.point_landmarks
    for segment in segment_ids:
        indices = np.asarray(measurements.segments.point_indices[segment], dtype=np.int64)
        landmarks = landmark_of[indices]
        landmarks = np.unique(landmarks[landmarks >= 0])
        if len(landmarks) < state.config.vlad.min_segment_points:
            continue
        key = (keyframe.keyframe_id, int(segment))
        object_map.segment_landmarks[key] = landmarks
        state.segment_index.add(object_map.object_id, key,
                               state.vocabulary.encode(object_map.points.descriptors[landmarks]))


def ensure_vocabulary(state: SceneState, measurements: FrameMeasurements) -> None:
    """Train the VLAD vocabulary once, on the static map's descriptors (and this frame's)."""
    if state.vocabulary is not None:
        return
    descriptors = np.concatenate([state.static_map.points.descriptors, measurements.points.descriptors])
    rng = np.random.default_rng(state.config.seed)  # its own stream: RANSAC draws stay unchanged
    state.vocabulary = VladVocabulary.train_on_sample(descriptors, state.config.vlad, rng)
    logger.info("VLAD vocabulary of %d words trained on %d descriptors", state.vocabulary.size,
                min(len(descriptors), state.config.vlad.training_descriptors))


def update_static(state: SceneState, ctx: FrameContext) -> None:
    """Add a keyframe to the static map (its own measurements only) when the view is new and
    the registration that found it has ``keyframes.static_min_inliers`` inliers: landmarks
    made at a poorly supported pose would be a shifted copy of the scene.

    The view is new when the pose is far from every keyframe (``keyframes.translation``,
    ``rotation_degrees``), or when the map is losing it: the frame matches fewer map
    landmarks than ``keyframes.tracked_share`` of the best frame since the last keyframe, and
    has fewer than ``keyframes.weak_inliers`` inliers (people covering the view, a slow turn).
    Waiting for the distance there let the inliers fall below the minimum first, and the map
    stopped growing. Matches, not inliers, measure the view: an object that moves away keeps
    its matches (as outliers) and is no reason for a keyframe."""
    frame, measurements, report, static, assignment = ctx.frame, ctx.measurements, ctx.report, ctx.static, ctx.assignment
    pose, settings, camera = report.T_w_c, state.config.keyframes, state.camera
    matches = static.result.num_matches
    if not (static.bridged or ctx.force_static_keyframe):
        camera.best_matches = max(camera.best_matches, matches)
        fading = (matches < settings.tracked_share * camera.best_matches
                  and static.result.num_inliers < settings.weak_inliers)
        if not (fading or state.static_map.needs_keyframe(pose, settings)):
            return
        if static.result.num_inliers < settings.static_min_inliers:
            logger.debug("frame %d: no static keyframe: %d registration inliers, fewer than "
                         "keyframes.static_min_inliers", frame.index, static.result.num_inliers)
            return
        if fading:
            logger.debug("frame %d: static keyframe: %d matches to the map, fewer than %.2f of the %d of the "
                         "best frame since the last keyframe", frame.index, matches, settings.tracked_share,
                         camera.best_matches)
    camera.best_matches = 0
    points, planes = measurements.points, measurements.planes
    static_points = np.flatnonzero(assignment.point_owner == 0)
    static_planes = np.flatnonzero(assignment.plane_owner == 0)
    if holding_back(state.config, ctx) and not static.bridged:
        static_points, static_planes = without_suspects(ctx, static_points, static_planes)
    static_points, static_planes = without_dynamic(ctx, static_points, static_planes)
    if static.bridged:  # matched to the previous frame, not to the map: all measurements are new
        landmark_of = np.full(len(points), -1, dtype=np.int64)
        plane_landmark_of = np.full(len(planes), -1, dtype=np.int64)
    else:
        landmark_of = inlier_landmarks(static.matched, static.result, len(points))
        plane_landmark_of = inlier_plane_landmarks(static.matched, static.result, len(planes))
    if ctx.given_to_static is not None:  # landmarks a dissolved candidate gave: observed here
        landmark_of = np.where(landmark_of < 0, ctx.given_to_static, landmark_of)
    state.static_map.add_keyframe(
        frame.index, frame.timestamp, pose, points, static_points, landmark_of[static_points],
        sample_colors(frame, points.pixels[static_points]), planes, static_planes,
        plane_landmark_of[static_planes],
    )
    report.new_keyframe = True
    remember_depth(state, ctx)
    started = time.perf_counter()
    state.places.pending = find_loop(state.places, state.static_map, measurements, state.config, state.streams.loops)
    ctx.timings["loop_detection"] = (time.perf_counter() - started) * 1000.0
    state.bundle.maybe_start(state.static_map)


def remember_depth(state: SceneState, ctx: FrameContext) -> None:
    """Keep the new static keyframe's depth on its static pixels: subsampled for free-space
    tests (objects on) and sampled with normals for the dense term of tracking
    (``dense.enabled``, :mod:`~jsr.pipeline.dense_alignment`) and for placing a frame on a
    free-space view (``objects.free_space_registered``); with the dense term, how far its depth
    alone moves it from its features' pose (whether the depth is trusted). Where objects (and
    people) were, nothing is known of any of these."""
    free_space = state.config.objects.enabled and state.config.objects.free_space_detection
    surfaces = state.config.dense.enabled or (free_space and state.config.objects.free_space_registered)
    if not (free_space or surfaces):
        return
    unknown = not_static_pixels(state, ctx)
    keyframes = state.static_map.keyframes
    if free_space:
        state.free_space.remember(keyframes[-1], ctx.frame.depth, unknown)
    if surfaces:
        if state.config.dense.enabled:
            measure_disagreement(state, ctx, ~unknown)
        for old in keyframes[-state.config.dense.keyframes - 1:-state.config.dense.keyframes]:
            state.depth_surfaces.pop(old.keyframe_id, None)  # only the latest are aligned to
        state.depth_surfaces[keyframes[-1].keyframe_id] = depth_surface(
            ctx.frame.depth, ~unknown, state.intrinsics, state.config.dense, state.config.noise)


def measure_disagreement(state: SceneState, ctx: FrameContext, static_pixels: np.ndarray) -> None:
    """For a new static keyframe that its features placed (not its depth, not a bridge to the
    previous frame): how far its depth alone, on ``static_pixels`` ``(H, W)`` bool, moves it
    from that pose against the previous keyframes' depth
    (:func:`~jsr.pipeline.dense_alignment.disagreement`), kept in ``state.depth_disagreements``
    (the evidence whether the depth is trusted, :func:`~jsr.pipeline.dense_alignment.trusted`)."""
    static, config = ctx.static, state.config.dense
    if static is None or static.bridged or static.by_depth:
        return
    target = keyframes_target(state.static_map.keyframes[-config.keyframes - 1:-1], state.depth_surfaces)
    if target is None:
        return
    source, source_sigma = frame_samples(ctx.frame.depth, static_pixels, state.intrinsics, config, state.config.noise)
    moved = disagreement(source, source_sigma, target, static.result.transformation, config)
    if moved is None:
        return
    state.depth_disagreements.append(moved)
    logger.debug("frame %d: its depth alone moves the keyframe %.1f cm from its features' pose", ctx.frame.index,
                 100 * moved)


def not_static_pixels(state: SceneState, ctx: FrameContext) -> np.ndarray:
    """``(H, W)`` bool: the frame's pixels given to objects or left dynamic, and those of the
    segments held back because they may have moved (see ``without_suspects``)."""
    unknown = ownership_image(ctx.measurements, ctx.assignment, ctx.dynamic) > 0
    if holding_back(state.config, ctx):
        unknown |= np.isin(ctx.measurements.segments.label_image, ctx.suspects)
    return unknown


def update_object(state: SceneState, ctx: FrameContext, outcome: ObjectTrackingResult) -> None:
    """Record the object's pose and add a keyframe when the object-relative view is new."""
    frame, measurements, report, assignment = ctx.frame, ctx.measurements, ctx.report, ctx.assignment
    object_map = outcome.object_map
    if object_map not in state.object_maps:
        return  # merged into another map earlier in this frame
    best = outcome.best
    if best is None:
        return
    matched, result = best
    T_o_c = result.transformation
    object_map.lost = False
    object_map.dormant = False
    object_map.last_T_o_c = T_o_c
    object_map.last_tracked_frame = frame.index
    object_map.frames_tracked += 1
    if object_map.confirmed:
        report.objects_tracked.append(object_map.object_id)
    if report.tracked:
        T_w_o = report.T_w_c @ np.linalg.inv(T_o_c)
        object_map.last_T_w_o = T_w_o
        object_map.last_pose_registered = not outcome.pose_from_surface
        object_map.record_pose(frame.index, frame.timestamp, T_w_o)
    if not object_map.confirmed:
        return  # a candidate keeps the model it was detected with: is that one rigid body?
    points, planes = measurements.points, measurements.planes
    own_points = np.flatnonzero(assignment.point_owner == object_map.object_id)
    landmark_of = inlier_landmarks(matched, result, len(points))
    if not (object_map.needs_keyframe(T_o_c, state.config.keyframes)
            or map_would_grow(state.config, object_map, points, own_points, landmark_of)):
        return
    own_planes = np.flatnonzero(assignment.plane_owner == object_map.object_id)
    plane_landmark_of = inlier_plane_landmarks(matched, result, len(planes))
    keyframe = object_map.add_keyframe(
        frame.index, frame.timestamp, T_o_c, points, own_points, landmark_of[own_points],
        sample_colors(frame, points.pixels[own_points]), planes, own_planes, plane_landmark_of[own_planes])
    own_segments = np.flatnonzero(assignment.segment_owner == object_map.object_id)
    index_segments(state, object_map, keyframe, measurements, own_segments)
    state.bundle.maybe_start(object_map)


def map_would_grow(config: Config, object_map: ObjectMap, points: PointMeasurements, own_points: np.ndarray,
                   landmark_of: np.ndarray) -> bool:
    """Whether this frame's 3D measurements given to the object and matching none of its
    landmarks are at least ``objects.grow_keyframe_ratio`` times its active landmarks (and
    at least ``detection.min_object_points``): a map starts from the few features of the
    segments that gave it away, and should take the rest of the object in as soon as it
    is seen, not only once the object-relative view has changed (measured on
    kitchen_box120: a map started from 26 points was tracked by 9-15 inliers for 12 frames,
    until a view change gave it a keyframe of 188 points)."""
    ratio = config.objects.grow_keyframe_ratio
    if ratio <= 0 or not len(own_points):
        return False
    new = int(np.count_nonzero(points.has_depth[own_points] & (landmark_of[own_points] < 0)))
    return new >= max(config.detection.min_object_points, ratio * object_map.points.active_count)


def claim_region(measurements: FrameMeasurements, group: list[int], outcome: ObjectTrackingResult,
                 matched: MatchedFrame, result: RegistrationResult, assignment: FrameAssignment) -> None:
    """The segments ``group`` and their unowned features go to ``outcome``'s object, which
    is tracked in this frame by ``result``."""
    object_id = outcome.object_map.object_id
    outcome.frame_matched, outcome.frame_result = matched, result
    assignment.segment_owner[group] = object_id
    points_in, planes_in = features_in_segments(measurements, group)
    assignment.point_owner[points_in & (assignment.point_owner == 0)] = object_id
    assignment.plane_owner[planes_in & (assignment.plane_owner == 0)] = object_id


def features_in_segments(measurements: FrameMeasurements, segment_ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """``(N,)`` bool over the frame's points and ``(P,)`` bool over its planes: those lying in
    one of the segments ``segment_ids``."""
    segments = measurements.segments
    members = np.zeros(len(segments), dtype=bool)
    members[segment_ids] = True
    point_segment = segments.segment_of_points(len(measurements.points))
    plane_segment = segment_of_planes(segments, len(measurements.planes))
    return ((point_segment >= 0) & members[np.maximum(point_segment, 0)],
            (plane_segment >= 0) & members[np.maximum(plane_segment, 0)])
