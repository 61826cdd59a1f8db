"""Object tracking: every object map registered against the frame (Caccamo et al. 2017,
Section 2.2), predicted where the object was, and kept there while it rests. An object not seen
for ``objects.dormant_after_frames`` frames is dormant: it is no longer registered every frame
(the cost of a frame does not grow with the number of maps); re-identification tries it when a
new moving region could be it.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from jsr.config import Config
from jsr.pipeline.detection import segment_outlier_stats
from jsr.pipeline.object_registration import ObjectTrackingResult, segment_vlads
from jsr.pipeline.registration import evaluate_pose, pose_cost
from jsr.pipeline.state import FrameContext, SceneState

logger = logging.getLogger(__name__)


def register_objects(state: SceneState, ctx: FrameContext) -> None:
    """Frame- and segment-based registration of the frame against every object map that is not
    dormant: sets ``ctx.outcomes`` (one per map registered) and marks the maps not found as
    lost, and those lost for ``objects.dormant_after_frames`` frames as dormant."""
    if not state.object_maps:
        return
    measurements, report = ctx.measurements, ctx.report
    vlads = None
    if state.config.objects.segment_registration != "off" and state.vocabulary is not None:
        vlads = segment_vlads(state.vocabulary, measurements)
    skip = static_segments(state.config, ctx)
    outcomes = []
    for object_map in state.object_maps:
        if object_map.confirmed and not object_map.dormant and \
                measurements.frame_index - object_map.last_tracked_frame > state.config.objects.dormant_after_frames:
            object_map.dormant = True
            logger.info("frame %d: object %d dormant (not seen since frame %d)", measurements.frame_index,
                        object_map.object_id, object_map.last_tracked_frame)
        if object_map.dormant:
            continue
        predicted = object_map.last_T_o_c
        where_it_was = None  # T_o_c: its last world pose seen from this camera
        if report.tracked and object_map.last_T_w_o is not None:
            # The object most often stays where it was: predict it there.
            predicted = where_it_was = np.linalg.inv(object_map.last_T_w_o) @ report.T_w_c
        outcome = state.registrar.register_object(measurements, vlads, object_map, state.segment_index, predicted,
                                                  skip)
        if where_it_was is not None and object_map.last_pose_registered and outcome.success:
            outcome = kept_at_rest(state.config, outcome, where_it_was, measurements.frame_index)
        outcomes.append(outcome)
        logger.debug(
            "frame %d: object %d frame-based %s (%d matches, %d inliers), segment-based %s (%d pairs)",
            measurements.frame_index, object_map.object_id, outcome.frame_success,
            outcome.frame_result.num_matches, outcome.frame_result.num_inliers, outcome.segment_success,
            outcome.segment_pairs_tried)
        if not outcome.success:
            if not object_map.lost:
                logger.info("frame %d: object %d not found", measurements.frame_index, object_map.object_id)
            object_map.lost = True
    ctx.outcomes = outcomes


def kept_at_rest(config: Config, outcome: ObjectTrackingResult, resting_T_o_c: np.ndarray,
                 frame_index: int) -> ObjectTrackingResult:
    """``outcome`` with its registration replaced by one at ``resting_T_o_c`` (4x4, camera to
    object map frame: the object's last world pose seen from this camera) when that pose
    explains the registration's inliers nearly as well as the registered pose: its
    :func:`pose_cost` is at most ``objects.resting_max_extra_cost`` higher (marked
    ``at_rest``). Else ``outcome`` (marked ``moved_from_rest``).

    Why: a resting object registered anew each frame wanders within the noise (a cylinder
    about its axis by degrees over a sequence), and every keyframe taken at a wandered pose
    makes its map agree with the wandering.
    """
    bound = config.objects.resting_max_extra_cost
    if bound <= 0:
        return outcome
    _, registered = outcome.best
    ransac, noise = config.ransac, config.noise
    extra = (pose_cost(resting_T_o_c, registered, ransac, noise)
             - pose_cost(registered.transformation, registered, ransac, noise))
    object_id = outcome.object_map.object_id
    if extra > bound:
        logger.debug("frame %d: object %d moved (its last world pose costs %.1f more)", frame_index, object_id,
                     extra)
        return dataclasses.replace(outcome, moved_from_rest=True)
    resting = evaluate_pose(resting_T_o_c, registered.correspondences, ransac, noise)
    if not resting.success:
        logger.debug("frame %d: object %d moved (its last world pose: %s)", frame_index, object_id,
                     resting.reason)
        return dataclasses.replace(outcome, moved_from_rest=True)
    logger.debug("frame %d: object %d at rest (its last world pose costs %.1f more)", frame_index, object_id,
                 extra)
    if outcome.segment_success:
        return dataclasses.replace(outcome, segment_result=resting, at_rest=True)
    return dataclasses.replace(outcome, frame_result=resting, at_rest=True)


def static_segments(config: Config, ctx: FrameContext) -> np.ndarray:
    """``(S,)`` bool: segments whose matched features clearly follow the static map (they
    are not tried in segment-based registration, which saves most of its RANSAC runs)."""
    segments = ctx.measurements.segments
    if not ctx.registered:
        return np.zeros(len(segments), dtype=bool)
    inliers, _ = ctx.static_inliers()
    stats = segment_outlier_stats(segments, ctx.static_matched(), inliers)
    detection = config.detection
    return (stats.matched >= detection.min_segment_features) & (
        stats.outlier_ratio <= 0.5 * detection.segment_outlier_ratio)
