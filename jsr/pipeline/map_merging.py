"""Object-map merging: two maps found to be one object become one (beyond the paper, whose
maps of one object stay apart when a jump showed sides the first map never saw).

The evidence: two maps explaining the same measurements in one frame
(:func:`merge_duplicates`). The older map keeps its id.
"""

from __future__ import annotations

import logging

import numpy as np

from jsr.geometry import transform_planes, transform_points
from jsr.pipeline.association import inlier_mask
from jsr.pipeline.maps import Keyframe, ObjectMap
from jsr.pipeline.state import FrameContext, SceneState

logger = logging.getLogger(__name__)


def merge_object_maps(target: ObjectMap, source: ObjectMap, T_target_source: np.ndarray) -> np.ndarray:
    """Move everything of ``source`` into ``target`` (two maps found to be one object).

    ``T_target_source`` maps ``source``'s object frame into ``target``'s. Landmarks, planes and
    keyframes are appended (keyframes then renumbered in frame order), the segments' landmark
    lists remapped, and the trajectories joined (``target``'s pose wins in a frame both have).
    Returns ``(L_source,)`` the new landmark id of every ``source`` landmark.
    """
    points = source.points
    new_ids = target.points.add(
        transform_points(T_target_source, points.positions), points.descriptors,
        1.0 / np.sqrt(np.maximum(points.weights, 1e-12)), points.colors)
    target.points.observations[new_ids] = points.observations
    target.points.retire(new_ids[~points.active])
    new_plane_ids = np.zeros(0, dtype=np.int64)
    if len(source.planes):
        new_plane_ids = target.planes.add(transform_planes(T_target_source, source.planes.planes),
                                          transform_points(T_target_source, source.planes.centroids),
                                          source.planes.point_counts)
    keyframes = list(target.keyframes)
    source_keyframe_position = {}
    for keyframe in source.keyframes:
        source_keyframe_position[keyframe.keyframe_id] = len(keyframes)
        keyframes.append(Keyframe(
            keyframe_id=-1, frame_index=keyframe.frame_index, timestamp=keyframe.timestamp,
            T_map_cam=T_target_source @ keyframe.T_map_cam, point_measurements=keyframe.point_measurements,
            point_landmarks=new_ids[keyframe.point_landmarks], camera_points=keyframe.camera_points,
            pixels=keyframe.pixels, sigma_z=keyframe.sigma_z,
            plane_landmarks=new_plane_ids[keyframe.plane_landmarks] if len(keyframe.plane_landmarks) else
            keyframe.plane_landmarks, camera_planes=keyframe.camera_planes,
            T_map_cam_tracked=T_target_source @ keyframe.T_map_cam_tracked))
    target_keyframe_position = {keyframe.keyframe_id: i for i, keyframe in enumerate(target.keyframes)}
    order = sorted(range(len(keyframes)), key=lambda i: (keyframes[i].frame_index, i))
    new_keyframe_id = {position: rank for rank, position in enumerate(order)}
    target.keyframes = [keyframes[i] for i in order]
    for rank, keyframe in enumerate(target.keyframes):
        keyframe.keyframe_id = rank
    segments = {}
    for (keyframe_id, segment), landmarks in target.segment_landmarks.items():
        segments[(new_keyframe_id[target_keyframe_position[keyframe_id]], segment)] = landmarks
    for (keyframe_id, segment), landmarks in source.segment_landmarks.items():
        segments[(new_keyframe_id[source_keyframe_position[keyframe_id]], segment)] = new_ids[landmarks]
    target.segment_landmarks = segments
    by_frame = {index: (index, timestamp, T_w_o @ np.linalg.inv(T_target_source))
                for index, timestamp, T_w_o in source.trajectory}
    target_frames = {index for index, _, _ in target.trajectory}
    by_frame.update({index: (index, timestamp, T_w_o) for index, timestamp, T_w_o in target.trajectory})
    target.trajectory = [by_frame[index] for index in sorted(by_frame)]
    # the source's anchors follow its keyframes into the target (target's entries win, as above)
    moved_keyframe = {id(keyframe): keyframes[source_keyframe_position[keyframe.keyframe_id]]
                      for keyframe in source.keyframes}
    anchors = {index: (moved_keyframe[id(keyframe)], T_target_source @ T_map_cam)
               for index, (keyframe, T_map_cam) in source.trajectory_anchors.items() if index not in target_frames}
    anchors.update(target.trajectory_anchors)
    target.trajectory_anchors = anchors
    target.frames_tracked = len(target.trajectory)
    target.created_at_frame = min(target.created_at_frame, source.created_at_frame)
    return new_ids


def merge_duplicates(state: SceneState, ctx: FrameContext) -> None:
    """Two object maps that explain the same measurements in one frame are one object (its
    first map saw a side the second never did, e.g. before a jump that turned it): the
    newer map is merged into the older one (``objects.merge_maps``); ``ctx.outcomes`` loses
    the merged map's registration. The older map stays, or the object when the other is a
    candidate (:func:`keeps`)."""
    config = state.config.objects
    successful = [o for o in ctx.outcomes if o.success]
    if not config.merge_maps or len(successful) < 2:
        return
    measurements = ctx.measurements
    num_points, num_planes = len(measurements.points), len(measurements.planes)
    inliers = {o.object_map.object_id: inlier_mask(*o.best, num_points, num_planes)[0] for o in successful}
    merged: set[int] = set()
    for i, target in enumerate(successful):
        for source in successful[i + 1:]:
            target_id, source_id = target.object_map.object_id, source.object_map.object_id
            if target_id in merged or source_id in merged:
                continue
            shared = int((inliers[target_id] & inliers[source_id]).sum())
            if shared < config.merge_min_shared_inliers:
                continue
            keep, gone = (target, source) if keeps(target.object_map, source.object_map) else (source, target)
            merge_maps(state, keep.object_map, gone.object_map, keep.T_o_c @ np.linalg.inv(gone.T_o_c),
                       measurements.frame_index, f"{shared} shared inliers")
            inliers[keep.object_map.object_id] |= inliers[gone.object_map.object_id]
            merged.add(gone.object_map.object_id)
    ctx.outcomes = [o for o in ctx.outcomes if o.object_map.object_id not in merged]


def keeps(first: ObjectMap, second: ObjectMap) -> bool:
    """Whether ``first`` is the map that stays when two maps of one object are merged: a
    confirmed object rather than a candidate, else the older map."""
    if first.confirmed != second.confirmed:
        return first.confirmed
    return first.object_id < second.object_id


def merge_maps(state: SceneState, target: ObjectMap, source: ObjectMap, T_target_source: np.ndarray,
               frame_index: int, evidence: str) -> None:
    """Move ``source`` into ``target`` (:func:`merge_object_maps`; ``T_target_source`` maps
    ``source``'s object frame into ``target``'s) and keep every index of the scene consistent:
    segment VLADs, the merged-id table, the keyframe ownership masks, the surface samples, and
    the tracking state (``source``'s when it was tracked later)."""
    state.bundle.finish(target)
    state.bundle.finish(source)
    source_frames = [keyframe.frame_index for keyframe in source.keyframes]
    source_last, target_last = source.last_tracked_frame, target.last_tracked_frame
    merge_object_maps(target, source, T_target_source)
    target.last_tracked_frame = max(source_last, target_last)
    if source_last > target_last and source.last_T_o_c is not None:
        # the source saw the object last: the merged map continues from there
        target.last_T_o_c = T_target_source @ source.last_T_o_c
        target.last_T_w_o = None if source.last_T_w_o is None else source.last_T_w_o @ np.linalg.inv(T_target_source)
        target.last_pose_registered = source.last_pose_registered
        target.lost = source.lost
    state.object_maps.remove(source)
    reindex_segments(state, target)
    state.segment_index.remove_map(source.object_id)
    state.merged_into[source.object_id] = target.object_id
    for earlier, into in state.merged_into.items():
        if into == source.object_id:
            state.merged_into[earlier] = target.object_id
    for index in source_frames:
        mask = state.keyframe_masks.get(index)
        if mask is not None:
            mask[mask == source.object_id] = target.object_id
    state.surfaces.move(source_frames, source.object_id, target.object_id)
    logger.info("frame %d: object %d is object %d (%s); maps merged", frame_index, source.object_id,
                target.object_id, evidence)


def reindex_segments(state: SceneState, object_map: ObjectMap) -> None:
    """Rebuild the VLADs of an object map's segments (after its keyframes were renumbered)."""
    state.segment_index.remove_map(object_map.object_id)
    if state.vocabulary is None:
        return
    for key, landmarks in object_map.segment_landmarks.items():
        state.segment_index.add(object_map.object_id, key,
                                state.vocabulary.encode(object_map.points.descriptors[landmarks]))
