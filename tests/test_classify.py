"""Algorithm 1, lines 14-24: classification of measurements into static and object maps."""

from __future__ import annotations

import numpy as np
import pytest

from jsr.pipeline.classify import ObjectRegistration, classify_measurements, segment_of_planes
from jsr.pipeline.measurements import Segments

N, P = 12, 4


def _mask(count: int, indices=()) -> np.ndarray:
    mask = np.zeros(count, dtype=bool)
    mask[list(indices)] = True
    return mask


def _registration(
    object_id: int,
    frame_success: bool = False,
    frame_points=(),
    frame_planes=(),
    segment_success: bool = False,
    matching=(),
    segment_points=(),
    segment_planes=(),
) -> ObjectRegistration:
    return ObjectRegistration(
        object_id=object_id,
        frame_success=frame_success,
        frame_inliers_points=_mask(N, frame_points),
        frame_inliers_planes=_mask(P, frame_planes),
        segment_success=segment_success,
        matching_segments=list(matching),
        segment_inliers_points=_mask(N, segment_points),
        segment_inliers_planes=_mask(P, segment_planes),
    )


# Points 0-2 in segment 0, 3-5 in segment 1, 6-8 in segment 2, 9-11 in no segment.
POINT_SEGMENT = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2, -1, -1, -1])
# Plane 0 is segment 0, plane 1 segment 1, plane 2 segment 2, plane 3 in no segment.
PLANE_SEGMENT = np.array([0, 1, 2, -1])


def _classify(*registrations):
    return classify_measurements(N, P, POINT_SEGMENT, PLANE_SEGMENT, list(registrations))


def test_no_object_maps_everything_static():
    points, planes = _classify()
    np.testing.assert_array_equal(points, np.zeros(N))
    np.testing.assert_array_equal(planes, np.zeros(P))


def test_matching_segment_claims_all_its_measurements():
    # Lines 15-16: everything inside matching segment 1 goes to the object, inlier or not.
    reg = _registration(3, segment_success=True, matching=[1], segment_points=[3])
    points, planes = _classify(reg)
    np.testing.assert_array_equal(points, [0, 0, 0, 3, 3, 3, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(planes, [0, 3, 0, 0])


def test_frame_inliers_go_to_the_object():
    # Line 18, first condition: inliers of the frame-based registration, inside a segment or not.
    reg = _registration(2, frame_success=True, frame_points=[0, 10], frame_planes=[3])
    points, planes = _classify(reg)
    np.testing.assert_array_equal(points, [2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 2, 0])
    np.testing.assert_array_equal(planes, [0, 0, 0, 2])


def test_segment_inliers_outside_matching_segments_go_to_the_object():
    # Line 18, second condition: refined segment-based inliers outside the matching segment
    # (e.g. features without a segment) belong to the object too.
    reg = _registration(1, segment_success=True, matching=[2], segment_points=[6, 7, 9, 11], segment_planes=[0])
    points, planes = _classify(reg)
    np.testing.assert_array_equal(points, [0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 0, 1])
    np.testing.assert_array_equal(planes, [1, 0, 1, 0])


def test_failed_registrations_are_ignored():
    failed_frame = _registration(1, frame_success=False, frame_points=[0, 1], frame_planes=[0],
                                 segment_success=True, segment_points=[5])
    failed_segment = _registration(2, frame_success=True, frame_points=[9],
                                   segment_success=False, matching=[2], segment_points=[10], segment_planes=[1])
    points, planes = _classify(failed_frame, failed_segment)
    np.testing.assert_array_equal(points, [0, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0])
    np.testing.assert_array_equal(planes, [0, 0, 0, 0])
    nothing = _registration(4, frame_points=range(N), matching=[0, 1, 2], segment_points=range(N))
    points, planes = _classify(nothing)
    assert not points.any() and not planes.any()


def test_inlier_beats_matching_segment_of_another_object():
    # Object 1 has frame inliers at points 1-8 and plane 1; object 2 matched segment 0 only.
    # A feature one map explains within the noise stays with it; the rest of the segment
    # (point 0, plane 0) goes to the map that matched it.
    big = _registration(1, frame_success=True, frame_points=range(1, 9), frame_planes=[1])
    small = _registration(2, segment_success=True, matching=[0])
    points, planes = _classify(big, small)
    np.testing.assert_array_equal(points, [2, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(planes, [2, 1, 0, 0])
    # Order of the registrations does not matter.
    points2, planes2 = _classify(small, big)
    np.testing.assert_array_equal(points2, points)
    np.testing.assert_array_equal(planes2, planes)


def test_equal_claims_go_to_the_registration_with_more_inliers():
    # Both claim points 3-5 as inliers; object 7 has 5 inliers, object 4 has 4.
    a = _registration(4, frame_success=True, frame_points=[3, 4, 5, 9])
    b = _registration(7, segment_success=True, segment_points=[3, 4, 5, 10], segment_planes=[2])
    points, planes = _classify(a, b)
    np.testing.assert_array_equal(points, [0, 0, 0, 7, 7, 7, 0, 0, 0, 4, 7, 0])
    np.testing.assert_array_equal(planes, [0, 0, 7, 0])
    # Both matched segment 1: the one with more inliers (counted over both masks) wins.
    c = _registration(5, frame_success=True, frame_points=[0, 9], segment_success=True, matching=[1],
                      segment_points=[9, 10])  # 3 distinct inliers
    d = _registration(6, segment_success=True, matching=[1, 2], segment_points=[3])  # 1 inlier
    points, planes = _classify(d, c)
    # point 3 is 6's inlier in a segment both matched: the inlier decides
    np.testing.assert_array_equal(points, [5, 0, 0, 6, 5, 5, 6, 6, 6, 5, 5, 0])
    np.testing.assert_array_equal(planes, [0, 5, 6, 0])


def test_equal_inlier_counts_go_to_the_smaller_object_id():
    a = _registration(9, frame_success=True, frame_points=[1, 2])
    b = _registration(3, frame_success=True, frame_points=[2, 4])
    points, _ = _classify(a, b)
    np.testing.assert_array_equal(points, [0, 9, 3, 0, 3, 0, 0, 0, 0, 0, 0, 0])


def test_invalid_inputs_are_rejected():
    with pytest.raises(ValueError):
        _classify(_registration(0, frame_success=True))
    with pytest.raises(ValueError):
        _classify(_registration(1), _registration(1))
    with pytest.raises(ValueError):
        classify_measurements(N, P, POINT_SEGMENT[:-1], PLANE_SEGMENT, [])
    bad = _registration(1, frame_success=True)
    bad.frame_inliers_points = np.zeros(N + 1, dtype=bool)
    with pytest.raises(ValueError):
        _classify(bad)


def test_segment_of_planes():
    segments = Segments(
        label_image=np.zeros((2, 2), dtype=np.int32),
        plane_index=np.array([1, 0, -1, -1]),
        point_indices=[np.zeros(0, np.int64)] * 4,
    )
    np.testing.assert_array_equal(segment_of_planes(segments, 3), [1, 0, -1])
