"""Which keyframes of a bundle adjustment window the landmarks tie together (its gauge).

The window's free keyframes are placed by the landmarks they share with the fixed ones. A group
of free keyframes tied to the fixed ones by landmarks that do not pin its pose is free to move
wherever the few ties and its own inner tensions take it. Two keyframes are *linked* when they
share at least ``bundle_adjustment.min_shared_landmarks`` landmarks **and** those landmarks
pin the newer keyframe (:func:`link_spread`): the motion they leave it, at one sigma of their
noise, moves none of the landmarks it observes by more than
``bundle_adjustment.link_max_spread`` inlier thresholds. A group linked to no fixed keyframe
has its oldest keyframe held fixed (:mod:`jsr.pipeline.bundle`).

Why pinning and not a count: on bonn_crowd_people (RANSAC seed 0) two keyframes taken after a
bridge shared with the older ones 5 points within 15 cm of each other and the floor. The floor
holds height, pitch and roll, the points' translation; the turn about the vertical through
the points is held by their 15 cm only (3.7 degrees at one sigma, 22 cm at the camera), and
bundle adjustment turned the two keyframes 65 cm away, with the map they had made.

Frames: landmark positions and planes in the map frame; ``T_map_cam`` ``(4, 4)``.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from jsr.config import BundleAdjustmentConfig, NoiseConfig
from jsr.geometry import cross_matrices


def linked_groups(num_frames: int, point_frames: np.ndarray, point_landmarks: np.ndarray, plane_frames: np.ndarray,
                  plane_landmarks: np.ndarray, min_shared: int, pins=None) -> np.ndarray:
    """``(num_frames,)`` group label per keyframe of a problem: keyframes are linked when they
    observe at least ``min_shared`` common landmarks (points and planes together) and, given
    ``pins(older, newer, shared_points, shared_planes) -> bool`` (keyframe slots and ``(S,)``,
    ``(Q,)`` landmark ids), those pin them; a group is what links connect. Observations are
    given as keyframe slots ``(K,)`` and landmark ids ``(K,)``, point and plane ids counted apart.

    Links are counted per pair of keyframes: a group tied to two fixed keyframes by 2 landmarks
    each counts as unlinked (on the safe side: it keeps its pose)."""
    labels = np.arange(num_frames)
    columns, rows = [], []
    offset = 0  # point and plane landmarks get columns of their own
    kinds = []
    for frames, landmarks in ((point_frames, point_landmarks), (plane_frames, plane_landmarks)):
        ids = np.unique(landmarks) if len(frames) else np.zeros(0, dtype=np.int64)
        if len(frames):
            rows.append(frames)
            columns.append(np.searchsorted(ids, landmarks) + offset)
        kinds.append((offset, ids))
        offset += len(ids)
    if not rows:
        return labels
    rows_all, columns_all = np.concatenate(rows), np.concatenate(columns)
    incidence = coo_matrix((np.ones(len(rows_all)), (rows_all, columns_all)), shape=(num_frames, offset)).tocsr()
    incidence.data[:] = 1.0  # a landmark observed twice by one keyframe counts once
    shared = (incidence @ incidence.T).tocoo()
    strong = (shared.data >= min_shared) & (shared.row < shared.col)
    pairs = list(zip(shared.row[strong].tolist(), shared.col[strong].tolist()))
    if pins is not None:
        def common(older: int, newer: int) -> list[np.ndarray]:
            """The point and the plane landmark ids both keyframes observe."""
            both = np.intersect1d(incidence[older].indices, incidence[newer].indices)
            return [ids[both[(both >= start) & (both < start + len(ids))] - start] for start, ids in kinds]
        pairs = [(a, b) for a, b in pairs if pins(a, b, *common(a, b))]
    if not pairs:
        return labels
    a, b = np.array(pairs).T
    links = coo_matrix((np.ones(len(a)), (a, b)), shape=(num_frames, num_frames))
    return connected_components(links, directed=False)[1]


def link_spread(shared_points: np.ndarray, shared_normals: np.ndarray, own_points: np.ndarray, T_map_cam: np.ndarray,
                noise: NoiseConfig, config: BundleAdjustmentConfig) -> float:
    """How loosely landmarks shared by two keyframes pin the newer one (pose ``T_map_cam``):
    the largest standard deviation, in inlier thresholds, that the motion they leave it gives
    to the landmarks it observes (``own_points`` ``(K, 3)``, may be empty); inf when they
    leave a motion free.

    ``shared_points`` ``(S, 3)``: each with the noise of a bundle adjustment point
    (``max(min_inlier_threshold / inlier_sigmas, sigma_Z)``, isotropic); ``shared_normals``
    ``(Q, 3)``: unit normals of shared planes, each holding the turns about the axes across it
    (``plane_normal_sigma``) and the translation along it (``plane_offset_sigma``). The motion
    is a small turn ``w`` about the camera centre and a translation ``t``; the information of
    each tie is summed, inverted, and carried to each own landmark ``x``: ``w x (x - c) + t``."""
    centre, z_axis = T_map_cam[:3, 3], T_map_cam[:3, 2]
    floor = noise.min_inlier_threshold / noise.inlier_sigmas

    def sigma(points: np.ndarray) -> np.ndarray:
        depth = np.maximum((points - centre) @ z_axis, 0.0)
        return np.maximum(floor, noise.sigma_z_coefficient * depth**2)

    def motion_rows(points: np.ndarray) -> np.ndarray:
        """``(K, 3, 6)``: how a point moves with ``(w, t)``."""
        return np.concatenate([-cross_matrices(points - centre), np.tile(np.eye(3), (len(points), 1, 1))], axis=2)

    rows = [(motion_rows(shared_points) / sigma(shared_points)[:, None, None]).reshape(-1, 6)]
    if len(shared_normals):
        turn = np.concatenate([-cross_matrices(shared_normals), np.zeros((len(shared_normals), 3, 3))], axis=2)
        rows.append(turn.reshape(-1, 6) / config.plane_normal_sigma)
        rows.append(np.hstack([np.zeros((len(shared_normals), 3)), shared_normals]) / config.plane_offset_sigma)
    jacobian = np.vstack(rows)
    information = jacobian.T @ jacobian
    eigenvalues = np.linalg.eigvalsh(information)
    if eigenvalues[0] <= 1e-9 * eigenvalues[-1]:
        return float("inf")
    covariance = np.linalg.inv(information)
    if not len(own_points):  # a keyframe of planes only: what it shares, and a point a metre ahead
        own_points = np.vstack([shared_points, (centre + z_axis)[None]])
    moved = motion_rows(own_points)
    spread = np.einsum("kij,jl,kml->kim", moved, covariance, moved)
    deviation = np.sqrt(np.maximum(np.linalg.eigvalsh(spread)[:, -1], 0.0))
    return float(np.max(deviation / (noise.inlier_sigmas * sigma(own_points))))
