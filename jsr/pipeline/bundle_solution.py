"""What a bundle adjustment returns, and writing its solution into a map that went on living.

Bundle adjustment runs on a snapshot of a map (:class:`~jsr.pipeline.bundle.BundleProblem`),
in the background while the next frames are tracked
(:class:`~jsr.pipeline.bundle_scheduler.BundleScheduler`). By the time its solution is
applied the map has new keyframes, landmarks and planes, and fused observations of old ones:
:func:`apply_solution` therefore applies the solution as corrections, never as overwrites.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from jsr.geometry import invert_transform, transform_points
from jsr.pipeline.bundle_noise import GROUPS
from jsr.pipeline.maps import Map


@dataclass
class BundleResult:
    """Summary of one bundle adjustment run.

    ``initial_cost``/``final_cost`` are scipy's robust cost ``0.5 * sum rho(r^2)`` of the
    whitened residuals. ``iterations`` counts residual evaluations outside the Jacobian (one per
    trust-region step, what ``max_iterations`` bounds). ``landmarks_optimised`` counts the points
    solved for; ``points_carried`` those seen by one keyframe, moved with it instead
    (:meth:`BundleProblem._carry_single_view_points`). ``seconds`` is wall time of the solve,
    ``cpu_seconds`` the CPU time of the thread that ran it. ``correction`` is
    ``T_after @ inv(T_before)`` of the newest free keyframe (identity if none moved): a caller
    holding a pose expressed against the old map (e.g. the tracker's last pose) can left-multiply
    it. ``noise_components`` ``(5,)``: each residual group's sigma (:data:`~jsr.pipeline.bundle_noise.GROUPS`)
    as a multiple of the configured one: when the run estimated them
    (:mod:`~jsr.pipeline.bundle_noise`), the estimate from its last solve's residuals (what the
    next run starts from; the last solve itself used the one before), else those it used.
    ``passes``: the solves it took (``iterations`` counts over all of them, up to
    ``max_iterations`` each).
    """

    success: bool
    initial_cost: float
    final_cost: float
    keyframes_optimised: int
    landmarks_optimised: int
    observations: int
    iterations: int
    seconds: float
    planes_optimised: int = 0
    keyframes_fixed: int = 0
    cpu_seconds: float = 0.0
    points_carried: int = 0
    message: str = ""
    correction: np.ndarray = field(default_factory=lambda: np.eye(4))
    noise_components: np.ndarray = field(default_factory=lambda: np.ones(len(GROUPS)))
    passes: int = 0


@dataclass
class BundleSolution:
    """The outcome of solving a :class:`BundleProblem`: before/after values, not yet applied."""

    result: BundleResult
    keyframe_indices: np.ndarray
    poses_before: np.ndarray
    poses_after: np.ndarray
    point_ids: np.ndarray
    positions_before: np.ndarray
    positions_after: np.ndarray
    plane_ids: np.ndarray
    planes_before: np.ndarray
    planes_after: np.ndarray
    carried_point_ids: np.ndarray
    carried_keyframes: np.ndarray
    num_keyframes: int
    num_points: int
    num_planes: int


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(Q, 3, 3)`` smallest rotations taking unit vectors ``a`` to unit vectors ``b``."""
    axis = np.cross(a, b)
    sine = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(sine, np.sum(a * b, axis=1))
    axis = np.where(sine[:, None] > 1e-15, axis / np.maximum(sine, 1e-300)[:, None], 0.0)
    return Rotation.from_rotvec(axis * angle[:, None]).as_matrix()


def apply_solution(map: Map, solution: BundleSolution) -> None:
    """Write a successful solution into ``map``, which may have changed since the snapshot.

    Every update is applied as a *correction* rather than an overwrite, so anything that
    happened meanwhile is kept: a snapshot keyframe gets ``T <- T_after inv(T_before) T``; a
    snapshot landmark ``X <- X + (X_after - X_before)`` (a landmark fused meanwhile keeps its new
    information, shifted by the BA correction); a snapshot plane is rotated by the smallest
    rotation from its old to its new normal and shifted by the offset change. Keyframes,
    landmarks and planes created after the snapshot were placed with poses relative to the old
    map, so they get the rigid correction of the newest optimised keyframe. A point seen by one
    keyframe only (not solved for) moves with that keyframe's correction. When nothing changed
    meanwhile this is exactly (up to rounding) the optimised state.
    """
    if not solution.result.success:
        return
    keyframes = map.keyframes
    moved_by = {int(index): after @ invert_transform(before)  # T_after inv(T_before) per optimised keyframe
                for index, before, after in zip(solution.keyframe_indices, solution.poses_before, solution.poses_after)}
    for index, keyframe_correction in moved_by.items():
        keyframes[index].T_map_cam = keyframe_correction @ keyframes[index].T_map_cam
    correction = solution.result.correction
    moved = not np.array_equal(correction, np.eye(4))
    if moved:
        for keyframe in keyframes[solution.num_keyframes:]:
            keyframe.T_map_cam = correction @ keyframe.T_map_cam

    positions = map.points.positions
    positions[solution.point_ids] += solution.positions_after - solution.positions_before
    for index, keyframe_correction in moved_by.items():
        carried = solution.carried_point_ids[solution.carried_keyframes == index]
        if len(carried):
            positions[carried] = transform_points(keyframe_correction, positions[carried])
    if moved and len(map.points) > solution.num_points:
        new = slice(solution.num_points, len(map.points))
        positions[new] = transform_points(correction, positions[new])

    if len(solution.plane_ids):
        ids = solution.plane_ids
        live = map.planes.planes[ids]
        rotation = _rotation_between(solution.planes_before[:, :3], solution.planes_after[:, :3])
        normals = np.einsum("qij,qj->qi", rotation, live[:, :3])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        offsets = live[:, 3] + solution.planes_after[:, 3] - solution.planes_before[:, 3]
        map.planes.planes[ids] = np.column_stack([normals, offsets])
        centroids = map.planes.centroids[ids]
        distance = np.sum(centroids * normals, axis=1) + offsets
        map.planes.centroids[ids] = centroids - distance[:, None] * normals  # back onto the plane
    if moved and len(map.planes) > solution.num_planes:
        new = slice(solution.num_planes, len(map.planes))
        normals = map.planes.planes[new, :3] @ correction[:3, :3].T
        offsets = map.planes.planes[new, 3] - normals @ correction[:3, 3]
        map.planes.planes[new] = np.column_stack([normals, offsets])
        map.planes.centroids[new] = transform_points(correction, map.planes.centroids[new])
