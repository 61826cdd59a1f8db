"""SIFT point measurements: 3D points (keypoints with depth) and 2D points (bearings only).

One OpenCV SIFT call per frame on the grey image (``max_keypoints``, ``contrast_threshold``,
``edge_threshold``). With ``half_resolution`` (the default) the image is halved first:
OpenCV's SIFT doubles its input, so its scale space then starts at the full resolution
instead of twice it. That is about three times faster; it loses only the finest-scale
keypoints, and with ``contrast_threshold`` 0.02 it keeps about as many geometrically correct
matches between nearby frames as full-resolution SIFT with OpenCV's default 0.04 (measured
on redkitchen300: median 184 versus 212 correct 3D-3D matches between frames 8 apart, worst
case 41 versus 30).

Small objects are the exception: a 200 x 150 pixel box carries 35-60 half-resolution
keypoints, too few to follow it through a jump that turns it. :func:`detect_detail_keypoints`
adds the missing finest octave inside given boxes (the front-end passes the boxes of the
objects of the previous frame, ``features.object_detail``): 150-300 keypoints on that box, at
about 9 ms per 300 x 250 box.

A keypoint's depth is looked up robustly in the raw depth image, which is registered to the
raw (distorted) colour image: the median of the valid depths in a ``(2r+1)^2`` window around
the rounded keypoint pixel (``r = depth_window``). The lookup fails, and the keypoint becomes a
2D point, when fewer than half of the window has depth or when the window straddles a depth
discontinuity: some valid depth differs from the median by more than
``max(min_depth_spread, depth_spread_sigmas * sigma_Z(median))``. This keeps keypoints on
object silhouettes from taking the depth of the background.

A surface seen at a grazing angle spreads the window's depths beyond that limit too, with no
discontinuity: at 320x240 a box face 2 m away, 64 degrees from the view direction, spreads 3 cm
over 5 pixels, so a whole face had no 3D keypoint (at 640x480 half as much). A window whose
depths lie on one plane (largest residual of the least-squares plane at most half the limit: a
step of h leaves up to 0.4 h) gives the plane's depth at the keypoint when that plane is seen
at most ``slanted_max_incidence`` degrees from face-on: beyond, a pixel of keypoint error
is several pixels' footprint of depth error. Such a window may still span a crease (the bottom
edge of a box on a grazing table top), so once the frame is segmented,
:func:`keep_slanted_within_segments` turns back into 2D points the slanted ones whose window
reaches another segment (measured at 320x240: without that, 3-8% of the object maps' landmarks
lay on the table beside the box). Off by default (``slanted_max_incidence`` 0): the measured
trade-off is in ``configs/default.yaml``.

The 3D point back-projects the undistorted keypoint (when the camera has distortion and
``undistort`` is on) with that depth; ``sigma_z = noise.sigma_z_coefficient * Z^2``.
"""

from __future__ import annotations

import itertools
import logging

import cv2
import numpy as np

from jsr.config import FeaturesConfig, NoiseConfig
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline.measurements import PointMeasurements

logger = logging.getLogger(__name__)


def create_sift(cfg: FeaturesConfig) -> cv2.SIFT:
    """An OpenCV SIFT detector with the configured limits (reuse it across frames)."""
    return cv2.SIFT_create(
        nfeatures=int(cfg.max_keypoints),
        contrastThreshold=float(cfg.contrast_threshold),
        edgeThreshold=float(cfg.edge_threshold),
    )


def to_grey(color_rgb: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 grey image of an RGB (or already grey) image."""
    if color_rgb.ndim == 2:
        return color_rgb
    return cv2.cvtColor(color_rgb, cv2.COLOR_RGB2GRAY)


def detect_keypoints(
    grey: np.ndarray, cfg: FeaturesConfig, sift: cv2.SIFT | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """One SIFT detect-and-describe call on a grey image.

    Returns ``(pixels (N, 2) float64 raw pixel coordinates, descriptors (N, 128) float32)``.
    With ``half_resolution`` SIFT runs on the image downsampled by 2: OpenCV's SIFT then
    upsamples it back, so the scale space starts at the full image resolution instead of at
    twice it (about 4x faster, without the finest-scale keypoints); coordinates are mapped
    back to the full image.
    """
    if sift is None:
        sift = create_sift(cfg)
    scale = 1.0
    image = grey
    if cfg.half_resolution:
        image = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA)
        scale = grey.shape[1] / image.shape[1]
    keypoints, descriptors = sift.detectAndCompute(image, None)
    if not keypoints:
        return np.zeros((0, 2)), np.zeros((0, 128), dtype=np.float32)
    pixels = np.array([keypoint.pt for keypoint in keypoints], dtype=np.float64)
    if scale != 1.0:
        pixels = (pixels + 0.5) * scale - 0.5
    return pixels, np.asarray(descriptors, dtype=np.float32)


DETAIL_CROP_MARGIN = 8  # px of context around a detail box (SIFT's border and its descriptor window)
FINEST_OCTAVE = 255  # OpenCV's octave byte of the keypoints found on the doubled image (octave -1)


def detect_detail_keypoints(
    grey: np.ndarray, boxes: list[tuple[int, int, int, int]], sift: cv2.SIFT
) -> tuple[np.ndarray, np.ndarray]:
    """The finest-scale SIFT keypoints inside ``boxes`` (``x0, y0, x1, y1`` pixels, exclusive
    ends), which half-resolution SIFT (:func:`detect_keypoints`) does not find.

    Each box (overlapping boxes joined first) is cropped with a small margin and run through
    full-resolution SIFT; only keypoints of its first octave (on the doubled image) and inside
    the box are kept, so none repeats a keypoint of the half-resolution pass. Returns
    ``(pixels (N, 2) float64 full-image coordinates, descriptors (N, 128) float32)``.
    """
    height, width = grey.shape
    all_pixels, all_descriptors = [], []
    for x0, y0, x1, y1 in join_boxes(boxes):
        cx0, cy0 = max(0, x0 - DETAIL_CROP_MARGIN), max(0, y0 - DETAIL_CROP_MARGIN)
        cx1, cy1 = min(width, x1 + DETAIL_CROP_MARGIN), min(height, y1 + DETAIL_CROP_MARGIN)
        if cx1 - cx0 < 16 or cy1 - cy0 < 16:
            continue
        keypoints, descriptors = sift.detectAndCompute(grey[cy0:cy1, cx0:cx1], None)
        if not keypoints:
            continue
        pixels = np.array([k.pt for k in keypoints], dtype=np.float64) + [cx0, cy0]
        finest = np.array([(k.octave & 255) == FINEST_OCTAVE for k in keypoints])
        inside = (pixels[:, 0] >= x0) & (pixels[:, 0] < x1) & (pixels[:, 1] >= y0) & (pixels[:, 1] < y1)
        keep = finest & inside
        all_pixels.append(pixels[keep])
        all_descriptors.append(np.asarray(descriptors, dtype=np.float32)[keep])
    if not all_pixels:
        return np.zeros((0, 2)), np.zeros((0, 128), dtype=np.float32)
    return np.concatenate(all_pixels), np.concatenate(all_descriptors)


def join_boxes(boxes: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Boxes ``(x0, y0, x1, y1)`` with every overlapping pair replaced by its union, in a
    deterministic order."""
    joined = [tuple(int(v) for v in box) for box in boxes if box[2] > box[0] and box[3] > box[1]]
    merged = True
    while merged:  # until no two boxes overlap
        merged = False
        for i, j in itertools.combinations(range(len(joined)), 2):
            a, b = joined[i], joined[j]
            if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                joined[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                del joined[j]
                merged = True
                break
    return sorted(joined)


def lookup_depth(
    depth: np.ndarray, pixels: np.ndarray, cfg: FeaturesConfig, noise_cfg: NoiseConfig,
    focal_length: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Robust depth at ``(N, 2)`` raw pixel positions; returns ``(depth (N,), valid (N,))``.
    Slanted windows (``cfg.slanted_max_incidence``) need the ``focal_length`` (pixels).

    Vectorised: all windows are gathered with one fancy index into an ``(N, K)`` array and
    sorted row-wise (invalid depths sort last), so the median of the valid values is read at
    the middle of each row's valid part.
    """
    count = len(pixels)
    if count == 0:
        return np.zeros(0), np.zeros(0, dtype=bool)
    radius = int(cfg.depth_window)
    u, v, uu, vv = _window_pixels(pixels, radius, depth.shape)
    # Border pixels repeat when a window is clipped; acceptable for a robust statistic.
    windows = depth[vv, uu].reshape(count, -1).astype(np.float64)
    size = windows.shape[1]
    valid_count = (windows > 0).sum(axis=1)
    ordered = np.sort(np.where(windows > 0, windows, np.inf), axis=1)
    low = np.clip((valid_count - 1) // 2, 0, size - 1)
    high = np.clip(valid_count // 2, 0, size - 1)
    median = 0.5 * (
        np.take_along_axis(ordered, low[:, None], axis=1)[:, 0] + np.take_along_axis(ordered, high[:, None], axis=1)[:, 0]
    )
    enough = valid_count * 2 >= size
    median = np.where(enough, median, 0.0)
    smallest = ordered[:, 0]
    largest = np.take_along_axis(ordered, np.maximum(valid_count - 1, 0)[:, None], axis=1)[:, 0]
    limit = np.maximum(cfg.min_depth_spread, cfg.depth_spread_sigmas * noise_cfg.sigma_z_coefficient * median * median)
    continuous = (median - smallest <= limit) & (largest - median <= limit)
    result = np.where(continuous, median, 0.0)
    if cfg.slanted_max_incidence > 0 and focal_length is not None:
        # A surface seen at a grazing angle spreads its depths over the window by more than the
        # limit (at 320x240, 2 m away and 64 degrees from the view direction: 3 cm over 5 px)
        # without any discontinuity: its depths lie on one plane. A depth edge does not (a step
        # of h leaves residuals up to 0.4 h to the plane fitted across it), hence half the limit.
        slanted = np.flatnonzero(enough & ~continuous & (median > 0))
        shape = (count, 2 * radius + 1, 2 * radius + 1)
        du = np.broadcast_to(uu - u[:, None, None], shape).reshape(count, -1)
        dv = np.broadcast_to(vv - v[:, None, None], shape).reshape(count, -1)
        plane_depth, residual, slope = _window_planes(windows[slanted], du[slanted], dv[slanted])
        # depth change per pixel over the pixel's footprint (z / f): tan of the angle between
        # the surface normal and the view ray (near the image centre)
        incidence = np.degrees(np.arctan(slope * focal_length / np.maximum(plane_depth, 1e-6)))
        accept = (residual <= 0.5 * limit[slanted]) & (incidence <= cfg.slanted_max_incidence)
        result[slanted[accept]] = plane_depth[accept]
    valid = enough & (result > 0)
    return np.where(valid, result, 0.0), valid


def keep_slanted_within_segments(points: PointMeasurements, pixels: np.ndarray, depth: np.ndarray,
                                 segment_labels: np.ndarray, cfg: FeaturesConfig, noise_cfg: NoiseConfig) -> int:
    """Turn into 2D points, in place, the 3D points of ``points`` whose depth came from a
    slanted window (see :func:`lookup_depth`) that reaches a pixel of another segment or of
    none in ``segment_labels`` ``(H, W)`` (-1: no segment). ``pixels`` ``(N, 2)``: the raw
    keypoint pixels the depth was looked up at. Returns how many were turned."""
    if cfg.slanted_max_incidence <= 0 or not len(points):
        return 0
    plain = lookup_depth(depth, pixels, cfg, noise_cfg)[1]  # without a focal length: no slanted windows
    slanted = np.flatnonzero(points.has_depth & ~plain)
    if not len(slanted):
        return 0
    u, v, uu, vv = _window_pixels(pixels[slanted], int(cfg.depth_window), segment_labels.shape)
    window = segment_labels[vv, uu].reshape(len(slanted), -1)
    own = segment_labels[v, u]
    straddling = slanted[(own < 0) | (window != own[:, None]).any(axis=1)]
    points.has_depth[straddling] = False
    points.points[straddling] = np.nan
    points.sigma_z[straddling] = 0.0
    return len(straddling)


def _window_pixels(pixels: np.ndarray, radius: int, shape: tuple[int, int]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rounded pixels ``u``, ``v`` ``(N,)`` of ``(N, 2)`` raw ``pixels`` and the columns
    ``(N, 1, 2r+1)`` and rows ``(N, 2r+1, 1)`` of their ``(2r+1)^2`` windows (``r = radius``),
    all clipped to an image of ``shape`` ``(H, W)``: ``image[rows, columns]`` is ``(N, 2r+1, 2r+1)``."""
    height, width = shape
    offsets = np.arange(-radius, radius + 1)
    u = np.clip(np.rint(pixels[:, 0]).astype(np.int64), 0, width - 1)
    v = np.clip(np.rint(pixels[:, 1]).astype(np.int64), 0, height - 1)
    columns = np.clip(u[:, None, None] + offsets[None, None, :], 0, width - 1)
    rows = np.clip(v[:, None, None] + offsets[None, :, None], 0, height - 1)
    return u, v, columns, rows


def _window_planes(windows: np.ndarray, du: np.ndarray, dv: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares planes ``z = a du + b dv + c`` through the valid (> 0) depths of ``(N, K)``
    windows at pixel offsets ``du``, ``dv`` ``(N, K)`` from their keypoints' pixels: the depth
    ``c`` at each keypoint's pixel ``(N,)``, the largest absolute residual ``(N,)`` and the
    depth change per pixel ``hypot(a, b)`` ``(N,)``."""
    if len(windows) == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    weight = (windows > 0).astype(np.float64)
    design = np.stack([du, dv, np.ones_like(du)], axis=2).astype(np.float64)  # (N, K, 3)
    normal = np.einsum("nk,nki,nkj->nij", weight, design, design)
    rhs = np.einsum("nk,nki,nk->ni", weight, design, windows)
    solvable = np.abs(np.linalg.det(normal)) > 1e-9
    coefficients = np.zeros((len(windows), 3))
    coefficients[solvable] = np.linalg.solve(normal[solvable], rhs[solvable][..., None])[..., 0]
    residual = np.abs(windows - np.einsum("nki,ni->nk", design, coefficients)) * weight
    largest = np.where(solvable, residual.max(axis=1), np.inf)
    return coefficients[:, 2], largest, np.hypot(coefficients[:, 0], coefficients[:, 1])


def build_point_measurements(
    pixels: np.ndarray,
    descriptors: np.ndarray,
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    cfg: FeaturesConfig,
    noise_cfg: NoiseConfig,
) -> PointMeasurements:
    """Point measurements from raw keypoint ``pixels`` ``(N, 2)`` and their descriptors."""
    if len(pixels) == 0:
        return PointMeasurements.empty()
    z, has_depth = lookup_depth(depth, pixels, cfg, noise_cfg, intrinsics.fx)
    ideal = pixels
    if cfg.undistort and intrinsics.has_distortion:
        ideal = intrinsics.undistort_pixels(pixels)
    x = (ideal[:, 0] - intrinsics.cx) / intrinsics.fx
    y = (ideal[:, 1] - intrinsics.cy) / intrinsics.fy
    rays = np.column_stack([x, y, np.ones_like(x)])
    bearings = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    points = np.full((len(pixels), 3), np.nan)
    points[has_depth] = rays[has_depth] * z[has_depth, None]
    sigma_z = np.where(has_depth, noise_cfg.sigma_z_coefficient * z * z, 0.0)
    return PointMeasurements(
        pixels=np.ascontiguousarray(ideal, dtype=np.float64),
        points=points,
        has_depth=has_depth,
        bearings=bearings,
        sigma_z=sigma_z,
        descriptors=np.ascontiguousarray(descriptors, dtype=np.float32),
    )


def extract_point_measurements(
    color_rgb: np.ndarray,
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    features_cfg: FeaturesConfig,
    noise_cfg: NoiseConfig,
    sift: cv2.SIFT | None = None,
) -> PointMeasurements:
    """SIFT on the grey image, robust depth lookup, back-projection: the frame's points."""
    pixels, descriptors = detect_keypoints(to_grey(color_rgb), features_cfg, sift)
    measurements = build_point_measurements(pixels, descriptors, depth, intrinsics, features_cfg, noise_cfg)
    logger.debug("%d keypoints, %d with depth", len(measurements), int(measurements.has_depth.sum()))
    return measurements
