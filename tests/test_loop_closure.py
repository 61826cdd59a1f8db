"""Loop closure of the static map: the keyframe pose graph, the correction of a map by a verified
loop, and loops found in a sequence that comes back to where it started."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsr.config import load_config
from jsr.geometry import invert_transform, make_transform, rotation_angle, transform_points
from jsr.io.dataset import open_sequence
from jsr.pipeline.loop_closure import LoopClosure, close_loop, find_loop, recognised_landmarks, similar_keyframes
from jsr.pipeline.maps import Map
from jsr.pipeline.pose_graph import PoseEdge, chain_edges, optimise_pose_graph
from jsr.pipeline.reconstruct import Reconstructor
from jsr.pipeline.registration import register
from jsr.pipeline.association import match_frame_to_map
from tests.test_bundle import build_map, make_scene


def ring(count: int) -> np.ndarray:
    """``(count, 4, 4)`` poses on a 1 m circle, each turned to face along it."""
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i, angle in enumerate(np.linspace(0, 2 * np.pi, count, endpoint=False)):
        poses[i] = make_transform(Rotation.from_euler("z", angle).as_matrix(), [np.cos(angle), np.sin(angle), 0.0])
    return poses


def drifted_chain(truth: np.ndarray, rng, translation: float = 0.01, radians: float = 0.01) -> np.ndarray:
    """The poses chained from ``truth``'s relative poses, each step off by a small random motion."""
    chained = [truth[0]]
    for i in range(1, len(truth)):
        noise = make_transform(Rotation.from_rotvec(rng.normal(0, radians, 3)).as_matrix(), rng.normal(0, translation, 3))
        chained.append(chained[-1] @ invert_transform(truth[i - 1]) @ truth[i] @ noise)
    return np.stack(chained)


def test_pose_graph_spreads_a_loops_disagreement_over_the_chain():
    rng = np.random.default_rng(0)
    truth = ring(20)
    drifted = drifted_chain(truth, rng)
    edges = chain_edges(drifted, 0.01, 0.01)
    # without a loop the chain agrees with itself: nothing moves
    assert np.allclose(optimise_pose_graph(drifted, edges), drifted, atol=1e-9)
    loop = PoseEdge(0, 19, invert_transform(truth[0]) @ truth[19], 0.01, 0.01)
    optimised = optimise_pose_graph(drifted, edges + [loop], fixed=0)
    assert np.array_equal(optimised[0], drifted[0])
    error_before = np.linalg.norm(drifted[:, :3, 3] - truth[:, :3, 3], axis=1)
    error_after = np.linalg.norm(optimised[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert error_before[-1] > 0.1
    assert error_after[-1] < 0.1 * error_before[-1]
    assert error_after.max() < 0.5 * error_before.max()


def drifted_map(seed: int = 5):
    """A static map of 12 keyframes in which keyframes 6-11 drifted (each 8 mm and 0.3 degrees
    more than the one before) and the landmarks they made drifted with them; keyframe 11 also
    made duplicates of 30 landmarks keyframe 0 sees. Returns the map, the true poses and the
    ``[duplicate, original]`` pairs."""
    rng = np.random.default_rng(seed)
    scene = make_scene(rng, keyframes=12, landmarks=600, arc_degrees=60.0, planes=0)
    the_map = build_map(scene, rng, perturb=False)
    step = make_transform(Rotation.from_rotvec([0.0, 0.0, np.radians(0.3)]).as_matrix(), [0.008, 0.0, 0.0])
    first_observer = np.full(len(the_map.points), -1)
    for k, keyframe in enumerate(the_map.keyframes):
        unseen = keyframe.point_landmarks[first_observer[keyframe.point_landmarks] < 0]
        first_observer[unseen] = k
    for k, keyframe in enumerate(the_map.keyframes):
        if k >= 6:
            drift = np.linalg.matrix_power(step, k - 5)
            keyframe.T_map_cam = drift @ keyframe.T_map_cam
            made_here = np.flatnonzero(first_observer == k)
            the_map.points.positions[made_here] = transform_points(drift, the_map.points.positions[made_here])
    last, first = the_map.keyframes[11], the_map.keyframes[0]
    shared = np.intersect1d(np.intersect1d(last.point_landmarks, first.point_landmarks),
                            np.flatnonzero(first_observer == 0))[:30]
    duplicates = the_map.points.add(transform_points(last.T_map_cam @ invert_transform(scene.poses[11]),
                                                     the_map.points.positions[shared]),
                                    the_map.points.descriptors[shared], np.full(len(shared), 0.005),
                                    the_map.points.colors[shared])
    for original, duplicate in zip(shared, duplicates):
        last.point_landmarks[last.point_landmarks == original] = duplicate
    return the_map, scene.poses, np.column_stack([duplicates, shared])


def test_a_verified_loop_corrects_the_keyframes_and_fuses_the_duplicated_landmarks():
    the_map, truth, pairs = drifted_map()
    positions_before = the_map.points.positions.copy()
    loop = LoopClosure(frame_index=110, keyframe=11, matched_keyframe=0, similarity=0.9, inliers=200,
                       T_matched_keyframe=invert_transform(truth[0]) @ truth[11], fused_landmarks=pairs)
    error_before = np.linalg.norm(the_map.keyframe_poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    first = the_map.keyframes[0].T_map_cam.copy()
    closed = close_loop(the_map, loop)
    poses = the_map.keyframe_poses
    error_after = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert np.array_equal(poses[0], first)
    assert error_before[11] > 0.04 and error_after[11] < 0.2 * error_before[11]
    assert error_after[6:].max() < 0.5 * error_before[6:].max()
    turn = np.degrees(rotation_angle((invert_transform(truth[11]) @ poses[11])[:3, :3]))
    assert turn < 0.5  # 1.8 degrees before
    assert closed.correction_cm > 3.0 and len(closed.fused_landmarks) == 30
    # the duplicates are retired, keyframe 11 observes the originals again
    duplicates, originals = pairs[:, 0], pairs[:, 1]
    assert not the_map.points.active[duplicates].any()
    assert np.isin(originals, the_map.keyframes[11].point_landmarks).all()
    assert not np.isin(duplicates, the_map.keyframes[11].point_landmarks).any()
    # landmarks made before the drift did not move; those made by drifted keyframes moved back
    assert np.allclose(the_map.points.positions[originals], positions_before[originals], rtol=0, atol=1e-12)
    made_by_11 = np.setdiff1d(the_map.keyframes[11].point_landmarks,
                              np.concatenate([kf.point_landmarks for kf in the_map.keyframes[:11]]))
    if len(made_by_11):
        assert not np.allclose(the_map.points.positions[made_by_11], positions_before[made_by_11])


def test_a_landmark_pair_a_keyframe_observes_both_of_is_not_fused():
    the_map, truth, pairs = drifted_map()
    duplicate, original = pairs[0]
    landmarks = the_map.keyframes[10].point_landmarks
    assert original in landmarks
    landmarks[np.flatnonzero(~np.isin(landmarks, pairs))[0]] = duplicate  # keyframe 10 now sees both
    loop = LoopClosure(110, 11, 0, 0.9, 200, invert_transform(truth[0]) @ truth[11], pairs)
    closed = close_loop(the_map, loop)
    assert len(closed.fused_landmarks) == len(pairs) - 1
    assert the_map.points.active[duplicate]


@pytest.fixture(scope="module")
def forward_sequence(tmp_path_factory) -> Path:
    """A static synthetic scene (320x240, 24 frames, seed 3; the camera moves 3-5 cm and 1-1.7
    degrees a frame)."""
    from jsr.synth.options import SynthOptions
    from jsr.synth.write import generate_sequence

    root = tmp_path_factory.mktemp("loop") / "forward"
    generate_sequence(root, SynthOptions(frames=24, objects=0, motion="static", width=320, height=240, seed=3))
    return root


def reconstruct(sequence, overrides: list[str], frames: range) -> Reconstructor:
    reconstructor = Reconstructor(load_config(None, overrides), sequence.intrinsics)
    try:
        for index in frames:
            reconstructor.process(sequence[index])
        reconstructor.finish()
    finally:
        reconstructor.close()
    return reconstructor


def test_a_place_mapped_again_is_recognised_verified_and_closed(forward_sequence):
    """The camera's way out is mapped (every other frame); then frame 3 comes back as a new
    keyframe whose measurements match no landmark (as after tracking lost the association) at a
    pose 6 cm and 2 degrees off. Its place is recognised among the old keyframes, the loop is
    verified against their landmarks, and closing it puts the keyframe back at its true pose
    and fuses its landmarks into the old ones."""
    sequence = open_sequence(forward_sequence)
    config = ["loop_closure.min_keyframe_gap=2", "bundle_adjustment.final_global=false"]
    reconstructor = reconstruct(sequence, config, range(0, 24, 2))
    state, static_map = reconstructor.state, reconstructor.static_map
    assert len(static_map.keyframes) >= 4 and state.places.closed == []
    truth = invert_transform(sequence.groundtruth[1][0]) @ sequence.groundtruth[1]  # the map's frame: camera 0
    frame = sequence[3]
    measurements = reconstructor.frontend.process(frame)
    offset = make_transform(Rotation.from_rotvec([0.0, np.radians(2.0), 0.0]).as_matrix(), [0.06, 0.0, 0.0])
    drifted = truth[3] @ offset
    points = measurements.points
    every = np.arange(len(points))
    static_map.add_keyframe(frame.index, frame.timestamp, drifted, points, every, np.full(len(points), -1),
                            np.zeros((len(points), 3), np.uint8))
    newest = len(static_map.keyframes) - 1
    active_before = static_map.points.active_count
    loop = find_loop(state.places, static_map, measurements, reconstructor.config, np.random.default_rng(0))
    assert loop is not None and loop.keyframe == newest
    matched_frame = static_map.keyframes[loop.matched_keyframe].frame_index
    assert matched_frame in (2, 4) and loop.inliers >= 50 and len(loop.fused_landmarks) >= 50
    # the loop measures the keyframe's true pose relative to the old one
    measured = static_map.keyframes[loop.matched_keyframe].T_map_cam @ loop.T_matched_keyframe
    assert np.linalg.norm(measured[:3, 3] - truth[3][:3, 3]) < 0.01
    closed = close_loop(static_map, loop)
    corrected = static_map.keyframes[newest].T_map_cam
    assert np.linalg.norm(corrected[:3, 3] - truth[3][:3, 3]) < 0.015  # 6 cm before
    assert np.degrees(rotation_angle((invert_transform(truth[3]) @ corrected)[:3, :3])) < 0.5
    assert 4.0 < closed.correction_cm < 8.0
    assert static_map.points.active_count == active_before - len(closed.fused_landmarks)


def test_a_lost_frame_is_matched_to_the_keyframes_that_look_like_it(forward_sequence):
    """Relocalisation by place recognition: among the 12 keyframes of the way (one every frame
    out of two), those that look most like frame 3 are those of its place, and the landmarks
    around them place the camera."""
    sequence = open_sequence(forward_sequence)
    overrides = ["bundle_adjustment.final_global=false", "keyframes.translation=0.03", "keyframes.rotation_degrees=5"]
    reconstructor = reconstruct(sequence, overrides, range(0, 24, 2))
    state, static_map, config = reconstructor.state, reconstructor.static_map, reconstructor.config
    assert len(static_map.keyframes) == 12
    measurements = reconstructor.frontend.process(sequence[3])
    ranked = similar_keyframes(state.places, static_map, measurements.points.descriptors, config)
    assert static_map.keyframes[ranked[0]].frame_index in (2, 4)
    assert all(abs(static_map.keyframes[k].frame_index - 3) <= 5 for k in ranked[:3])
    landmarks = recognised_landmarks(state.places, static_map, measurements.points.descriptors, config)
    assert landmarks is not None and 0 < len(landmarks) < static_map.points.active_count
    matched = match_frame_to_map(measurements, static_map, landmarks, None, config)
    result = register(matched.correspondences, config.ransac, config.noise, np.random.default_rng(0))
    truth = invert_transform(sequence.groundtruth[1][0]) @ sequence.groundtruth[1][3]
    assert result.success and np.linalg.norm(result.transformation[:3, 3] - truth[:3, 3]) < 0.01
    off = load_config(None, ["loop_closure.enabled=false"])
    assert recognised_landmarks(state.places, static_map, measurements.points.descriptors, off) is None
