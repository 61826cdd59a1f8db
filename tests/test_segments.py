"""Segmentation (jsr.pipeline.segments): purity and coverage against ground-truth labels.

Synthetic frames of ``jsr.synth`` (labels: 0 static scene, k object k) and small hand-made
depth images for the rules (cuts at discontinuities, small regions merged or dropped, point
assignment). A real-data check on ``kitchen_box120`` (labels of the composited box) is marked
``real``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from jsr.config import Config
from jsr.io.camera import CameraIntrinsics
from jsr.io.dataset import Frame
from jsr.pipeline.frontend import FrontEnd
from jsr.pipeline.measurements import PointMeasurements
from jsr.pipeline.planes import empty_planes, extract_planes
from jsr.pipeline.segments import build_segments

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def purity_and_coverage(segment_labels: np.ndarray, truth: np.ndarray, min_object_pixels: int = 2000):
    """Per segment: the fraction of its pixels with its majority label. Per object (label
    > 0) visible over ``min_object_pixels``: the fraction of its pixels in segments whose
    majority it is."""
    purities = {}
    majority = {}
    for s in np.unique(segment_labels[segment_labels >= 0]):
        counts = np.bincount(truth[segment_labels == s])
        purities[int(s)] = counts.max() / counts.sum()
        majority[int(s)] = int(counts.argmax())
    coverage = {}
    for k in np.unique(truth[truth > 0]):
        visible = truth == k
        if visible.sum() <= min_object_pixels:
            continue
        owners = [s for s, label in majority.items() if label == k]
        coverage[int(k)] = float(np.isin(segment_labels[visible], owners).mean())
    return purities, coverage


@pytest.fixture(scope="module")
def synth_measurements():
    from jsr.synth.options import SynthOptions
    from jsr.synth.render import SynthRenderer
    from jsr.synth.scene import build_scene_plan

    options = SynthOptions(frames=30, objects=3, width=640, height=480, seed=1)
    plan = build_scene_plan(options)
    renderer = SynthRenderer(plan)
    config = Config()
    results = []
    with FrontEnd(config, plan.intrinsics, parallel=False) as frontend:
        for index in (0, 15, 29):
            rendered = renderer.render(index)
            depth = (np.round(rendered.depth * 5000.0) / 5000.0).astype(np.float32)
            frame = Frame(index, float(index), rendered.color, depth, plan.intrinsics, str(index), Path(), Path())
            results.append((frame, rendered.labels.astype(np.int64), frontend.process(frame)))
    return results


def test_synth_segments_are_pure(synth_measurements):
    for frame, labels, measurements in synth_measurements:
        purities, _ = purity_and_coverage(measurements.segments.label_image, labels)
        worst = min(purities, key=purities.get)
        summary = ", ".join(f"{s}: {p:.3f}" for s, p in sorted(purities.items()))
        assert purities[worst] >= 0.95, f"frame {frame.index}: segment {worst} is {purities[worst]:.3f} pure ({summary})"


def test_synth_objects_are_covered_by_their_segments(synth_measurements):
    checked = 0
    for frame, labels, measurements in synth_measurements:
        _, coverage = purity_and_coverage(measurements.segments.label_image, labels)
        checked += len(coverage)
        for k, fraction in coverage.items():
            assert fraction >= 0.90, f"frame {frame.index}: object {k} covered {fraction:.3f} ({coverage})"
    assert checked >= 6


def test_segment_structure_and_points(synth_measurements):
    for frame, _, measurements in synth_measurements:
        segments, planes, points = measurements.segments, measurements.planes, measurements.points
        labels = segments.label_image
        assert labels.dtype == np.int32 and labels.shape == frame.depth.shape
        assert len(segments) == len(segments.plane_index) == len(segments.pixel_counts) == len(segments.point_indices)
        # Plane segments first, in plane order, each covering (at least) its plane's mask.
        assert np.array_equal(segments.plane_index[: len(planes)], np.arange(len(planes)))
        assert np.all(segments.plane_index[len(planes) :] == -1)
        plane_pixels = planes.label_image >= 0
        assert np.array_equal(labels[plane_pixels], planes.label_image[plane_pixels])
        np.testing.assert_array_equal(np.bincount(labels[labels >= 0], minlength=len(segments)), segments.pixel_counts)
        assert np.all(labels[frame.depth <= 0] == -1)
        # Points: by the rounded pixel, 2D points included, every point in at most one segment.
        u = np.rint(points.pixels[:, 0]).astype(int)
        v = np.rint(points.pixels[:, 1]).astype(int)
        owner = segments.segment_of_points(len(points))
        for s, indices in enumerate(segments.point_indices):
            assert np.all(labels[v[indices], u[indices]] == s)
        assert np.all(labels[v[owner < 0], u[owner < 0]] == -1)
        assert sum(len(i) for i in segments.point_indices) == int((owner >= 0).sum())
        assert np.any(~points.has_depth[owner >= 0]) or np.all(points.has_depth)


# --------------------------------------------------------------------------------------
# Rules on hand-made depth images

INTRINSICS = CameraIntrinsics(300.0, 300.0, 79.5, 59.5, 160, 120)


def _segments_of(depth: np.ndarray, min_segment_pixels: int = 400, planes=None, points=None):
    config = Config()
    config.segments.min_segment_pixels = min_segment_pixels
    planes = planes if planes is not None else empty_planes(*depth.shape)
    points = points if points is not None else PointMeasurements.empty()
    return build_segments(planes, depth.astype(np.float32), points, INTRINSICS, config.segments, config.noise)


def test_discontinuities_cut_and_the_foreground_keeps_its_silhouette():
    depth = np.full((120, 160), 2.0)
    depth[30:70, 40:100] = 1.5  # a 40 x 60 object 50 cm in front
    segments = _segments_of(depth)
    assert len(segments) == 2
    object_label = segments.label_image[50, 70]
    assert np.array_equal(segments.label_image == object_label, depth == 1.5)
    assert np.all(segments.label_image >= 0)  # the cut background pixels went back to the background
    assert sorted(segments.pixel_counts.tolist()) == [2400, 120 * 160 - 2400]


def test_small_regions_are_dropped_or_merged():
    depth = np.full((120, 160), 2.0)
    depth[10:20, 10:20] = 1.0  # 100 px, discontinuous: dropped
    depth[60:110, 20:60] = 1.2  # 2000 px, kept
    segments = _segments_of(depth, min_segment_pixels=400)
    assert len(segments) == 2
    assert np.all(segments.label_image[10:20, 10:20] == -1)
    # Invalid pixels separate nothing by themselves: a region is one segment if it is
    # connected around them.
    depth = np.full((120, 160), 2.0)
    depth[:, 80] = 0.0  # a column without depth ...
    depth[:20, 80] = 2.0  # ... except at the top, where both halves touch
    segments = _segments_of(depth, min_segment_pixels=400)
    assert len(segments) == 1 and np.all(segments.label_image[:, 80][20:] == -1)


def test_small_region_next_to_a_plane_joins_the_plane_segment():
    depth = np.full((120, 160), 2.0, dtype=np.float32)
    planes = empty_planes(120, 160)
    planes.label_image[:, :100] = 0  # pretend plane 0 covers most of the image
    planes.normals = np.array([[0.0, 0.0, -1.0]])
    planes.offsets = np.array([2.0])
    planes.centroids = np.array([[0.0, 0.0, 2.0]])
    planes.point_counts = np.array([12000])
    planes.fit_rmse = np.array([0.001])
    planes.label_image[:, 130:] = 0  # a strip of the plane ...
    planes.label_image[:15, 100:130] = 0
    planes.label_image[25:, 100:130] = 0  # ... leaving a 10 x 30 pocket at rows 15-25
    segments = _segments_of(depth, min_segment_pixels=400, planes=planes)
    assert len(segments) == 1 and segments.plane_index[0] == 0
    assert np.all(segments.label_image == 0)


def test_points_are_assigned_by_pixel_including_2d_points():
    depth = np.full((120, 160), 2.0)
    depth[30:70, 40:100] = 1.5
    pixels = np.array([[50.2, 40.4], [10.0, 10.0], [159.4, 119.4], [70.0, 50.0]])
    has_depth = np.array([True, True, False, False])
    points = PointMeasurements(
        pixels=pixels,
        points=np.where(has_depth[:, None], 1.0, np.nan) * np.ones((4, 3)),
        has_depth=has_depth,
        bearings=np.tile([0.0, 0.0, 1.0], (4, 1)),
        sigma_z=np.zeros(4),
        descriptors=np.zeros((4, 128), dtype=np.float32),
    )
    segments = _segments_of(depth, points=points)
    object_label = segments.label_image[50, 70]
    background = 1 - object_label
    assert sorted(segments.point_indices[object_label].tolist()) == [0, 3]
    assert sorted(segments.point_indices[background].tolist()) == [1, 2]
    # Raw keypoint positions, when given, take precedence over the (undistorted) pixels.
    config = Config()
    moved = build_segments(
        empty_planes(120, 160), depth.astype(np.float32), points, INTRINSICS, config.segments, config.noise,
        keypoint_pixels=pixels[[3, 2, 1, 0]],
    )
    assert sorted(moved.point_indices[moved.label_image[50, 70]].tolist()) == [0, 3]


def test_plane_segments_on_a_rendered_room():
    from test_planes import INTRINSICS as ROOM_INTRINSICS, render_analytic

    depth, face_ids, _ = render_analytic(seed=8)
    config = Config()
    planes = extract_planes(depth, ROOM_INTRINSICS, config.planes, config.noise)
    segments = build_segments(planes, depth, PointMeasurements.empty(), ROOM_INTRINSICS, config.segments, config.noise)
    solids = face_ids // 6  # 0 room, 1 box, 2 table top
    purities, _ = purity_and_coverage(segments.label_image, solids)
    assert min(purities.values()) >= 0.95, purities
    assert len(segments) >= len(planes)


# --------------------------------------------------------------------------------------
# Real data: the composited box of kitchen_box120


@pytest.mark.real
def test_kitchen_box_segments(shared_data):
    from jsr.io.dataset import open_sequence

    folder = SHARED_DATA / "kitchen_box120"
    if not (folder / "labels").is_dir():
        pytest.skip(f"{folder} absent")
    config = Config()
    sequence = open_sequence(folder, min_depth=config.input.min_depth, max_depth=config.input.max_depth)
    with FrontEnd(config, sequence.intrinsics, parallel=False) as frontend:
        for index in (0, 24, 64, 104):
            frame = sequence[index]
            truth = cv2.imread(str(folder / "labels" / f"{frame.name}.png"), cv2.IMREAD_UNCHANGED).astype(np.int64)
            segments = frontend.process(frame).segments
            purities, coverage = purity_and_coverage(segments.label_image, truth)
            assert coverage.get(1, 0.0) >= 0.9, f"frame {index}: box covered {coverage}"
            on_box = [s for s in purities if np.bincount(truth[segments.label_image == s]).argmax() == 1]
            assert all(purities[s] >= 0.95 for s in on_box), f"frame {index}: {[purities[s] for s in on_box]}"


def _fold(slope: float) -> np.ndarray:
    """Depth of two planes meeting at the middle column: ``slope < 0`` folds away from the
    camera there (concave, a room corner), ``slope > 0`` towards it (convex, a box edge)."""
    u = np.arange(160, dtype=np.float64)
    x = (u - INTRINSICS.cx) / INTRINSICS.fx  # ray slope; the surface z = 2 + slope |X| along it
    z = 2.0 / (1.0 - slope * np.abs(x))
    return np.tile(z, (120, 1))


def test_concave_creases_cut_folds_away_from_the_camera_only():
    from jsr.pipeline.segments import concave_creases

    concave = concave_creases(_fold(-0.6).astype(np.float32), INTRINSICS, 30.0)
    columns = np.flatnonzero(concave.any(axis=0))
    assert len(columns) and np.all(np.abs(columns - INTRINSICS.cx) <= 4)  # a band 8 px wide at the fold
    assert concave[:, int(INTRINSICS.cx)].mean() > 0.9  # all the way down
    assert not concave_creases(_fold(0.6).astype(np.float32), INTRINSICS, 30.0).any()
    assert not concave_creases(_fold(-0.1).astype(np.float32), INTRINSICS, 30.0).any()  # an 11 degree fold
    # two faces of a room corner are two segments, two faces of a box edge one; every pixel is kept
    corner = _segments_of(_fold(-0.6))
    assert len(corner) == 2 and np.all(corner.label_image >= 0)
    assert corner.label_image[60, 20] != corner.label_image[60, 140]
    assert len(_segments_of(_fold(0.6))) == 1
