"""Segments of a frame (Caccamo et al. 2017, Section 2.1): plane segments, then depth segments.

Every extracted plane starts a segment (the plane and the point features inside it). The
remaining valid pixels are cut into connected regions at depth discontinuities: two
4-neighbours are apart if their depths differ by more than
``max(min_discontinuity, discontinuity_sigmas * sigma_Z(z_near))``. Only the farther pixel
of such a pair is cut out (so foreground objects keep their silhouette), the regions are
``cv2.connectedComponentsWithStats`` of the remaining pixels, and the cut pixels then join
the neighbouring segment they are continuous with. Regions smaller than
``min_segment_pixels`` join the adjacent segment they share the longest depth-continuous
border with, or are dropped if they have none.

Concave creases (``segments.concave_angle_degrees``, beyond the paper) cut too: where the
surface folds *away* from the camera's side by more than that angle (a box standing on a
table, a mug on a desk), the two sides are not one surface even though their depth is
continuous. Convex folds (the edges of a box) keep an object together. The test compares
normals ``CREASE_BASELINE`` pixels apart, on every ``CREASE_STEP``-th pixel (normals from
``CREASE_WINDOW`` x ``CREASE_WINDOW`` summed cross products of the back-projected depth): the pair is concave when
``(n_p - n_q) . (X_p - X_q) < 0`` (normals towards the camera) and the normals differ by
more than the angle; a band of pixels at the middle of such pairs is cut like the far side
of a discontinuity (its pixels then join the region on either side they are continuous with).

Segment ``i < P`` is plane ``i``; depth segments follow, largest first.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from jsr.config import NoiseConfig, SegmentsConfig
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline.measurements import PlaneMeasurements, PointMeasurements, Segments
from jsr.pipeline.planes import jump_mask

logger = logging.getLogger(__name__)


def build_segments(
    planes: PlaneMeasurements,
    depth: np.ndarray,
    points: PointMeasurements,
    intrinsics: CameraIntrinsics,
    segments_cfg: SegmentsConfig,
    noise_cfg: NoiseConfig,
    keypoint_pixels: np.ndarray | None = None,
) -> Segments:
    """Plane segments plus depth-discontinuity segments of one frame.

    ``depth``: ``(H, W)`` float32 metres (0 = invalid) on the raw image grid, like
    ``planes.label_image``. Points are assigned to segments by their rounded pixel;
    ``keypoint_pixels`` ``(N, 2)`` gives their raw (distorted) pixel positions when
    ``points.pixels`` were undistorted; by default ``points.pixels`` are used.
    ``intrinsics`` is accepted for symmetry with the other stages (segmentation works on the
    raw image grid and needs no calibration).
    """
    depth = np.asarray(depth, dtype=np.float32)
    height, width = depth.shape
    plane_labels = np.asarray(planes.label_image, dtype=np.int32)
    plane_count = len(planes)
    coefficient = noise_cfg.sigma_z_coefficient
    jump_h, jump_v = jump_mask(depth, coefficient, segments_cfg.discontinuity_sigmas, segments_cfg.min_discontinuity)

    # Cut the farther pixel of every discontinuous pair.
    cut = np.zeros((height, width), dtype=bool)
    right_farther = depth[:, 1:] > depth[:, :-1]
    cut[:, 1:] |= jump_h & right_farther
    cut[:, :-1] |= jump_h & ~right_farther
    down_farther = depth[1:, :] > depth[:-1, :]
    cut[1:, :] |= jump_v & down_farther
    cut[:-1, :] |= jump_v & ~down_farther
    if segments_cfg.concave_angle_degrees > 0:
        cut |= concave_creases(depth, intrinsics, segments_cfg.concave_angle_degrees, segments_cfg.min_discontinuity,
                               segments_cfg.discontinuity_sigmas, coefficient)
    valid = depth > 0
    free = valid & (plane_labels < 0) & ~cut
    count, components = cv2.connectedComponents(free.view(np.uint8), connectivity=4, ltype=cv2.CV_32S)
    labels = np.where(components > 0, components + np.int32(plane_count - 1), plane_labels)
    total = plane_count + count - 1

    # Cut pixels join the neighbour they are continuous with (one pass per pixel of width:
    # discontinuity cuts are 1-2 px wide, crease bands about (CREASE_BAND + 2) * CREASE_STEP).
    pending = np.flatnonzero(valid & (labels < 0) & cut)
    flat_labels = labels.ravel()
    passes = max(2, (CREASE_BAND + 2) * CREASE_STEP) if segments_cfg.concave_angle_degrees > 0 else 2
    for _ in range(passes):
        if len(pending) == 0:
            break
        joined = _absorb_from_neighbours(flat_labels, depth.ravel(), pending, jump_h, jump_v, width)
        pending = pending[flat_labels[pending] < 0] if joined else pending[:0]

    sizes = np.bincount(flat_labels + 1, minlength=total + 1)[1:]
    merged = _merge_small_segments(labels, sizes, jump_h, jump_v, plane_count, segments_cfg.min_segment_pixels)
    mapping, pixel_counts = _renumber(merged, sizes, plane_count)
    labels = mapping[labels]
    segment_count = len(pixel_counts)
    plane_index = np.full(segment_count, -1, dtype=np.int64)
    plane_index[:plane_count] = np.arange(plane_count)
    point_indices = _points_per_segment(labels, points, keypoint_pixels, segment_count)
    logger.debug("%d segments (%d planes), %d pixels unsegmented", segment_count, plane_count, int((labels < 0).sum()))
    return Segments(label_image=labels, plane_index=plane_index, point_indices=point_indices, pixel_counts=pixel_counts)


CREASE_STEP = 2  # creases are looked for on every 2nd pixel of every 2nd row (4x less work)
CREASE_BASELINE = 8  # full-resolution px between the two normals compared at a crease (their windows do not overlap)
CREASE_WINDOW = 3  # subsampled px: side of the window the normals are summed over
CREASE_BAND = 1  # subsampled px: dilation of the cut along a crease (1: none; the straddling pairs make it 3 wide)


def concave_creases(depth: np.ndarray, intrinsics: CameraIntrinsics, angle_degrees: float,
                    max_step: float = 0.02, step_sigmas: float = 4.0, sigma_coefficient: float = 1.425e-3,
                    ) -> np.ndarray:
    """``(H, W)`` bool: the pixels of concave creases (see the module docstring): the middles
    of all straddling pairs, a band about 6-8 px wide (dilated by ``CREASE_BAND``), so that
    the cut has few gaps for a region to leak through.

    ``depth`` ``(H, W)`` float32 metres, 0 invalid; pinhole back-projection with
    ``intrinsics``. Tangents across a depth discontinuity (a depth change of more than
    ``max(max_step, step_sigmas sigma_Z)`` per full-resolution pixel) give no normal.
    """
    full = np.asarray(depth, dtype=np.float32)
    full_height, full_width = full.shape
    step = CREASE_STEP
    depth = full[::step, ::step]  # creases are found on every step-th pixel, then mapped back
    height, width = depth.shape
    u = (np.arange(width, dtype=np.float32) * step - np.float32(intrinsics.cx)) / np.float32(intrinsics.fx)
    v = (np.arange(height, dtype=np.float32) * step - np.float32(intrinsics.cy)) / np.float32(intrinsics.fy)
    points = np.stack([depth * u[None, :], depth * v[:, None], depth], axis=2)  # (h, w, 3)
    valid = depth > 0
    # Tangents by central differences, where both ends have depth; their cross product is a
    # normal weighted by the patch area, summed over a window (one box filter per component).
    d_u = np.zeros_like(points)
    d_v = np.zeros_like(points)
    d_u[:, 1:-1] = points[:, 2:] - points[:, :-2]
    d_v[1:-1, :] = points[2:, :] - points[:-2, :]
    ok_u = np.zeros_like(valid)
    ok_v = np.zeros_like(valid)
    limit = 2 * step * np.maximum(np.float32(max_step), np.float32(step_sigmas * sigma_coefficient) * depth * depth)
    ok_u[:, 1:-1] = valid[:, 2:] & valid[:, :-2] & (np.abs(d_u[:, 1:-1, 2]) < limit[:, 1:-1])
    ok_v[1:-1, :] = valid[2:, :] & valid[:-2, :] & (np.abs(d_v[1:-1, :, 2]) < limit[1:-1, :])
    normals = np.cross(d_v, d_u) * (ok_u & ok_v)[:, :, None]  # towards the camera (x right, y down, z ahead)
    normals = cv2.boxFilter(normals, -1, (CREASE_WINDOW, CREASE_WINDOW), normalize=False)
    length = np.linalg.norm(normals, axis=2, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    has_normal = (length[:, :, 0] > 0) & valid
    cos_limit = np.float32(np.cos(np.deg2rad(angle_degrees)))
    k = max(1, CREASE_BASELINE // step)
    band = np.zeros((height, width), dtype=np.uint8)
    for axis, size in ((1, width), (0, height)):
        if size <= k:
            continue
        first = [slice(None), slice(None)]
        second = [slice(None), slice(None)]
        first[axis], second[axis] = slice(0, size - k), slice(k, size)
        first, second = tuple(first), tuple(second)
        n_p, n_q = normals[first], normals[second]
        both = has_normal[first] & has_normal[second]
        bent = np.einsum("...i,...i->...", n_p, n_q) < cos_limit
        concave = np.einsum("...i,...i->...", n_p - n_q, points[first] - points[second]) < 0
        crease = both & bent & concave  # the pair (i, i + k) straddles a crease: mark its middle
        middle = [slice(None), slice(None)]
        middle[axis] = slice(k // 2, k // 2 + size - k)
        band[tuple(middle)] |= crease.astype(np.uint8)
    band = cv2.dilate(band, np.ones((CREASE_BAND, CREASE_BAND), np.uint8))
    full_band = cv2.resize(band, (full_width, full_height), interpolation=cv2.INTER_NEAREST)
    return full_band.astype(bool)


def _absorb_from_neighbours(
    flat_labels: np.ndarray,
    flat_depth: np.ndarray,
    pending: np.ndarray,
    jump_h: np.ndarray,
    jump_v: np.ndarray,
    width: int,
) -> bool:
    """Give each ``pending`` pixel (flat index) the label of its depth-closest continuous 4-neighbour.

    Updates ``flat_labels`` in place; returns whether any pixel got a label.
    """
    total = len(flat_labels)
    rows, cols = np.divmod(pending, width)
    height = total // width
    best_gap = np.full(len(pending), np.inf, dtype=np.float32)
    best_label = np.full(len(pending), -1, dtype=flat_labels.dtype)
    jump_h_flat = jump_h.ravel()  # (H, W-1): pair (r, c)-(r, c+1) at r * (W-1) + c
    jump_v_flat = jump_v.ravel()  # (H-1, W): pair (r, c)-(r+1, c) at r * W + c
    for d_row, d_col in ((0, -1), (0, 1), (-1, 0), (1, 0)):
        n_rows, n_cols = rows + d_row, cols + d_col
        inside = (n_rows >= 0) & (n_rows < height) & (n_cols >= 0) & (n_cols < width)
        index = np.flatnonzero(inside)
        neighbour = n_rows[index] * width + n_cols[index]
        if d_row == 0:
            pair_col = np.minimum(cols[index], n_cols[index])
            jumps = jump_h_flat[rows[index] * (width - 1) + pair_col]
        else:
            pair_row = np.minimum(rows[index], n_rows[index])
            jumps = jump_v_flat[pair_row * width + cols[index]]
        neighbour_labels = flat_labels[neighbour]
        neighbour_depth = flat_depth[neighbour]
        gap = np.abs(flat_depth[pending[index]] - neighbour_depth)
        take = (neighbour_labels >= 0) & ~jumps & (neighbour_depth > 0) & (gap < best_gap[index])
        best_gap[index[take]] = gap[take]
        best_label[index[take]] = neighbour_labels[take]
    found = best_label >= 0
    flat_labels[pending[found]] = best_label[found]
    return bool(found.any())


def _merge_small_segments(
    labels: np.ndarray, sizes: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray, plane_count: int, min_pixels: int
) -> np.ndarray:
    """Where each segment goes: itself, the segment a small one joins, or -1 (dropped).

    Depth segments below ``min_pixels`` point to the neighbouring segment they share the most
    depth-continuous 4-neighbour pairs with. Groups linked by these pointers contain at most
    one large segment (a large segment points nowhere); a group with one takes its id, a
    group of small segments only is kept if together it reaches ``min_pixels``, else
    dropped. Plane segments count as large. Returns ``(S,)`` ids.
    """
    total = len(sizes)
    identity = np.arange(total)
    small = sizes < min_pixels
    small[:plane_count] = False
    if total == 0 or not small.any():
        return identity
    # Depth-continuous pairs of neighbouring pixels in different segments.
    left, right = labels[:, :-1], labels[:, 1:]
    up, down = labels[:-1, :], labels[1:, :]
    border_h = (left != right) & ~jump_h & (left >= 0) & (right >= 0)
    border_v = (up != down) & ~jump_v & (up >= 0) & (down >= 0)
    first = np.concatenate([left[border_h], up[border_v]]).astype(np.int64)
    second = np.concatenate([right[border_h], down[border_v]]).astype(np.int64)
    source = np.concatenate([first, second])
    target = np.concatenate([second, first])
    from_small = small[source]
    source, target = source[from_small], target[from_small]
    pointer = identity.copy()
    if len(source):
        codes, contacts = np.unique(source * total + target, return_counts=True)
        pair_source, pair_target = codes // total, codes % total
        # The target with the most contacts per source (ties: the larger target).
        order = np.lexsort((sizes[pair_target], contacts, pair_source))
        last = np.ones(len(order), dtype=bool)
        last[:-1] = pair_source[order][1:] != pair_source[order][:-1]
        pointer[pair_source[order][last]] = pair_target[order][last]
    linked = pointer != identity
    graph = coo_matrix((np.ones(int(linked.sum())), (identity[linked], pointer[linked])), shape=(total, total))
    _, group = connected_components(graph, directed=False)
    group_size = np.bincount(group, weights=sizes, minlength=total)
    # Id of each group: its large member if any, else its smallest member if big enough.
    group_id = np.full(total, -1, dtype=np.int64)
    large = ~small
    group_id[group[large]] = identity[large]
    orphan = group_id < 0
    if orphan.any():
        first_member = np.full(total, total, dtype=np.int64)
        np.minimum.at(first_member, group, identity)
        keep = orphan & (group_size >= min_pixels)
        group_id[keep] = first_member[keep]
    return group_id[group]


def _renumber(merged: np.ndarray, sizes: np.ndarray, plane_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Final ids: planes keep ``0..P-1``, surviving depth segments follow, largest first.

    ``merged``: ``(S,)`` id each segment is merged into (-1 dropped). Returns the mapping
    from the pre-merge labels (with -1 at index -1) to final ids, and the final pixel counts.
    """
    total = len(sizes)
    kept = merged >= 0
    final_sizes = np.bincount(merged[kept], weights=sizes[kept], minlength=max(total, plane_count)).astype(np.int64)
    depth_ids = np.arange(plane_count, total)
    depth_ids = depth_ids[final_sizes[depth_ids] > 0]
    depth_ids = depth_ids[np.argsort(-final_sizes[depth_ids], kind="stable")]
    final_id = np.full(max(total, plane_count), -1, dtype=np.int32)
    final_id[:plane_count] = np.arange(plane_count)
    final_id[depth_ids] = np.arange(plane_count, plane_count + len(depth_ids))
    mapping = np.full(total + 1, -1, dtype=np.int32)  # the last entry serves label -1
    mapping[:total] = np.where(kept, final_id[np.maximum(merged, 0)], -1)
    counts = np.concatenate([final_sizes[:plane_count], final_sizes[depth_ids]])
    return mapping, counts


def _points_per_segment(
    labels: np.ndarray, points: PointMeasurements, keypoint_pixels: np.ndarray | None, segment_count: int
) -> list[np.ndarray]:
    """Indices of the point measurements whose rounded pixel lies in each segment."""
    pixels = points.pixels if keypoint_pixels is None else np.asarray(keypoint_pixels, dtype=np.float64)
    if len(pixels) == 0 or segment_count == 0:
        return [np.zeros(0, dtype=np.int64) for _ in range(segment_count)]
    height, width = labels.shape
    u = np.rint(pixels[:, 0]).astype(np.int64)
    v = np.rint(pixels[:, 1]).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    owner = np.full(len(pixels), -1, dtype=np.int64)
    owner[inside] = labels[v[inside], u[inside]]
    order = np.argsort(owner, kind="stable")
    boundaries = np.searchsorted(owner[order], np.arange(segment_count + 1))
    return [order[boundaries[i] : boundaries[i + 1]] for i in range(segment_count)]


def depth_adjacent_segments(label_image: np.ndarray, depth: np.ndarray, noise, segments_config,
                            max_gap_pixels: int = 3, min_boundary_pixels: int = 10) -> np.ndarray:
    """``(E, 2)`` pairs ``(a, b)``, ``a < b``, of segments that touch *in 3D*: along at least
    ``min_boundary_pixels`` image neighbours (up to ``max_gap_pixels`` apart, horizontally or
    vertically), their depths differ by less than the segmentation's discontinuity threshold.

    Segments are cut at depth discontinuities, so two segments whose boundary is continuous in
    depth meet at an edge (two faces of a box, a box standing on a table); a box in front of
    a wall is image-adjacent to it but not depth-adjacent.
    """
    labels = np.asarray(label_image)
    z = np.asarray(depth, dtype=np.float64)
    pairs = []
    for gap in range(1, max_gap_pixels + 2):
        for a, b, za, zb in (
            (labels[:, :-gap], labels[:, gap:], z[:, :-gap], z[:, gap:]),
            (labels[:-gap, :], labels[gap:, :], z[:-gap, :], z[gap:, :]),
        ):
            keep = (a >= 0) & (b >= 0) & (a != b) & (za > 0) & (zb > 0)
            if not keep.any():
                continue
            za_k, zb_k = za[keep], zb[keep]
            mean_z = 0.5 * (za_k + zb_k)
            sigma = noise.sigma_z_coefficient * mean_z**2
            threshold = np.maximum(segments_config.min_discontinuity, segments_config.discontinuity_sigmas * sigma)
            continuous = np.abs(za_k - zb_k) < threshold * gap
            if continuous.any():
                pairs.append(np.sort(np.stack([a[keep][continuous], b[keep][continuous]], axis=1), axis=1))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    stacked = np.concatenate(pairs).astype(np.int64)
    # one integer key per pair (a * S + b): counting keys is much faster than unique rows,
    # and sorted keys are the pairs in lexicographic order
    count = int(stacked.max()) + 1
    keys, counts = np.unique(stacked[:, 0] * count + stacked[:, 1], return_counts=True)
    keys = keys[counts >= min_boundary_pixels]
    return np.stack([keys // count, keys % count], axis=1)
