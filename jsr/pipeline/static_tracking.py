"""Static tracking: the camera registered against the static map (Caccamo et al. 2017, Section
2.2.1, frame-based registration), with relocalisation after a loss and a bridge to the previous
frame when the map has no good view of this one. Features on what moved without a rigid map to
explain it in the previous frame (people) are left out: they would drag the camera.
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from jsr.pipeline.association import match_frame_to_map
from jsr.pipeline.loop_closure import recognised_landmarks
from jsr.pipeline.maps import Map
from jsr.pipeline.registration import register
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.state import DYNAMIC, CameraTrack, FrameContext, FrameReport, SceneState, StaticRegistration

logger = logging.getLogger(__name__)


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
    bridged = False
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
    ctx.timings["matching"], ctx.timings["registration"] = matching_ms, registration_ms
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
    ctx.static = StaticRegistration(matched, result, bridged)


def static_candidates(state: SceneState, measurements: FrameMeasurements) -> np.ndarray | None:
    """``(K,)`` the point measurements static registration may match: all (None) but those
    within ``detection.dynamic_margin_px`` (640 wide) of the previous frame's dynamic pixels
    (people keep moving: the margin covers a frame's motion of their edges)."""
    previous = state.memory.previous_mask
    if previous is None or not np.any(previous == DYNAMIC):
        return None
    dynamic = (previous == DYNAMIC).astype(np.uint8)
    radius = int(round(state.config.detection.dynamic_margin_px * previous.shape[1] / 640))
    if radius > 0:
        dynamic = cv2.dilate(dynamic, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    height, width = previous.shape
    pixels = np.round(measurements.points.pixels).astype(np.int64)
    u, v = np.clip(pixels[:, 0], 0, width - 1), np.clip(pixels[:, 1], 0, height - 1)
    return np.flatnonzero(dynamic[v, u] == 0)


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
