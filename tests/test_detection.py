"""Moving-object detection from segment outlier ratios (Section 2.1)."""

from __future__ import annotations


import numpy as np
import pytest

from jsr.config import DetectionConfig
from jsr.pipeline.detection import (
    MIN_DISPLACED_PER_SEGMENT,
    detect_moving_segments,
    displaced_landmark_groups,
    merge_adjacent_moving_segments,
    segment_adjacency_pairs,
    segment_outlier_stats,
)
from jsr.pipeline.measurements import Segments


def _segments(label_image: np.ndarray, point_indices: list[list[int]]) -> Segments:
    count = len(point_indices)
    labels = np.asarray(label_image, dtype=np.int32)
    return Segments(
        label_image=labels,
        plane_index=np.full(count, -1, dtype=np.int64),
        point_indices=[np.asarray(p, dtype=np.int64) for p in point_indices],
        pixel_counts=np.array([(labels == i).sum() for i in range(count)], dtype=np.int64),
    )


def _four_segments() -> tuple[Segments, np.ndarray, np.ndarray]:
    """Segments of 10 points each (0-9, 10-19, 20-29, 30-39); points 40-44 are in none.

    Segment 0: 10 matched, 1 outlier  (ratio 0.1)   static
    Segment 1: 10 matched, 8 outliers (ratio 0.8)   moving
    Segment 2: 4 matched, 4 outliers  (ratio 1.0)   too few matched features
    Segment 3: 10 matched, 6 outliers (ratio 0.6)   exactly at the threshold: not moving
    """
    labels = np.full((4, 8), -1)
    labels[:, 0:2], labels[:, 2:4], labels[:, 4:6], labels[:, 6:8] = 0, 1, 2, 3
    segments = _segments(labels, [list(range(i * 10, i * 10 + 10)) for i in range(4)])
    matched = np.ones(45, dtype=bool)
    matched[24:30] = False
    inlier = matched.copy()
    inlier[[0]] = False
    inlier[10:18] = False
    inlier[20:24] = False
    inlier[30:36] = False
    inlier[40:45] = False  # outliers outside every segment do not matter
    return segments, matched, inlier


def test_outlier_stats_per_segment():
    segments, matched, inlier = _four_segments()
    stats = segment_outlier_stats(segments, matched, inlier)
    np.testing.assert_array_equal(stats.matched, [10, 10, 4, 10])
    np.testing.assert_array_equal(stats.outliers, [1, 8, 4, 6])
    np.testing.assert_allclose(stats.outlier_ratio, [0.1, 0.8, 1.0, 0.6])


def test_detects_segments_with_high_outlier_ratio_and_enough_features():
    segments, matched, inlier = _four_segments()
    config = DetectionConfig(segment_outlier_ratio=0.6, min_segment_features=5, significance=1.0)
    assert detect_moving_segments(segments, matched, inlier, config) == [1]
    # Lower the feature minimum: segment 2 qualifies; lower the ratio: segment 3 does.
    assert detect_moving_segments(segments, matched, inlier, DetectionConfig(0.6, 4, significance=1.0)) == [1, 2]
    assert detect_moving_segments(segments, matched, inlier, DetectionConfig(0.55, 5, significance=1.0)) == [1, 3]
    assert detect_moving_segments(segments, matched, inlier, DetectionConfig(0.85, 1, significance=1.0)) == [2]


def test_outliers_must_exceed_what_the_frame_outlier_ratio_explains():
    segments, matched, inlier = _four_segments()
    # In this frame 24 of 39 matches are outliers: 8 of 10 in segment 1 is not unusual.
    assert detect_moving_segments(segments, matched, inlier, DetectionConfig(0.6, 5, significance=0.01)) == []
    # With every other match an inlier, 8 outliers of 10 are far beyond chance.
    clean = inlier.copy()
    clean[[0]] = True
    clean[20:24] = True
    clean[30:36] = True
    clean[40:45] = True
    clean = np.concatenate([clean, np.ones(200, dtype=bool)])
    wide_matched = np.concatenate([matched, np.ones(200, dtype=bool)])
    assert detect_moving_segments(segments, wide_matched, clean, DetectionConfig(0.6, 5, significance=0.01)) == [1]


def test_unmatched_inliers_are_ignored():
    segments, matched, inlier = _four_segments()
    inlier = inlier.copy()
    inlier[24:30] = True  # flagged inliers that were never matched: still not counted
    stats = segment_outlier_stats(segments, matched, inlier)
    assert stats.matched[2] == 4 and stats.outliers[2] == 4


def test_excluded_measurements_are_ignored():
    segments, matched, inlier = _four_segments()
    config = DetectionConfig(segment_outlier_ratio=0.6, min_segment_features=5, significance=1.0)
    exclude = np.zeros(45, dtype=bool)
    exclude[10:16] = True  # six outliers of segment 1 already belong to an object map
    stats = segment_outlier_stats(segments, matched, inlier, exclude)
    assert stats.matched[1] == 4 and stats.outliers[1] == 2
    assert detect_moving_segments(segments, matched, inlier, config, exclude=exclude) == []
    exclude[:] = False
    exclude[36:40] = True  # four inliers of segment 3 gone: 6 of 6 outliers
    assert detect_moving_segments(segments, matched, inlier, config, exclude=exclude) == [1, 3]


def test_bad_mask_shape_and_no_points():
    segments, matched, inlier = _four_segments()
    with pytest.raises(ValueError):
        segment_outlier_stats(segments, matched, inlier[:-1])
    empty = _segments(np.full((2, 2), -1), [[], []])
    stats = segment_outlier_stats(empty, np.zeros(0, bool), np.zeros(0, bool))
    np.testing.assert_array_equal(stats.matched, [0, 0])
    assert detect_moving_segments(empty, np.zeros(0, bool), np.zeros(0, bool), DetectionConfig()) == []


def _grid_segments() -> Segments:
    """A 6x9 label image:

        0 0 1 1 -1 2 2 -1 -1
        0 0 1 1 -1 2 2 -1 -1
        3 3 3 -1 -1 -1 -1 -1 4
        3 3 3 -1 -1 -1 -1 4 -1
        -1 -1 -1 -1 -1 -1 -1 -1 -1
        5 5 -1 -1 -1 -1 -1 6 6
    """
    labels = np.array(
        [
            [0, 0, 1, 1, -1, 2, 2, -1, -1],
            [0, 0, 1, 1, -1, 2, 2, -1, -1],
            [3, 3, 3, -1, -1, -1, -1, -1, 4],
            [3, 3, 3, -1, -1, -1, -1, 4, -1],
            [-1, -1, -1, -1, -1, -1, -1, -1, -1],
            [5, 5, -1, -1, -1, -1, -1, 6, 6],
        ]
    )
    return _segments(labels, [[] for _ in range(7)])


def test_adjacency_pairs():
    segments = _grid_segments()
    pairs = {tuple(p) for p in segment_adjacency_pairs(segments.label_image).tolist()}
    # 0-1 side by side, 0-3 and 1-3 stacked (1-3 also diagonally); 2 and 4 touch nothing
    # directly; 4's two pixels touch each other diagonally (same label, no pair).
    assert pairs == {(0, 1), (0, 3), (1, 3)}
    gap1 = {tuple(p) for p in segment_adjacency_pairs(segments.label_image, max_gap_pixels=1).tolist()}
    # Across one pixel: 1-2 (background column), 3-5 (background row), 2-4 (one column and
    # one row apart), 4-6 (background row).
    assert gap1 == {(0, 1), (0, 3), (1, 3), (1, 2), (3, 5), (2, 4), (4, 6)}


def test_merge_groups_touching_moving_segments_only():
    segments = _grid_segments()
    # 0 and 3 touch; 1 would bridge them but is not moving, 0-3 touch anyway.
    assert merge_adjacent_moving_segments(segments, [3, 0, 2]) == [[0, 3], [2]]
    # 1 and 2 are separated by a one-pixel column of background.
    assert merge_adjacent_moving_segments(segments, [1, 2]) == [[1], [2]]
    assert merge_adjacent_moving_segments(segments, [1, 2], max_gap_pixels=1) == [[1, 2]]
    # Transitive: 0-1 and 1-3 give one group; 4 (diagonal pixels only) and 6 stay apart.
    assert merge_adjacent_moving_segments(segments, [4, 6, 1, 0, 3]) == [[0, 1, 3], [4], [6]]
    assert merge_adjacent_moving_segments(segments, []) == []
    with pytest.raises(ValueError):
        merge_adjacent_moving_segments(segments, [7])


def test_merge_with_a_non_moving_segment_in_between():
    labels = np.array([[0, 1, 2], [0, 1, 2]])
    segments = _segments(labels, [[], [], []])
    # Segments 0 and 2 only touch through segment 1, which is static: two objects.
    assert merge_adjacent_moving_segments(segments, [0, 2]) == [[0], [2]]
    assert merge_adjacent_moving_segments(segments, [0, 1, 2]) == [[0, 1, 2]]


def _displaced_scene(rest_projecting: int):
    """Segments 0 and 1 touch; segment 2 stands apart; segments 3 and 4 touch segment 2;
    segment 5 (below them all) is the rest of the frame, with ``rest_projecting`` landmarks
    none of which is displaced.

    Displaced / projecting landmarks: 5/5, 4/4, 6/7, 1/4 (segment 3: mostly still in place),
    1/1 (segment 4: a single landmark, as often a depth edge as motion), 0/rest_projecting.
    """
    labels = np.full((6, 14), -1)
    labels[:4, 0:3], labels[:4, 3:5], labels[:4, 8:10], labels[:4, 10:12], labels[:4, 12:14] = 0, 1, 2, 3, 4
    labels[4:, :] = 5
    segments = _segments(labels, [[], [], [], [], [], []])
    return segments, np.array([5, 4, 6, 1, 1, 0]), np.array([5, 4, 7, 4, 1, rest_projecting])


@pytest.mark.parametrize("rest_projecting, expected, expected_without_1", [
    (64, [[0, 1]], []),                # a fifth of the frame's landmarks displaced (17 of 85: blur)
    (1000, [[0, 1], [2]], [[0], [2]]),  # 17 of 1021: tested at the floor of 1 in 20
])
def test_displaced_landmarks_are_weighed_against_the_frame_and_count_together(rest_projecting, expected,
                                                                               expected_without_1):
    """A group moves when the frame's own share of displaced landmarks makes its count
    unlikely (binomial tail below 1e-6). Where a fifth of them are displaced, 9 of 9 over
    two touching segments move, though neither segment alone (5 of 5, 4 of 4) would, and 6 of
    7 apart do not; where few are, 6 of 7 do. Segment 3 (1 of 4) is no candidate, nor
    segment 4 (its one landmark) or segment 5 (none displaced)."""
    segments, displaced, projecting = _displaced_scene(rest_projecting)
    config = DetectionConfig(min_segment_features=5, displaced_share=0.8, displaced_significance=1e-6)
    assert MIN_DISPLACED_PER_SEGMENT == 2
    supported = np.ones(6, dtype=bool)
    groups = displaced_landmark_groups(segments, displaced, projecting, supported, config)
    assert groups == expected
    # a segment the static map shows in place (features that are static inliers) is no
    # candidate: segment 0's 5 of 5 alone are chance in the blurred frame, not in the quiet one
    supported[1] = False
    groups = displaced_landmark_groups(segments, displaced, projecting, supported, config)
    assert groups == expected_without_1


def test_adjacency_pairs_match_every_pixel_pair_within_the_gap():
    """The pairs equal those of a direct scan over every pixel pair within the gap, for labels
    anywhere in the image (the scan is cropped to the labels' box)."""
    rng = np.random.default_rng(5)
    for trial in range(6):
        labels = np.full((40, 50), -1)
        top, left = rng.integers(0, 30), rng.integers(0, 40)
        labels[top:top + 10, left:left + 10] = rng.integers(-1, 4 + trial, size=(10, 10))[: 40 - top, : 50 - left]
        for gap in (0, 2):
            reach = gap + 1
            expected = set()
            for y, x in zip(*np.nonzero(labels >= 0)):
                window = labels[max(0, y - reach):y + reach + 1, max(0, x - reach):x + reach + 1]
                for other in np.unique(window[(window >= 0) & (window != labels[y, x])]):
                    expected.add((min(labels[y, x], other), max(labels[y, x], other)))
            assert {tuple(p) for p in segment_adjacency_pairs(labels, gap).tolist()} == expected
    assert segment_adjacency_pairs(np.full((5, 5), -1)).shape == (0, 2)


def test_depth_offsets_before_are_taken_at_the_previous_frame_adjusted_pose():
    """The measured-minus-predicted depth of static landmarks in the previous frame, at that
    frame's pose as its reference keyframe stands now (moved 5 cm towards the wall by bundle
    adjustment since): a landmark 5 cm in front of the wall is 10 cm off from there. Landmarks
    not judged, over a depth hole or outside the image count 0 (judged by their prediction)."""
    from types import SimpleNamespace

    from jsr.io.camera import CameraIntrinsics
    from jsr.pipeline.maps import PointLandmarks
    from jsr.pipeline.moving_regions import depth_offsets_before
    from jsr.pipeline.state import FrameReport

    intrinsics = CameraIntrinsics(fx=100.0, fy=100.0, cx=39.5, cy=29.5, width=80, height=60)
    depth = np.full((60, 80), 2.0)
    depth[:, :20] = 0.0  # a hole on the left
    points = PointLandmarks()
    positions = np.array([[0.2, 0.0, 1.95], [0.0, 0.1, 1.95], [-0.9, 0.0, 1.95], [5.0, 0.0, 1.95]])
    ids = points.add(positions, np.zeros((4, 128), np.float32), np.full(4, 0.01), np.zeros((4, 3), np.uint8))
    keyframe_now = np.eye(4)
    keyframe_now[2, 3] = 0.05  # where bundle adjustment put the reference keyframe since
    report = FrameReport(7, 0.0, "7", tracked=True, T_w_c=np.eye(4))
    report.reference_keyframe, report.T_keyframe_cam = 0, np.eye(4)
    state = SimpleNamespace(memory=SimpleNamespace(previous_depth=depth), reports=[report], intrinsics=intrinsics,
                            static_map=SimpleNamespace(points=points, keyframes=[SimpleNamespace(T_map_cam=keyframe_now)]))
    judged = np.array([True, False, True, True])
    assert np.allclose(depth_offsets_before(state, ids, judged), [0.10, 0.0, 0.0, 0.0])
    every = np.ones(4, dtype=bool)
    assert np.allclose(depth_offsets_before(state, ids, every)[:2], [0.10, 0.10])
    state.memory.previous_depth = None  # the previous frame was not registered
    assert not depth_offsets_before(state, ids, every).any()
