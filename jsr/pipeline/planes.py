"""Fast plane extraction on the organized point cloud of a depth image.

After Feng, Taguchi and Kamat, "Fast plane extraction in organized point clouds using
agglomerative hierarchical clustering" (ICRA 2014):

1. The image is cut into ``block_size`` x ``block_size`` blocks. The first and second moments
   of the 3D points of every block come from separable sums (``X = a_u Z``, ``Y = b_v Z`` for
   a pinhole camera: a few per-pixel products, then sums over block rows and columns), plus
   the sum of ``Z^4`` for the noise model. A cluster of blocks is the sum of their moments,
   so fitting it is O(1): the plane normal is the eigenvector of the smallest eigenvalue of
   the covariance (closed-form symmetric 3x3 eigen-solver, vectorised over all clusters).
2. Blocks are rejected when more than ``max_block_missing`` of their pixels have no depth,
   when two neighbouring pixels inside differ by more than
   ``max(min_depth_jump, depth_jump_sigmas * sigma_Z)`` (a discontinuity), or when their fit
   RMSE exceeds ``max_block_rmse_sigmas * sigma_Z``.
3. Agglomerative hierarchical clustering of the graph of adjacent planar blocks; two clusters
   may merge when their normals agree (within ``merge_angle_degrees``, widened for clusters
   whose normal is noisy, see :class:`_MergeRule`) and the merged RMSE stays below
   ``merge_rmse_sigmas * sigma_Z``; the cheapest merge (merged MSE relative to the noise
   expected at its depths) goes first. The lower levels of the hierarchy, where merges are
   independent, are computed in vectorised rounds (mutually best pairs, and stars of blocks
   around them); a binary heap then finishes the hierarchy sequentially, with lazy
   re-evaluation of pairs whose clusters changed after they were queued.
4. Clusters of at least ``min_plane_pixels`` pixels become planes.
5. Refinement (``refine``, Feng et al.'s Algorithm 4): the border blocks of every plane are
   eroded; pixels of its eroded blocks and of the blocks next to it (rejected ones included)
   join the plane at the smallest point-to-plane distance, if that distance is below
   ``refine_distance_sigmas * max(sigma_Z(z), plane RMSE)``. Every plane is then refitted on
   its own final pixels, robustly: blocks and pixels that straddle a crease with a
   neighbouring surface are left out of the fit (see :func:`_refine`).

Noise model: ``sigma_Z = noise.sigma_z_coefficient * Z^2``. The thresholds of a cluster use
the RMS of sigma_Z over its points (a moment of ``Z^4``), so a wall spanning 1 m to 4 m is
judged against the noise it really has. Depths quantised by structured-light sensors make
the normals of small far blocks meaningless; the angle test accounts for that.

Lens distortion: with ``undistort`` and a distorted camera, the depth image is resampled
(nearest neighbour) to the ideal pinhole grid, planes are extracted there, and the label
image is mapped back to the raw image grid that colour, depth and keypoints share.
"""

from __future__ import annotations

import functools
import heapq
import logging
import math
import operator
import threading

import cv2
import numpy as np

from jsr.config import NoiseConfig, PlanesConfig
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline.measurements import PlaneMeasurements

logger = logging.getLogger(__name__)

# Moment channels of a block or a cluster: n, Sx, Sy, Sz, Sxx, Sxy, Sxz, Syy, Syz, Szz, Sz^4.
_N_MOMENTS = 11
_TWO_THIRDS_PI = 2.0 * math.pi / 3.0
# A cluster's normal is defined only if its narrower in-plane spread exceeds the noise
# variance by this factor (eigenvalue gap); otherwise the angle test does not apply to it.
_MIN_GAP_TO_NOISE = 4.0
# Floor of the measured plane RMSE used to select the pixels of a refit (metres; the depth
# PNG resolution is 0.2 mm).
_MIN_REFIT_RMSE = 0.001
# Merge test: the residual increase per point of the smaller cluster stays below this many T^2.
_INCREASE_FACTOR = 4.0


def empty_planes(height: int, width: int) -> PlaneMeasurements:
    """No planes: every pixel labelled -1."""
    return PlaneMeasurements(
        normals=np.zeros((0, 3)),
        offsets=np.zeros(0),
        centroids=np.zeros((0, 3)),
        point_counts=np.zeros(0, dtype=np.int64),
        fit_rmse=np.zeros(0),
        label_image=np.full((height, width), -1, dtype=np.int32),
    )


# --------------------------------------------------------------------------------------
# Camera geometry helpers
# --------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _undistortion_maps(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maps between the raw (distorted) image grid and the ideal pinhole grid.

    Returns ``(map_x, map_y, raw_to_pinhole)``: ``cv2.remap`` maps that resample a raw image
    onto the pinhole grid, and for every raw pixel the flat index of its nearest pinhole
    pixel (-1 when it falls outside the image).
    """
    size = (intrinsics.width, intrinsics.height)
    k, dist = intrinsics.matrix, intrinsics.distortion_coefficients
    map_x, map_y = cv2.initUndistortRectifyMap(k, dist, None, k, size, cv2.CV_32FC1)
    u, v = np.meshgrid(np.arange(intrinsics.width, dtype=np.float64), np.arange(intrinsics.height, dtype=np.float64))
    ideal = intrinsics.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]))
    iu = np.rint(ideal[:, 0]).astype(np.int64)
    iv = np.rint(ideal[:, 1]).astype(np.int64)
    inside = (iu >= 0) & (iu < intrinsics.width) & (iv >= 0) & (iv < intrinsics.height)
    raw_to_pinhole = np.where(inside, iv * intrinsics.width + iu, -1).reshape(intrinsics.height, intrinsics.width)
    for array in (map_x, map_y, raw_to_pinhole):
        array.setflags(write=False)
    return map_x, map_y, raw_to_pinhole


def _pinhole_rays(intrinsics: CameraIntrinsics, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``a_u = (u - cx) / fx`` ``(W,)`` and ``b_v = (v - cy) / fy`` ``(H,)``: X = a_u Z, Y = b_v Z."""
    a = (np.arange(width, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
    b = (np.arange(height, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
    return a, b


def jump_mask(depth: np.ndarray, sigma_coefficient: float, sigmas: float, minimum: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth discontinuities between 4-neighbours.

    Returns ``(horizontal (H, W-1), vertical (H-1, W))`` bool arrays: True where both pixels
    have depth and differ by more than ``max(minimum, sigmas * sigma_Z(z_near))``, with
    ``z_near`` the nearer of the two depths. (OpenCV arithmetic: several times faster than
    the same numpy expressions on a full image.)
    """
    depth = np.asarray(depth, dtype=np.float32)
    scale = float(sigmas * sigma_coefficient)
    floor = np.float32(minimum)
    masks = []
    for first, second in ((depth[:, :-1], depth[:, 1:]), (depth[:-1, :], depth[1:, :])):
        difference = cv2.absdiff(first, second)
        near = cv2.min(first, second)
        threshold = cv2.multiply(near, near, scale=scale)
        np.maximum(threshold, floor, out=threshold)
        jumps = cv2.bitwise_and(
            cv2.compare(difference, threshold, cv2.CMP_GT), cv2.compare(near, 0.0, cv2.CMP_GT)
        )
        masks.append(jumps > 0)
    return masks[0], masks[1]


# --------------------------------------------------------------------------------------
# Block moments and fits
# --------------------------------------------------------------------------------------


_workspace = threading.local()


def _scratch(shape: tuple[int, int], count: int) -> list[np.ndarray]:
    """``count`` reusable float64 images of ``shape`` (per thread).

    Fresh multi-megabyte temporaries cost page faults on every frame (several ms); reusing
    buffers avoids that.
    """
    cached = getattr(_workspace, "buffers", None)
    if cached is None or cached[0] != shape or len(cached[1]) < count:
        cached = (shape, [np.empty(shape) for _ in range(count)])
        _workspace.buffers = cached
    return cached[1][:count]


def _block_moments(depth: np.ndarray, a: np.ndarray, b: np.ndarray, block: int) -> np.ndarray:
    """``(Hb, Wb, 11)`` moment sums of the 3D points of every block (invalid pixels excluded).

    Uses the separable pinhole rays ``X = a_u Z``, ``Y = b_v Z``: per-pixel products involve
    only ``Z`` and the row ray ``b_v``; sums over the rows of each block row come first, and
    the column ray ``a_u`` weights those column sums before they are added up per block.
    """
    hb, wb = depth.shape[0] // block, depth.shape[1] // block
    shape = (hb * block, wb * block)
    z, z2, product = _scratch(shape, 3)
    np.copyto(z, depth[: shape[0], : shape[1]])
    np.multiply(z, z, out=z2)
    a = a[: shape[1]]
    b_column = b[: shape[0], None]

    def column_sums(image: np.ndarray) -> np.ndarray:  # (Hb, W): sums over the rows of each block row
        return image.reshape(hb, block, shape[1]).sum(axis=1)

    def block_sums(columns: np.ndarray) -> np.ndarray:  # (Hb, W) -> (Hb, Wb)
        return columns.reshape(hb, wb, block).sum(axis=2)

    c_valid = column_sums(depth[: shape[0], : shape[1]] > 0).astype(np.float64)
    c_z, c_z2 = column_sums(z), column_sums(z2)
    c_bz = column_sums(np.multiply(z, b_column, out=product))
    c_bz2 = column_sums(np.multiply(z2, b_column, out=product))
    c_b2z2 = column_sums(np.multiply(product, b_column, out=product))
    c_z4 = column_sums(np.multiply(z2, z2, out=product))
    moments = np.empty((hb, wb, _N_MOMENTS))
    moments[..., 0] = block_sums(c_valid)
    moments[..., 1] = block_sums(a * c_z)  # Sx
    moments[..., 2] = block_sums(c_bz)  # Sy
    moments[..., 3] = block_sums(c_z)  # Sz
    moments[..., 4] = block_sums(a * a * c_z2)  # Sxx
    moments[..., 5] = block_sums(a * c_bz2)  # Sxy
    moments[..., 6] = block_sums(a * c_z2)  # Sxz
    moments[..., 7] = block_sums(c_b2z2)  # Syy
    moments[..., 8] = block_sums(c_bz2)  # Syz
    moments[..., 9] = block_sums(c_z2)  # Szz
    moments[..., 10] = block_sums(c_z4)  # Sz^4
    return moments


def _covariances(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Means ``(..., 3)`` and covariances ``(..., 3, 3)`` from moment sums ``(..., 11)``."""
    n = np.maximum(moments[..., 0], 1.0)
    mean = moments[..., 1:4] / n[..., None]
    second = moments[..., [4, 5, 6, 5, 7, 8, 6, 8, 9]].reshape(moments.shape[:-1] + (3, 3)) / n[..., None, None]
    covariance = second - mean[..., :, None] * mean[..., None, :]
    return mean, covariance


def fit_planes_from_moments(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares planes of a stack of moment sums ``(B, 11)``.

    Returns ``(normals (B, 3) oriented towards the camera, offsets (B,), centroids (B, 3),
    mse (B,))`` with ``n . x + d = 0``; mse is the smallest covariance eigenvalue.
    """
    normals, offsets, mean, eigenvalues = _fit_stack(moments)
    return normals, offsets, mean, eigenvalues[..., 0]


def _fit_stack(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Like :func:`fit_planes_from_moments` but returns all eigenvalues ``(B, 3)`` ascending.

    Closed form, vectorised (much faster than ``np.linalg.eigh`` on many small matrices):
    eigenvalues by the trigonometric solution of the characteristic polynomial, the normal
    as the largest cross product of two rows of ``C - lambda_min I``.
    """
    mean, cov = _covariances(moments)
    a00, a01, a02 = cov[..., 0, 0], cov[..., 0, 1], cov[..., 0, 2]
    a11, a12, a22 = cov[..., 1, 1], cov[..., 1, 2], cov[..., 2, 2]
    smallest, middle, largest = _sym3_eigenvalues(a00, a01, a02, a11, a12, a22)
    r00, r11, r22 = a00 - smallest, a11 - smallest, a22 - smallest
    # Cross products row0 x row1, row0 x row2, row1 x row2 of C - lambda_min I; keep the longest.
    x0, y0, z0 = a01 * a12 - a02 * r11, a02 * a01 - r00 * a12, r00 * r11 - a01 * a01
    x1, y1, z1 = a01 * r22 - a02 * a12, a02 * a02 - r00 * r22, r00 * a12 - a01 * a02
    x2, y2, z2 = r11 * r22 - a12 * a12, a12 * a02 - a01 * r22, a01 * a12 - r11 * a02
    n0 = x0 * x0 + y0 * y0 + z0 * z0
    n1 = x1 * x1 + y1 * y1 + z1 * z1
    n2 = x2 * x2 + y2 * y2 + z2 * z2
    use1 = (n1 > n0) & (n1 >= n2)
    use2 = (n2 > n0) & (n2 > n1)
    nx = np.where(use2, x2, np.where(use1, x1, x0))
    ny = np.where(use2, y2, np.where(use1, y1, y0))
    nz = np.where(use2, z2, np.where(use1, z1, z0))
    length = np.sqrt(np.where(use2, n2, np.where(use1, n1, n0)))
    degenerate = ~(length > 0)
    length = np.where(degenerate, 1.0, length)
    normals = np.stack([nx / length, ny / length, np.where(degenerate, -1.0, nz / length)], axis=-1)
    flip = np.einsum("...i,...i->...", normals, mean) > 0
    normals = np.where(flip[..., None], -normals, normals)
    offsets = -np.einsum("...i,...i->...", normals, mean)
    eigenvalues = np.maximum(np.stack([smallest, middle, largest], axis=-1), 0.0)
    return normals, offsets, mean, eigenvalues


def _sym3_eigenvalues(a00, a01, a02, a11, a12, a22) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) of symmetric 3x3 matrices given by their six entries."""
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    p = np.sqrt(p2 / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.clip(det / (2.0 * p * p * p), -1.0, 1.0)
    r = np.where(p > 0, r, 0.0)
    phi = np.arccos(r) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + _TWO_THIRDS_PI)
    middle = 3.0 * q - largest - smallest
    return smallest, middle, largest


def _smallest_eigenvalues(moments: np.ndarray) -> np.ndarray:
    """Smallest covariance eigenvalue (the plane-fit MSE) of moment rows ``(E, 11)``, closed form."""
    n = np.maximum(moments[:, 0], 1.0)
    mx, my, mz = moments[:, 1] / n, moments[:, 2] / n, moments[:, 3] / n
    smallest, _, _ = _sym3_eigenvalues(
        moments[:, 4] / n - mx * mx,
        moments[:, 5] / n - mx * my,
        moments[:, 6] / n - mx * mz,
        moments[:, 7] / n - my * my,
        moments[:, 8] / n - my * mz,
        moments[:, 9] / n - mz * mz,
    )
    return np.maximum(smallest, 0.0)


def _normal_variance(moments: np.ndarray, eigenvalues: np.ndarray, coefficient: float, correlation: float) -> np.ndarray:
    """Variance (rad^2) of the fitted normal of each moment row from its noise and extent.

    ``sigma_n^2 / (N_eff * (lambda_mid - lambda_min))``: the noise variance (the larger of the
    fit MSE and the model's mean sigma_Z^2) over the effective sample count times the
    eigenvalue gap (the spread along the plane's narrower in-plane axis beyond the noise; a
    strip narrower than a few noise sigmas has no defined normal: infinite variance, so that
    only the merged-fit test decides). Depth quantisation (steps of about 2 sigma_Z on
    structured-light sensors) makes the errors of neighbouring pixels strongly correlated: a
    small block sees one or two depth steps, and its normal can tilt by tens of degrees at
    3 m while its RMSE stays small. ``N_eff = N / correlation`` (the block side length)
    accounts for that, so the angle test is loose for small far clusters and strict for
    large ones (Feng et al. widen their angle threshold with depth for the same reason).
    """
    n = np.maximum(moments[..., 0], 1.0) / correlation
    noise = np.maximum(eigenvalues[..., 0], _noise_variance(moments, coefficient))
    gap = eigenvalues[..., 1] - eigenvalues[..., 0]
    variance = noise / (n * np.maximum(gap, 1e-12))
    return np.where(gap > _MIN_GAP_TO_NOISE * noise, variance, np.inf)


def _noise_variance(moments: np.ndarray, coefficient: float) -> np.ndarray:
    """Mean of sigma_Z^2 over the points of each moment row: ``c^2 * E[Z^4]``."""
    return coefficient * coefficient * moments[..., 10] / np.maximum(moments[..., 0], 1.0)


def _fit_scalar(m: list[float], with_normal: bool) -> tuple[float, ...]:
    """Closed-form plane fit of one cluster (pure Python: it runs inside the heap loop).

    Returns ``(mse, lambda_mid, mean Z^4)`` and, ``with_normal``, also ``(nx, ny, nz)``
    oriented towards the camera. Eigenvalues by the trigonometric solution of the
    characteristic polynomial; the eigenvector of the smallest one by the largest cross
    product of two rows of ``C - lambda I``.
    """
    inv = 1.0 / m[0]
    mx, my, mz = m[1] * inv, m[2] * inv, m[3] * inv
    a00 = m[4] * inv - mx * mx
    a01 = m[5] * inv - mx * my
    a02 = m[6] * inv - mx * mz
    a11 = m[7] * inv - my * my
    a12 = m[8] * inv - my * mz
    a22 = m[9] * inv - mz * mz
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    z4 = m[10] * inv
    if p2 <= 1e-30:
        lam = q if q > 0.0 else 0.0
        return (lam, lam, z4, 0.0, 0.0, -1.0) if with_normal else (lam, lam, z4)
    p = math.sqrt(p2 / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    r = det / (2.0 * p * p * p)
    r = -1.0 if r < -1.0 else (1.0 if r > 1.0 else r)
    phi = math.acos(r) / 3.0
    lam_max = q + 2.0 * p * math.cos(phi)
    lam = q + 2.0 * p * math.cos(phi + _TWO_THIRDS_PI)
    lam_mid = 3.0 * q - lam - lam_max
    if lam < 0.0:
        lam = 0.0
    if not with_normal:
        return lam, lam_mid, z4
    r00, r11, r22 = a00 - lam, a11 - lam, a22 - lam
    c0 = (a01 * a12 - a02 * r11, a02 * a01 - r00 * a12, r00 * r11 - a01 * a01)  # row0 x row1
    c1 = (a01 * r22 - a02 * a12, a02 * a02 - r00 * r22, r00 * a12 - a01 * a02)  # row0 x row2
    c2 = (r11 * r22 - a12 * a12, a12 * a02 - a01 * r22, a01 * a12 - r11 * a02)  # row1 x row2
    n0 = c0[0] * c0[0] + c0[1] * c0[1] + c0[2] * c0[2]
    n1 = c1[0] * c1[0] + c1[1] * c1[1] + c1[2] * c1[2]
    n2 = c2[0] * c2[0] + c2[1] * c2[1] + c2[2] * c2[2]
    if n0 >= n1 and n0 >= n2:
        best, norm2 = c0, n0
    elif n1 >= n2:
        best, norm2 = c1, n1
    else:
        best, norm2 = c2, n2
    if norm2 <= 0.0:
        return lam, lam_mid, z4, 0.0, 0.0, -1.0
    scale = 1.0 / math.sqrt(norm2)
    if (best[0] * mx + best[1] * my + best[2] * mz) > 0.0:  # towards the camera
        scale = -scale
    return lam, lam_mid, z4, best[0] * scale, best[1] * scale, best[2] * scale


# --------------------------------------------------------------------------------------
# Agglomerative hierarchical clustering
# --------------------------------------------------------------------------------------


class _MergeRule:
    """The merge test of two clusters and its cost (shared by the batch and heap stages).

    Two clusters may merge if the angle between their normals is below
    ``max(merge_angle, angle_noise_sigmas * sqrt(var_a + var_b))`` (the normal variances of
    :func:`_normal_variance`: small far blocks have noisy normals, large planes precise ones)
    and the merged fit MSE is below ``T^2 = merge_rmse_sigmas^2 * c^2 * E[Z^4]``. The cost
    is the ratio of the two, so merges are ranked relative to the noise at their depths.
    Besides (not in Feng et al.): the increase of the summed squared residuals caused by the
    merge, per point of the smaller cluster, must stay below ``(2 T)^2``. Far away (where
    ``T`` reaches several centimetres) the merged RMSE of a large wall and a small parallel
    surface 15 cm in front of it (book backs, a cabinet door) can pass, while the smaller
    cluster's points are clearly off the wall's plane. (The factor 2 leaves room for the
    low-frequency warping of real depth sensors, about 1 cm at 1-2 m.)
    """

    def __init__(self, cfg: PlanesConfig, coefficient: float):
        self.min_angle = math.radians(cfg.merge_angle_degrees)
        self.angle_sigmas = cfg.angle_noise_sigmas
        self.merge_factor = cfg.merge_rmse_sigmas**2 * coefficient**2
        self.coefficient2 = coefficient**2
        self.max_angle = math.radians(89.0)
        self.correlation = float(cfg.block_size)

    def costs(
        self,
        moments: np.ndarray,
        normals: np.ndarray,
        normal_var: np.ndarray,
        mse: np.ndarray,
        first: np.ndarray,
        second: np.ndarray,
    ) -> np.ndarray:
        """Merge costs of cluster pairs ``(first[i], second[i])``; inf where not allowed."""
        angle_limit = np.clip(
            self.angle_sigmas * np.sqrt(normal_var[first] + normal_var[second]), self.min_angle, self.max_angle
        )
        dots = np.abs(np.einsum("ij,ij->i", normals[first], normals[second]))
        merged = moments[first] + moments[second]
        merged_mse = _smallest_eigenvalues(merged)
        limit = self.merge_factor * merged[:, 10] / np.maximum(merged[:, 0], 1.0)
        costs = merged_mse / limit
        # Residual increase, per point of the smaller cluster (a parallel plane a few noise
        # sigmas away fails this while the merged RMSE can still pass).
        n_first, n_second = moments[first, 0], moments[second, 0]
        increase = merged[:, 0] * merged_mse - n_first * mse[first] - n_second * mse[second]
        costs[increase > _INCREASE_FACTOR * limit * np.minimum(n_first, n_second)] = np.inf
        costs[dots < np.cos(angle_limit)] = np.inf
        costs[~(costs < 1.0)] = np.inf
        return costs

    def cost(
        self, ma: list[float], mb: list[float], na: tuple, nb: tuple, va: float, vb: float, ea: float, eb: float
    ) -> float:
        """Scalar version of :meth:`costs` for the heap loop."""
        angle_limit = self.angle_sigmas * math.sqrt(va + vb)
        if angle_limit < self.min_angle:
            angle_limit = self.min_angle
        elif angle_limit > self.max_angle:
            angle_limit = self.max_angle
        if abs(na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]) < math.cos(angle_limit):
            return math.inf
        merged = list(map(operator.add, ma, mb))
        mse, _, z4 = _fit_scalar(merged, False)
        limit = self.merge_factor * z4
        if not limit > 0.0 or mse >= limit:
            return math.inf
        if merged[0] * mse - ma[0] * ea - mb[0] * eb > _INCREASE_FACTOR * limit * min(ma[0], mb[0]):
            return math.inf
        return mse / limit


def _unique_cluster_pairs(owner: np.ndarray, block_pairs: np.ndarray, count: int) -> np.ndarray:
    """Distinct pairs ``(a < b)`` of different clusters adjacent through ``block_pairs``."""
    a = owner[block_pairs[:, 0]]
    b = owner[block_pairs[:, 1]]
    different = a != b
    low = np.minimum(a[different], b[different])
    high = np.maximum(a[different], b[different])
    codes = np.sort(low * count + high)
    if len(codes):
        codes = codes[np.concatenate([[True], codes[1:] != codes[:-1]])]
    return np.column_stack([codes // count, codes % count])


def _batch_merge_rounds(
    moments: np.ndarray,
    normals: np.ndarray,
    normal_var: np.ndarray,
    mse: np.ndarray,
    block_pairs: np.ndarray,
    rule: _MergeRule,
    coefficient: float,
    max_rounds: int = 12,
    min_fraction: float = 0.15,
) -> tuple[np.ndarray, ...]:
    """Lower levels of the hierarchy, vectorised over all clusters at once.

    Every cluster points to its cheapest allowed neighbour. A mutually best pair would also
    be merged by the sequential algorithm before either joins another cluster, so all such
    pairs merge in one numpy step; the larger cluster of the pair is the centre. Clusters
    whose cheapest neighbour is a centre (or its partner) join that centre in the same step
    (the star merges a growing plane makes block by block in the sequential algorithm), if
    the fit of the whole group still passes the merge test; otherwise only the pair merges.
    Rounds repeat until one merges fewer than ``min_fraction`` of the clusters; the heap stage
    then finishes the hierarchy.

    ``moments``, ``normals``, ``normal_var``, ``mse`` describe the initial clusters (planar
    blocks), ``block_pairs`` their adjacency. Returns ``(owner (B,) cluster of each initial
    cluster, moments, normals, normal_var, mse, pairs (P, 2), costs (P,))`` for the clusters
    after the rounds, with their allowed pairs and merge costs.
    """
    count = len(moments)
    owner = np.arange(count)
    index = np.arange(count)
    moments = moments.copy()
    normals = normals.copy()
    normal_var = normal_var.copy()
    mse = mse.copy()
    finished = False
    for round_number in range(max_rounds + 1):
        pairs = _unique_cluster_pairs(owner, block_pairs, count)
        costs = rule.costs(moments, normals, normal_var, mse, pairs[:, 0], pairs[:, 1])
        allowed = np.isfinite(costs)
        pairs, costs = pairs[allowed], costs[allowed]
        if len(pairs) == 0 or finished or round_number == max_rounds:
            break
        # Cheapest allowed neighbour of every cluster.
        ends = np.concatenate([pairs[:, 0], pairs[:, 1]])
        others = np.concatenate([pairs[:, 1], pairs[:, 0]])
        both_costs = np.concatenate([costs, costs])
        cheapest = np.full(count, np.inf)
        np.minimum.at(cheapest, ends, both_costs)
        is_best = both_costs == cheapest[ends]
        target = np.full(count, -1, dtype=np.int64)
        target[ends[is_best]] = others[is_best]
        has_target = target >= 0
        safe_target = np.where(has_target, target, index)
        mutual = has_target & (safe_target[safe_target] == index)
        size = moments[:, 0]
        larger = (size > size[safe_target]) | ((size == size[safe_target]) & (index < safe_target))
        centre = mutual & larger
        partner = mutual & ~larger
        group = index.copy()
        group[partner] = safe_target[partner]
        joiner = has_target & ~mutual
        to_centre = joiner & centre[safe_target]
        to_partner = joiner & partner[safe_target]
        group[to_centre] = safe_target[to_centre]
        group[to_partner] = safe_target[safe_target[to_partner]]
        live = np.flatnonzero(np.bincount(owner, minlength=count))
        # Whole-group test of the stars; a failing star keeps only its pair merge.
        grouped = _group_sums(moments, live, group[live], count)
        stars = np.unique(group[live[joiner[live] & (group[live] != live)]])
        if len(stars):
            merged = grouped[stars]
            star_cost = _smallest_eigenvalues(merged) / (rule.merge_factor * merged[:, 10] / np.maximum(merged[:, 0], 1.0))
            failed = np.zeros(count, dtype=bool)
            failed[stars[~(star_cost < 1.0)]] = True
            revert = joiner & failed[group]
            if revert.any():
                group[revert] = index[revert]
                grouped = _group_sums(moments, live, group[live], count)
        moved = live[group[live] != live]
        if len(moved) == 0:
            break
        finished = len(moved) < min_fraction * len(live)
        logger.debug("round %d: %d clusters, %d pairs, %d merged", round_number, len(live), len(pairs), len(moved))
        centres = np.unique(group[moved])
        moments[centres] = grouped[centres]
        centre_normals, _, _, eigenvalues = _fit_stack(moments[centres])
        normals[centres] = centre_normals
        normal_var[centres] = _normal_variance(moments[centres], eigenvalues, coefficient, rule.correlation)
        mse[centres] = eigenvalues[:, 0]
        owner = group[owner]
    return owner, moments, normals, normal_var, mse, pairs, costs


def _group_sums(moments: np.ndarray, members: np.ndarray, groups: np.ndarray, count: int) -> np.ndarray:
    """``(count, 11)`` moment sums of ``members`` added up by their ``groups`` id."""
    sums = np.zeros((count, _N_MOMENTS))
    for channel in range(_N_MOMENTS):
        sums[:, channel] = np.bincount(groups, weights=moments[members, channel], minlength=count)
    return sums


def _heap_merge(
    moments: np.ndarray,
    normals: np.ndarray,
    normal_var: np.ndarray,
    mse: np.ndarray,
    pairs: np.ndarray,
    costs: np.ndarray,
    rule: _MergeRule,
    coefficient: float,
) -> np.ndarray:
    """Sequential agglomerative clustering with a binary heap; returns the root of every cluster.

    The heap holds ``(cost, a, b, version_a, version_b)``; the cheapest pair is merged. A
    popped pair whose clusters changed since it was queued (or that now belong to other
    clusters) is re-evaluated on the current clusters, once per pair and version, and queued
    again if still allowed. Merging adds moment sums: the merged fit is O(1).
    """
    count = len(moments)
    parent = list(range(count))
    version = [0] * count
    involved = np.unique(pairs).tolist()
    cluster_moments: list[list[float] | None] = [None] * count
    cluster_normal: list[tuple | None] = [None] * count
    cluster_var = [0.0] * count
    cluster_mse = [0.0] * count
    for index, row, normal, variance, error in zip(
        involved,
        moments[involved].tolist(),
        normals[involved].tolist(),
        normal_var[involved].tolist(),
        mse[involved].tolist(),
    ):
        cluster_moments[index] = row
        cluster_normal[index] = normal
        cluster_var[index] = variance
        cluster_mse[index] = error
    zeros = [0] * len(pairs)
    heap = list(zip(costs.tolist(), pairs[:, 0].tolist(), pairs[:, 1].tolist(), zeros, zeros))
    heapq.heapify(heap)
    evaluated: dict[tuple[int, int], tuple[int, int]] = {}
    heappop, heappush = heapq.heappop, heapq.heappush
    coefficient2 = coefficient * coefficient
    add = operator.add
    cost_of = rule.cost
    correlation = rule.correlation

    def find(node: int) -> int:
        while parent[node] != node:
            parent[node] = parent[parent[node]]
            node = parent[node]
        return node

    merges = reevaluations = 0
    while heap:
        _, a, b, va, vb = heappop(heap)
        ra = find(a)
        rb = find(b)
        if ra == rb:
            continue
        if ra == a and rb == b and version[a] == va and version[b] == vb:
            ma, mb = cluster_moments[a], cluster_moments[b]
            if mb[0] > ma[0]:  # the larger cluster keeps its id
                a, b, ma, mb = b, a, mb, ma
            merged = list(map(add, ma, mb))
            mse, lam_mid, z4, nx, ny, nz = _fit_scalar(merged, True)
            noise = mse if mse > coefficient2 * z4 else coefficient2 * z4
            parent[b] = a
            cluster_moments[a] = merged
            cluster_moments[b] = None
            cluster_normal[a] = (nx, ny, nz)
            cluster_mse[a] = mse
            gap = lam_mid - mse
            if gap > _MIN_GAP_TO_NOISE * noise:
                cluster_var[a] = noise * correlation / (merged[0] * gap)
            else:
                cluster_var[a] = math.inf
            version[a] += 1
            merges += 1
            continue
        key = (ra, rb) if ra < rb else (rb, ra)
        current = (version[key[0]], version[key[1]])
        if evaluated.get(key) == current:
            continue
        evaluated[key] = current
        reevaluations += 1
        cost = cost_of(
            cluster_moments[ra],
            cluster_moments[rb],
            cluster_normal[ra],
            cluster_normal[rb],
            cluster_var[ra],
            cluster_var[rb],
            cluster_mse[ra],
            cluster_mse[rb],
        )
        if cost < 1.0:
            heappush(heap, (cost, ra, rb, version[ra], version[rb]))
    logger.debug("plane clustering heap: %d clusters, %d merges, %d re-evaluations", len(involved), merges, reevaluations)
    roots = np.array(parent, dtype=np.int64)
    while True:
        next_roots = roots[roots]
        if np.array_equal(next_roots, roots):
            return roots
        roots = next_roots


def cluster_blocks(
    moments: np.ndarray,
    planar: np.ndarray,
    grid_shape: tuple[int, int],
    cfg: PlanesConfig,
    coefficient: float,
    max_heap_passes: int = 4,
) -> np.ndarray:
    """Agglomerative hierarchical clustering of the planar blocks of a ``grid_shape`` grid.

    ``moments``: ``(B, 11)`` moment sums per block; ``planar``: ``(B,)`` bool. Returns the
    cluster id (a block index) of every block, -1 for non-planar blocks.
    """
    hb, wb = grid_shape
    rule = _MergeRule(cfg, coefficient)
    labels = np.full(hb * wb, -1, dtype=np.int64)
    planar_index = np.flatnonzero(planar)
    if len(planar_index) == 0:
        return labels
    compact = np.full(hb * wb, -1, dtype=np.int64)
    compact[planar_index] = np.arange(len(planar_index))
    grid = np.arange(hb * wb).reshape(hb, wb)
    block_pairs = np.concatenate(
        [
            np.column_stack([grid[:, :-1].ravel(), grid[:, 1:].ravel()]),
            np.column_stack([grid[:-1, :].ravel(), grid[1:, :].ravel()]),
        ]
    )
    block_pairs = compact[block_pairs]
    block_pairs = block_pairs[(block_pairs[:, 0] >= 0) & (block_pairs[:, 1] >= 0)]
    block_moments = moments[planar_index]
    normals, _, _, eigenvalues = _fit_stack(block_moments)
    normal_var = _normal_variance(block_moments, eigenvalues, coefficient, rule.correlation)
    owner, cluster_moments, cluster_normals, cluster_var, cluster_mse, pairs, costs = _batch_merge_rounds(
        block_moments, normals, normal_var, eigenvalues[:, 0], block_pairs, rule, coefficient
    )
    # The heap drops a pair that fails the merge test; the pair may pass later, once one of
    # its clusters has grown (its normal is then better determined). A final vectorised check
    # of all adjacent clusters catches those; the heap runs again until none is left.
    count = len(block_moments)
    for _ in range(max_heap_passes):
        if len(pairs) == 0:
            break
        roots = _heap_merge(cluster_moments, cluster_normals, cluster_var, cluster_mse, pairs, costs, rule, coefficient)
        owner = roots[owner]
        live = np.flatnonzero(np.bincount(owner, minlength=count))
        cluster_moments = _group_sums(block_moments, np.arange(count), owner, count)
        fitted_normals, _, _, eigenvalues = _fit_stack(cluster_moments[live])
        cluster_normals[live] = fitted_normals
        cluster_var[live] = _normal_variance(cluster_moments[live], eigenvalues, coefficient, rule.correlation)
        cluster_mse[live] = eigenvalues[:, 0]
        pairs = _unique_cluster_pairs(owner, block_pairs, count)
        costs = rule.costs(cluster_moments, cluster_normals, cluster_var, cluster_mse, pairs[:, 0], pairs[:, 1])
        allowed = np.isfinite(costs)
        pairs, costs = pairs[allowed], costs[allowed]
    labels[planar_index] = planar_index[owner]
    return labels


# --------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------


def extract_planes(
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    planes_cfg: PlanesConfig,
    noise_cfg: NoiseConfig,
    undistort: bool = True,
) -> PlaneMeasurements:
    """Planes of one depth image (``(H, W)`` float32 metres, 0 = invalid).

    ``undistort``: with a distorted camera, extract planes in the ideal pinhole geometry
    (the label image is still returned on the raw image grid).
    """
    depth = np.asarray(depth, dtype=np.float32)
    height, width = depth.shape
    if not planes_cfg.enabled:
        return empty_planes(height, width)
    distorted = undistort and intrinsics.has_distortion and (intrinsics.width, intrinsics.height) == (width, height)
    if distorted:
        map_x, map_y, raw_to_pinhole = _undistortion_maps(intrinsics)
        depth = cv2.remap(depth, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    result = _extract_pinhole(depth, intrinsics, planes_cfg, noise_cfg)
    if distorted and len(result):
        flat = result.label_image.ravel()
        labels = np.where(raw_to_pinhole >= 0, flat[np.maximum(raw_to_pinhole, 0)], -1).astype(np.int32)
        result.label_image = labels
    return result


def _extract_pinhole(
    depth: np.ndarray, intrinsics: CameraIntrinsics, cfg: PlanesConfig, noise_cfg: NoiseConfig
) -> PlaneMeasurements:
    height, width = depth.shape
    block = cfg.block_size
    hb, wb = height // block, width // block
    if hb == 0 or wb == 0:
        return empty_planes(height, width)
    coefficient = noise_cfg.sigma_z_coefficient
    a, b = _pinhole_rays(intrinsics, height, width)

    # (a) block moments
    moments = _block_moments(depth, a, b, block)
    flat_moments = moments.reshape(-1, _N_MOMENTS)
    block_pixels = block * block

    # (b) rejection: missing depth, discontinuities, poor fit
    complete = flat_moments[:, 0] >= (1.0 - cfg.max_block_missing) * block_pixels - 1e-9
    complete &= flat_moments[:, 0] >= 3
    jump_h, jump_v = jump_mask(depth[: hb * block, : wb * block], coefficient, cfg.depth_jump_sigmas, cfg.min_depth_jump)
    # A jump between a pixel and its right (lower) neighbour inside the same block.
    inner_h = np.zeros((hb * block, wb * block), dtype=bool)
    inner_h[:, :-1] = jump_h
    inner_h[:, block - 1 :: block] = False
    inner_v = np.zeros((hb * block, wb * block), dtype=bool)
    inner_v[:-1, :] = jump_v
    inner_v[block - 1 :: block, :] = False
    inner = inner_h | inner_v
    discontinuous = inner.reshape(hb, block, wb * block).any(axis=1).reshape(hb, wb, block).any(axis=2).ravel()
    planar = complete & ~discontinuous
    mse = np.full(hb * wb, np.inf)
    mse[planar] = _smallest_eigenvalues(flat_moments[planar])
    planar &= mse <= cfg.max_block_rmse_sigmas**2 * _noise_variance(flat_moments, coefficient)

    # (c) agglomerative hierarchical clustering of adjacent planar blocks
    roots = cluster_blocks(flat_moments, planar, (hb, wb), cfg, coefficient)

    # (d) clusters large enough to be planes
    cluster_sizes = np.bincount(roots[planar], minlength=hb * wb)
    plane_roots = np.flatnonzero(cluster_sizes * block_pixels >= cfg.min_plane_pixels)
    if len(plane_roots) == 0:
        return empty_planes(height, width)
    plane_roots = plane_roots[np.argsort(-cluster_sizes[plane_roots], kind="stable")]
    root_to_plane = np.full(hb * wb, -1, dtype=np.int64)
    root_to_plane[plane_roots] = np.arange(len(plane_roots))
    block_labels = np.full(hb * wb, -1, dtype=np.int64)
    block_labels[planar] = root_to_plane[roots[planar]]
    block_labels = block_labels.reshape(hb, wb)

    # (e) refinement
    if cfg.refine:
        labels, plane_moments = _refine(depth, intrinsics, moments, block_labels, len(plane_roots), cfg, coefficient)
    else:
        labels = np.full((height, width), -1, dtype=np.int32)
        labels[: hb * block, : wb * block] = np.repeat(np.repeat(block_labels, block, axis=0), block, axis=1)
        plane_moments = np.zeros((len(plane_roots), _N_MOMENTS))
        in_plane = block_labels.ravel() >= 0
        np.add.at(plane_moments, block_labels.ravel()[in_plane], flat_moments[in_plane])
    return _finish(labels, plane_moments, depth, cfg.min_plane_pixels)


def _refine(
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    moments: np.ndarray,
    block_labels: np.ndarray,
    plane_count: int,
    cfg: PlanesConfig,
    coefficient: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-level refinement (Feng et al., Algorithm 4); returns the label image and the
    moment sums each plane is refitted from.

    Border blocks of every plane (a 4-neighbour block that is not the same plane) are eroded;
    the plane keeps its interior blocks whole. The pixels of the blocks 8-adjacent to a
    plane's blocks that are not interior to any plane (its eroded border, rejected blocks,
    blocks of small clusters) are its candidates: each pixel joins the candidate plane at the
    smallest distance to the plane of its whole cluster, if that distance is below
    ``refine_distance_sigmas * max(sigma_Z(z), cluster rmse)``.

    The refit (moment sums, no pass over the image) uses the interior blocks and the joined
    pixels of the plane's own eroded blocks that are within 2.5 times the interior's
    measured RMSE; pixels taken over from other blocks only extend the mask. Finally units
    (blocks, parts of blocks) whose mean offset from the plane is an outlier are dropped
    (:func:`_trimmed_moments`). Both keep the points of a neighbouring face just past a
    crease, which lie within the noise threshold of the plane but all on one side of it, from
    tilting the plane.
    """
    height, width = depth.shape
    block = cfg.block_size
    hb, wb = block_labels.shape
    padded = np.pad(block_labels, 1, constant_values=-2)
    centre = padded[1:-1, 1:-1]
    same = np.ones_like(block_labels, dtype=bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        neighbour = padded[dy : dy + hb, dx : dx + wb]
        same &= (neighbour == centre) | (neighbour == -2)  # the image border does not erode
    interior = np.where(same, block_labels, -1)
    # A plane that erodes away entirely keeps its blocks as interior.
    present = np.zeros(plane_count, dtype=bool)
    present[interior[interior >= 0]] = True
    if not present.all():
        keep_whole = (block_labels >= 0) & ~present[np.maximum(block_labels, 0)]
        interior = np.where(keep_whole, block_labels, interior)

    flat_interior = interior.ravel()
    flat_moments = moments.reshape(-1, _N_MOMENTS)
    plane_moments = np.zeros((plane_count, _N_MOMENTS))
    interior_blocks = flat_interior >= 0
    np.add.at(plane_moments, flat_interior[interior_blocks], flat_moments[interior_blocks])
    # Pixels are judged against the plane of the whole cluster (interior and border blocks):
    # the interior alone can be a single column of blocks, too narrow to fix the normal.
    cluster_moments = np.zeros((plane_count, _N_MOMENTS))
    cluster_blocks_mask = block_labels.ravel() >= 0
    np.add.at(cluster_moments, block_labels.ravel()[cluster_blocks_mask], flat_moments[cluster_blocks_mask])
    normals, offsets, _, eigenvalues = _fit_stack(cluster_moments)
    rmse = np.sqrt(eigenvalues[:, 0])

    labels = np.full((height, width), -1, dtype=np.int32)
    labels[: hb * block, : wb * block] = cv2.resize(
        interior.astype(np.int32), (wb * block, hb * block), interpolation=cv2.INTER_NEAREST
    )

    # Candidate (plane, block) pairs: the 8-neighbourhood of the plane's blocks, not interior.
    one_hot = np.zeros((plane_count, hb + 2, wb + 2), dtype=bool)
    rows, cols = np.nonzero(block_labels >= 0)
    one_hot[block_labels[rows, cols], rows + 1, cols + 1] = True
    dilated = np.zeros((plane_count, hb, wb), dtype=bool)
    for dy in range(3):
        for dx in range(3):
            dilated |= one_hot[:, dy : dy + hb, dx : dx + wb]
    dilated &= (interior < 0)[None]
    # Block-major order: the candidate rows of one block are contiguous.
    block_of, plane_of = np.nonzero(dilated.reshape(plane_count, -1).T)
    remainder = height > hb * block or width > wb * block
    if len(plane_of) == 0:
        if remainder:
            _label_remainder(labels, depth, intrinsics, normals, offsets, rmse, hb * block, wb * block, cfg, coefficient)
        return labels, plane_moments
    pixel_index, ray_a, ray_b = _block_pixel_tables(intrinsics, height, width, block)
    pixels = pixel_index[block_of]  # (K, block^2)
    z = depth.ravel()[pixels]  # float32
    n = normals[plane_of].astype(np.float32)
    distance = np.abs(
        z * (n[:, 0:1] * ray_a[block_of] + n[:, 1:2] * ray_b[block_of] + n[:, 2:3])
        + offsets[plane_of].astype(np.float32)[:, None]
    )
    threshold = np.maximum(np.float32(coefficient) * z * z, rmse[plane_of].astype(np.float32)[:, None])
    threshold *= np.float32(cfg.refine_distance_sigmas)
    accepted = (z > 0) & (distance < threshold)
    # Nearest plane per pixel: one integer key (distance in micrometres, then plane id) so
    # that a min-reduction over the rows of a block gives both the distance and the plane.
    plane_bits = max(int(plane_count).bit_length(), 1)
    keys = np.where(
        accepted, (np.rint(distance * 1e6).astype(np.int64) << plane_bits) | plane_of[:, None], np.iinfo(np.int64).max
    )
    new_block = np.concatenate([[True], block_of[1:] != block_of[:-1]])
    starts = np.flatnonzero(new_block)
    group = np.cumsum(new_block) - 1
    nearest = np.minimum.reduceat(keys, starts, axis=0)  # (G, block^2)
    found = nearest != np.iinfo(np.int64).max
    labels.ravel()[pixel_index[block_of[starts]]] = np.where(found, nearest & ((1 << plane_bits) - 1), -1)
    winner = accepted & (keys == nearest[group])
    if remainder:
        _label_remainder(labels, depth, intrinsics, normals, offsets, rmse, hb * block, wb * block, cfg, coefficient)
    # For the refit, a joined pixel must also be within 2.5 times the plane's interior RMSE
    # (the noise it really has): pixels of a neighbouring face just past a crease are within
    # the (model) distance threshold but not within the measured noise.
    interior_rmse = np.sqrt(np.maximum(_fit_stack(plane_moments)[3][:, 0], _MIN_REFIT_RMSE**2))
    interior_rmse = np.where(plane_moments[:, 0] >= 3 * block * block, interior_rmse, rmse)
    fitting = winner & (distance <= (2.5 * interior_rmse[plane_of]).astype(np.float32)[:, None])
    # Moment sums of the fitting pixels per (block, plane) row: within a block the column ray
    # a_u varies only along columns and b_v only along rows, so the sums separate.
    zz = (z * fitting).astype(np.float64).reshape(-1, block, block)  # (K, rows v, cols u)
    zz2 = zz * zz
    a_cols = ray_a[block_of, :block].astype(np.float64)  # the first row of a block holds its columns' rays
    b_rows = ray_b[block_of, ::block].astype(np.float64)  # the first column holds its rows' rays
    ones = np.ones(block)
    col_z, row_z = (ones @ zz), (zz @ ones)  # sums over rows / over columns (matmul: faster than sum)
    col_z2, row_z2 = (ones @ zz2), (zz2 @ ones)
    row_moments = np.column_stack(
        [
            fitting.sum(axis=1),
            (col_z * a_cols).sum(axis=1),
            (row_z * b_rows).sum(axis=1),
            col_z.sum(axis=1),
            (col_z2 * a_cols * a_cols).sum(axis=1),
            (((b_rows[:, None, :] @ zz2)[:, 0, :]) * a_cols).sum(axis=1),
            (col_z2 * a_cols).sum(axis=1),
            (row_z2 * b_rows * b_rows).sum(axis=1),
            (row_z2 * b_rows).sum(axis=1),
            col_z2.sum(axis=1),
            (zz2 * zz2).reshape(len(zz2), -1) @ np.ones(block * block),
        ]
    )
    # The refit uses the plane's own blocks (interior and eroded border); pixels it took over
    # from other blocks (rejected, or of other clusters) extend its mask only. At grazing
    # views a table edge a few centimetres tall lies within the distance threshold of the top,
    # and fitting those pixels would tilt and shift the plane.
    own = (block_labels.ravel()[block_of] == plane_of) & (row_moments[:, 0] > 0)
    units = np.concatenate([flat_moments[interior_blocks], row_moments[own]])
    unit_plane = np.concatenate([flat_interior[interior_blocks], plane_of[own]])
    return labels, _trimmed_moments(units, unit_plane, plane_count, coefficient)


def _label_remainder(
    labels: np.ndarray,
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    normals: np.ndarray,
    offsets: np.ndarray,
    rmse: np.ndarray,
    grid_height: int,
    grid_width: int,
    cfg: PlanesConfig,
    coefficient: float,
) -> None:
    """Pixels right of / below the block grid (image sides not divisible by the block size)
    take the label of the nearest grid pixel if they are within the distance threshold of
    that plane. Updates ``labels`` in place."""
    height, width = depth.shape
    v, u = np.nonzero((np.arange(height)[:, None] >= grid_height) | (np.arange(width)[None, :] >= grid_width))
    nearest = labels[np.minimum(v, grid_height - 1), np.minimum(u, grid_width - 1)]
    inside = nearest >= 0
    v, u, nearest = v[inside], u[inside], nearest[inside]
    z = depth[v, u].astype(np.float64)
    a, b = _pinhole_rays(intrinsics, height, width)
    n = normals[nearest]
    distance = np.abs(z * (n[:, 0] * a[u] + n[:, 1] * b[v] + n[:, 2]) + offsets[nearest])
    threshold = cfg.refine_distance_sigmas * np.maximum(coefficient * z * z, rmse[nearest])
    accept = (z > 0) & (distance < threshold)
    labels[v[accept], u[accept]] = nearest[accept]


def _group_medians(values: np.ndarray, groups: np.ndarray, group_count: int) -> np.ndarray:
    """Median of ``values`` within each group id ``0..group_count-1`` (0 for empty groups)."""
    order = np.lexsort((values, groups))
    counts = np.bincount(groups, minlength=group_count)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    last = max(len(values) - 1, 0)
    low = np.minimum(starts + np.maximum(counts - 1, 0) // 2, last)
    high = np.minimum(starts + counts // 2, last)
    ordered = values[order] if len(values) else np.zeros(1)
    return np.where(counts > 0, 0.5 * (ordered[low] + ordered[high]), 0.0)


def _trimmed_moments(units: np.ndarray, unit_plane: np.ndarray, plane_count: int, coefficient: float) -> np.ndarray:
    """Moment sums of each plane over its consistent units (blocks or parts of blocks).

    A plane is fitted to all its units; a unit whose mean signed distance to that plane is an
    outlier, beyond ``3 * max(1.4826 * MAD, sigma_Z / (2 sqrt(n)))`` from the median of the
    plane's units, is dropped and the plane refitted. Such units straddle a crease (a table
    edge, the foot of a wall): their points lie within the noise of the plane but all on one
    side, which would tilt it. The robust scale (MAD) adapts the test to sensors whose
    surfaces are warped more than their noise model says. At most half of a plane's points
    are dropped; otherwise it keeps all its units.
    """
    totals = np.zeros((plane_count, _N_MOMENTS))
    np.add.at(totals, unit_plane, units)
    normals, offsets, _, _ = fit_planes_from_moments(totals)
    count = np.maximum(units[:, 0], 1.0)
    mean_distance = (np.einsum("ij,ij->i", units[:, 1:4], normals[unit_plane]) + offsets[unit_plane] * units[:, 0]) / count
    noise = np.sqrt(_noise_variance(units, coefficient) / count)
    centre = _group_medians(mean_distance, unit_plane, plane_count)
    deviation = np.abs(mean_distance - centre[unit_plane])
    spread = 1.4826 * _group_medians(deviation, unit_plane, plane_count)
    outlier = deviation > 3.0 * np.maximum(spread[unit_plane], 0.5 * noise)
    members = np.bincount(unit_plane, minlength=plane_count)
    points = np.bincount(unit_plane, weights=units[:, 0], minlength=plane_count)
    dropped = np.bincount(unit_plane, weights=units[:, 0] * outlier, minlength=plane_count)
    allowed = (members >= 4) & (dropped <= 0.5 * points)
    keep = ~(outlier & allowed[unit_plane])
    trimmed = np.zeros((plane_count, _N_MOMENTS))
    np.add.at(trimmed, unit_plane[keep], units[keep])
    return trimmed


@functools.lru_cache(maxsize=4)
def _block_pixel_tables(
    intrinsics: CameraIntrinsics, height: int, width: int, block: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block: flat pixel indices ``(B, block^2)`` and the rays ``a_u``, ``b_v`` (float32) there."""
    a, b = _pinhole_rays(intrinsics, height, width)
    hb, wb = height // block, width // block
    v = np.arange(hb)[:, None] * block + np.arange(block)[None, :]  # (hb, block)
    u = np.arange(wb)[:, None] * block + np.arange(block)[None, :]  # (wb, block)
    vv = np.broadcast_to(v[:, None, :, None], (hb, wb, block, block)).reshape(hb * wb, block * block)
    uu = np.broadcast_to(u[None, :, None, :], (hb, wb, block, block)).reshape(hb * wb, block * block)
    tables = (vv * width + uu, a[uu].astype(np.float32), b[vv].astype(np.float32))
    for table in tables:
        table.setflags(write=False)
    return tables


def _finish(labels: np.ndarray, plane_moments: np.ndarray, depth: np.ndarray, min_plane_pixels: int) -> PlaneMeasurements:
    """Drop planes below ``min_plane_pixels`` (pixels with depth in the mask), renumber by
    size, fit and package. Pixels without depth are never labelled."""
    height, width = labels.shape
    labels[depth <= 0] = -1
    counts = np.bincount(labels.ravel() + 1, minlength=len(plane_moments) + 1)[1:].astype(np.int64)
    keep = np.flatnonzero(counts >= min_plane_pixels)
    if len(keep) == 0:
        return empty_planes(height, width)
    keep = keep[np.argsort(-counts[keep], kind="stable")]
    remap = np.full(len(plane_moments) + 1, -1, dtype=np.int32)
    remap[keep] = np.arange(len(keep), dtype=np.int32)
    labels = remap[labels]  # label -1 indexes the last entry, which is -1
    normals, offsets, centroids, mse = fit_planes_from_moments(plane_moments[keep])
    return PlaneMeasurements(
        normals=normals,
        offsets=offsets,
        centroids=centroids,
        point_counts=counts[keep],
        fit_rmse=np.sqrt(mse),
        label_image=labels.astype(np.int32),
    )
