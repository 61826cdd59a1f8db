"""Tests of jsr.evaluate: ATE, RPE, object pose error, mask precision/recall, whole runs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from jsr.errors import InputError
from jsr.evaluate.masks import mask_precision_recall
from jsr.evaluate.objects import ObjectPoseError, match_objects, object_pose_error
from jsr.evaluate.run import evaluate_run, write_metrics
from jsr.evaluate.trajectory import absolute_trajectory_error, associate_poses, relative_pose_error
from jsr.geometry import invert_transform, make_transform, rotation_about_axis
from jsr.io.trajectory import read_tum_trajectory, write_tum_trajectory


def smooth_trajectory(rng: np.random.Generator, count: int) -> np.ndarray:
    """``(count, 4, 4)`` poses on a random smooth 3D curve with smoothly varying orientation."""
    time = np.linspace(0.0, 1.0, count)
    frequencies = rng.uniform(0.5, 2.0, size=(2, 3))
    phases = rng.uniform(0.0, 2 * np.pi, size=(2, 3))
    amplitudes = rng.uniform(0.3, 1.5, size=3)
    positions = amplitudes * np.sin(2 * np.pi * frequencies[0] * time[:, None] + phases[0])
    rotvecs = 0.6 * np.sin(2 * np.pi * frequencies[1] * time[:, None] + phases[1])
    rotations = Rotation.from_rotvec(rotvecs).as_matrix()
    return np.stack([make_transform(rotation, position) for rotation, position in zip(rotations, positions)])


def random_transform(rng: np.random.Generator, translation_scale: float = 1.0) -> np.ndarray:
    return make_transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(scale=translation_scale, size=3))


def translation(vector: np.ndarray) -> np.ndarray:
    return make_transform(np.eye(3), vector)


# ---------------------------------------------------------------------------------- ATE


def test_ate_of_ground_truth_and_of_rigidly_moved_ground_truth_is_zero():
    rng = np.random.default_rng(1)
    gt = smooth_trajectory(rng, 60)
    assert absolute_trajectory_error(gt, gt).rmse < 1e-9
    moved = random_transform(rng, 2.0)
    result = absolute_trajectory_error(moved @ gt, gt)
    assert result.rmse < 1e-9
    assert result.max < 1e-9
    assert result.count == 60
    # alignment is T_gt_est, which maps the moved trajectory back: the inverse of the motion.
    np.testing.assert_allclose(result.alignment, invert_transform(moved), atol=1e-9)


def test_ate_matches_brute_force_least_squares():
    rng = np.random.default_rng(2)
    gt = smooth_trajectory(rng, 80)
    motion = make_transform(rotation_about_axis([0.3, -0.5, 1.0], np.radians(35.0)), [0.4, -0.2, 0.7])
    est = gt.copy()
    est[:, :3, 3] += rng.normal(scale=0.03, size=(80, 3))
    est = motion @ est
    result = absolute_trajectory_error(est, gt)

    # Independent check: minimise over the 6 SE(3) parameters numerically, from the identity.
    est_positions, gt_positions = est[:, :3, 3], gt[:, :3, 3]

    def residuals(parameters):
        rotation = Rotation.from_rotvec(parameters[:3]).as_matrix()
        return (est_positions @ rotation.T + parameters[3:] - gt_positions).ravel()

    solution = least_squares(residuals, np.zeros(6), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    per_frame = np.linalg.norm(solution.fun.reshape(-1, 3), axis=1)
    brute_force_rmse = math.sqrt(np.mean(per_frame**2))
    assert result.rmse > 0.01  # the noise is really there
    assert abs(result.rmse - brute_force_rmse) < 1e-6
    assert abs(result.mean - per_frame.mean()) < 1e-6
    assert abs(result.max - per_frame.max()) < 1e-6


def test_ate_of_alternating_offsets_on_out_and_back_trajectory_is_the_offset():
    # The camera goes out along p_0..p_{n-1} and comes back along the same points reversed,
    # so p_m is visited at frames m and 2n-1-m, which have opposite parity. Offsetting even
    # frames by +d*a and odd frames by -d*a (signs s_i) therefore gives sum(s_i) = 0 and
    # sum(s_i * g_i) = 0: the estimate has the same centroid as the truth and the cross-
    # covariance is H = sum(g~ g~^T) + d * (sum s_i g~_i) a^T = sum(g~ g~^T), symmetric positive
    # definite, for which the best rotation is the identity (and the best translation zero).
    # Every frame is then exactly d away from the truth: ATE RMSE = mean = max = d.
    rng = np.random.default_rng(3)
    out = smooth_trajectory(rng, 25)
    gt = np.concatenate([out, out[::-1]])
    d = 0.037
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    signs = np.where(np.arange(len(gt)) % 2 == 0, 1.0, -1.0)
    est = gt.copy()
    est[:, :3, 3] += d * signs[:, None] * axis
    result = absolute_trajectory_error(est, gt)
    assert result.rmse == pytest.approx(d, abs=1e-12)
    assert result.max == pytest.approx(d, abs=1e-12)
    assert result.median == pytest.approx(d, abs=1e-12)
    np.testing.assert_allclose(result.alignment, np.eye(4), atol=1e-12)


def test_associate_poses_pairs_by_nearest_timestamp():
    rng = np.random.default_rng(4)
    poses = smooth_trajectory(rng, 10)
    gt_timestamps = np.arange(10) * 0.1
    est_timestamps = np.array([0.005, 0.2, 0.31, 0.55, 0.9 - 0.01])  # 0.55 has no partner within 0.02
    timestamps, est, gt = associate_poses(est_timestamps, poses[:5], gt_timestamps, poses, max_difference=0.02)
    np.testing.assert_allclose(timestamps, [0.005, 0.2, 0.31, 0.89])
    np.testing.assert_allclose(est, poses[[0, 1, 2, 4]])
    np.testing.assert_allclose(gt, poses[[0, 2, 3, 9]])


# ---------------------------------------------------------------------------------- RPE


def test_rpe_of_constant_velocity_with_known_per_step_error():
    rng = np.random.default_rng(5)
    step = make_transform(rotation_about_axis([0.2, 1.0, 0.1], np.radians(3.0)), [0.05, 0.01, 0.0])
    error = make_transform(rotation_about_axis([1.0, -0.3, 0.4], np.radians(0.5)), [0.002, -0.001, 0.0005])
    gt = [random_transform(rng)]
    est = [random_transform(rng)]  # a different world frame does not matter
    for _ in range(30):
        gt.append(gt[-1] @ step)
        est.append(est[-1] @ step @ error)
    result = relative_pose_error(np.stack(est), np.stack(gt), delta=1)
    # inv(G_i)G_{i+1} = step and inv(P_i)P_{i+1} = step @ error, so every E_i = error.
    assert result.count == 30
    assert result.translation_rmse == pytest.approx(np.linalg.norm([0.002, -0.001, 0.0005]), abs=1e-12)
    assert result.rotation_rmse == pytest.approx(0.5, abs=1e-9)


def test_rpe_with_delta_two_on_pure_translation():
    velocity = np.array([0.1, 0.0, 0.02])
    drift = np.array([0.0, 0.003, 0.004])  # 5 mm per step
    gt = np.stack([translation(i * velocity) for i in range(12)])
    est = np.stack([translation(i * (velocity + drift)) for i in range(12)])
    result = relative_pose_error(est, gt, delta=2)
    assert result.count == 10
    assert result.translation_rmse == pytest.approx(0.010, abs=1e-12)
    assert result.rotation_rmse == pytest.approx(0.0, abs=1e-9)


# ---------------------------------------------------------------------------------- objects


def object_scene(seed: int, count: int = 40):
    """Ground-truth cameras and object poses, an object-frame offset X and a world change W."""
    rng = np.random.default_rng(seed)
    cameras = smooth_trajectory(rng, count)
    objects = smooth_trajectory(rng, count)
    objects[:, :3, 3] += [0.0, 0.0, 2.0]
    offset = random_transform(rng, 0.2)
    world = random_transform(rng, 3.0)
    return rng, cameras, objects, offset, world


def test_object_pose_error_is_zero_for_a_perfect_estimate_with_offset_and_other_world():
    _, cameras, objects, offset, world = object_scene(6)
    result = object_pose_error(world @ cameras, world @ objects @ offset, cameras, objects, estimated_id=3, true_id=1)
    assert isinstance(result, ObjectPoseError)
    assert (result.estimated_id, result.true_id, result.frames) == (3, 1, 40)
    assert result.translation_rmse_cm < 1e-9
    assert result.rotation_rmse_deg < 1e-9
    np.testing.assert_allclose(result.offset, offset, atol=1e-9)


def test_object_pose_error_of_one_centimetre_in_the_camera_frame():
    _, cameras, objects, offset, world = object_scene(7)
    in_camera = invert_transform(cameras) @ objects
    # Shift the object by 1 cm in the camera frame, along +R u on even and -R u on odd frames
    # (R: true object rotation in the camera frame). Then inv(C_gt) C_est has translation
    # t_X +/- u: a symmetric set whose median is exactly t_X, so the offset is recovered exactly
    # and every frame is exactly 1 cm off.
    u = np.array([0.6, 0.0, -0.8]) * 0.01
    signs = np.where(np.arange(len(cameras)) % 2 == 0, 1.0, -1.0)
    shifts = np.stack([translation(sign * c[:3, :3] @ u) for sign, c in zip(signs, in_camera)])
    est_cameras = world @ cameras
    est_objects = est_cameras @ shifts @ in_camera @ offset
    result = object_pose_error(est_cameras, est_objects, cameras, objects)
    assert result.translation_rmse_cm == pytest.approx(1.0, abs=1e-9)
    assert result.translation_median_cm == pytest.approx(1.0, abs=1e-9)
    assert result.rotation_rmse_deg < 1e-9
    np.testing.assert_allclose(result.offset, offset, atol=1e-9)


def test_object_pose_error_ignores_a_single_lost_frame_in_translation():
    _, cameras, objects, offset, world = object_scene(8)
    est_cameras = world @ cameras
    est_objects = world @ objects @ offset
    # Frame 5: 1 cm error along the camera x axis. The median offset is unaffected.
    est_objects[5] = est_cameras[5] @ translation([0.01, 0.0, 0.0]) @ invert_transform(est_cameras[5]) @ est_objects[5]
    result = object_pose_error(est_cameras, est_objects, cameras, objects)
    assert result.translation_median_cm < 1e-9
    assert result.translation_max_cm == pytest.approx(1.0, abs=1e-9)
    assert result.translation_rmse_cm == pytest.approx(1.0 / math.sqrt(40), abs=1e-9)
    assert np.argmax(result.translation_errors_cm) == 5


def test_object_pose_error_of_two_degrees():
    _, cameras, objects, offset, world = object_scene(9)
    # +2 and -2 degrees about a fixed axis through the true object's centre on alternate
    # frames: the chordal mean of inv(X) R(-2) and inv(X) R(+2) is exactly inv(X) (R(+a) + R(-a)
    # is symmetric positive definite), so every frame is exactly 2 degrees off and the centre
    # does not move.
    axis = np.array([0.3, 0.9, -0.2])
    errors = np.stack(
        [make_transform(rotation_about_axis(axis, np.radians(2.0 * (-1) ** i)), np.zeros(3)) for i in range(40)]
    )
    result = object_pose_error(world @ cameras, world @ objects @ errors @ offset, cameras, objects)
    assert result.rotation_rmse_deg == pytest.approx(2.0, abs=1e-7)
    assert result.rotation_median_deg == pytest.approx(2.0, abs=1e-7)
    assert result.translation_rmse_cm < 1e-9
    np.testing.assert_allclose(result.offset, offset, atol=1e-9)


def test_object_pose_error_is_measured_at_the_true_centre_not_at_a_far_frame_origin():
    """jsr's object frame is the camera of the detecting frame, 1.5 m from the object: a
    rotation error about the object's centre must not count as centimetres of translation,
    while the same rotation about that far origin moves the centre by 1.5 m x angle."""
    _, cameras, objects, _, world = object_scene(10)
    far_origin = make_transform(np.eye(3), np.array([0.0, 0.3, -1.5]))  # X: estimated frame 1.5 m away
    axis = np.array([0.0, 1.0, 0.0])
    turns = np.stack([make_transform(rotation_about_axis(axis, np.radians(1.0 * (-1) ** i)), np.zeros(3))
                      for i in range(40)])
    about_centre = object_pose_error(world @ cameras, world @ objects @ turns @ far_origin, cameras, objects)
    assert about_centre.translation_rmse_cm < 1e-9
    assert about_centre.rotation_rmse_deg == pytest.approx(1.0, abs=1e-7)
    about_far_origin = object_pose_error(world @ cameras, world @ objects @ far_origin @ turns, cameras, objects)
    lever = np.linalg.norm(np.cross(axis, far_origin[:3, 3]))  # distance of the centre from the turn axis
    assert about_far_origin.translation_median_cm == pytest.approx(100.0 * lever * np.radians(1.0), rel=1e-3)


def _fake_error(estimated_id: int, true_id: int, median: float, frames: int = 10,
                followed: int | None = None) -> ObjectPoseError:
    return ObjectPoseError(estimated_id, true_id, frames, median, median, 0.0, 0.0, np.eye(4),
                           frames_followed=frames if followed is None else followed)


def test_match_objects_ties_in_coverage_go_by_median_translation_error():
    errors = [
        _fake_error(1, 1, 5.0),
        _fake_error(1, 2, 1.0),
        _fake_error(2, 2, 2.0),
        _fake_error(2, 1, 3.0),
        _fake_error(3, 1, 0.1, frames=2),  # too few frames to be matched
        _fake_error(4, 1, 9.0),
    ]
    matches = match_objects(errors)
    assert [(m.estimated_id, m.true_id) for m in matches] == [(1, 2), (2, 1)]


def test_match_objects_prefers_the_map_that_follows_the_object_longest():
    """The bundled sample's case: one box followed by a 26-frame map and, later, a 4-frame map
    that happens to be more accurate; and a long map of something else that follows nothing."""
    errors = [
        _fake_error(1, 1, 0.8, frames=26),
        _fake_error(2, 1, 0.01, frames=4),
        _fake_error(3, 1, 30.0, frames=40, followed=1),  # a static thing taken for an object
    ]
    (match,) = match_objects(errors)
    assert match.estimated_id == 1


def test_frames_followed_counts_frames_within_the_follow_gate():
    _, cameras, objects, _, world = object_scene(10, count=10)
    wrong = objects.copy()
    wrong[6:, :3, 3] += [0.2, 0.0, 0.0]  # the last 4 frames 20 cm off: followed in the first 6 only
    error = object_pose_error(world @ cameras, world @ wrong, cameras, objects)
    assert error.frames == 10 and error.frames_followed == 6


# ---------------------------------------------------------------------------------- masks


def test_mask_precision_recall_on_crafted_images():
    label = np.zeros((4, 5), dtype=np.uint8)
    label[0, 0:3] = 1  # 3 px of object 1
    label[2:4, 3:5] = 2  # 4 px of object 2
    mask = np.zeros((4, 5), dtype=np.uint8)
    mask[0, 1:4] = 7  # 2 of object 1 hit, (0, 3) is static
    mask[3, 3:5] = 8  # 2 of object 2 hit
    mask[1, 0] = 8  # static pixel
    # Second frame: nothing predicted, object 1 with 2 px.
    label_2 = np.zeros((4, 5), dtype=np.uint8)
    label_2[1, 1:3] = 1
    mask_2 = np.zeros((4, 5), dtype=np.uint8)

    result = mask_precision_recall([(mask, label), (mask_2, label_2)], matches=[(7, 1), (8, 2), (9, 1)])
    assert result["frames"] == 2
    # Overall: predicted 3 + 2 + 1 = 6, true 3 + 4 + 2 = 9, hits 2 + 2 = 4.
    assert result["precision"] == pytest.approx(4 / 6)
    assert result["recall"] == pytest.approx(4 / 9)
    assert result["iou"] == pytest.approx(4 / 11)
    pairs = {(p["estimated_id"], p["true_id"]): p for p in result["pairs"]}
    assert pairs[(7, 1)]["precision"] == pytest.approx(2 / 3)
    assert pairs[(7, 1)]["recall"] == pytest.approx(2 / 5)
    assert pairs[(8, 2)]["precision"] == pytest.approx(2 / 3)
    assert pairs[(8, 2)]["recall"] == pytest.approx(2 / 4)
    assert pairs[(9, 1)]["precision"] is None  # nothing predicted as 9
    assert pairs[(9, 1)]["recall"] == 0.0
    json.dumps(result, allow_nan=False)


def test_mask_precision_recall_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        mask_precision_recall([(np.zeros((2, 2)), np.zeros((2, 3)))])


# ---------------------------------------------------------------------------------- whole run


def make_run(tmp_path: Path):
    """A fake sequence and results folder; returns (sequence, results, true offset X)."""
    rng = np.random.default_rng(10)
    count = 20
    timestamps = 1000.0 + np.arange(count) / 30.0
    cameras = smooth_trajectory(rng, count)
    objects = smooth_trajectory(rng, count)
    objects[:, :3, 3] += [0.0, 0.0, 2.0]
    offset = random_transform(rng, 0.2)

    sequence = tmp_path / "seq"
    (sequence / "labels").mkdir(parents=True)
    write_tum_trajectory(sequence / "groundtruth.txt", timestamps + 0.003, cameras)
    write_tum_trajectory(sequence / "objects" / "object_1.txt", timestamps, objects)
    stems = [f"{t:.6f}" for t in timestamps]
    rgb_lines = [f"{float(t)!r} rgb/{stem}.png" for t, stem in zip(timestamps, stems)]
    (sequence / "rgb.txt").write_text("# colour\n" + "\n".join(rgb_lines) + "\n")
    for i, stem in enumerate(stems):
        label = np.zeros((64, 64), dtype=np.uint8)
        if i < 15:
            label[5:55, 5:55] = 1  # 2500 px: visible
        else:
            label[5:15, 5:15] = 1  # 100 px: not visible
        assert cv2.imwrite(str(sequence / "labels" / f"{stem}.png"), label)

    results = tmp_path / "results"
    (results / "masks").mkdir(parents=True)
    world = invert_transform(cameras[0])  # world = first camera frame
    # Frame 19 was not tracked; est timestamps are those of the colour frames.
    write_tum_trajectory(results / "camera.tum", timestamps[:19], world @ cameras[:19])
    object_1 = world @ objects[:10] @ offset
    write_tum_trajectory(results / "objects" / "object_1" / "trajectory.tum", timestamps[:10], object_1)
    junk = np.stack([random_transform(rng) for _ in range(8)])
    write_tum_trajectory(results / "objects" / "object_2" / "trajectory.tum", timestamps[2:10], junk)
    for stem in stems[:4]:
        mask = np.zeros((64, 64), dtype=np.uint8)
        mask[5:55, 10:60] = 1  # 2500 px, 2250 on the object
        mask[58:62, 0:10] = 2  # 40 static px
        assert cv2.imwrite(str(results / "masks" / f"{stem}.png"), mask)
    assert cv2.imwrite(str(results / "masks" / "no_label.png"), np.zeros((64, 64), dtype=np.uint8))
    return sequence, results, offset


def test_evaluate_run_end_to_end(tmp_path):
    sequence, results, offset = make_run(tmp_path)
    metrics = evaluate_run(results, sequence)

    camera = metrics["camera"]
    assert camera["frames_estimated"] == 19
    assert camera["frames_associated"] == 19
    assert camera["gt_frames"] == 20
    assert camera["gt_frames_without_estimate"] == 1
    assert camera["coverage"] == pytest.approx(19 / 20)
    assert camera["ate"]["rmse"] < 1e-9
    assert camera["ate"]["count"] == 19
    assert camera["rpe"]["translation_rmse"] < 1e-9
    assert camera["rpe"]["rotation_rmse"] < 1e-9
    assert camera["rpe"]["count"] == 18

    objects = metrics["objects"]
    assert [entry["id"] for entry in objects["estimated"]] == [1, 2]
    assert objects["true"] == [{"id": 1, "frames": 20, "visible_frames": 15}]
    assert objects["unmatched_estimated"] == [2]
    assert objects["unmatched_true"] == []
    (match,) = objects["matches"]
    assert (match["estimated_id"], match["true_id"], match["frames"]) == (1, 1, 10)
    assert match["translation_rmse_cm"] < 1e-9
    assert match["rotation_rmse_deg"] < 1e-9
    np.testing.assert_allclose(match["offset"], offset, atol=1e-9)
    assert match["visible_frames"] == 15
    assert match["tracked_frames"] == 10
    assert match["tracked_share"] == pytest.approx(10 / 15)

    masks = metrics["masks"]
    assert masks["frames"] == 4
    assert masks["mask_files"] == 5
    assert masks["precision"] == pytest.approx(2250 / 2540)
    assert masks["recall"] == pytest.approx(2250 / 2500)
    (pair,) = masks["pairs"]
    assert (pair["estimated_id"], pair["true_id"]) == (1, 1)
    assert pair["precision"] == pytest.approx(0.9)
    assert pair["recall"] == pytest.approx(0.9)

    path = write_metrics(results, metrics)
    assert path == results / "metrics.json"
    assert json.loads(path.read_text()) == json.loads(json.dumps(metrics, allow_nan=False))


def test_evaluate_run_without_object_ground_truth_or_masks(tmp_path):
    sequence, results, _ = make_run(tmp_path)
    for path in (sequence / "objects").iterdir():
        path.unlink()
    for path in (results / "masks").iterdir():
        path.unlink()
    metrics = evaluate_run(results, sequence)
    assert metrics["objects"] is None
    assert metrics["masks"] is None
    assert metrics["camera"]["ate"]["rmse"] < 1e-9
    assert any("--save-masks" in note for note in metrics["notes"])  # the reader is told why


def test_evaluate_run_says_when_the_run_did_not_complete(tmp_path):
    sequence, results, _ = make_run(tmp_path)
    assert evaluate_run(results, sequence)["notes"] == [] and evaluate_run(results, sequence)["run_status"] is None
    (results / "summary.json").write_text(json.dumps({"status": "interrupted"}))
    metrics = evaluate_run(results, sequence)
    assert metrics["run_status"] == "interrupted"
    assert any("interrupted" in note for note in metrics["notes"])


def test_evaluate_run_reports_missing_inputs(tmp_path):
    sequence, results, _ = make_run(tmp_path)
    (results / "camera.tum").unlink()
    with pytest.raises(InputError, match="camera.tum"):
        evaluate_run(results, sequence)


def test_evaluate_run_reports_missing_ground_truth_and_wrong_sequence(tmp_path):
    sequence, results, _ = make_run(tmp_path)
    text = (sequence / "groundtruth.txt").read_text()
    (sequence / "groundtruth.txt").unlink()
    with pytest.raises(InputError, match="groundtruth.txt"):
        evaluate_run(results, sequence)
    # Ground truth of another time range: nothing associates.
    shifted = []
    for line in text.splitlines():
        if line.startswith("#"):
            shifted.append(line)
        else:
            fields = line.split()
            shifted.append(" ".join([repr(float(fields[0]) + 500.0), *fields[1:]]))
    (sequence / "groundtruth.txt").write_text("\n".join(shifted) + "\n")
    with pytest.raises(InputError, match="ground-truth pose"):
        evaluate_run(results, sequence)
    with pytest.raises(InputError, match="does not exist"):
        evaluate_run(tmp_path / "nowhere", sequence)


def test_further_maps_of_one_object_are_pooled(tmp_path):
    """A second map that follows the true object in other frames (one object seen as two
    maps) counts for that object; a map that follows nothing stays unmatched."""
    sequence, results, offset = make_run(tmp_path)
    rng = np.random.default_rng(3)
    cameras = read_tum_trajectory(sequence / "groundtruth.txt")[1]
    timestamps, objects = read_tum_trajectory(sequence / "objects" / "object_1.txt")
    world = invert_transform(cameras[0])
    other_offset = random_transform(rng, 0.2)  # the second map has its own object frame
    write_tum_trajectory(results / "objects" / "object_3" / "trajectory.tum", timestamps[10:15],
                         world @ objects[10:15] @ other_offset)
    objects_section = evaluate_run(results, sequence)["objects"]
    (match,) = objects_section["matches"]
    assert match["estimated_id"] == 1 and match["further_maps"] == [3]
    assert match["tracked_share"] == pytest.approx(10 / 15)
    assert match["tracked_share_all_maps"] == pytest.approx(15 / 15)
    assert objects_section["unmatched_estimated"] == [2]
    assert [entry["estimated_id"] for entry in objects_section["further_maps"]] == [3]


def test_evaluate_tables_fit_80_columns(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import jsr.cli

    sequence, results, _ = make_run(tmp_path)
    monkeypatch.setattr(jsr.cli.console, "width", 80)
    result = CliRunner().invoke(jsr.cli.app, ["evaluate", str(results), str(sequence)])
    assert result.exit_code == 0, result.output
    assert "Objects" in result.output and "…" not in result.output
    assert max(len(line) for line in result.output.splitlines()) <= 80
