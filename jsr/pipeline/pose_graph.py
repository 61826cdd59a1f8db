"""Keyframe pose graph: the static map's keyframe poses adjusted to agree with measured relative
poses (odometry between consecutive keyframes, and the loops that place recognition found).

A loop closure (:mod:`~jsr.pipeline.loop_closure`) measures where the newest keyframe is
against landmarks mapped long before; the chain of keyframes between the two disagrees with it
by the drift accumulated on the way. Spreading that disagreement over the chain, weighted by the
stated sigmas, is a small nonlinear least-squares problem over ``SE(3)`` poses: one residual of
6 per edge, ``log(Z_ij^-1 T_i^-1 T_j)`` (rotation vector over its sigma, translation over its
sigma), solved with scipy's sparse trust-region solver (each residual depends on two poses).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from jsr.geometry import invert_transform

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PoseEdge:
    """A measured relative pose ``T_first_second`` ``(4, 4)`` (the pose of node ``second`` in
    node ``first``'s frame) with its sigmas: metres, and radians of rotation."""

    first: int
    second: int
    relative: np.ndarray
    sigma_translation: float
    sigma_rotation: float


def chain_edges(poses: np.ndarray, sigma_translation: float, sigma_rotation: float) -> list[PoseEdge]:
    """Edges between consecutive nodes of ``poses`` ``(N, 4, 4)`` at their current relative
    poses: the odometry a loop edge is weighed against."""
    return [PoseEdge(i, i + 1, invert_transform(poses[i]) @ poses[i + 1], sigma_translation, sigma_rotation)
            for i in range(len(poses) - 1)]


def _to_matrices(parameters: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` poses from ``(N * 6,)`` rotation vectors and translations."""
    values = parameters.reshape(-1, 6)
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(values[:, :3]).as_matrix()
    poses[:, :3, 3] = values[:, 3:]
    return poses


def _to_parameters(poses: np.ndarray) -> np.ndarray:
    return np.column_stack([Rotation.from_matrix(poses[:, :3, :3]).as_rotvec(), poses[:, :3, 3]]).ravel()


def edge_residuals(poses: np.ndarray, edges: list[PoseEdge]) -> np.ndarray:
    """``(E, 6)`` whitened residuals: rotation vector and translation of ``Z^-1 T_i^-1 T_j``."""
    if not edges:
        return np.zeros((0, 6))
    first = np.array([e.first for e in edges])
    second = np.array([e.second for e in edges])
    measured_inverse = invert_transform(np.stack([e.relative for e in edges]))
    error = measured_inverse @ invert_transform(poses[first]) @ poses[second]
    rotation = Rotation.from_matrix(error[:, :3, :3]).as_rotvec()
    sigmas_t = np.array([e.sigma_translation for e in edges])[:, None]
    sigmas_r = np.array([e.sigma_rotation for e in edges])[:, None]
    return np.hstack([rotation / sigmas_r, error[:, :3, 3] / sigmas_t])


def optimise_pose_graph(poses: np.ndarray, edges: list[PoseEdge], fixed: int = 0,
                        max_evaluations: int = 100) -> np.ndarray:
    """The poses ``(N, 4, 4)`` (``T_map_node``) that best agree with ``edges``, node ``fixed``
    held where it is (the gauge). Returns the input when there is nothing to solve or the
    solver fails."""
    count = len(poses)
    if count < 2 or not edges:
        return poses.copy()
    free = np.array([i for i in range(count) if i != fixed])
    slot = np.full(count, -1)
    slot[free] = np.arange(len(free))
    start = _to_parameters(poses[free])

    def residuals(x: np.ndarray) -> np.ndarray:
        current = poses.copy()
        current[free] = _to_matrices(x)
        return edge_residuals(current, edges).ravel()

    sparsity = lil_matrix((6 * len(edges), 6 * len(free)), dtype=np.int8)
    for row, edge in enumerate(edges):
        for node in (edge.first, edge.second):
            if slot[node] >= 0:
                sparsity[6 * row : 6 * row + 6, 6 * slot[node] : 6 * slot[node] + 6] = 1
    try:
        solution = least_squares(residuals, start, jac_sparsity=sparsity.tocsr(), method="trf",
                                 max_nfev=max_evaluations, x_scale="jac")
    except (ValueError, np.linalg.LinAlgError) as error:
        logger.debug("pose graph: solver failed: %s", error)
        return poses.copy()
    if not np.all(np.isfinite(solution.x)):
        return poses.copy()
    optimised = poses.copy()
    optimised[free] = _to_matrices(solution.x)
    logger.debug("pose graph: %d nodes, %d edges, cost %.4g -> %.4g in %d evaluations", count, len(edges),
                 0.5 * float(np.sum(residuals(start) ** 2)), float(solution.cost), int(solution.nfev))
    return optimised
