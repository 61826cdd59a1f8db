"""Least-squares refinement of a registered pose ``T_map_cam`` on the inliers of its
correspondences: metric residuals (:func:`refine_pose`, ``scipy.optimize.least_squares``) or
residuals shaped like the sensor's noise in image space under a Huber loss
(:func:`refine_pose_image_space`, Levenberg-Marquardt with analytic derivatives), with the
SO(3) Jacobians they need.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from jsr.geometry import cross_matrices
from jsr.pipeline.robust_loss import huber_cost
from jsr.pipeline.correspondences import depth_thresholds
from jsr.pipeline.pose_scoring import RegistrationProblem


# --------------------------------------------------------------------------------------
# Least-squares refinement
# --------------------------------------------------------------------------------------


def _exp_and_left_jacobian(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SO(3) exponential of a rotation vector and its left Jacobian."""
    angle = float(np.linalg.norm(omega))
    w = cross_matrices(omega)
    w2 = w @ w
    if angle < 1e-6:
        a, b, c = 1.0 - angle**2 / 6.0, 0.5 - angle**2 / 24.0, 1.0 / 6.0 - angle**2 / 120.0
    else:
        a = math.sin(angle) / angle
        b = (1.0 - math.cos(angle)) / angle**2
        c = (angle - math.sin(angle)) / angle**3
    eye = np.eye(3)
    return eye + a * w + b * w2, eye + b * w + c * w2


def refine_pose(
    problem: RegistrationProblem, transform: np.ndarray, masks: list[np.ndarray]
) -> np.ndarray | None:
    """Least squares on the inliers; the pose is ``[Exp(w) R0 | t0 + v]`` over ``x = (w, v)``."""
    m3, m2, mp = masks
    p, q, s3 = problem.p[m3], problem.q[m3], problem.threshold3[m3]
    bearings, x2 = problem.bearings[m2], problem.x2[m2]
    pc, pm = problem.planes_c[mp], problem.planes_m[mp]
    rows = 3 * len(p) + 3 * len(x2) + 4 * len(pc)
    if rows < 6:
        return None
    r0, t0 = transform[:3, :3], transform[:3, 3]
    # 2D thresholds depend on the landmark depth; fixed at the start pose for a smooth cost.
    depth = ((x2 - t0) @ r0)[:, 2]
    s2 = depth_thresholds(depth, problem.noise)
    projector = np.eye(3) - bearings[:, :, None] * bearings[:, None, :]
    sa, sd = problem.angle_threshold, problem.distance_threshold

    def pose(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rotation_increment, left_jacobian = _exp_and_left_jacobian(x[:3])
        return rotation_increment @ r0, t0 + x[3:], left_jacobian

    def residuals(x: np.ndarray) -> np.ndarray:
        rotation, translation, _ = pose(x)
        parts = [((p @ rotation.T + translation - q) / s3[:, None]).ravel()]
        camera = (x2 - translation) @ rotation
        parts.append((np.einsum("bij,bj->bi", projector, camera) / s2[:, None]).ravel())
        normals = pc[:, :3] @ rotation.T
        plane = np.concatenate(
            [
                (normals - pm[:, :3]) / sa,
                ((pc[:, 3] - normals @ translation - pm[:, 3]) / sd)[:, None],
            ],
            axis=1,
        )
        parts.append(plane.ravel())
        return np.concatenate(parts)

    def jacobian(x: np.ndarray) -> np.ndarray:
        rotation, translation, left = pose(x)
        blocks = []
        if len(p):
            j = np.zeros((len(p), 3, 6))
            j[:, :, :3] = -cross_matrices(p @ rotation.T) @ left
            j[:, :, 3:] = np.eye(3)
            blocks.append((j / s3[:, None, None]).reshape(-1, 6))
        if len(x2):
            j = np.zeros((len(x2), 3, 6))
            j[:, :, :3] = rotation.T @ cross_matrices(x2 - translation) @ left
            j[:, :, 3:] = -rotation.T
            j = np.matmul(projector, j) / s2[:, None, None]
            blocks.append(j.reshape(-1, 6))
        if len(pc):
            normals = pc[:, :3] @ rotation.T
            d_normals = -cross_matrices(normals) @ left  # (C, 3, 3)
            j = np.zeros((len(pc), 4, 6))
            j[:, :3, :3] = d_normals / sa
            j[:, 3, :3] = -np.einsum("i,cij->cj", translation, d_normals) / sd
            j[:, 3, 3:] = -normals / sd
            blocks.append(j.reshape(-1, 6))
        return np.concatenate(blocks, axis=0)

    solution = least_squares(
        residuals, np.zeros(6), jac=jacobian, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=50
    )
    if not np.all(np.isfinite(solution.x)):
        return None
    rotation, translation, _ = pose(solution.x)
    refined = np.eye(4)
    refined[:3, :3] = rotation
    refined[:3, 3] = translation
    return refined


def refine_pose_image_space(
    problem: RegistrationProblem,
    transform: np.ndarray,
    masks: list[np.ndarray],
    focal_length: float,
) -> np.ndarray | None:
    """Least squares on the inliers with residuals shaped like the sensor's noise
    (:func:`image_space_terms`), minimised with a Huber loss (scale 2 sigma) by
    :func:`minimise_huber` from ``transform``. None when too few residuals constrain the pose."""
    linearised = image_space_terms(problem, transform, masks, focal_length)
    if linearised is None:
        return None
    refined = minimise_huber(linearised, transform[:3, :3], transform[:3, 3], HUBER_SCALE, max_iterations=50)
    if refined is None:
        return None
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = refined
    return pose


def image_space_terms(
    problem: RegistrationProblem,
    transform: np.ndarray,
    masks: list[np.ndarray],
    focal_length: float,
) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None:
    """The residuals of the inliers ``masks`` as a function ``linearised(rotation (3, 3),
    translation (3,)) -> (residuals (M,), jacobian (M, 6))`` of the pose ``T_map_cam``; None
    when they are fewer than six.

    A structured-light depth camera measures the image position of a point far better than its
    depth: about ``pixel_sigma`` pixels across the ray against ``sigma_Z = c Z^2`` along it. An
    isotropic 3D distance weighs both by ``sigma_Z`` and throws away most of the lateral
    information, which lets far-away scenes jitter. Here each 3D-3D pair gives two
    reprojection residuals (landmark projected with the pose vs the measured pixel, in units of
    ``pixel_sigma``) and one depth residual (in units of the combined depth noise of measurement
    and landmark); each 2D-3D pair gives two reprojection residuals; planes as in
    :func:`refine_pose`. Inliers kept by the depth fallback at ``transform`` (see
    :mod:`jsr.pipeline.pose_scoring`) get no depth residual.
    """
    m3, m2, mp = masks
    p, q = problem.p[m3], problem.q[m3]
    bearings, x2 = problem.bearings[m2], problem.x2[m2]
    pc, pm = problem.planes_c[mp], problem.planes_m[mp]
    if 3 * len(p) + 2 * len(x2) + 4 * len(pc) < 6:
        return None
    r0, t0 = transform[:3, :3], transform[:3, 3]
    angular_sigma = problem.noise.pixel_sigma / focal_length
    measured_uv = p[:, :2] / p[:, 2:3]
    bearing_uv = bearings[:, :2] / bearings[:, 2:3]
    depth_sigma = np.sqrt(2.0) * np.maximum(
        problem.noise.sigma_z_coefficient * p[:, 2] ** 2, problem.noise.min_inlier_threshold / problem.noise.inlier_sigmas
    )
    sa, sd = problem.angle_threshold, problem.distance_threshold
    # Inliers by the depth fallback (depth off by more than the threshold at the start pose)
    # constrain the pose through their reprojection only.
    depth_weight = (np.abs(((q - t0) @ r0)[:, 2] - p[:, 2]) < problem.threshold3[m3]).astype(float)

    angular_weight = 1.0 / angular_sigma
    depth_scale = depth_weight / depth_sigma

    def linearised(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals ``(M,)`` at the pose and their Jacobian ``(M, 6)`` with respect to the
        increment ``[w, dt]`` that maps it to ``(Exp(w) rotation, translation + dt)``."""
        parts, jacobians = [], []
        for targets, observed in ((q, measured_uv), (x2, bearing_uv)):
            relative = targets - translation
            landmarks = relative @ rotation  # in the camera frame: R^T (X - t)
            z = np.maximum(landmarks[:, 2], 1e-6)
            # d landmark / d w = R^T [X - t]_x, d landmark / d t = -R^T
            d_landmark = np.concatenate([np.einsum("ji,njk->nik", rotation, cross_matrices(relative)),
                                         np.broadcast_to(-rotation.T, (len(z), 3, 3))], axis=2)
            projected = landmarks[:, :2] / z[:, None]
            d_projected = (d_landmark[:, :2] - projected[:, :, None] * d_landmark[:, 2:3]) / z[:, None, None]
            parts.append(((projected - observed) * angular_weight).ravel())
            jacobians.append((d_projected * angular_weight).reshape(-1, 6))
            if targets is q:
                parts.append(depth_scale * (landmarks[:, 2] - p[:, 2]))
                jacobians.append(depth_scale[:, None] * d_landmark[:, 2])
        normals = pc[:, :3] @ rotation.T
        parts.append(((normals - pm[:, :3]) / sa).ravel())
        d_normals = np.zeros((len(pc), 3, 6))
        d_normals[:, :, :3] = -cross_matrices(normals)  # d (Exp(w) n) / d w = -[n]_x
        jacobians.append(d_normals.reshape(-1, 6) / sa)
        parts.append((pc[:, 3] - normals @ translation - pm[:, 3]) / sd)
        d_offsets = np.concatenate([np.cross(translation, normals), -normals], axis=1)
        jacobians.append(d_offsets / sd)
        return np.concatenate(parts), np.concatenate(jacobians, axis=0)

    return linearised


HUBER_SCALE = 2.0  # residuals (in sigmas) beyond this weigh linearly, not quadratically


def minimise_huber(linearised: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
                   rotation: np.ndarray, translation: np.ndarray, scale: float,
                   max_iterations: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose ``(rotation (3, 3), translation (3,))`` minimising the Huber cost (``scale``) of
    ``linearised(rotation, translation) -> (residuals (M,), jacobian (M, 6))``: Levenberg-
    Marquardt on iteratively reweighted normal equations (the curvature model of
    :func:`~jsr.pipeline.robust_loss.huber_loss`), each step ``[w, dt]`` applied as
    ``(Exp(w) rotation, translation + dt)``. None if the cost is not finite.

    Written out rather than ``scipy.optimize.least_squares``: with six unknowns and analytic
    derivatives, its finite differences and per-step SVD of the ``(M, 6)`` Jacobian were a
    quarter of the whole pipeline's run time (synth_two, 60 frames)."""
    residuals, jacobian = linearised(rotation, translation)
    cost = huber_cost(residuals, scale)
    if not np.isfinite(cost):
        return None
    damping = 1e-3
    for _ in range(max_iterations):
        magnitude = np.abs(residuals)
        weights = np.where(magnitude <= scale, 1.0, scale / np.maximum(magnitude, 1e-300))
        normal = jacobian.T @ (weights[:, None] * jacobian)
        gradient = jacobian.T @ (weights * residuals)
        if not np.all(np.isfinite(normal)) or not np.all(np.isfinite(gradient)):
            return None
        improved = False
        while damping < 1e10:
            damped = normal + damping * np.diag(np.maximum(np.diag(normal), 1e-12))
            try:
                step = -np.linalg.solve(damped, gradient)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            new_rotation = Rotation.from_rotvec(step[:3]).as_matrix() @ rotation
            new_translation = translation + step[3:]
            new_residuals, new_jacobian = linearised(new_rotation, new_translation)
            new_cost = huber_cost(new_residuals, scale)
            if np.isfinite(new_cost) and new_cost <= cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break
        converged = cost - new_cost <= 1e-10 * max(cost, 1e-12) or np.linalg.norm(step) <= 1e-10
        rotation, translation = new_rotation, new_translation
        residuals, jacobian, cost = new_residuals, new_jacobian, new_cost
        damping = max(damping / 10.0, 1e-9)
        if converged:
            break
    return rotation, translation


__all__ = ["HUBER_SCALE", "image_space_terms", "minimise_huber", "refine_pose", "refine_pose_image_space"]
