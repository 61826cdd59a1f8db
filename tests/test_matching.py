"""Descriptor matching (ratio test), plane matching under a pose, guided matching."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsr.io.camera import CameraIntrinsics
from jsr.geometry import transform_planes
from jsr.pipeline.matching import guided_match, match_descriptors, match_planes

CAMERA = CameraIntrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)


def _random_descriptors(rng: np.random.Generator, n: int) -> np.ndarray:
    """SIFT-like: non-negative, L2 norm 512."""
    values = rng.random((n, 128)).astype(np.float32) ** 4
    return (values / np.linalg.norm(values, axis=1, keepdims=True) * 512).astype(np.float32)


def _pose(rotvec, translation) -> np.ndarray:
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    transform[:3, 3] = translation
    return transform


# ---------------------------------------------------------------------- descriptors


def test_ratio_test_on_crafted_descriptors() -> None:
    map_desc = np.zeros((3, 128), np.float32)
    map_desc[0, 0] = 10.0
    map_desc[1, 1] = 10.0
    map_desc[2, 1] = 10.0
    map_desc[2, 2] = 0.3  # map 1 and 2 are nearly the same descriptor
    frame_desc = np.zeros((3, 128), np.float32)
    frame_desc[0, 0] = 9.5  # clearly map 0
    frame_desc[1, 1] = 9.5  # ambiguous: distances 0.5 and 0.58 to map 1 and 2 (ratio 0.86)
    frame_desc[2, 0] = 7.0  # between map 0 and map 1: distances 7.1 and 7.1
    frame_desc[2, 1] = 7.0
    pairs = match_descriptors(frame_desc, map_desc, ratio=0.8)
    np.testing.assert_array_equal(pairs, [[0, 0]])
    # A permissive ratio lets the ambiguous frame descriptor 1 through, not the tie 2.
    pairs = match_descriptors(frame_desc, map_desc, ratio=0.99)
    np.testing.assert_array_equal(pairs, [[0, 0], [1, 1]])


def test_ratio_threshold_boundary() -> None:
    map_desc = np.zeros((2, 128), np.float32)
    map_desc[0, 0] = 1.0
    map_desc[1, 0] = -3.0
    frame_desc = np.zeros((1, 128), np.float32)  # distances 1 and 3: ratio 1/3
    assert len(match_descriptors(frame_desc, map_desc, ratio=0.34)) == 1
    assert len(match_descriptors(frame_desc, map_desc, ratio=0.33)) == 0


def test_matches_shuffled_noisy_descriptors() -> None:
    rng = np.random.default_rng(0)
    map_desc = _random_descriptors(rng, 300)
    permutation = rng.permutation(300)[:200]
    frame_desc = map_desc[permutation] + rng.normal(0, 5, (200, 128)).astype(np.float32)
    frame_desc = np.vstack([frame_desc, _random_descriptors(rng, 50)])  # unmatched keypoints
    pairs = match_descriptors(frame_desc, map_desc, ratio=0.8)
    truth = dict(enumerate(permutation))
    correct = sum(truth.get(f) == m for f, m in pairs)
    assert correct >= 190
    assert len(pairs) - correct <= 5
    assert np.all(np.diff(pairs[:, 0]) > 0)  # sorted by frame index, one match per frame keypoint


def test_max_distance_on_normalised_descriptors() -> None:
    map_desc = np.zeros((2, 128), np.float32)
    map_desc[0, 0] = 512.0
    map_desc[1, 1] = 512.0
    frame_desc = np.zeros((1, 128), np.float32)
    frame_desc[0, 0] = 300.0
    frame_desc[0, 2] = 300.0  # 45 degrees from map 0: normalised distance 0.77
    assert len(match_descriptors(frame_desc, map_desc, ratio=0.8)) == 1
    assert len(match_descriptors(frame_desc, map_desc, ratio=0.8, max_distance=0.7)) == 0


def test_empty_and_single_inputs() -> None:
    rng = np.random.default_rng(1)
    desc = _random_descriptors(rng, 5)
    assert match_descriptors(desc, np.zeros((0, 128), np.float32), 0.8).shape == (0, 2)
    assert match_descriptors(np.zeros((0, 128), np.float32), desc, 0.8).shape == (0, 2)
    single = match_descriptors(desc[:2], desc[3:4], 0.8)  # no second neighbour: nearest kept
    np.testing.assert_array_equal(single[:, 1], [0, 0])


def test_descriptor_matching_is_deterministic() -> None:
    rng = np.random.default_rng(2)
    map_desc = _random_descriptors(rng, 400)
    frame_desc = map_desc[rng.permutation(400)[:300]] + rng.normal(0, 8, (300, 128)).astype(np.float32)
    np.testing.assert_array_equal(
        match_descriptors(frame_desc, map_desc, 0.8), match_descriptors(frame_desc, map_desc, 0.8)
    )


# ---------------------------------------------------------------------- planes


def _map_planes() -> np.ndarray:
    """Floor, two walls and a table top in the map frame, normals towards the origin."""
    return np.array(
        [
            [0.0, -1.0, 0.0, 1.2],  # floor y = 1.2 (camera y points down)
            [0.0, 0.0, -1.0, 3.0],  # wall z = 3
            [-1.0, 0.0, 0.0, 2.0],  # wall x = 2
            [0.0, -1.0, 0.0, 0.5],  # table y = 0.5, parallel to the floor
        ]
    )


def test_plane_matching_under_a_pose() -> None:
    truth = _pose([0.05, -0.2, 0.03], [0.1, -0.05, 0.3])
    map_planes = _map_planes()
    frame_planes = transform_planes(np.linalg.inv(truth), map_planes)
    rng = np.random.default_rng(3)
    frame_planes[:, 3] += rng.normal(0, 0.01, len(frame_planes))
    order = np.array([2, 0, 3, 1])
    pairs = match_planes(frame_planes[order], map_planes, truth, angle_deg=10.0, distance=0.05)
    assert len(pairs) == 4
    np.testing.assert_array_equal(order[pairs[:, 0]], pairs[:, 1])


def test_plane_matching_rejects_far_planes_and_wrong_poses() -> None:
    truth = _pose([0.0, 0.3, 0.0], [0.0, 0.0, 0.5])
    map_planes = _map_planes()
    frame_planes = transform_planes(np.linalg.inv(truth), map_planes)
    # with the identity as prediction the walls are rotated 17 degrees away: only the
    # horizontal floor and table survive the angle test, and their offsets still agree
    pairs = match_planes(frame_planes, map_planes, np.eye(4), angle_deg=10.0, distance=0.05)
    np.testing.assert_array_equal(pairs, [[0, 0], [3, 3]])
    # an offset error above the threshold is no match
    shifted = frame_planes.copy()
    shifted[:, 3] += 0.08
    assert len(match_planes(shifted, map_planes, truth, 10.0, 0.05)) == 0
    # a flipped normal (the other side of a wall) is no match
    flipped = -frame_planes
    assert len(match_planes(flipped, map_planes, truth, 10.0, 0.05)) == 0


def test_plane_matching_is_one_to_one_best_first() -> None:
    map_planes = np.array([[0.0, 0.0, -1.0, 3.0]])
    frame_planes = np.array([[0.0, 0.0, -1.0, 3.03], [0.0, 0.0, -1.0, 3.01]])
    pairs = match_planes(frame_planes, map_planes, np.eye(4), 10.0, 0.05)
    np.testing.assert_array_equal(pairs, [[1, 0]])


# ---------------------------------------------------------------------- guided matching


def _guided_scene(seed: int, n: int = 200):
    rng = np.random.default_rng(seed)
    truth = _pose([0.1, -0.15, 0.05], [0.2, 0.1, -0.1])
    u, v, z = rng.uniform(10, 630, n), rng.uniform(10, 470, n), rng.uniform(1.0, 4.0, n)
    camera = np.column_stack([(u - CAMERA.cx) / CAMERA.fx * z, (v - CAMERA.cy) / CAMERA.fy * z, z])
    landmarks = camera @ truth[:3, :3].T + truth[:3, 3]
    map_desc = _random_descriptors(rng, n)
    order = rng.permutation(n)  # frame keypoint i observes landmark order[i]
    pixels = np.column_stack([u, v])[order] + rng.normal(0, 1.0, (n, 2))
    frame_desc = map_desc[order] + rng.normal(0, 10, (n, 128)).astype(np.float32)
    return truth, landmarks, map_desc, pixels, frame_desc, order, rng


def test_guided_matching_finds_the_projected_keypoints() -> None:
    truth, landmarks, map_desc, pixels, frame_desc, order, _ = _guided_scene(0)
    predicted = truth @ _pose([0.0, 0.004, 0.0], [0.005, 0.0, 0.0])  # a slightly wrong prediction
    pairs = guided_match(
        pixels, frame_desc, landmarks, map_desc, predicted, CAMERA, radius_px=15.0, ratio=0.8
    )
    assert len(pairs) >= 195
    np.testing.assert_array_equal(order[pairs[:, 0]], pairs[:, 1])
    assert len(np.unique(pairs[:, 0])) == len(pairs) and len(np.unique(pairs[:, 1])) == len(pairs)


def test_guided_matching_rejects_far_keypoints() -> None:
    truth, landmarks, map_desc, pixels, frame_desc, order, _ = _guided_scene(1)
    moved = pixels.copy()
    moved[:50] += [40.0, 0.0]  # these keypoints are now 40 px from their landmark's projection
    pairs = guided_match(
        moved, frame_desc, landmarks, map_desc, truth, CAMERA, radius_px=15.0, ratio=0.8, max_distance=0.7
    )
    assert not np.isin(pairs[:, 0], np.arange(50)).any()
    assert len(pairs) >= 145
    np.testing.assert_array_equal(order[pairs[:, 0]], pairs[:, 1])
    # unguided matching would have found them: the descriptors alone are distinctive
    unguided = match_descriptors(frame_desc, map_desc, ratio=0.8)
    assert np.isin(unguided[:, 0], np.arange(50)).sum() >= 45


def test_guided_matching_ratio_test_within_the_window() -> None:
    truth, landmarks, map_desc, pixels, frame_desc, order, _ = _guided_scene(2, n=20)
    # a second keypoint with the same descriptor right next to keypoint 0
    pixels = np.vstack([pixels, pixels[0] + [3.0, 0.0]])
    frame_desc = np.vstack([frame_desc, frame_desc[0] + 1.0])
    pairs = guided_match(pixels, frame_desc, landmarks, map_desc, truth, CAMERA, radius_px=15.0, ratio=0.8)
    assert order[0] not in pairs[:, 1]
    assert 0 not in pairs[:, 0] and 20 not in pairs[:, 0]


def test_guided_matching_ignores_landmarks_behind_or_outside() -> None:
    truth, landmarks, map_desc, pixels, frame_desc, order, _ = _guided_scene(3, n=30)
    camera_from_map = np.linalg.inv(truth)
    behind = camera_from_map[:3, :3] @ landmarks[order[0]] + camera_from_map[:3, 3]
    behind[2] = -behind[2]  # mirror landmark order[0] behind the camera
    landmarks = landmarks.copy()
    landmarks[order[0]] = truth[:3, :3] @ behind + truth[:3, 3]
    pairs = guided_match(pixels, frame_desc, landmarks, map_desc, truth, CAMERA, radius_px=15.0, ratio=0.8)
    assert order[0] not in pairs[:, 1]
    assert len(pairs) >= 27


def test_guided_matching_accepts_a_calibration_matrix_and_max_distance() -> None:
    truth, landmarks, map_desc, pixels, frame_desc, order, rng = _guided_scene(4, n=50)
    frame_desc[:10] = _random_descriptors(rng, 10)  # keypoints that look nothing like their landmark
    pairs = guided_match(
        pixels, frame_desc, landmarks, map_desc, truth, CAMERA.matrix, 15.0, 0.8, max_distance=0.7
    )
    assert not np.isin(pairs[:, 0], np.arange(10)).any()
    np.testing.assert_array_equal(order[pairs[:, 0]], pairs[:, 1])
    assert len(pairs) >= 38


def test_guided_matching_empty_inputs() -> None:
    empty = np.zeros((0, 128), np.float32)
    assert guided_match(np.zeros((0, 2)), empty, np.zeros((5, 3)), np.ones((5, 128), np.float32),
                        np.eye(4), CAMERA, 10.0, 0.8).shape == (0, 2)
    assert guided_match(np.zeros((5, 2)), np.ones((5, 128), np.float32), np.zeros((0, 3)), empty,
                        np.eye(4), CAMERA, 10.0, 0.8).shape == (0, 2)


@pytest.mark.parametrize("radius", [5.0, 30.0])
def test_guided_matching_is_deterministic(radius: float) -> None:
    truth, landmarks, map_desc, pixels, frame_desc, _, _ = _guided_scene(5)
    first = guided_match(pixels, frame_desc, landmarks, map_desc, truth, CAMERA, radius, 0.8)
    second = guided_match(pixels, frame_desc, landmarks, map_desc, truth, CAMERA, radius, 0.8)
    np.testing.assert_array_equal(first, second)
