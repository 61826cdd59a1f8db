"""Static-map hygiene (beyond the paper, whose main weakness it is): what belongs to an object
must not stay in, or enter, the static map, where it would keep pulling the camera.

Landmarks matched to an object's measurements or to a dynamic segment's (a person), or seen
through where an object has left, are retired. Segments that may have moved but are not yet
known to (:attr:`FrameContext.suspects`), and faces beside an object that has just moved, are
kept out of the static keyframe.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from scipy.spatial import cKDTree

from jsr.config import Config
from jsr.io.dataset import Frame
from jsr.pipeline.classify import segment_of_planes
from jsr.pipeline.free_space import depth_at_map_points
from jsr.pipeline.state import FrameContext, SceneState, StaticRegistration

logger = logging.getLogger(__name__)


def holding_back(config: Config, ctx: FrameContext) -> bool:
    """Whether this frame has suspect segments to keep out of a static keyframe
    (``objects.hold_back_suspects``)."""
    return bool(config.objects.hold_back_suspects and ctx.suspects)


def without_suspects(ctx: FrameContext, point_ids: np.ndarray, plane_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``point_ids`` ``(K,)`` and ``plane_ids`` ``(L,)`` without the measurements of this
    frame's suspect segments (``ctx.suspects``) that are no static inliers: segments whose outliers agree on
    an in-place turn not yet confirmed (:func:`~jsr.pipeline.region_motion.rigidly_moved`), moving
    regions too poor in 3D points to start a map (:mod:`~jsr.pipeline.moving_regions`), faces
    beside an object that just moved (:func:`beside_moved_objects`). ``remember_depth`` leaves
    their pixels out of the free-space views too.

    Why: a small object that turned and moved a few centimetres keeps only 6-9 matched
    outliers. A static keyframe taking its new surface as landmarks would make it static
    in every later frame, so the turn would never be confirmed. Held back, its old
    landmarks stay outliers and nothing of its new place enters the static map."""
    measurements = ctx.measurements
    point_inliers, plane_inliers = ctx.static_inliers()
    point_segment = measurements.segments.segment_of_points(len(measurements.points))
    held = np.isin(point_segment[point_ids], ctx.suspects) & ~point_inliers[point_ids]
    plane_segment = segment_of_planes(measurements.segments, len(measurements.planes))
    held_planes = np.isin(plane_segment[plane_ids], ctx.suspects) & ~plane_inliers[plane_ids]
    if held.any() or held_planes.any():
        logger.debug("frame %d: %d points and %d planes of suspect segments %s held back from the static keyframe",
                     measurements.frame_index, int(held.sum()), int(held_planes.sum()), ctx.suspects)
    return point_ids[~held], plane_ids[~held_planes]


def without_dynamic(ctx: FrameContext, point_ids: np.ndarray, plane_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``point_ids`` ``(K,)`` and ``plane_ids`` ``(L,)`` without the measurements of this frame's
    dynamic segments (``ctx.dynamic``: people and other movers no rigid map explains), static
    inliers or not: a person standing still a moment matches the static map by chance, and
    must not become part of it."""
    if not ctx.dynamic:
        return point_ids, plane_ids
    measurements = ctx.measurements
    point_segment = measurements.segments.segment_of_points(len(measurements.points))
    plane_segment = segment_of_planes(measurements.segments, len(measurements.planes))
    return (point_ids[~np.isin(point_segment[point_ids], ctx.dynamic)],
            plane_ids[~np.isin(plane_segment[plane_ids], ctx.dynamic)])


def beside_moved_objects(state: SceneState, ctx: FrameContext) -> list[int]:
    """Segments to hold back from the static keyframe (``objects.hold_back_beside_moved``):
    unowned, with no static inlier (point or plane), and depth-adjacent to a segment of an
    object that moved in this frame: started (or a candidate detected), found again after it was lost, or registered
    away from its last world pose (the resting test, ``objects.resting_max_extra_cost``;
    with that test off, a tracked object never counts as moved).

    Why: where an object has just moved to, the static map knows nothing, and a face of it
    that its map has not taken (a side seen at a grazing angle, whose keypoints have little
    depth) would give the static keyframe its landmarks and its depth. From then on the face
    is static: its features are static inliers and its surface is where a keyframe saw one.
    Held back, it stays unexplained, and the growth rules can give it to the object in the
    next frames (synth_jump s1 at 320x240: the box's side face, frames 29-37)."""
    frame, measurements, assignment = ctx.frame, ctx.measurements, ctx.assignment
    moved = set(ctx.report.objects_created) | {m.object_id for m in state.object_maps
                                                if not m.confirmed and m.candidacy.born == frame.index}
    for outcome in ctx.outcomes:
        object_map = outcome.object_map
        if outcome.best is not None and (object_map.lost or outcome.moved_from_rest):
            moved.add(object_map.object_id)  # found again in this frame, or away from its last world pose
    owner = assignment.segment_owner
    of_moved = np.isin(owner, sorted(moved))
    if not of_moved.any():
        return []
    adjacency = ctx.segment_adjacency(state.config)
    if not len(adjacency):
        return []
    point_inliers, plane_inliers = ctx.static_inliers()
    point_segment = measurements.segments.segment_of_points(len(measurements.points))
    plane_segment = segment_of_planes(measurements.segments, len(measurements.planes))
    static_count = np.bincount(point_segment[point_inliers & (point_segment >= 0)],
                               minlength=len(measurements.segments))
    static_count += np.bincount(plane_segment[plane_inliers & (plane_segment >= 0)],
                                minlength=len(measurements.segments))  # a featureless table top's plane
    beside = np.zeros(len(owner), dtype=bool)
    first, second = adjacency[:, 0], adjacency[:, 1]
    beside[first[of_moved[second]]] = True
    beside[second[of_moved[first]]] = True
    held = np.flatnonzero(beside & (owner == 0) & (static_count == 0)).tolist()
    if held:
        logger.debug("frame %d: objects %s moved; segments %s beside them, with no static inlier, are held back",
                     frame.index, sorted(moved), held)
    return held


def retire_static_landmarks(state: SceneState, ctx: FrameContext) -> None:
    """Static-map hygiene: landmarks the static map took from an object (before it moved)
    would keep pulling the camera. A landmark matched to a measurement that went to an
    object, or that lies in a dynamic segment (a person), is retired. Those matched to a
    candidate's measurements stay until it is confirmed: they are the evidence that it moved."""
    static, assignment, config = ctx.static, ctx.assignment, state.config.objects
    if static.bridged or not (config.enabled and config.retire_object_matches):
        return
    matched = static.matched
    landmarks = matched.point_landmarks
    if not len(landmarks):
        return
    confirmed = [m.object_id for m in state.object_maps if m.confirmed]
    retire = np.isin(assignment.point_owner[matched.point_measurements], confirmed)
    if ctx.dynamic:
        point_segment = ctx.measurements.segments.segment_of_points(len(ctx.measurements.points))
        retire |= np.isin(point_segment[matched.point_measurements], ctx.dynamic)
    retired = landmarks[retire & state.static_map.points.active[landmarks]]
    if len(retired):
        state.static_map.points.retire(retired)
        logger.debug("static map: %d landmarks retired", len(retired))


def retire_vacated_landmarks(state: SceneState, frame: Frame, T_w_c: np.ndarray, static: StaticRegistration) -> None:
    """Static-map hygiene, geometric: a landmark of the static map that projects into
    this frame where the measured surface lies clearly *behind* it has lost its surface (an
    object it was on moved away). Seen through in ``objects.retire_after_vacated`` frames in
    a row, and not a registration inlier meanwhile, it is retired ("in a row" counts the
    frames that measure depth where it projects: its count survives frames out of view).
    Only once some object has been detected: before that nothing moved, and a landmark seen
    through is a depth edge or a colour/depth misregistration (measured: retiring those
    costs redkitchen300 ATE). Even then, only when no pixel within
    ``objects.vacated_window_px`` of its projection is near it (its surface is not just
    beside) and at least ``objects.vacated_cluster_size`` other landmarks within
    ``objects.vacated_cluster_radius`` are seen through too (an object's old place is an
    area)."""
    config = state.config.objects
    if config.retire_after_vacated <= 0 or not state.static_map.keyframes:
        return
    if not state.objects_seen:
        return  # nothing was seen to move yet: a surface seen through is a depth artefact
    points = state.static_map.points
    # every active landmark, not only the recent keyframes': what an object carried before
    # it moved was taken by the keyframes of before the motion, often no longer recent
    # when its old place comes back into view (synth_two seed 4: the static landmarks on
    # objects 2.1% -> 1.0%: 85 fewer landmarks, all of object origin)
    ids = state.static_map.recent_point_landmarks(None)
    if not len(ids):
        return
    camera, (u, v), inside, measured = depth_at_map_points(points.positions[ids], T_w_c, frame.depth, state.intrinsics)
    z = camera[:, 2]
    seen = measured > 0
    noise = state.config.noise
    # the free-space test's margins: only a surface clearly gone counts, not a depth edge
    margin = np.maximum(config.free_space_margin, config.free_space_sigmas * noise.sigma_z_coefficient * z**2)
    through = seen & (measured > z + margin)
    if config.vacated_window_px > 0 and through.any():
        # gone means gone around it too: a landmark on a depth edge, projected a few pixels
        # off, has its own surface next to the pixel behind it
        radius = max(1, int(round(config.vacated_window_px * frame.depth.shape[1] / 640)))
        nearest = cv2.erode(np.where(frame.depth > 0, frame.depth, np.inf).astype(np.float32),
                            np.ones((2 * radius + 1, 2 * radius + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)
        near_surface = np.zeros(len(z))
        near_surface[inside] = nearest[v[inside], u[inside]]
        through &= near_surface > z + margin
    if not static.bridged:
        # a landmark registered as an inlier in this frame is where its feature is: a
        # "seen through" reading there is a depth edge or colour/depth misregistration
        result = static.result
        inliers = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
        through &= ~np.isin(ids, static.matched.point_landmarks[inliers])
    counts = points.seen_through
    counts[ids[seen & ~through]] = 0
    counts[ids[through]] += 1
    retire = through & (counts[ids] >= config.retire_after_vacated)
    if config.vacated_cluster_size > 0 and retire.any():
        # the place an object left is an area of landmarks seen through together; a depth
        # edge or misregistered pixel gives them one by one (measured on kitchen_box120:
        # the box's old place, 45 landmarks with a median of 32 seen-through neighbours
        # within 15 cm; elsewhere mostly single ones)
        through_positions = points.positions[ids[through]]
        neighbours = cKDTree(through_positions).query_ball_point(
            points.positions[ids[retire]], config.vacated_cluster_radius, return_length=True)
        retire[retire] = neighbours - 1 >= config.vacated_cluster_size  # itself is one of them
    retire = ids[retire]
    if len(retire):
        points.retire(retire)
        logger.debug("static map: %d landmarks retired, their surface is gone", len(retire))
