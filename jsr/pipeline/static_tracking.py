"""Static tracking: the camera registered against the static map (Caccamo et al. 2017, Section
2.2.1, frame-based registration), with relocalisation after a loss and a bridge to the previous
frame when the map has no good view of this one. Features on what moved without a rigid map to
explain it in the previous frame (people) are left out: they would drag the camera.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import cv2
import numpy as np

from jsr.pipeline.association import match_frame_to_map
from jsr.pipeline.loop_closure import recognised_landmarks
from jsr.pipeline.maps import Map
from jsr.pipeline.dense_alignment import align_depth, carries, frame_samples, keyframes_target, trusted
from jsr.pipeline.pose_refinement import image_space_terms
from jsr.pipeline.pose_scoring import RegistrationProblem
from jsr.pipeline.correspondences import RegistrationResult
from jsr.pipeline.registration import evaluate_pose, pose_cost, register, surface_pose_result
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.state import DYNAMIC, CameraTrack, FrameContext, FrameReport, SceneState, StaticRegistration

logger = logging.getLogger(__name__)

CHI_SQUARE_6DOF_99 = 16.81  # 99% quantile of a chi-square with 6 degrees of freedom (a pose's)


def predicted_pose(camera: CameraTrack) -> np.ndarray | None:
    """``T_w_c`` predicted for the next frame: constant velocity in the camera frame."""
    if camera.last_pose is None:
        return None
    return camera.last_pose @ camera.velocity


def register_static(state: SceneState, ctx: FrameContext) -> None:
    """Frame-based registration of the frame against the static map: sets ``ctx.static``
    (None when it failed) and the report's pose, and moves the camera track on."""
    config, camera, report, measurements = state.config, state.camera, ctx.report, ctx.measurements
    relocalise = camera.lost
    predicted = None if relocalise else predicted_pose(camera)
    # Tracking matches the landmarks of the last N keyframes. After a loss the frame is
    # relocalised: first against those same keyframes without a pose prior (the camera is
    # usually still near where it was lost), then against the keyframes that look most like
    # it (place recognition), then against the whole map. The whole map alone is not enough:
    # its many near-duplicate landmarks make Lowe's ratio test reject most matches.
    usable = static_candidates(state, measurements)
    static_map, descriptors = state.static_map, measurements.points.descriptors
    attempts = [lambda: static_map.recent_point_landmarks(config.matching.recent_keyframes)]
    if relocalise and len(static_map.keyframes) > config.matching.recent_keyframes:
        usable_descriptors = descriptors if usable is None else descriptors[usable]
        attempts += [lambda: recognised_landmarks(state.places, static_map, usable_descriptors, config),
                     lambda: static_map.recent_point_landmarks(None)]
    matching_ms = registration_ms = 0.0
    for attempt in attempts:
        landmark_ids = attempt()
        if landmark_ids is None:  # no place recognition (loop closure off)
            continue
        tic = time.perf_counter()
        matched = match_frame_to_map(measurements, state.static_map, landmark_ids, predicted, config,
                                     state.focal_length, point_measurements=usable)
        matching_ms += (time.perf_counter() - tic) * 1000.0
        tic = time.perf_counter()
        result = register(matched.correspondences, config.ransac, config.noise, state.streams.static,
                          initial_guess=predicted)
        registration_ms += (time.perf_counter() - tic) * 1000.0
        if result.success:
            break
    bridged, dense_ms = False, 0.0
    if not result.success and config.dense.enabled:
        # The depth first: it places the frame against the map's keyframes themselves, where
        # a bridge chains it to the previous frame and makes a keyframe of what the features
        # saw (a blurred view, which bundle adjustment then holds poorly)
        tic = time.perf_counter()
        carried = with_depth(state, ctx, result, predicted)
        dense_ms += (time.perf_counter() - tic) * 1000.0
        if carried is not None:
            result, report.by_depth = carried, True
    if not result.success and camera.previous is not None and config.matching.bridge_with_previous_frame:
        # The map has no good view of this frame (fast motion into unmapped space): register
        # against the previous tracked frame instead, and make this frame a keyframe so that
        # the map grows into the new view rather than being lost for good.
        tic = time.perf_counter()
        previous_map = previous_frame_map(camera)
        bridge = match_frame_to_map(measurements, previous_map, np.arange(len(previous_map.points)),
                                    predicted, config, state.focal_length, point_measurements=usable)
        bridge_result = register(bridge.correspondences, config.ransac, config.noise, state.streams.static,
                                 initial_guess=predicted)
        registration_ms += (time.perf_counter() - tic) * 1000.0
        if bridge_result.success:
            matched, result, bridged = bridge, bridge_result, True
            camera.frames_bridged += 1
    if result.success and not report.by_depth and config.dense.enabled:
        tic = time.perf_counter()
        with_dense = with_depth(state, ctx, result, predicted)  # a poorly supported frame, or dense.refine
        dense_ms += (time.perf_counter() - tic) * 1000.0
        if with_dense is not None:
            report.by_depth = result.num_inliers < config.dense.carry_below_inliers  # carried, not refined
            result = with_dense
    ctx.timings["matching"], ctx.timings["registration"] = matching_ms, registration_ms
    if config.dense.enabled:
        ctx.timings["dense"] = dense_ms
    report.matches, report.inliers = result.num_matches, result.num_inliers

    if not result.success:
        report.reason = result.reason
        camera.frames_lost += 1
        camera.lost = True
        camera.previous = None
        logger.info("frame %d: static registration failed (%s)", ctx.frame.index, result.reason)
        return

    pose = result.transformation
    report.tracked, report.T_w_c, report.relocalised, report.bridged = True, pose, relocalise, bridged
    if camera.last_pose is not None and not relocalise:
        camera.velocity = np.linalg.inv(camera.last_pose) @ pose
    else:
        camera.velocity = np.eye(4)
    camera.last_pose = pose
    camera.lost = False
    camera.previous = (measurements, pose)
    ctx.static = StaticRegistration(matched, result, bridged, report.by_depth)


def with_depth(state: SceneState, ctx: FrameContext, result: RegistrationResult,
               predicted: np.ndarray | None) -> RegistrationResult | None:
    """The feature registration ``result`` with the frame's depth
    (:func:`~jsr.pipeline.dense_alignment.align_depth` against the latest static keyframes'),
    or None when the depth adds nothing.

    * The features failed or are poorly supported (fewer than ``dense.carry_below_inliers``
      inliers: blur, a view covered by people): the depth, with whatever feature inliers there
      are, places the frame from the feature pose (the predicted pose when they failed), if
      it :func:`~jsr.pipeline.dense_alignment.carries` it.
    * Otherwise, with ``dense.refine``: features and depth minimised together, kept if the
      feature inliers' cost rises by less than a chi-square with 6 degrees of freedom (99%):
      beyond, depth and features disagree (the sensor's depth distortion, a surface that
      moved) and the features are kept.

    Either only while the depth is trusted
    (:func:`~jsr.pipeline.dense_alignment.trusted`: it agreed with the features at the latest
    keyframes). The result's inliers are the correspondences that agree with the new pose."""
    config = state.config
    weak = not result.success or result.num_inliers < config.dense.carry_below_inliers
    start = result.transformation if result.success else predicted
    if start is None or not (weak or config.dense.refine):
        return None
    if not trusted(state.depth_disagreements, config.dense):
        logger.debug("frame %d: the depth is not trusted (it disagreed with the features at the latest keyframes)",
                     ctx.frame.index)
        return None
    target = keyframes_target(state.static_map.keyframes[-config.dense.keyframes:], state.depth_surfaces)
    if target is None:
        return None
    source, source_sigma = frame_samples(ctx.frame.depth, static_pixels(state), state.intrinsics, config.dense,
                                         config.noise)
    corr, features = result.correspondences, None
    if result.success:
        problem = RegistrationProblem(corr, config.ransac, config.noise)
        masks = [result.inliers_point3d, result.inliers_point2d, result.inliers_plane]
        features = image_space_terms(problem, result.transformation, masks, state.intrinsics.fx)
    fit = align_depth(source, source_sigma, target, start, config.dense, features)
    if fit is None or fit.pairs < 6:  # the depth took no part
        return None
    if weak:
        if not carries(fit, config.dense):
            return None
        how = "failed" if not result.success else f"poorly supported ({result.num_inliers} inliers)"
        logger.info("frame %d: features %s; placed by its depth (%.0f%% of samples on the map)", ctx.frame.index,
                    how, 100 * fit.overlap)
        carried = surface_pose_result(fit.pose, corr, config.ransac, config.noise, config.ransac.min_inliers)
        return dataclasses.replace(carried, reason=f"pose from the frame's depth (features {how})")
    rise = pose_cost(fit.pose, result, config.ransac, config.noise) - \
        pose_cost(result.transformation, result, config.ransac, config.noise)
    refined = evaluate_pose(fit.pose, corr, config.ransac, config.noise)
    if rise > CHI_SQUARE_6DOF_99 or not refined.success:
        logger.debug("frame %d: the depth-refined pose costs the features %.1f more; kept theirs",
                     ctx.frame.index, rise)
        return None
    return dataclasses.replace(refined, iterations=result.iterations, time_ms=result.time_ms)


def static_candidates(state: SceneState, measurements: FrameMeasurements) -> np.ndarray | None:
    """``(K,)`` the point measurements static registration may match: all (None) but those
    within ``detection.dynamic_margin_px`` (640 wide) of the previous frame's dynamic pixels
    (people keep moving: the margin covers a frame's motion of their edges)."""
    previous = state.memory.previous_mask
    if previous is None or not np.any(previous == DYNAMIC):
        return None
    dynamic = _grown(previous == DYNAMIC, state.config.detection.dynamic_margin_px)
    height, width = previous.shape
    pixels = np.round(measurements.points.pixels).astype(np.int64)
    u, v = np.clip(pixels[:, 0], 0, width - 1), np.clip(pixels[:, 1], 0, height - 1)
    return np.flatnonzero(~dynamic[v, u])


def static_pixels(state: SceneState) -> np.ndarray | None:
    """``(H, W)`` bool: the pixels the dense term may align, away (``detection.dynamic_margin_px``)
    from whatever the previous frame gave to an object or left dynamic; None when it was all
    static."""
    previous = state.memory.previous_mask
    if previous is None or not np.any(previous > 0):
        return None
    return ~_grown(previous > 0, state.config.detection.dynamic_margin_px)


def _grown(mask: np.ndarray, margin_px: float) -> np.ndarray:
    """``(H, W)`` bool ``mask`` grown by ``margin_px`` given at 640 wide."""
    radius = int(round(margin_px * mask.shape[1] / 640))
    if radius <= 0:
        return mask
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)) > 0


def previous_frame_map(camera: CameraTrack) -> Map:
    """A one-keyframe map made of the previous tracked frame's 3D points (world frame)."""
    measurements, pose = camera.previous
    points = measurements.points
    previous = Map("previous_frame")
    previous.add_keyframe(-1, 0.0, pose, points, np.arange(len(points)), np.full(len(points), -1),
                          np.zeros((len(points), 3), np.uint8))
    return previous


def static_inlier_landmarks(static: StaticRegistration) -> np.ndarray:
    """Sorted ids of the static landmarks matched as inliers by ``static`` (none if it failed)."""
    if not static.result.success:
        return np.zeros(0, dtype=np.int64)
    inlier_rows = np.concatenate([static.result.inliers_point3d, static.result.inliers_point2d]).astype(bool)
    return np.unique(static.matched.point_landmarks[inlier_rows])


def current_pose(static_map: Map, report: FrameReport) -> np.ndarray | None:
    """``T_w_c`` of a tracked frame with the latest keyframe poses (after bundle adjustment):
    the frame's pose relative to its reference keyframe, placed at that keyframe's pose now."""
    if not report.tracked:
        return None
    if report.reference_keyframe < 0:
        return report.T_w_c
    return static_map.keyframes[report.reference_keyframe].T_map_cam @ report.T_keyframe_cam
