"""Fast plane extraction on the organized point cloud of a depth image.

After Feng, Taguchi and Kamat, "Fast plane extraction in organized point clouds using
agglomerative hierarchical clustering" (ICRA 2014):

1. The image is cut into ``block_size`` x ``block_size`` blocks. The first and second moments
   of the 3D points of every block come from separable sums (``X = a_u Z``, ``Y = b_v Z`` for
   a pinhole camera: a few per-pixel products, then sums over block rows and columns), plus
   the sum of ``Z^4`` for the noise model. A cluster of blocks is the sum of their moments,
   so fitting it is O(1): the plane normal is the eigenvector of the smallest eigenvalue of
   the covariance (closed-form symmetric 3x3 eigen-solver, vectorised over all clusters;
   :mod:`jsr.pipeline.plane_fitting`).
2. Blocks are rejected when more than ``max_block_missing`` of their pixels have no depth,
   when two neighbouring pixels inside differ by more than
   ``max(min_depth_jump, depth_jump_sigmas * sigma_Z)`` (a discontinuity), or when their fit
   RMSE exceeds ``max_block_rmse_sigmas * sigma_Z``.
3. Agglomerative hierarchical clustering of the graph of adjacent planar blocks; two clusters
   may merge when their normals agree (within ``merge_angle_degrees``, widened for clusters
   whose normal is noisy, see :mod:`jsr.pipeline.plane_clustering`) and the merged RMSE
   stays below ``merge_rmse_sigmas * sigma_Z``; the cheapest merge (merged MSE relative to
   the noise expected at its depths) goes first. The lower levels of the hierarchy, where
   merges are independent, are computed in vectorised rounds (mutually best pairs, and stars
   of blocks around them); a binary heap then finishes the hierarchy sequentially, with lazy
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

import cv2
import numpy as np

from jsr.config import NoiseConfig, PlanesConfig
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline.measurements import PlaneMeasurements
from jsr.pipeline.plane_clustering import cluster_blocks
from jsr.pipeline.plane_fitting import (
    N_MOMENTS,
    block_moments,
    fit_planes_from_moments,
    fit_stack,
    noise_variance,
    smallest_eigenvalues,
)

# Floor of the measured plane RMSE used to select the pixels of a refit (metres; the depth
# PNG resolution is 0.2 mm).
_MIN_REFIT_RMSE = 0.001


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
    moments = block_moments(depth, a, b, block)
    flat_moments = moments.reshape(-1, N_MOMENTS)
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
    mse[planar] = smallest_eigenvalues(flat_moments[planar])
    planar &= mse <= cfg.max_block_rmse_sigmas**2 * noise_variance(flat_moments, coefficient)

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
        plane_moments = np.zeros((len(plane_roots), N_MOMENTS))
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
    flat_moments = moments.reshape(-1, N_MOMENTS)
    plane_moments = np.zeros((plane_count, N_MOMENTS))
    interior_blocks = flat_interior >= 0
    np.add.at(plane_moments, flat_interior[interior_blocks], flat_moments[interior_blocks])
    # Pixels are judged against the plane of the whole cluster (interior and border blocks):
    # the interior alone can be a single column of blocks, too narrow to fix the normal.
    cluster_moments = np.zeros((plane_count, N_MOMENTS))
    cluster_blocks_mask = block_labels.ravel() >= 0
    np.add.at(cluster_moments, block_labels.ravel()[cluster_blocks_mask], flat_moments[cluster_blocks_mask])
    normals, offsets, _, eigenvalues = fit_stack(cluster_moments)
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
    interior_rmse = np.sqrt(np.maximum(fit_stack(plane_moments)[3][:, 0], _MIN_REFIT_RMSE**2))
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
    totals = np.zeros((plane_count, N_MOMENTS))
    np.add.at(totals, unit_plane, units)
    normals, offsets, _, _ = fit_planes_from_moments(totals)
    count = np.maximum(units[:, 0], 1.0)
    mean_distance = (np.einsum("ij,ij->i", units[:, 1:4], normals[unit_plane]) + offsets[unit_plane] * units[:, 0]) / count
    noise = np.sqrt(noise_variance(units, coefficient) / count)
    centre = _group_medians(mean_distance, unit_plane, plane_count)
    deviation = np.abs(mean_distance - centre[unit_plane])
    spread = 1.4826 * _group_medians(deviation, unit_plane, plane_count)
    outlier = deviation > 3.0 * np.maximum(spread[unit_plane], 0.5 * noise)
    members = np.bincount(unit_plane, minlength=plane_count)
    points = np.bincount(unit_plane, weights=units[:, 0], minlength=plane_count)
    dropped = np.bincount(unit_plane, weights=units[:, 0] * outlier, minlength=plane_count)
    allowed = (members >= 4) & (dropped <= 0.5 * points)
    keep = ~(outlier & allowed[unit_plane])
    trimmed = np.zeros((plane_count, N_MOMENTS))
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
