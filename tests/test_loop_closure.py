"""Loop closure of the static map: the keyframe pose graph, the correction of a map by a verified
loop, a place mapped again recognised and verified, relocalisation by place recognition, and a
loop's path through the pipeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsr.config import load_config
from jsr.geometry import invert_transform, make_transform, rotation_angle, transform_points
from jsr.io.dataset import open_sequence
from jsr.io.trajectory import read_tum_trajectory
from jsr.pipeline.association import match_frame_to_map
from jsr.pipeline.loop_closure import (LoopClosure, PlaceIndex, close_loop, find_loop, recognised_landmarks,
                                      similar_keyframes)
from jsr.pipeline.pose_graph import PoseEdge, chain_edges, optimise_pose_graph
from jsr.pipeline.reconstruct import Reconstructor
from jsr.pipeline.registration import register
from jsr.pipeline.run import run_reconstruction
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


def drop_observations(keyframe, landmark_ids) -> None:
    """Remove a keyframe's observations of ``landmark_ids``."""
    keep = ~np.isin(keyframe.point_landmarks, landmark_ids)
    for name in ("point_measurements", "point_landmarks", "camera_points", "pixels", "sigma_z"):
        setattr(keyframe, name, getattr(keyframe, name)[keep])


def drifted_map(seed: int = 5):
    """A static map of 12 keyframes, each drifted 8 mm and 0.3 degrees more than the one before,
    with the landmarks it made (first observed); keyframes 6-11 made 40 each (no earlier
    keyframe observes them). Keyframe 11 also made duplicates of 30 landmarks keyframe 0 made. Returns the map, the scene (true poses and landmarks), the ids of the landmarks
    made by each drifted keyframe ``{k: (40,)}`` and the ``[duplicate, original]`` pairs."""
    rng = np.random.default_rng(seed)
    scene = make_scene(rng, keyframes=12, landmarks=900, arc_degrees=60.0, planes=0)
    the_map = build_map(scene, rng, perturb=False)
    keyframes = the_map.keyframes
    shared = np.intersect1d(keyframes[11].point_landmarks, keyframes[0].point_landmarks)[:30]
    made_by = {}
    taken = shared.copy()
    for k in range(6, 12):
        made_by[k] = np.setdiff1d(keyframes[k].point_landmarks, taken)[:40]
        taken = np.concatenate([taken, made_by[k]])
        for earlier in keyframes[:k]:
            drop_observations(earlier, made_by[k])
    step = make_transform(Rotation.from_rotvec([0.0, 0.0, np.radians(0.3)]).as_matrix(), [0.008, 0.0, 0.0])
    first_observer = np.full(len(the_map.points), -1)
    for k, keyframe in enumerate(keyframes):
        unseen = keyframe.point_landmarks[first_observer[keyframe.point_landmarks] < 0]
        first_observer[unseen] = k
    for k in range(1, 12):
        drift = np.linalg.matrix_power(step, k)
        keyframes[k].T_map_cam = drift @ keyframes[k].T_map_cam
        made_here = np.flatnonzero(first_observer == k)
        the_map.points.positions[made_here] = transform_points(drift, the_map.points.positions[made_here])
    last = keyframes[11]
    duplicates = the_map.points.add(transform_points(last.T_map_cam @ invert_transform(scene.poses[11]),
                                                     the_map.points.positions[shared]),
                                    the_map.points.descriptors[shared], np.full(len(shared), 0.005),
                                    the_map.points.colors[shared])
    for original, duplicate in zip(shared, duplicates):
        last.point_landmarks[last.point_landmarks == original] = duplicate
    return the_map, scene, made_by, np.column_stack([duplicates, shared])


def test_a_verified_loop_corrects_the_keyframes_and_landmarks_and_fuses_the_duplicates():
    the_map, scene, made_by, pairs = drifted_map()
    truth = scene.poses
    positions_before = the_map.points.positions.copy()
    loop = LoopClosure(frame_index=110, keyframe=11, matched_keyframe=0, similarity=0.9, inliers=200,
                       T_matched_keyframe=invert_transform(truth[0]) @ truth[11], fused_landmarks=pairs)
    poses_before = the_map.keyframe_poses
    error_before = np.linalg.norm(poses_before[:, :3, 3] - truth[:, :3, 3], axis=1)
    first = the_map.keyframes[0].T_map_cam.copy()
    closed, correction = close_loop(the_map, loop)
    poses = the_map.keyframe_poses
    error_after = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert np.array_equal(poses[0], first)
    assert error_before[11] > 0.08 and error_after[11] < 0.1 * error_before[11]
    assert error_after[1:].max() < 0.2 * error_before[1:].max()
    turn = lambda pose: np.degrees(rotation_angle((invert_transform(truth[11]) @ pose)[:3, :3]))  # noqa: E731
    assert turn(poses_before[11]) > 3.0 and turn(poses[11]) < 0.3 * turn(poses_before[11])
    assert closed.correction_cm > 3.0 and len(closed.fused_landmarks) == 30
    assert np.allclose(correction @ poses_before[11], poses[11])  # what the new keyframe moved by
    # the duplicates are retired, keyframe 11 observes the originals again
    duplicates, originals = pairs[:, 0], pairs[:, 1]
    assert not the_map.points.active[duplicates].any()
    assert np.isin(originals, the_map.keyframes[11].point_landmarks).all()
    assert not np.isin(duplicates, the_map.keyframes[11].point_landmarks).any()
    # landmarks made before the drift did not move; those the drifted keyframes made moved with them
    assert np.allclose(the_map.points.positions[originals], positions_before[originals], rtol=0, atol=1e-12)
    for k, ids in made_by.items():
        assert len(ids) == 40
        # each stays where its keyframe saw it ...
        seen_before = transform_points(invert_transform(poses_before[k]), positions_before[ids])
        seen_after = transform_points(invert_transform(poses[k]), the_map.points.positions[ids])
        assert np.allclose(seen_after, seen_before, rtol=0, atol=1e-9)
        # ... and so ends nearer the truth (by 15-25% along the loop, three
        # quarters at its end: the graph spreads the turn evenly, the drift was not)
        before = np.linalg.norm(positions_before[ids] - scene.landmarks[ids], axis=1).mean()
        after = np.linalg.norm(the_map.points.positions[ids] - scene.landmarks[ids], axis=1).mean()
        assert before > 0.04 and after < 0.9 * before, (k, before, after)
    assert np.linalg.norm(the_map.points.positions[made_by[11]] - scene.landmarks[made_by[11]], axis=1).mean() < 0.03


def test_a_landmark_pair_a_keyframe_observes_both_of_is_not_fused():
    the_map, scene, _, pairs = drifted_map()
    truth = scene.poses
    duplicate, original = pairs[0]
    landmarks = the_map.keyframes[10].point_landmarks
    assert original in landmarks
    landmarks[np.flatnonzero(~np.isin(landmarks, pairs))[0]] = duplicate  # keyframe 10 now sees both
    loop = LoopClosure(110, 11, 0, 0.9, 200, invert_transform(truth[0]) @ truth[11], pairs)
    closed, _ = close_loop(the_map, loop)
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
    closed, _ = close_loop(static_map, loop)
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


def test_a_loop_found_at_a_keyframe_is_applied_at_the_next_frame(forward_sequence, monkeypatch, tmp_path):
    """The pipeline's path: ``find_loop`` runs at each new static keyframe (here it makes up a
    loop at the fourth keyframe: keyframe 0's landmarks place it 3 cm off where tracking put
    it); the loop is applied at the start of the next frame, moves the keyframe, is listed in
    ``summary.json``, and the camera goes on from the corrected pose."""
    import jsr.pipeline.map_updates as map_updates

    made = []

    def made_up_loop(index, static_map, measurements, config, rng):
        keyframes = static_map.keyframes
        if len(keyframes) != 4 or made:
            return None
        shift = make_transform(np.eye(3), [0.03, 0.0, 0.0])
        T_first_newest = invert_transform(keyframes[0].T_map_cam) @ keyframes[3].T_map_cam @ shift
        made.append(keyframes[3].T_map_cam.copy())
        return LoopClosure(keyframes[3].frame_index, 3, 0, 1.0, 100, T_first_newest, np.zeros((0, 2), np.int64))

    monkeypatch.setattr(map_updates, "find_loop", made_up_loop)
    sequence = open_sequence(forward_sequence)
    config = load_config(None, ["bundle_adjustment.enabled=false"])  # nothing else moves the keyframes
    summary = run_reconstruction(sequence, config, tmp_path, dense_models=False)
    assert summary["status"] == "complete" and made
    [loop] = summary["loops_closed"]
    assert loop["keyframe"] == 3 and loop["matched_keyframe"] == 0 and loop["landmarks_fused"] == 0
    # three odometry edges and the loop share the 3 cm: the keyframe moves about three quarters of it
    assert 1.8 < loop["correction_cm"] < 2.6
    timestamps, keyframe_poses = read_tum_trajectory(tmp_path / "static" / "keyframes.tum")
    moved = np.linalg.norm(keyframe_poses[3][:3, 3] - made[0][:3, 3]) * 100
    assert abs(moved - loop["correction_cm"]) < 0.01
    # the frames after it are tracked on from there: no jump back to the uncorrected pose
    frame_times, poses = read_tum_trajectory(tmp_path / "camera.tum")
    after = np.flatnonzero(frame_times > timestamps[3])[:3]
    steps = np.linalg.norm(np.diff(poses[after[0] - 1: after[-1] + 1, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.06  # the camera moves 3-5 cm a frame


def test_a_map_without_active_landmarks_gives_no_loop_and_no_place():
    """No descriptor to train the place vocabulary on: nothing is recognised, nothing raises."""
    the_map, _, _, _ = drifted_map()
    the_map.points.retire(np.arange(len(the_map.points)))
    config = load_config(None, ["loop_closure.min_keyframe_gap=3"])
    index = PlaceIndex()
    # (no measurements: without a vocabulary no candidate is verified)
    assert find_loop(index, the_map, None, config, np.random.default_rng(0)) is None
    descriptors = np.random.default_rng(1).random((50, 128)).astype(np.float32)
    assert recognised_landmarks(index, the_map, descriptors, config) is None
    assert index.vocabulary is None
