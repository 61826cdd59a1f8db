"""An object's extent: the convex hull of its points (object frame), and which pixels and
segments of a frame lie inside it (beyond the paper: faces of an object whose keypoints have no
reliable depth still join the object when they lie inside its extent)."""

from __future__ import annotations

import numpy as np

from jsr.geometry import backproject_pixels, inlier_threshold, transform_points


def segments_inside_extent(label_image: np.ndarray, depth: np.ndarray, intrinsics, T_o_c: np.ndarray,
                           hull, noise, num_segments: int, margin: float, min_share: float,
                           stride: int = 4, min_samples: int = 10) -> np.ndarray:
    """``(S,)`` bool: segments whose surface lies inside the object's extent, ``hull``
    (:func:`extent_hull` of its landmarks, object frame; None: nothing is inside), widened by
    ``max(margin, inlier_sigmas sigma_Z)`` (the outermost keypoints of a face lie a few
    centimetres inside its edges): at least ``min_share`` of their sampled pixels (every ``stride``-th, with
    depth; at least ``min_samples`` of them) moved into the object frame with ``T_o_c`` fall
    inside. A face of a box seen at a grazing angle, whose keypoints have no reliable depth,
    lies on the hull of the landmarks of the faces next to it; the table the box stands on
    reaches far outside it.
    """
    result = np.zeros(num_segments, dtype=bool)
    if hull is None or num_segments == 0:
        return result
    labels = np.asarray(label_image)[::stride, ::stride]
    z = np.asarray(depth, dtype=np.float64)[::stride, ::stride]
    rows, cols = np.nonzero((labels >= 0) & (z > 0))
    if not len(rows):
        return result
    inside_pixel = pixels_inside_hull(rows * stride, cols * stride, z[rows, cols], intrinsics, T_o_c, hull, noise,
                                      margin)
    segment = labels[rows, cols]
    samples = np.bincount(segment, minlength=num_segments)
    inside = np.bincount(segment, weights=inside_pixel.astype(float), minlength=num_segments)
    return (samples >= min_samples) & (inside >= min_share * np.maximum(samples, 1))


EXTENT_OUTLIER_FACTOR = 3.0  # landmarks farther from the median than this many median distances are left out


def without_strays(points: np.ndarray) -> np.ndarray:
    """The ``(N, 3)`` points without those farther from their median than
    ``EXTENT_OUTLIER_FACTOR`` times the median distance (``(M, 3)``, ``M <= N``)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if not len(points):
        return points
    distance = np.linalg.norm(points - np.median(points, axis=0), axis=1)
    return points[distance <= EXTENT_OUTLIER_FACTOR * max(float(np.median(distance)), 1e-6)]


def extent_hull(landmarks: np.ndarray):
    """The convex hull (scipy ``ConvexHull``) of ``(L, 3)`` object points (its landmarks, and
    with ``objects.extent_from_surface`` its surface samples), or None when there are fewer
    than 8 of them or they span no volume. Points farther from their median than
    ``EXTENT_OUTLIER_FACTOR`` times the median distance are left out: one stray landmark (a
    scene feature the object map took) must not stretch the extent over the scene."""
    from scipy.spatial import ConvexHull, QhullError

    landmarks = without_strays(landmarks)
    if len(landmarks) < 8:
        return None
    try:
        return ConvexHull(landmarks)
    except (QhullError, ValueError):  # flat or degenerate: no volume to be inside of
        return None


def pixels_inside_hull(rows: np.ndarray, cols: np.ndarray, depths: np.ndarray, intrinsics, T_o_c: np.ndarray,
                       hull, noise, margin: float) -> np.ndarray:
    """``(M,)`` bool: pixels ``(rows, cols)`` with depth ``depths`` (metres) whose 3D point,
    moved into the object frame with ``T_o_c``, lies inside ``hull`` widened by
    ``max(margin, inlier_sigmas sigma_Z)``."""
    zs = np.asarray(depths, dtype=np.float64)
    camera = backproject_pixels(cols, rows, zs, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    in_object = transform_points(T_o_c, camera)
    threshold = inlier_threshold(zs, noise.sigma_z_coefficient, noise.inlier_sigmas, margin)
    normals, offsets = hull.equations[:, :3], hull.equations[:, 3]
    # A point's distance outside the hull is the largest over its facets (> 0: outside). Most
    # pixels lie far from the object: a few facets facing every way already put them past
    # the threshold, and only the rest need all facets (the result is the same).
    few = np.unique(np.argmax(normals @ _PREFILTER_DIRECTIONS.T, axis=0))
    candidate = np.max(in_object @ normals[few].T + offsets[few], axis=1) <= threshold
    inside = np.zeros(len(zs), dtype=bool)
    inside[candidate] = np.max(in_object[candidate] @ normals.T + offsets, axis=1) <= threshold[candidate]
    return inside


# the 6 axis and 8 diagonal directions: a hull's facets facing closest to them bound it on all sides
_PREFILTER_DIRECTIONS = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)
                                  if abs(x) + abs(y) + abs(z) in (1, 3)], dtype=float)


SIZE_FACTOR = 1.5  # a surface this much wider than everything known of an object is not part of it


def largest_spread(points: np.ndarray) -> float:
    """The width of ``(N, 3)`` points: their largest spread along their principal axes (metres;
    rotation invariant, so a partial view of an object is never wider than the object)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) < 2:
        return 0.0
    centred = points - points.mean(axis=0)
    axes = np.linalg.svd(centred[:: max(1, len(centred) // 2000)], full_matrices=False)[2]
    spread = centred @ axes.T
    return float((spread.max(axis=0) - spread.min(axis=0)).max())


def wider_than(label_image: np.ndarray, depth: np.ndarray, intrinsics, segments: np.ndarray,
               object_width: float) -> np.ndarray:
    """``(len(segments),)`` bool: segments whose surface (:func:`segment_widths`) is more than
    ``SIZE_FACTOR`` times ``object_width`` (metres): wider than the object can be."""
    return segment_widths(label_image, depth, intrinsics, segments) > SIZE_FACTOR * object_width


def segment_widths(label_image: np.ndarray, depth: np.ndarray, intrinsics, segments: np.ndarray,
                   stride: int = 4) -> np.ndarray:
    """``(len(segments),)`` the :func:`largest_spread` of each segment's surface (every
    ``stride``-th pixel with depth, camera frame; 0 without depth)."""
    labels = np.asarray(label_image)[::stride, ::stride]
    z = np.asarray(depth, dtype=np.float64)[::stride, ::stride]
    widths = np.zeros(len(segments))
    for k, segment in enumerate(segments):
        rows, cols = np.nonzero((labels == segment) & (z > 0))
        if len(rows) >= 2:
            widths[k] = largest_spread(backproject_pixels(cols * stride, rows * stride, z[rows, cols], intrinsics.fx,
                                                          intrinsics.fy, intrinsics.cx, intrinsics.cy))
    return widths
