"""Point measurements (jsr.pipeline.features): depth lookup, back-projection, undistortion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jsr.config import Config
from jsr.io.camera import CAMERA_PRESETS, CameraIntrinsics
from jsr.pipeline.features import (
    build_point_measurements,
    create_sift,
    detect_detail_keypoints,
    detect_keypoints,
    join_boxes,
    keep_slanted_within_segments,
    extract_point_measurements,
    lookup_depth,
    to_grey,
)

SIGMA = 1.425e-3


def textured_image(height: int = 480, width: int = 640, seed: int = 0) -> np.ndarray:
    """A colour image with plenty of SIFT keypoints (random blobs and lines)."""
    rng = np.random.default_rng(seed)
    image = np.full((height, width, 3), 128, np.uint8)
    for _ in range(400):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        if rng.random() < 0.5:
            cv2.circle(image, centre, int(rng.integers(3, 20)), colour, -1)
        else:
            end = (centre[0] + int(rng.integers(-40, 40)), centre[1] + int(rng.integers(-40, 40)))
            cv2.line(image, centre, end, colour, int(rng.integers(1, 4)))
    return image


def reference_lookup(depth: np.ndarray, pixel: np.ndarray, radius: int, spread_sigmas: float, min_spread: float):
    """Straightforward per-keypoint version of the robust depth lookup."""
    height, width = depth.shape
    u, v = int(np.clip(np.rint(pixel[0]), 0, width - 1)), int(np.clip(np.rint(pixel[1]), 0, height - 1))
    values = []
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            values.append(depth[min(max(v + dv, 0), height - 1), min(max(u + du, 0), width - 1)])
    values = np.array(values, dtype=np.float64)
    valid = values[values > 0]
    if 2 * len(valid) < len(values):
        return None
    median = float(np.median(valid))
    limit = max(min_spread, spread_sigmas * SIGMA * median**2)
    if np.any(np.abs(valid - median) > limit):
        return None
    return median


@pytest.fixture(scope="module")
def synth_pair():
    """One synthetic frame rendered noise-free and with Kinect noise (same colour image)."""
    from jsr.synth.options import SynthOptions
    from jsr.synth.render import SynthRenderer
    from jsr.synth.scene import build_scene_plan

    options = SynthOptions(frames=10, objects=2, width=640, height=480, seed=2)
    plan = build_scene_plan(options)
    renderer = SynthRenderer(plan)
    clean = renderer.render(4, depth_noise=False, dropout=0.0)
    noisy = renderer.render(4, depth_noise=True, dropout=0.0)
    return plan.intrinsics, clean, noisy


def test_points_agree_with_noise_free_geometry(synth_pair):
    intrinsics, clean, noisy = synth_pair
    config = Config()
    assert np.array_equal(clean.color, noisy.color)
    exact = extract_point_measurements(clean.color, clean.depth.astype(np.float32), intrinsics, config.features, config.noise)
    measured = extract_point_measurements(noisy.color, noisy.depth.astype(np.float32), intrinsics, config.features, config.noise)
    np.testing.assert_array_equal(exact.pixels, measured.pixels)
    both = exact.has_depth & measured.has_depth
    assert both.sum() > 300
    z = exact.points[both, 2]
    error = np.linalg.norm(measured.points[both] - exact.points[both], axis=1)
    within = error < 3.0 * SIGMA * z**2
    assert within.mean() > 0.97, f"only {within.mean():.3f} of {both.sum()} points within 3 sigma_Z"
    # The robust lookup (a median of 25 depths) is much better than a single pixel.
    assert np.median(error / (SIGMA * z**2)) < 0.5
    # Noise makes few lookups fail.
    assert measured.has_depth[exact.has_depth].mean() > 0.95


def test_exact_depth_backprojects_onto_the_surface(synth_pair):
    intrinsics, clean, _ = synth_pair
    config = Config()
    result = extract_point_measurements(clean.color, clean.depth.astype(np.float32), intrinsics, config.features, config.noise)
    points = result.points[result.has_depth]
    pixels = result.pixels[result.has_depth]
    # Reprojection gives the keypoint back (the depth is that of the rounded pixel).
    projected = points[:, :2] / points[:, 2:3] * [intrinsics.fx, intrinsics.fy] + [intrinsics.cx, intrinsics.cy]
    np.testing.assert_allclose(projected, pixels, atol=1e-9)
    # Depth equals the exact depth near the keypoint on smooth surfaces.
    u = np.rint(pixels[:, 0]).astype(int)
    v = np.rint(pixels[:, 1]).astype(int)
    exact = clean.depth[v, u]
    assert np.median(np.abs(points[:, 2] - exact)) < 1e-3


def test_2d_points_are_exactly_those_without_valid_depth():
    config = Config()
    intrinsics = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    image = textured_image()
    rng = np.random.default_rng(3)
    depth = np.full((480, 640), 2.0, dtype=np.float32)
    depth[:, 320:] = 3.2  # a discontinuity down the middle
    depth[100:220, 50:250] = 0.0  # a hole
    depth[300:400, 400:600] = np.where(rng.random((100, 200)) < 0.6, 0.0, 2.5)  # sparse depth
    depth += (rng.standard_normal(depth.shape) * SIGMA * depth**2).astype(np.float32) * (depth > 0)
    result = extract_point_measurements(image, depth, intrinsics, config.features, config.noise)
    assert len(result) > 200
    pixels, _ = detect_keypoints(to_grey(image), config.features)
    expected = [
        reference_lookup(depth, p, config.features.depth_window, config.features.depth_spread_sigmas,
                         config.features.min_depth_spread)
        for p in pixels
    ]
    expected_valid = np.array([value is not None for value in expected])
    np.testing.assert_array_equal(result.has_depth, expected_valid)
    np.testing.assert_allclose(result.points[expected_valid, 2], [e for e in expected if e is not None], rtol=1e-6)
    # Both kinds are present: the hole, the sparse patch and the discontinuity make 2D points.
    assert 20 < (~result.has_depth).sum() < len(result) - 100
    assert np.all(np.isnan(result.points[~result.has_depth]))
    assert np.all(result.sigma_z[~result.has_depth] == 0.0)
    z = result.points[result.has_depth, 2]
    np.testing.assert_allclose(result.sigma_z[result.has_depth], SIGMA * z**2)
    np.testing.assert_allclose(np.linalg.norm(result.bearings, axis=1), 1.0)
    directions = result.points[result.has_depth] / np.linalg.norm(result.points[result.has_depth], axis=1, keepdims=True)
    np.testing.assert_allclose(directions, result.bearings[result.has_depth], atol=1e-12)
    assert result.descriptors.shape == (len(result), 128) and result.descriptors.dtype == np.float32
    # Keypoints whose window straddles the discontinuity at u = 320 are 2D points.
    straddling = np.abs(np.rint(result.pixels[:, 0]) - 319.5) < config.features.depth_window
    assert straddling.any() and not result.has_depth[straddling].any()


def test_lookup_median_and_rejections():
    config = Config()
    depth = np.zeros((20, 20), dtype=np.float32)
    depth[:, :10] = 1.0
    depth[5:10, 2:7] = np.arange(25, dtype=np.float32).reshape(5, 5) * 0.0005 + 1.0  # 1.0 .. 1.012
    pixels = np.array([[4.0, 7.0], [15.0, 7.0], [9.0, 15.0], [3.6, 7.4], [10.0, 15.0]])
    z, valid = lookup_depth(depth, pixels, config.features, config.noise)
    assert valid.tolist() == [True, False, True, True, False]
    assert z[0] == pytest.approx(1.006)  # the median of the 25 ramp values
    # (9, 15): 15 of 25 valid (columns 7-9 of 7-11): the median of the valid ones; (10, 15): 10 of 25.
    assert z[2] == pytest.approx(1.0)
    assert z[3] == pytest.approx(1.006)  # rounded to the same pixel
    depth[7, 4] = 1.5  # one outlier 50 cm off: the window straddles a discontinuity
    _, valid = lookup_depth(depth, pixels[:1], config.features, config.noise)
    assert not valid[0]


def test_undistortion_uses_opencv_undistort_points():
    config = Config()
    intrinsics = CAMERA_PRESETS["tum-fr1"]
    image = textured_image(seed=4)
    depth = np.full((480, 640), 1.8, dtype=np.float32)
    raw, descriptors = detect_keypoints(to_grey(image), config.features)
    result = build_point_measurements(raw, descriptors, depth, intrinsics, config.features, config.noise)
    expected = cv2.undistortPoints(raw.reshape(-1, 1, 2), intrinsics.matrix, intrinsics.distortion_coefficients,
                                   P=intrinsics.matrix).reshape(-1, 2)
    np.testing.assert_allclose(result.pixels, expected, atol=1e-9)
    assert np.max(np.linalg.norm(result.pixels - raw, axis=1)) > 2.0  # the lens really moves them
    rays = np.column_stack([(expected[:, 0] - intrinsics.cx) / intrinsics.fx,
                            (expected[:, 1] - intrinsics.cy) / intrinsics.fy, np.ones(len(expected))])
    np.testing.assert_allclose(result.points, rays * 1.8, rtol=1e-6)
    # Switched off: raw pixels are used as they are.
    config.features.undistort = False
    plain = build_point_measurements(raw, descriptors, depth, intrinsics, config.features, config.noise)
    np.testing.assert_array_equal(plain.pixels, raw)


def test_half_resolution_detection_maps_back_to_full_resolution():
    config = Config()
    image = np.zeros((480, 640), np.uint8)
    for r in range(6):
        for c in range(8):
            if (r + c) % 2 == 0:
                image[r * 80 : (r + 1) * 80, c * 80 : (c + 1) * 80] = 255
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    config.features.half_resolution = False
    full, _ = detect_keypoints(image, config.features)
    config.features.half_resolution = True
    half, descriptors = detect_keypoints(image, config.features)
    assert len(half) > 20 and descriptors.shape == (len(half), 128)
    # Checkerboard keypoints sit on corners and squares; the halved image finds the same
    # structures at the same full-resolution positions (to a pixel or two).
    distances = np.min(np.linalg.norm(half[:, None, :] - full[None, :, :], axis=2), axis=1)
    assert np.median(distances) < 2.0


def test_no_keypoints_gives_empty_measurements():
    config = Config()
    intrinsics = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    blank = np.full((480, 640, 3), 90, np.uint8)
    result = extract_point_measurements(blank, np.ones((480, 640), np.float32), intrinsics, config.features, config.noise)
    assert len(result) == 0 and result.points.shape == (0, 3) and result.descriptors.shape == (0, 128)


def test_detail_keypoints_add_the_finest_scale_inside_the_box_only():
    """Full-resolution SIFT in a box adds keypoints there that half-resolution SIFT misses,
    and none outside the box."""
    import dataclasses

    cfg = Config().features
    grey = to_grey(cv2.resize(textured_image(240, 320, seed=4), (640, 480), interpolation=cv2.INTER_LINEAR))
    grey = cv2.add(grey, np.random.default_rng(1).integers(0, 40, grey.shape, dtype=np.uint8))  # fine texture
    box = (200, 150, 400, 330)
    coarse, _ = detect_keypoints(grey, cfg)
    detail, descriptors = detect_detail_keypoints(grey, [box], create_sift(dataclasses.replace(cfg, max_keypoints=0)))
    assert len(detail) == len(descriptors) > 0
    inside = (detail[:, 0] >= box[0]) & (detail[:, 0] < box[2]) & (detail[:, 1] >= box[1]) & (detail[:, 1] < box[3])
    assert inside.all()
    coarse_inside = ((coarse[:, 0] >= box[0]) & (coarse[:, 0] < box[2]) & (coarse[:, 1] >= box[1])
                     & (coarse[:, 1] < box[3])).sum()
    assert len(detail) > coarse_inside  # the finest octave holds most keypoints of a fine texture


def test_join_boxes_merges_overlaps():
    assert join_boxes([(0, 0, 10, 10), (5, 5, 20, 20), (30, 30, 40, 40)]) == [(0, 0, 20, 20), (30, 30, 40, 40)]
    assert join_boxes([(0, 0, 10, 10), (10, 0, 20, 10)]) == [(0, 0, 10, 10), (10, 0, 20, 10)]  # touching only
    assert join_boxes([(5, 5, 5, 9)]) == []  # empty


def test_lookup_accepts_a_slanted_surface_but_not_a_depth_edge():
    """A surface seen at a grazing angle spreads its window's depths beyond the limit but on
    one plane: a 3D point at the plane's depth, if it is seen at most
    features.slanted_max_incidence degrees from face-on. A depth edge, even on a slanted
    surface, is not."""
    config = Config()
    config.features.slanted_max_incidence = 70.0  # off by default
    focal = 262.5  # 320x240
    columns = np.arange(40, dtype=np.float32)[None, :].repeat(40, axis=0)
    slanted = 0.794 + 0.0103 * columns  # 1.03 cm per pixel at 1 m: 69.7 degrees from face-on, 4.1 cm over 5 px
    pixels = np.array([[20.0, 20.0]])
    z, valid = lookup_depth(slanted, pixels, config.features, config.noise, focal)
    assert valid[0] and z[0] == pytest.approx(1.0, abs=1e-4)
    assert not lookup_depth(slanted, pixels, config.features, config.noise)[1][0]  # no focal length: plain
    config.features.slanted_max_incidence = 0.0
    assert not lookup_depth(slanted, pixels, config.features, config.noise, focal)[1][0]
    config.features.slanted_max_incidence = 65.0
    assert not lookup_depth(slanted, pixels, config.features, config.noise, focal)[1][0]
    config.features.slanted_max_incidence = 70.0
    edge = slanted.copy()
    edge[:, 21:] += 0.08  # an 8 cm step one pixel right of the keypoint
    assert not lookup_depth(edge, pixels, config.features, config.noise, focal)[1][0]


def test_slanted_keypoints_across_a_segment_border_become_2d():
    """A slanted window reaching into another segment (a crease: a box face on a grazing table
    top) gives no 3D point; one inside its segment keeps its depth, and so does a plain one."""
    config = Config()
    config.features.undistort = False
    config.features.slanted_max_incidence = 70.0  # off by default
    columns = np.arange(40, dtype=np.float32)[None, :].repeat(40, axis=0)
    depth = 0.794 + 0.0103 * columns
    depth[:, :10] = 1.3  # a flat, frontal part: plain lookups
    pixels = np.array([[20.0, 20.0], [29.0, 20.0], [4.0, 20.0], [8.0, 20.0]])
    intrinsics = CAMERA_PRESETS["tum-fr1"].with_resolution(320, 240)
    descriptors = np.zeros((len(pixels), 128), dtype=np.float32)
    points = build_point_measurements(pixels, descriptors, depth, intrinsics, config.features, config.noise)
    assert points.has_depth.tolist() == [True, True, True, False]  # (8, 20) straddles the step at column 10
    labels = np.zeros((40, 40), dtype=np.int32)
    labels[:, 30:] = 1  # a segment border inside the window of (29, 20)
    turned = keep_slanted_within_segments(points, pixels, depth, labels, config.features, config.noise)
    assert turned == 1 and points.has_depth.tolist() == [True, False, True, False]
    assert np.isnan(points.points[1]).all() and points.sigma_z[1] == 0.0
    config.features.slanted_max_incidence = 0.0
    assert keep_slanted_within_segments(points, pixels, depth, labels, config.features, config.noise) == 0
