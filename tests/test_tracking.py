"""Static-map camera tracking on synthetic sequences with exact ground truth."""

import cv2
import numpy as np
import pytest

from jsr.config import load_config
from jsr.evaluate.trajectory import absolute_trajectory_error, associate_poses
from jsr.io.dataset import open_sequence
from jsr.pipeline.reconstruct import Reconstructor
from jsr.synth.options import SynthOptions
from jsr.synth.write import generate_sequence


@pytest.fixture(scope="module")
def static_sequence(tmp_path_factory):
    root = tmp_path_factory.mktemp("tracking") / "static"
    generate_sequence(root, SynthOptions(frames=30, objects=0, motion="static", width=320, height=240, seed=4))
    return root


def track(sequence, overrides=()):
    reconstructor = Reconstructor(load_config(None, list(overrides)), sequence.intrinsics)
    reports = [reconstructor.process(frame) for frame in sequence]
    reconstructor.finish()
    return reconstructor, reports


def ate(reports, sequence):
    tracked = [r for r in reports if r.tracked]
    timestamps = np.array([r.timestamp for r in tracked])
    poses = np.array([r.T_w_c for r in tracked])
    _, estimate, truth = associate_poses(timestamps, poses, *sequence.groundtruth)
    return absolute_trajectory_error(estimate, truth).rmse


def test_tracker_ate_below_one_centimetre(static_sequence):
    sequence = open_sequence(static_sequence)
    reconstructor, reports = track(sequence)
    assert all(r.tracked for r in reports)
    assert ate(reports, sequence) < 0.01
    static_map = reconstructor.static_map
    assert len(static_map.keyframes) >= 2
    assert static_map.points.active_count > 200
    # world frame = first camera frame
    assert np.allclose(reports[0].T_w_c, np.eye(4))


def test_tracking_loss_is_survived_and_relocalised(static_sequence, tmp_path):
    import shutil

    root = tmp_path / "blanked"
    shutil.copytree(static_sequence, root)
    sequence = open_sequence(root)
    blanked = range(12, 18)
    for index in blanked:
        entry = sequence.entries[index]
        cv2.imwrite(str(entry.color_path), np.zeros((240, 320, 3), np.uint8))
        cv2.imwrite(str(entry.depth_path), np.zeros((240, 320), np.uint16))
    reconstructor, reports = track(sequence)
    assert [r.tracked for r in reports[12:18]] == [False] * 6
    assert reconstructor.state.camera.frames_lost == 6
    assert reports[18].tracked and reports[18].relocalised
    assert all(r.tracked for r in reports[18:])
    assert ate(reports, sequence) < 0.015


def test_same_seed_same_trajectory(static_sequence):
    sequence = open_sequence(static_sequence, max_frames=10)
    _, first = track(sequence)
    _, second = track(sequence)
    assert all(np.array_equal(a.T_w_c, b.T_w_c) for a, b in zip(first, second))


def test_previous_frame_bridges_what_the_map_cannot_see(static_sequence):
    # One keyframe only (huge keyframe thresholds) and a strict inlier ratio: the camera soon
    # sees too little of the first keyframe's scene, and frame-to-map registration fails.
    sequence = open_sequence(static_sequence)
    strict = ["keyframes.translation=100", "keyframes.rotation_degrees=180", "ransac.min_inlier_ratio=0.95"]
    _, without_bridge = track(sequence, strict + ["matching.bridge_with_previous_frame=false"])
    reconstructor, with_bridge = track(sequence, strict)
    assert sum(not r.tracked for r in without_bridge) > 0
    assert reconstructor.state.camera.frames_bridged > 0
    bridged = [r for r in with_bridge if r.bridged]
    assert all(r.new_keyframe for r in bridged)  # the map grows into the new view
    assert sum(r.tracked for r in with_bridge) > sum(r.tracked for r in without_bridge)
    assert ate(with_bridge, sequence) < 0.01


def test_no_static_keyframe_from_a_poorly_supported_pose(static_sequence):
    """keyframes.static_min_inliers: a new view becomes a static keyframe only when its
    registration has that many inliers. Asking more than any frame has leaves the first
    keyframe alone; the camera still tracks from it."""
    sequence = open_sequence(static_sequence, max_frames=15)
    reconstructor, reports = track(sequence)
    assert any(r.new_keyframe for r in reports[1:]), "the sequence moves enough for new keyframes"
    gated, gated_reports = track(sequence, ["keyframes.static_min_inliers=100000"])
    assert len(gated.static_map.keyframes) == 1 < len(reconstructor.static_map.keyframes)
    assert all(r.tracked and not r.new_keyframe for r in gated_reports[1:])


def test_a_keyframe_is_taken_when_the_map_loses_the_view(static_sequence):
    """keyframes.tracked_share: with the distance and angle thresholds out of reach, a frame
    becomes a static keyframe when its matches to the map fall below the share of the best
    frame's since the last keyframe (and its inliers below keyframes.weak_inliers), so the map
    keeps up with the camera instead of being bridged or lost."""
    sequence = open_sequence(static_sequence, max_frames=20)
    far = ["keyframes.translation=100", "keyframes.rotation_degrees=180", "keyframes.weak_inliers=100000"]
    alone, _ = track(sequence, far + ["keyframes.tracked_share=0", "matching.bridge_with_previous_frame=false"])
    assert len(alone.static_map.keyframes) == 1
    reconstructor, reports = track(sequence, far + ["keyframes.tracked_share=0.7",
                                                    "matching.bridge_with_previous_frame=false"])
    assert all(r.tracked for r in reports)
    taken = [i for i, r in enumerate(reports) if r.new_keyframe and i > 0]
    assert len(taken) >= 2
    last = 0
    for index in taken:
        best = max(r.matches for r in reports[last + 1:index])
        assert reports[index].matches < 0.7 * best
        assert all(r.matches >= 0.7 * max(q.matches for q in reports[last + 1:j + 1])
                   for j, r in enumerate(reports[last + 1:index], start=last + 1))  # not earlier
        last = index
    assert ate(reports, sequence) < 0.01
    # weak_inliers: a view still well supported is not a reason for a keyframe
    strong, _ = track(sequence, far[:2] + ["keyframes.tracked_share=0.7", "keyframes.weak_inliers=1",
                                                        "matching.bridge_with_previous_frame=false"])
    assert len(strong.static_map.keyframes) == 1


def test_depth_carries_frames_whose_features_fail(static_sequence, tmp_path):
    """dense: frames whose colour is blank (no feature at all) but whose depth is sharp are
    placed by their depth alone from the predicted pose; without the dense term they are lost."""
    import shutil

    root = tmp_path / "colourless"
    shutil.copytree(static_sequence, root)
    sequence = open_sequence(root)
    blanked = range(12, 15)
    for index in blanked:
        cv2.imwrite(str(sequence.entries[index].color_path), np.zeros((240, 320, 3), np.uint8))
    _, without_depth = track(sequence)
    assert not any(without_depth[i].tracked for i in blanked)
    reconstructor, reports = track(sequence, ["dense.enabled=true"])
    assert all(reports[i].tracked and reports[i].by_depth for i in blanked)
    assert not any(r.by_depth for i, r in enumerate(reports) if i not in blanked)
    assert all(r.tracked for r in reports)
    truth_times, truth_poses = sequence.groundtruth

    def truth_at(report):
        return truth_poses[np.argmin(np.abs(truth_times - report.timestamp))]

    for index in blanked:
        relative_truth = np.linalg.inv(truth_at(reports[0])) @ truth_at(reports[index])
        assert np.linalg.norm(reports[index].T_w_c[:3, 3] - relative_truth[:3, 3]) < 0.01
    assert ate(reports, sequence) < 0.01
    # the keyframes before them measured how far the depth moves a feature pose: within the bound
    measured = reconstructor.state.depth_disagreements
    assert measured and max(measured) < 0.015
    # a depth that never agreed that well with the features is not trusted: they are lost
    _, distrusted = track(sequence, ["dense.enabled=true", "dense.trust_within=0.0001"])
    assert not any(distrusted[i].tracked or distrusted[i].by_depth for i in blanked)


def test_depth_refinement_keeps_the_camera_on_depth_that_fits_its_noise_model(static_sequence):
    """dense.refine: on depth whose noise is the model's (synthetic), refining every frame on
    its depth beside the features moves the poses and keeps the camera within a centimetre."""
    sequence = open_sequence(static_sequence, max_frames=20)
    _, features_only = track(sequence)
    _, refined = track(sequence, ["dense.enabled=true", "dense.refine=true"])
    assert all(r.tracked and not r.by_depth for r in refined)
    moved = [np.linalg.norm(a.T_w_c[:3, 3] - b.T_w_c[:3, 3]) for a, b in zip(features_only[1:], refined[1:])]
    assert max(moved) > 1e-4  # the depth took part
    assert ate(refined, sequence) < 0.01


def test_dense_samples_keep_away_from_what_moved_in_the_previous_frame():
    from types import SimpleNamespace

    from jsr.pipeline.static_tracking import static_pixels

    config = load_config(None)
    state = SimpleNamespace(config=config, memory=SimpleNamespace(previous_mask=None))
    assert static_pixels(state) is None
    state.memory.previous_mask = np.zeros((480, 640), np.uint8)
    assert static_pixels(state) is None  # all static: every pixel may be aligned
    state.memory.previous_mask[200:240, 300:340] = 255  # dynamic (a person) ...
    state.memory.previous_mask[100:110, 100:110] = 3  # ... and an object
    keep = static_pixels(state)
    margin = config.detection.dynamic_margin_px
    assert not keep[200 - margin:240 + margin, 300 - margin:340 + margin].any()
    assert not keep[100 - margin:110 + margin, 100 - margin:110 + margin].any()
    assert keep[200 - margin - 1, 320] and keep[120, 105 + margin + 1]
    assert keep.sum() == 480 * 640 - (40 + 2 * margin) ** 2 - (10 + 2 * margin) ** 2


def test_depth_carries_poorly_supported_frames_when_asked(static_sequence):
    """dense.carry_below_inliers: a frame with fewer feature inliers than this is placed by its
    depth together with those inliers; asking more than any frame has, every frame is (the
    depth trusted from the start: nothing carried, no keyframe measures it)."""
    sequence = open_sequence(static_sequence, max_frames=12)
    _, reports = track(sequence, ["dense.enabled=true", "dense.carry_below_inliers=100000", "dense.trust_within=0"])
    assert all(r.tracked for r in reports)
    assert all(r.by_depth for r in reports[1:])
    assert ate(reports, sequence) < 0.01
