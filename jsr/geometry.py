"""Rigid-body maths, pinhole projection and the depth noise model.

Conventions used across jsr:

* ``T_a_b`` is a ``(4, 4)`` float64 homogeneous transform mapping coordinates in frame
  ``b`` to frame ``a`` (``T_w_c``: camera-to-world, ``T_w_o``: object-to-world).
* Points are ``(N, 3)`` float64 arrays, one point per row.
* Camera frames follow the computer-vision convention: x right, y down, z forward.
* Quaternions are ``(qx, qy, qz, qw)``, the TUM RGB-D order.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

KINECT_SIGMA_Z_COEFFICIENT = 1.425e-3
"""Kinect v1 axial depth noise: ``sigma_Z = 1.425e-3 * Z**2`` metres (Khoshelham and Elberink 2012)."""


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Build a ``(4, 4)`` transform from a ``(3, 3)`` rotation and a ``(3,)`` translation."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = np.asarray(translation, dtype=float).reshape(3)
    return transform


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid ``(4, 4)`` transform (or a ``(N, 4, 4)`` stack), using R^T."""
    transform = np.asarray(transform, dtype=float)
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    inverse = np.zeros_like(transform)
    inverse[..., :3, :3] = rotation_t
    inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, transform[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` to ``(N, 3)`` points given in frame b; returns ``(N, 3)`` points in frame a."""
    points = np.asarray(points, dtype=float)
    return points @ transform[:3, :3].T + transform[:3, 3]


def transform_planes(T_a_b: np.ndarray, planes_b: np.ndarray) -> np.ndarray:
    """Planes ``(P, 4)`` ``[n, d]`` (``n . x + d = 0``) in frame b to frame a.

    Each plane is first scaled to a unit normal (``n`` and ``d`` alike), then
    ``n_a = R n_b`` and ``d_a = d_b - n_a . t``.
    """
    planes_b = np.asarray(planes_b, dtype=float).reshape(-1, 4)
    planes_b = planes_b / np.linalg.norm(planes_b[:, :3], axis=1, keepdims=True)
    normals = planes_b[:, :3] @ T_a_b[:3, :3].T
    return np.column_stack([normals, planes_b[:, 3] - normals @ T_a_b[:3, 3]])


def rotation_angle(rotation: np.ndarray) -> np.ndarray:
    """Angle in radians of a ``(3, 3)`` rotation or a ``(N, 3, 3)`` stack, numerically safe."""
    trace = np.trace(rotation, axis1=-2, axis2=-1)
    return np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))


def pose_from_tum(values: np.ndarray) -> np.ndarray:
    """``(..., 7)`` rows ``tx ty tz qx qy qz qw`` to ``(..., 4, 4)`` transforms."""
    values = np.asarray(values, dtype=float)
    flat = values.reshape(-1, 7)
    poses = np.tile(np.eye(4), (len(flat), 1, 1))
    if len(flat):
        poses[:, :3, :3] = Rotation.from_quat(flat[:, 3:7]).as_matrix()
        poses[:, :3, 3] = flat[:, :3]
    return poses.reshape(values.shape[:-1] + (4, 4))


def pose_to_tum(poses: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` transforms to ``(..., 7)`` rows ``tx ty tz qx qy qz qw`` (qw >= 0)."""
    poses = np.asarray(poses, dtype=float)
    flat = poses.reshape(-1, 4, 4)
    rows = np.zeros((len(flat), 7))
    if len(flat):
        quats = Rotation.from_matrix(flat[:, :3, :3]).as_quat()
        # q and -q are the same rotation; a fixed sign makes files comparable line by line.
        quats[quats[:, 3] < 0] *= -1.0
        rows[:, :3] = flat[:, :3, 3]
        rows[:, 3:] = quats
    return rows.reshape(poses.shape[:-2] + (7,))


def cross_matrices(vectors: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` matrices of the cross product with ``vectors`` ``(..., 3)``:
    ``cross_matrices(v) @ u == np.cross(v, u)``."""
    vectors = np.asarray(vectors, dtype=float)
    out = np.zeros(vectors.shape[:-1] + (3, 3))
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def rotation_about_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """``(3, 3)`` rotation of ``angle`` radians about ``axis`` (any length > 0)."""
    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world ``T_w_c`` of a camera at ``eye`` looking at ``target``.

    The camera z axis points at the target and its y axis (image down) is as close as
    possible to ``-up``.
    """
    eye = np.asarray(eye, dtype=float)
    forward = np.asarray(target, dtype=float) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=float))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return make_transform(np.column_stack([right, down, forward]), eye)


def umeyama_alignment(
    source: np.ndarray, target: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, float]:
    """Least-squares similarity/rigid transform mapping ``source`` onto ``target``.

    Umeyama (1991). ``source`` and ``target`` are ``(N, 3)`` corresponding points.
    Returns ``(T_target_source, scale)``; ``T`` is a ``(4, 4)`` rigid transform and the
    full map is ``x -> scale * R x + t`` (``scale`` is 1.0 unless ``with_scale``).
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError("umeyama_alignment needs two (N, 3) arrays of the same shape")
    if len(source) < 3:
        raise ValueError("umeyama_alignment needs at least 3 point pairs")
    mean_source = source.mean(axis=0)
    mean_target = target.mean(axis=0)
    centred_source = source - mean_source
    centred_target = target - mean_target
    covariance = centred_target.T @ centred_source / len(source)
    u, singular_values, vt = np.linalg.svd(covariance)
    sign_fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign_fix[2, 2] = -1.0  # reflection otherwise
    rotation = u @ sign_fix @ vt
    scale = 1.0
    if with_scale:
        source_variance = (centred_source**2).sum() / len(source)
        scale = float(np.trace(np.diag(singular_values) @ sign_fix) / source_variance)
    translation = mean_target - scale * rotation @ mean_source
    return make_transform(rotation, translation), scale


def depth_noise_sigma(depth: np.ndarray, coefficient: float = KINECT_SIGMA_Z_COEFFICIENT) -> np.ndarray:
    """Axial depth noise standard deviation in metres: ``coefficient * Z**2``."""
    depth = np.asarray(depth, dtype=float)
    return coefficient * depth**2


def inlier_threshold(
    depth: np.ndarray,
    coefficient: float = KINECT_SIGMA_Z_COEFFICIENT,
    sigma_multiple: float = 3.0,
    minimum: float = 0.01,
) -> np.ndarray:
    """The paper's RANSAC inlier threshold ``sigma = max(1 cm, 3 sigma_Z(Z))`` in metres."""
    return np.maximum(minimum, sigma_multiple * depth_noise_sigma(depth, coefficient))


def backproject_pixels(
    u: np.ndarray, v: np.ndarray, depth: np.ndarray, fx: float, fy: float, cx: float, cy: float
) -> np.ndarray:
    """Pixel coordinates ``(N,)`` with depth ``(N,)`` in metres to ``(N, 3)`` camera-frame points."""
    depth = np.asarray(depth, dtype=float)
    x = (np.asarray(u, dtype=float) - cx) / fx * depth
    y = (np.asarray(v, dtype=float) - cy) / fy * depth
    return np.column_stack([x, y, depth])


def backproject_depth(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Organized point cloud: ``(H, W)`` depth in metres to ``(H, W, 3)`` camera-frame points.

    Invalid pixels (depth 0) give the point (0, 0, 0).
    """
    height, width = depth.shape
    u = np.arange(width, dtype=np.float64)[None, :]
    v = np.arange(height, dtype=np.float64)[:, None]
    z = depth.astype(np.float64)
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)


def project_points(points: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``(N, 3)`` camera-frame points to ``(N, 2)`` pixel coordinates (u, v). z must be > 0."""
    points = np.asarray(points, dtype=float)
    z = points[:, 2]
    return np.column_stack([fx * points[:, 0] / z + cx, fy * points[:, 1] / z + cy])
