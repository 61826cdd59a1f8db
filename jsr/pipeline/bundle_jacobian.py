"""The analytic Jacobian of bundle adjustment's residuals (:mod:`jsr.pipeline.bundle`).

``problem`` is a :class:`~jsr.pipeline.bundle.BundleProblem`; its residual vector stacks, per
observation, a block of 3 (3D point: reprojection u, v and depth), 2 (2D point: pixel u, v)
or 4 (plane: normal and offset) rows. Each block depends on its keyframe's 6 parameters (if
the keyframe is free) and its landmark's 3, so the Jacobian is stored as those dense blocks
in a sparse matrix. Why analytic: finite differences cost a dozen residual evaluations and a
sparse assembly per Jacobian, about half of a solve.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix

from jsr.geometry import cross_matrices


def left_jacobians(rotvecs: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` left Jacobians of SO(3) at rotation vectors ``(N, 3)``:
    ``exp(w + dw) = exp(J_l(w) dw) exp(w)`` to first order."""
    angle = np.linalg.norm(rotvecs, axis=1)
    small = angle < 1e-4
    safe = np.where(small, 1.0, angle)
    # series of (1 - cos a) / a^2 and (a - sin a) / a^3 below 1e-4 rad
    first = np.where(small, 0.5 - angle**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    second = np.where(small, 1.0 / 6.0 - angle**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    skew = cross_matrices(rotvecs)
    return np.eye(3) + first[:, None, None] * skew + second[:, None, None] * (skew @ skew)


def block_entries(rows_per_obs: int, row_offset: int, obs_count: int, col_starts: np.ndarray, cols_per_block: int):
    """COO (row, col) entries of dense ``rows_per_obs x cols_per_block`` blocks, one per observation."""
    rows = row_offset + np.arange(obs_count)[:, None] * rows_per_obs + np.arange(rows_per_obs)[None, :]
    cols = col_starts[:, None] + np.arange(cols_per_block)[None, :]
    rows = np.broadcast_to(rows[:, :, None], (obs_count, rows_per_obs, cols_per_block))
    cols = np.broadcast_to(cols[:, None, :], (obs_count, rows_per_obs, cols_per_block))
    return rows.ravel(), cols.ravel()


def jacobian_entries(problem) -> tuple[list, list]:
    """COO rows and columns of the Jacobian, per block in the order :func:`analytic_jacobian`
    fills them: for each observation kind, its landmark blocks, then its free keyframes'."""
    free_count = problem.num_free_keyframes
    point_base = 6 * free_count
    plane_base = point_base + 3 * len(problem.point_ids)
    rows, cols = [], []
    row_offset = 0
    for count, width, keyframe, landmark_cols in (
        (len(problem.obs3_keyframe), 3, problem.obs3_keyframe, point_base + 3 * problem.obs3_point),
        (len(problem.obs2_keyframe), 2, problem.obs2_keyframe, point_base + 3 * problem.obs2_point),
        (len(problem.obsp_keyframe), 4, problem.obsp_keyframe, plane_base + 3 * problem.obsp_plane),
    ):
        if count == 0:
            continue
        r, c = block_entries(width, row_offset, count, landmark_cols, 3)
        rows.append(r)
        cols.append(c)
        block = problem.free_index[keyframe]
        free = block >= 0
        r, c = block_entries(width, row_offset, count, 6 * block, 6)
        mask = np.repeat(free, width * 6)
        rows.append(r[mask])
        cols.append(c[mask])
        row_offset += width * count
    return rows, cols


def _sparse(problem, rows: list, cols: list, data: list) -> csr_matrix:
    cat = lambda parts, dtype: np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)
    return coo_matrix((cat(data, float), (cat(rows, np.int64), cat(cols, np.int64))),
                      shape=(problem.num_residuals, problem.num_parameters)).tocsr()


def jacobian_sparsity(problem) -> csr_matrix:
    """``(num_residuals, num_parameters)`` 0/1 pattern: a residual block depends on its
    keyframe's 6 parameters (if free) and its landmark's 3."""
    rows, cols = jacobian_entries(problem)
    return _sparse(problem, rows, cols, [np.ones(len(r)) for r in rows])


def analytic_jacobian(problem, x: np.ndarray) -> csr_matrix:
    """``(num_residuals, num_parameters)`` Jacobian of ``problem.residuals`` at ``x``.

    Rotations are perturbed on the left: ``exp(w + dw) R0 = exp(J_l(w) dw) exp(w) R0``
    with ``J_l`` the left Jacobian of SO(3), and ``exp(d) R`` moves a vector ``v`` by
    ``d x R v``."""
    free = problem.free_index >= 0
    pose_x = x[: 6 * problem.num_free_keyframes].reshape(-1, 6)
    rotations, translations, positions, planes = problem.unpack(x)
    left = np.tile(np.eye(3), (len(problem.poses), 1, 1))
    left[free] = left_jacobians(pose_x[:, :3])
    blocks = []  # (landmark blocks (n, width, 3), pose blocks (n, width, 6), keyframe slots (n,)) per kind

    def point_blocks(keyframe, point, d_local_fn):
        # camera point of landmark X: local = R^T (X - t); d local / dX = R^T,
        # d local / dt = -R^T, d local / dw = R^T [X - t]_x J_l(w)
        offset = positions[point] - translations[keyframe]
        transposed = rotations[keyframe].transpose(0, 2, 1)
        local = np.einsum("nij,nj->ni", transposed, offset)
        d_point = d_local_fn(local) @ transposed
        d_rotation = d_point @ cross_matrices(offset) @ left[keyframe]
        return d_point, np.concatenate([d_rotation, -d_point], axis=2), keyframe

    if len(problem.obs3_keyframe):
        scale = 0.5 * (problem.intrinsics[0, 0] + problem.intrinsics[1, 1]) * problem.pixel_weight

        def d_local3(local):  # rows: reprojection u, v, depth
            z = np.maximum(local[:, 2], 1e-3)
            d = np.zeros((len(local), 3, 3))
            d[:, 0, 0] = d[:, 1, 1] = scale / z
            d[:, 0, 2] = -scale * local[:, 0] / z**2
            d[:, 1, 2] = -scale * local[:, 1] / z**2
            d[:, 2, 2] = problem.obs3_weight
            return d

        blocks.append(point_blocks(problem.obs3_keyframe, problem.obs3_point, d_local3))
    if len(problem.obs2_keyframe):
        f = problem.intrinsics

        def d_local2(local):  # rows: pixel u, v
            z = np.maximum(local[:, 2], 1e-3)
            d = np.zeros((len(local), 2, 3))
            d[:, 0, 0] = f[0, 0] / z
            d[:, 0, 1] = f[0, 1] / z
            d[:, 0, 2] = -(f[0, 0] * local[:, 0] + f[0, 1] * local[:, 1]) / z**2
            d[:, 1, 1] = f[1, 1] / z
            d[:, 1, 2] = -f[1, 1] * local[:, 1] / z**2
            return d * problem.pixel2d_weight

        blocks.append(point_blocks(problem.obs2_keyframe, problem.obs2_point, d_local2))
    if len(problem.obsp_keyframe):
        # residual: (R n_c - n_L) w_n and (d_c - (R n_c) . t - d_L) w_d,
        # with n_L = exp(B a) n0 and d_L = d0 + dd
        k, count = problem.obsp_keyframe, len(problem.obsp_keyframe)
        normals = np.einsum("nij,nj->ni", rotations[k], problem.obsp_camera[:, :3])
        d_normal = -cross_matrices(normals) @ left[k]  # d (R n_c) / dw
        pose = np.zeros((count, 4, 6))
        pose[:, :3, :3] = d_normal * problem.normal_weight
        pose[:, 3, :3] = -np.einsum("ni,nij->nj", translations[k], d_normal) * problem.offset_weight
        pose[:, 3, 3:] = -normals * problem.offset_weight
        plane_x = x[6 * problem.num_free_keyframes + 3 * len(problem.point_ids):].reshape(-1, 3)
        rotvecs = np.einsum("qij,qj->qi", problem._bases, plane_x[:, :2])
        d_landmark_normal = cross_matrices(planes[:, :3]) @ left_jacobians(rotvecs) @ problem._bases  # -d n_L / da
        landmark = np.zeros((count, 4, 3))
        landmark[:, :3, :2] = d_landmark_normal[problem.obsp_plane] * problem.normal_weight
        landmark[:, 3, 2] = -problem.offset_weight
        blocks.append((landmark, pose, k))

    rows, cols = jacobian_entries(problem)
    data = []
    for landmark, pose, keyframe in blocks:
        data.append(landmark.ravel())
        data.append(pose[free[keyframe]].ravel())
    return _sparse(problem, rows, cols, data)
