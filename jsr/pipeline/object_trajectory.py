"""Object trajectories after bundle adjustment: each tracked object pose corrected by what bundle
adjustment did to the object's map since it was tracked (a pose registered just after a jump is
often a degree or two off, and later views refine its keyframes).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from jsr.pipeline.maps import Keyframe, Map, ObjectMap
from jsr.pipeline.state import FrameReport
from jsr.pipeline.static_tracking import current_pose


def object_trajectory(static_map: Map, reports: list[FrameReport], object_map: ObjectMap
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps ``(F,)`` and ``T_w_o`` ``(F, 4, 4)`` of an object in the frames it was
    tracked, after bundle adjustment of both maps. The camera pose is the static map's
    latest (as in ``camera.tum``; ``reports``: every frame's report). The object's pose relative to the camera, ``T_o_c`` as
    tracking measured it, is corrected by what bundle adjustment changed in the object's
    keyframes (:func:`keyframe_correction`): the mean correction of the keyframes taken
    while the object rested where it is (tracking kept one world pose), so that it stays
    at one place there; else what bundle adjustment did, since the first frame of the rest
    (or the frame itself, when the object moved), to the map's latest keyframe of that time
    (``trajectory_anchors``: the pose was registered against the map as it was then,
    already refined by earlier runs; a keyframe's whole correction would count those runs
    twice).

    Why: a registration right after a jump sees few of the map's landmarks and lands a
    degree or two off, and the object at rest keeps that pose; the keyframes taken there
    are refined with every later view of the same landmarks (synth_jump seed 7 without
    depth noise: 2.4 degrees as tracked, 0.6 at the keyframes). One keyframe alone can be
    off about a symmetry axis that its few landmarks hardly fix (a cylinder's)."""
    by_frame = {report.frame_index: report for report in reports}
    keyframe_frames = [keyframe.frame_index for keyframe in object_map.keyframes]
    corrections = [keyframe_correction(keyframe) for keyframe in object_map.keyframes]
    entries = object_map.trajectory
    # runs of consecutive entries at one world pose: the object at rest, as tracking kept it
    run_starts = [i for i in range(len(entries))
                  if i == 0 or not np.allclose(entries[i][2], entries[i - 1][2], rtol=0.0, atol=1e-9)]
    run_bounds = list(zip(run_starts, run_starts[1:] + [len(entries)]))
    timestamps, poses = [], []
    for start, stop in run_bounds:
        frames = {entries[i][0] for i in range(start, stop)}
        in_run = [k for k, frame_index in enumerate(keyframe_frames) if frame_index in frames]
        anchor = object_map.trajectory_anchors.get(entries[start][0])  # when the kept pose was registered
        if in_run:
            correction = mean_transform([corrections[k] for k in in_run])
        elif anchor is not None:
            correction = keyframe_correction(*anchor)
        else:  # (a map built by hand) the pose as tracked
            correction = np.eye(4)
        for frame_index, timestamp, T_w_o in entries[start:stop]:
            report = by_frame.get(frame_index)
            if report is not None and report.tracked:
                T_o_c = correction @ (np.linalg.inv(T_w_o) @ report.T_w_c)
                T_w_o = current_pose(static_map, report) @ np.linalg.inv(T_o_c)
            timestamps.append(timestamp)
            poses.append(T_w_o)
    return np.array(timestamps), np.array(poses).reshape(-1, 4, 4)


def keyframe_correction(keyframe: Keyframe, since: np.ndarray | None = None) -> np.ndarray:
    """``(4, 4)`` what bundle adjustment did to a keyframe, in its map's frame, since it was
    at ``since`` (its ``T_map_cam`` then; default: as tracked, ``T_map_cam_tracked``):
    ``T_map_cam @ inv(since)``, to left-multiply a pose measured against the map as it was then."""
    return keyframe.T_map_cam @ np.linalg.inv(keyframe.T_map_cam_tracked if since is None else since)


def mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """``(4, 4)`` the mean of rigid transforms: chordal L2 mean rotation, mean translation."""
    stack = np.asarray(transforms, dtype=float).reshape(-1, 4, 4)
    mean = np.eye(4)
    mean[:3, :3] = Rotation.from_matrix(stack[:, :3, :3]).mean().as_matrix()
    mean[:3, 3] = stack[:, :3, 3].mean(axis=0)
    return mean
