"""Plane fits of point sets given by their moment sums.

A block of pixels or a cluster of blocks is described by ``N_MOMENTS`` moment sums of its 3D
points (camera frame, metres): ``n, Sx, Sy, Sz, Sxx, Sxy, Sxz, Syy, Syz, Szz, Sz^4``. A union
of point sets is the sum of their moments, so fitting it is O(1): the plane normal is the
eigenvector of the smallest eigenvalue of the covariance (closed-form symmetric 3x3
eigen-solver, vectorised over many rows, or in pure Python for one cluster). Also here: the
block moments of a depth image from separable pinhole rays, and the noise model of a fit
(mean sigma_Z^2 with ``sigma_Z = c * Z^2``, the variance of the fitted normal). Used by the
plane extraction of :mod:`jsr.pipeline.planes` (after Feng, Taguchi and Kamat, ICRA 2014).
"""

from __future__ import annotations

import math
import threading

import numpy as np

# Moment channels of a block or a cluster: n, Sx, Sy, Sz, Sxx, Sxy, Sxz, Syy, Syz, Szz, Sz^4.
N_MOMENTS = 11
_TWO_THIRDS_PI = 2.0 * math.pi / 3.0
# A cluster's normal is defined only if its narrower in-plane spread exceeds the noise
# variance by this factor (eigenvalue gap); otherwise the angle test does not apply to it.
MIN_GAP_TO_NOISE = 4.0


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


def block_moments(depth: np.ndarray, a: np.ndarray, b: np.ndarray, block: int) -> np.ndarray:
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
    moments = np.empty((hb, wb, N_MOMENTS))
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
    normals, offsets, mean, eigenvalues = fit_stack(moments)
    return normals, offsets, mean, eigenvalues[..., 0]


def fit_stack(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def smallest_eigenvalues(moments: np.ndarray) -> np.ndarray:
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


def normal_variance(moments: np.ndarray, eigenvalues: np.ndarray, coefficient: float, correlation: float) -> np.ndarray:
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
    noise = np.maximum(eigenvalues[..., 0], noise_variance(moments, coefficient))
    gap = eigenvalues[..., 1] - eigenvalues[..., 0]
    variance = noise / (n * np.maximum(gap, 1e-12))
    return np.where(gap > MIN_GAP_TO_NOISE * noise, variance, np.inf)


def noise_variance(moments: np.ndarray, coefficient: float) -> np.ndarray:
    """Mean of sigma_Z^2 over the points of each moment row: ``c^2 * E[Z^4]``."""
    return coefficient * coefficient * moments[..., 10] / np.maximum(moments[..., 0], 1.0)


def fit_scalar(m: list[float], with_normal: bool) -> tuple[float, ...]:
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
