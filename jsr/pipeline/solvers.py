"""Minimal pose solvers for mixed point/plane registration (Pinpoint SLAM's minimal sets).

Every solver estimates ``T_map_cam``: the ``(4, 4)`` rigid transform mapping camera-frame
coordinates of the current frame into the map frame, ``x_map = R x_cam + t``.

Inputs are correspondences between frame measurements and map landmarks:

* a *3D point* pair: a camera-frame point ``p`` and a map point ``q`` (``q = R p + t``);
* a *2D point* pair: a unit bearing ray ``b`` in the camera and a map point ``X``
  (``R^T (X - t) = lambda b`` for some depth ``lambda > 0``);
* a *plane* pair: ``[n, d]`` in the camera and ``[m, e]`` in the map, planes ``n . x + d = 0``
  with unit normals (``m = R n`` and ``e = d - m . t``).

All point-only solvers follow one scheme: recover the camera-frame positions of the three
points (known for 3D points, the unknown depths of 2D points from the rigidity of the
triangle), then align the two triangles with Kabsch. The plane solvers take the rotation from
the normals (Wahba's problem, with point directions where needed) and the translation from a
small linear least-squares system.

Each solver has a batched form ``*_batch`` that takes ``H`` samples stacked along the first
axis and returns ``(transforms (K, 4, 4), sample_index (K,))``: every candidate with the
sample it came from (a sample can give 0 to 4 candidates). RANSAC uses these to build a batch
of hypotheses with a handful of numpy calls. The plain forms take one sample and return a
list of candidate transforms, possibly empty for degenerate input. On noise-free data every
solver is exact to numerical precision.
"""

from __future__ import annotations

import numpy as np

MIN_SINE = 1e-3
"""Default degeneracy tolerance: the sine of the smallest angle that still counts as "not
parallel" (normals, point directions) and the relative thinness below which a triangle
counts as collinear."""

_EMPTY = (np.zeros((0, 4, 4)), np.zeros(0, dtype=np.int64))


# --------------------------------------------------------------------------------------
# Small batched linear algebra
# --------------------------------------------------------------------------------------


def _as_batch(array: np.ndarray, item_ndim: int) -> np.ndarray:
    array = np.asarray(array, dtype=float)
    if array.ndim == item_ndim:
        return array[None]
    return array


def _transforms(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    out = np.zeros(rotations.shape[:-2] + (4, 4))
    out[..., :3, :3] = rotations
    out[..., :3, 3] = translations
    out[..., 3, 3] = 1.0
    return out


def _rotation_from_correlation(correlation: np.ndarray) -> np.ndarray:
    """Rotations ``R`` maximising ``trace(R^T M)`` for a batch ``M`` (H, 3, 3) (Wahba / Kabsch).

    ``M = sum_i w_i target_i source_i^T``; a rank-2 ``M`` (two independent directions, or a
    triangle) still gives a unique rotation thanks to the determinant fix.
    """
    u, _, vt = np.linalg.svd(correlation)
    sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    sign[sign == 0] = 1.0
    u = u.copy()
    u[:, :, 2] *= sign[:, None]
    return u @ vt


def kabsch_batch(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Rigid transforms ``T (H, 4, 4)`` with ``target ~ T source`` for ``(H, n, 3)`` point sets.

    Weighted least squares (Kabsch/Umeyama without scale), vectorised over the batch.
    Degeneracy is not checked here (see :func:`triangle_is_valid`).
    """
    source = _as_batch(source, 2)
    target = _as_batch(target, 2)
    if weights is None:
        weights = np.ones(source.shape[:2])
    weights = np.asarray(weights, dtype=float)
    weights = weights / weights.sum(axis=1, keepdims=True)
    mean_source = np.einsum("hn,hni->hi", weights, source)
    mean_target = np.einsum("hn,hni->hi", weights, target)
    correlation = np.einsum(
        "hn,hni,hnj->hij", weights, target - mean_target[:, None], source - mean_source[:, None]
    )
    rotations = _rotation_from_correlation(correlation)
    translations = mean_target - np.einsum("hij,hj->hi", rotations, mean_source)
    return _transforms(rotations, translations)


def triangle_is_valid(points: np.ndarray, min_sine: float = MIN_SINE) -> np.ndarray:
    """``(H,)`` True where the ``(H, 3, 3)`` point triples are not (nearly) collinear.

    The measure is ``2 * area / longest_side**2`` (about the sine of the smallest angle).
    """
    points = _as_batch(points, 2)
    e1 = points[:, 1] - points[:, 0]
    e2 = points[:, 2] - points[:, 0]
    e3 = points[:, 2] - points[:, 1]
    longest = np.max(
        np.stack([np.einsum("hi,hi->h", e, e) for e in (e1, e2, e3)], axis=1), axis=1
    )
    twice_area = np.linalg.norm(np.cross(e1, e2), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        thinness = np.where(longest > 0, twice_area / longest, 0.0)
    return thinness > min_sine


def _solve3x3(matrices: np.ndarray, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched 3x3 solve by the adjugate; returns (solutions, ok) and never raises."""
    a = matrices
    cof = np.empty_like(a)
    cof[:, 0, 0] = a[:, 1, 1] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 1]
    cof[:, 0, 1] = a[:, 1, 2] * a[:, 2, 0] - a[:, 1, 0] * a[:, 2, 2]
    cof[:, 0, 2] = a[:, 1, 0] * a[:, 2, 1] - a[:, 1, 1] * a[:, 2, 0]
    cof[:, 1, 0] = a[:, 0, 2] * a[:, 2, 1] - a[:, 0, 1] * a[:, 2, 2]
    cof[:, 1, 1] = a[:, 0, 0] * a[:, 2, 2] - a[:, 0, 2] * a[:, 2, 0]
    cof[:, 1, 2] = a[:, 0, 1] * a[:, 2, 0] - a[:, 0, 0] * a[:, 2, 1]
    cof[:, 2, 0] = a[:, 0, 1] * a[:, 1, 2] - a[:, 0, 2] * a[:, 1, 1]
    cof[:, 2, 1] = a[:, 0, 2] * a[:, 1, 0] - a[:, 0, 0] * a[:, 1, 2]
    cof[:, 2, 2] = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    det = np.einsum("hj,hj->h", a[:, 0], cof[:, 0])
    scale = np.abs(a).reshape(len(a), -1).max(axis=1) ** 3 if len(a) else np.zeros(0)
    ok = np.abs(det) > 1e-13 * np.maximum(scale, 1e-300)
    safe_det = np.where(ok, det, 1.0)
    # inverse = adj / det, adj = cof^T
    solutions = np.einsum("hji,hj->hi", cof, vectors) / safe_det[:, None]
    return np.where(ok[:, None], solutions, 0.0), ok


def _real_roots(coefficients: np.ndarray, imag_tol: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Roots of monic polynomials, batched: ``coefficients (H, n)`` are ``c`` in
    ``x^n + c[0] x^(n-1) + ... + c[n-1]``. Returns ``(roots (H, n) real parts, is_real (H, n))``.
    """
    h, n = coefficients.shape
    companion = np.zeros((h, n, n))
    companion[:, 0, :] = -coefficients
    if n > 1:
        companion[:, np.arange(1, n), np.arange(n - 1)] = 1.0
    finite = np.all(np.isfinite(companion), axis=(1, 2))
    companion[~finite] = 0.0
    roots = np.linalg.eigvals(companion)
    is_real = (np.abs(roots.imag) <= imag_tol * (1.0 + np.abs(roots.real))) & finite[:, None]
    return roots.real, is_real


# --------------------------------------------------------------------------------------
# Points
# --------------------------------------------------------------------------------------


def solve_points3d_batch(
    frame_points: np.ndarray, map_points: np.ndarray, min_sine: float = MIN_SINE
) -> tuple[np.ndarray, np.ndarray]:
    """Three 3D-3D point pairs per sample: ``(H, 3, 3)`` camera points and map points."""
    frame_points = _as_batch(frame_points, 2)
    map_points = _as_batch(map_points, 2)
    valid = triangle_is_valid(frame_points, min_sine) & triangle_is_valid(map_points, min_sine)
    index = np.flatnonzero(valid)
    if len(index) == 0:
        return _EMPTY
    return kabsch_batch(frame_points[index], map_points[index]), index


def solve_p3p_batch(
    frame_bearings: np.ndarray, map_points: np.ndarray, min_sine: float = MIN_SINE
) -> tuple[np.ndarray, np.ndarray]:
    """Three 2D-3D pairs per sample (P3P, Grunert's quartic; up to 4 candidates a sample).

    ``frame_bearings`` ``(H, 3, 3)`` unit rays in the camera, ``map_points`` ``(H, 3, 3)``.
    The depths along the rays come from the quartic of Grunert (1841) in the form reviewed by
    Haralick et al. (1994), are polished by Gauss-Newton on the three law-of-cosines equations,
    and the camera is then found by aligning the two triangles.
    """
    bearings = _as_batch(frame_bearings, 2)
    bearings = bearings / np.linalg.norm(bearings, axis=2, keepdims=True)
    world = _as_batch(map_points, 2)
    valid = triangle_is_valid(world, min_sine) & triangle_is_valid(bearings, min_sine)
    index = np.flatnonzero(valid)
    if len(index) == 0:
        return _EMPTY
    j, x = bearings[index], world[index]
    a2 = np.einsum("hi,hi->h", x[:, 1] - x[:, 2], x[:, 1] - x[:, 2])
    b2 = np.einsum("hi,hi->h", x[:, 0] - x[:, 2], x[:, 0] - x[:, 2])
    c2 = np.einsum("hi,hi->h", x[:, 0] - x[:, 1], x[:, 0] - x[:, 1])
    ca = np.einsum("hi,hi->h", j[:, 1], j[:, 2])
    cb = np.einsum("hi,hi->h", j[:, 0], j[:, 2])
    cg = np.einsum("hi,hi->h", j[:, 0], j[:, 1])
    amc = (a2 - c2) / b2
    apc = (a2 + c2) / b2
    coeffs = np.stack(
        [
            (amc - 1.0) ** 2 - 4.0 * c2 / b2 * ca**2,
            4.0 * (amc * (1.0 - amc) * cb - (1.0 - apc) * ca * cg + 2.0 * c2 / b2 * ca**2 * cb),
            2.0
            * (
                amc**2
                - 1.0
                + 2.0 * amc**2 * cb**2
                + 2.0 * (b2 - c2) / b2 * ca**2
                - 4.0 * apc * ca * cb * cg
                + 2.0 * (b2 - a2) / b2 * cg**2
            ),
            4.0 * (-amc * (1.0 + amc) * cb + 2.0 * a2 / b2 * cg**2 * cb - (1.0 - apc) * ca * cg),
            (1.0 + amc) ** 2 - 4.0 * a2 / b2 * cg**2,
        ],
        axis=1,
    )
    lead = coeffs[:, 0]
    ok_lead = np.abs(lead) > 1e-12 * np.abs(coeffs).max(axis=1)
    monic = coeffs[:, 1:] / np.where(ok_lead, lead, 1.0)[:, None]
    v, is_real = _real_roots(monic, imag_tol=1e-5)
    is_real &= ok_lead[:, None]
    # u from v (Haralick et al. 1994), then the distance along the first ray.
    denominator = 2.0 * (cg[:, None] - v * ca[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (
            (-1.0 + amc[:, None]) * v**2 - 2.0 * amc[:, None] * cb[:, None] * v + 1.0 + amc[:, None]
        ) / denominator
        s1_sq = b2[:, None] / (1.0 + v**2 - 2.0 * v * cb[:, None])
    usable = is_real & (np.abs(denominator) > 1e-12) & (s1_sq > 0) & (v > 0) & (u > 0)
    sample, root = np.nonzero(usable)
    if len(sample) == 0:
        return _EMPTY
    s1 = np.sqrt(s1_sq[sample, root])
    depths = np.stack([s1, u[sample, root] * s1, v[sample, root] * s1], axis=1)
    depths = _polish_p3p_depths(
        depths,
        np.stack([cg, cb, ca], axis=1)[sample],
        np.stack([c2, b2, a2], axis=1)[sample],
    )
    keep = np.all(np.isfinite(depths), axis=1) & np.all(depths > 0, axis=1)
    sample, depths = sample[keep], depths[keep]
    if len(sample) == 0:
        return _EMPTY
    camera_points = j[sample] * depths[:, :, None]
    return kabsch_batch(camera_points, x[sample]), index[sample]


_PAIRS = np.array([[0, 1], [0, 2], [1, 2]])


def _polish_p3p_depths(
    depths: np.ndarray, cosines: np.ndarray, squared_distances: np.ndarray, iterations: int = 3
) -> np.ndarray:
    """Gauss-Newton on ``s_i^2 + s_j^2 - 2 s_i s_j cos_ij = d_ij^2`` for pairs (01, 02, 12)."""
    rows = np.arange(3)
    for _ in range(iterations):
        si = depths[:, _PAIRS[:, 0]]
        sj = depths[:, _PAIRS[:, 1]]
        residual = si**2 + sj**2 - 2.0 * si * sj * cosines - squared_distances
        jacobian = np.zeros((len(depths), 3, 3))
        jacobian[:, rows, _PAIRS[:, 0]] = 2.0 * si - 2.0 * sj * cosines
        jacobian[:, rows, _PAIRS[:, 1]] = 2.0 * sj - 2.0 * si * cosines
        step, ok = _solve3x3(jacobian, -residual)
        depths = np.where(ok[:, None], depths + step, depths)
    return depths


def solve_2pt3d_1pt2d_batch(
    frame_points: np.ndarray,
    map_points: np.ndarray,
    frame_bearings: np.ndarray,
    map_points_2d: np.ndarray,
    min_sine: float = MIN_SINE,
) -> tuple[np.ndarray, np.ndarray]:
    """Two 3D-3D pairs and one 2D-3D pair per sample (up to 2 candidates a sample).

    ``frame_points``/``map_points`` ``(H, 2, 3)``; ``frame_bearings``/``map_points_2d`` ``(H, 3)``.
    The depth ``l`` of the 2D point must keep its distances to both 3D points:
    ``|l b - p_i|^2 = |X - q_i|^2`` (i = 1, 2). Both equations are met in the least-squares
    sense (the minima of a quartic in ``l``, found from its cubic derivative), which is exact
    on noise-free data and degrades gracefully with noise.
    """
    p = _as_batch(frame_points, 2)
    q = _as_batch(map_points, 2)
    b = _as_batch(frame_bearings, 1)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    x = _as_batch(map_points_2d, 1)
    beta = np.einsum("hi,hni->hn", b, p)  # (H, 2)
    gamma = np.einsum("hni,hni->hn", p, p) - np.einsum("hni,hni->hn", x[:, None] - q, x[:, None] - q)
    # d/dl sum_i (l^2 - 2 beta_i l + gamma_i)^2 = 0, divided by 8: monic cubic.
    cubic = np.stack(
        [
            -1.5 * beta.sum(axis=1),
            (2.0 * (beta**2).sum(axis=1) + gamma.sum(axis=1)) / 2.0,
            -(gamma * beta).sum(axis=1) / 2.0,
        ],
        axis=1,
    )
    roots, is_real = _real_roots(cubic, imag_tol=1e-6)
    # keep positive local minima (second derivative > 0)
    second = (
        (3.0 * roots**2)[..., None]
        - 6.0 * roots[..., None] * beta[:, None, :]
        + 2.0 * beta[:, None, :] ** 2
        + gamma[:, None, :]
    ).sum(axis=2)
    usable = is_real & (roots > 0) & (second > 0)
    sample, root = np.nonzero(usable)
    if len(sample) == 0:
        return _EMPTY
    depth = roots[sample, root]
    camera = np.concatenate([p[sample], (depth[:, None] * b[sample])[:, None]], axis=1)
    world = np.concatenate([q[sample], x[sample][:, None]], axis=1)
    valid = triangle_is_valid(camera, min_sine) & triangle_is_valid(world, min_sine)
    if not valid.any():
        return _EMPTY
    return kabsch_batch(camera[valid], world[valid]), sample[valid]


def solve_1pt3d_2pt2d_batch(
    frame_point: np.ndarray,
    map_point: np.ndarray,
    frame_bearings: np.ndarray,
    map_points_2d: np.ndarray,
    min_sine: float = MIN_SINE,
) -> tuple[np.ndarray, np.ndarray]:
    """One 3D-3D pair and two 2D-3D pairs per sample (up to 2 candidates a sample).

    ``frame_point``/``map_point`` ``(H, 3)``; ``frame_bearings``/``map_points_2d`` ``(H, 2, 3)``.
    Each 2D point's depth solves ``|l_j b_j - p|^2 = |X_j - q|^2`` (a quadratic; when noise
    makes it unsolvable the closest point of the ray is used). Sign combinations that keep
    both depths positive are ranked by the third rigidity constraint
    ``|l_1 b_1 - l_2 b_2| = |X_1 - X_2|`` and the best two are aligned by Kabsch.
    """
    p = _as_batch(frame_point, 1)
    q = _as_batch(map_point, 1)
    b = _as_batch(frame_bearings, 2)
    b = b / np.linalg.norm(b, axis=2, keepdims=True)
    x = _as_batch(map_points_2d, 2)
    beta = np.einsum("hni,hi->hn", b, p)  # (H, 2)
    gamma = np.einsum("hi,hi->h", p, p)[:, None] - np.einsum(
        "hni,hni->hn", x - q[:, None], x - q[:, None]
    )
    disc = np.maximum(beta**2 - gamma, 0.0)
    root = np.sqrt(disc)
    # numerically stable pair of roots of l^2 - 2 beta l + gamma = 0
    big = beta + np.where(beta >= 0, root, -root)
    with np.errstate(divide="ignore", invalid="ignore"):
        small = np.where(np.abs(big) > 0, gamma / big, 0.0)
    depth_options = np.stack([big, small], axis=2)  # (H, 2 points, 2 roots)
    combos = np.array([[0, 0], [0, 1], [1, 0], [1, 1]])
    l1 = depth_options[:, 0, combos[:, 0]]  # (H, 4)
    l2 = depth_options[:, 1, combos[:, 1]]
    usable = (l1 > 0) & (l2 > 0)
    # drop the duplicate combinations of a double root
    usable[:, 1] &= depth_options[:, 1, 1] != depth_options[:, 1, 0]
    usable[:, 2] &= depth_options[:, 0, 1] != depth_options[:, 0, 0]
    usable[:, 3] &= (depth_options[:, 0, 1] != depth_options[:, 0, 0]) & (
        depth_options[:, 1, 1] != depth_options[:, 1, 0]
    )
    # Of the sign combinations, keep the two that best meet the third rigidity constraint.
    pair = l1[..., None] * b[:, None, 0] - l2[..., None] * b[:, None, 1]  # (H, 4, 3)
    coupling = np.abs(
        np.linalg.norm(pair, axis=2) - np.linalg.norm(x[:, 0] - x[:, 1], axis=1)[:, None]
    )
    coupling = np.where(usable, coupling, np.inf)
    rank = np.argsort(np.argsort(coupling, axis=1, kind="stable"), axis=1, kind="stable")
    usable &= rank < 2
    sample, combo = np.nonzero(usable)
    if len(sample) == 0:
        return _EMPTY
    camera = np.stack(
        [
            p[sample],
            l1[sample, combo][:, None] * b[sample, 0],
            l2[sample, combo][:, None] * b[sample, 1],
        ],
        axis=1,
    )
    world = np.concatenate([q[sample][:, None], x[sample]], axis=1)
    valid = triangle_is_valid(camera, min_sine) & triangle_is_valid(world, min_sine)
    if not valid.any():
        return _EMPTY
    return kabsch_batch(camera[valid], world[valid]), sample[valid]


# --------------------------------------------------------------------------------------
# Planes (and planes with points)
# --------------------------------------------------------------------------------------


def _unit(vectors: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return vectors / np.where(norm > 0, norm, 1.0)


def _sine(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.cross(_unit(u), _unit(v)), axis=-1)


def _least_squares_translation(rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Batched ``argmin_t |rows t - values|``: normal equations of ``(H, k, 3)`` rows."""
    normal = np.einsum("hki,hkj->hij", rows, rows)
    rhs = np.einsum("hki,hk->hi", rows, values)
    solution, _ = _solve3x3(normal, rhs)
    return solution


def solve_3planes_batch(
    frame_planes: np.ndarray, map_planes: np.ndarray, min_sine: float = MIN_SINE
) -> tuple[np.ndarray, np.ndarray]:
    """Three plane pairs per sample: ``(H, 3, 4)`` ``[n, d]`` in the camera and in the map.

    Rotation from the normals (Wahba), translation from ``(R n_k) . t = d_k - e_k``. The
    normals must span 3D: ``|n_1 . (n_2 x n_3)| > min_sine`` in both frames.
    """
    fp = _as_batch(frame_planes, 2)
    mp = _as_batch(map_planes, 2)
    nc, nm = _unit(fp[:, :, :3]), _unit(mp[:, :, :3])
    volume_c = np.abs(np.einsum("hi,hi->h", nc[:, 0], np.cross(nc[:, 1], nc[:, 2])))
    volume_m = np.abs(np.einsum("hi,hi->h", nm[:, 0], np.cross(nm[:, 1], nm[:, 2])))
    index = np.flatnonzero((volume_c > min_sine) & (volume_m > min_sine))
    if len(index) == 0:
        return _EMPTY
    nc, nm, fp, mp = nc[index], nm[index], fp[index], mp[index]
    rotations = _rotation_from_correlation(np.einsum("hki,hkj->hij", nm, nc))
    rotated = np.einsum("hij,hkj->hki", rotations, nc)
    translations = _least_squares_translation(rotated, fp[:, :, 3] - mp[:, :, 3])
    return _transforms(rotations, translations), index


def solve_2planes_1pt_batch(
    frame_planes: np.ndarray,
    map_planes: np.ndarray,
    frame_point: np.ndarray,
    map_point: np.ndarray,
    min_sine: float = MIN_SINE,
) -> tuple[np.ndarray, np.ndarray]:
    """Two plane pairs ``(H, 2, 4)`` and one 3D point pair ``(H, 3)`` per sample.

    Rotation from the two (non-parallel) normals; translation from the point and the two
    plane offsets together (linear least squares, exact on noise-free data).
    """
    fp = _as_batch(frame_planes, 2)
    mp = _as_batch(map_planes, 2)
    p = _as_batch(frame_point, 1)
    q = _as_batch(map_point, 1)
    nc, nm = _unit(fp[:, :, :3]), _unit(mp[:, :, :3])
    index = np.flatnonzero(
        (_sine(nc[:, 0], nc[:, 1]) > min_sine) & (_sine(nm[:, 0], nm[:, 1]) > min_sine)
    )
    if len(index) == 0:
        return _EMPTY
    nc, nm, fp, mp, p, q = nc[index], nm[index], fp[index], mp[index], p[index], q[index]
    rotations = _rotation_from_correlation(np.einsum("hki,hkj->hij", nm, nc))
    rotated = np.einsum("hij,hkj->hki", rotations, nc)
    rows = np.concatenate([np.broadcast_to(np.eye(3), (len(index), 3, 3)), rotated], axis=1)
    values = np.concatenate(
        [q - np.einsum("hij,hj->hi", rotations, p), fp[:, :, 3] - mp[:, :, 3]], axis=1
    )
    return _transforms(rotations, _least_squares_translation(rows, values)), index


def solve_1plane_2pts_batch(
    frame_plane: np.ndarray,
    map_plane: np.ndarray,
    frame_points: np.ndarray,
    map_points: np.ndarray,
    min_sine: float = MIN_SINE,
) -> tuple[np.ndarray, np.ndarray]:
    """One plane pair ``(H, 4)`` and two 3D point pairs ``(H, 2, 3)`` per sample.

    Rotation from the normal and the direction between the two points (which must not be
    parallel to the normal); translation from both points and the plane offset.
    """
    fp = _as_batch(frame_plane, 1)
    mp = _as_batch(map_plane, 1)
    p = _as_batch(frame_points, 2)
    q = _as_batch(map_points, 2)
    nc, nm = _unit(fp[:, :3]), _unit(mp[:, :3])
    dc, dm = p[:, 1] - p[:, 0], q[:, 1] - q[:, 0]
    long_enough = (np.linalg.norm(dc, axis=1) > 1e-9) & (np.linalg.norm(dm, axis=1) > 1e-9)
    index = np.flatnonzero(
        long_enough & (_sine(nc, dc) > min_sine) & (_sine(nm, dm) > min_sine)
    )
    if len(index) == 0:
        return _EMPTY
    nc, nm, fp, mp, p, q = nc[index], nm[index], fp[index], mp[index], p[index], q[index]
    source = np.stack([nc, _unit(dc[index])], axis=1)
    target = np.stack([nm, _unit(dm[index])], axis=1)
    rotations = _rotation_from_correlation(np.einsum("hki,hkj->hij", target, source))
    rotated_normal = np.einsum("hij,hj->hi", rotations, nc)
    eye = np.broadcast_to(np.eye(3), (len(index), 3, 3))
    rows = np.concatenate([eye, eye, rotated_normal[:, None]], axis=1)
    values = np.concatenate(
        [
            q[:, 0] - np.einsum("hij,hj->hi", rotations, p[:, 0]),
            q[:, 1] - np.einsum("hij,hj->hi", rotations, p[:, 1]),
            (fp[:, 3] - mp[:, 3])[:, None],
        ],
        axis=1,
    )
    return _transforms(rotations, _least_squares_translation(rows, values)), index


# --------------------------------------------------------------------------------------
# Single-sample forms: a list of candidate transforms
# --------------------------------------------------------------------------------------


def _as_list(result: tuple[np.ndarray, np.ndarray]) -> list[np.ndarray]:
    return [transform for transform in result[0]]


def solve_points3d(frame_points: np.ndarray, map_points: np.ndarray) -> list[np.ndarray]:
    """Three 3D-3D pairs ``(3, 3)``; [] if either triangle is degenerate (collinear)."""
    return _as_list(solve_points3d_batch(frame_points, map_points))


def solve_p3p(frame_bearings: np.ndarray, map_points: np.ndarray) -> list[np.ndarray]:
    """Three bearing/map-point pairs ``(3, 3)``; up to 4 candidates."""
    return _as_list(solve_p3p_batch(frame_bearings, map_points))


def solve_2pt3d_1pt2d(
    frame_points: np.ndarray, map_points: np.ndarray, frame_bearing: np.ndarray, map_point_2d: np.ndarray
) -> list[np.ndarray]:
    """Two 3D-3D pairs ``(2, 3)`` and one 2D-3D pair ``(3,)``; up to 2 candidates."""
    return _as_list(solve_2pt3d_1pt2d_batch(frame_points, map_points, frame_bearing, map_point_2d))


def solve_1pt3d_2pt2d(
    frame_point: np.ndarray, map_point: np.ndarray, frame_bearings: np.ndarray, map_points_2d: np.ndarray
) -> list[np.ndarray]:
    """One 3D-3D pair ``(3,)`` and two 2D-3D pairs ``(2, 3)``; up to 2 candidates."""
    return _as_list(solve_1pt3d_2pt2d_batch(frame_point, map_point, frame_bearings, map_points_2d))


def solve_3planes(frame_planes: np.ndarray, map_planes: np.ndarray) -> list[np.ndarray]:
    """Three plane pairs ``(3, 4)``; [] if the normals do not span 3D."""
    return _as_list(solve_3planes_batch(frame_planes, map_planes))


def solve_2planes_1pt(
    frame_planes: np.ndarray, map_planes: np.ndarray, frame_point: np.ndarray, map_point: np.ndarray
) -> list[np.ndarray]:
    """Two plane pairs ``(2, 4)`` and one 3D point pair ``(3,)``; [] if the planes are parallel."""
    return _as_list(solve_2planes_1pt_batch(frame_planes, map_planes, frame_point, map_point))


def solve_1plane_2pts(
    frame_plane: np.ndarray, map_plane: np.ndarray, frame_points: np.ndarray, map_points: np.ndarray
) -> list[np.ndarray]:
    """One plane pair ``(4,)`` and two 3D point pairs ``(2, 3)``; [] if degenerate."""
    return _as_list(solve_1plane_2pts_batch(frame_plane, map_plane, frame_points, map_points))
