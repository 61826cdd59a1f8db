"""Moving objects: detection, object maps, masks, lost and found, manual start (Section 2 of
Caccamo et al. 2017) on seeded synthetic sequences with exact ground truth."""

import shutil
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsr.config import load_config
from jsr.evaluate.objects import object_pose_error
from jsr.geometry import make_transform, rotation_angle, transform_points
from jsr.io.dataset import open_sequence
from jsr.pipeline.classify import complete_segments
from jsr.pipeline.free_space import DepthView, FreeSpaceViews, depth_at_map_points, free_space_violations
from jsr.pipeline.map_merging import merge_maps
from jsr.pipeline.map_updates import map_would_grow
from jsr.pipeline.moving_regions import CANDIDATE_DETAIL_FRAMES
from jsr.pipeline.ownership import detail_boxes
from jsr.pipeline.reconstruct import Reconstructor
from jsr.pipeline.region_growth import grow, grow_region
from jsr.pipeline.region_motion import TURN_MEMORY_DEGREES_FACTOR, turn_seen_before
from jsr.pipeline.segments import depth_adjacent_segments
from jsr.pipeline.shape_reidentification import landmarks_agree_elsewhere
from jsr.pipeline.state import DetectionMemory, FrameContext
from jsr.pipeline.static_hygiene import retire_vacated_landmarks, without_suspects
from jsr.synth.options import SynthOptions
from jsr.synth.write import generate_sequence

WIDTH, HEIGHT = 320, 240
# Tests of one detection rule check the frame it detects an object in: they run with objects at
# once (the paper's way), not confirmed over the next frames (tests/test_confirmation.py).
AT_ONCE = "detection.confirm_frames=0"


def full_size_options(objects: int, seed: int, motion: str = "jump", simultaneous: bool = False) -> SynthOptions:
    """The benchmark's synthetic sequences (bench/objects.py): 60 frames at 640x480."""
    return SynthOptions(frames=60, objects=objects, motion=motion, simultaneous=simultaneous, width=640, height=480,
                        seed=seed)


@pytest.fixture(scope="module")
def jump_sequence(tmp_path_factory):
    root = tmp_path_factory.mktemp("objects") / "jump"
    generate_sequence(root, SynthOptions(frames=24, objects=1, motion="jump", width=WIDTH, height=HEIGHT, seed=0))
    return root


def motion_frames(root, true_id: int) -> np.ndarray:
    """The frames in which true object ``true_id`` stands somewhere else than in the one before."""
    rows = np.loadtxt(root / "objects" / f"object_{true_id}.txt")
    return np.flatnonzero(np.linalg.norm(np.diff(rows[:, 1:8], axis=0), axis=1) > 1e-6) + 1


def first_motion_frame(root, true_id: int) -> int:
    return int(motion_frames(root, true_id)[0])


def true_object_poses(root, true_id: int = 1):
    """``(F, 4, 4)`` true T_w_o of object ``true_id`` per frame, and the first frame it moved in."""
    rows = np.loadtxt(root / "objects" / f"object_{true_id}.txt")

    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return poses, first_motion_frame(root, true_id)


def labels_of(root, frame):
    return cv2.imread(str(root / "labels" / f"{frame.name}.png"), cv2.IMREAD_UNCHANGED)


def object_recalls(result, root, true_id: int, reports) -> list[float]:
    """For each of ``reports``, the share of true object ``true_id``'s pixels given to some object."""
    frames = list(result.sequence)
    return [float((report.mask[labels_of(root, frames[report.frame_index]) == true_id] > 0).mean())
            for report in reports]


def run(root, overrides=(), init_object_mask=None, sequence=None):
    sequence = sequence or open_sequence(root)
    reconstructor = Reconstructor(load_config(None, list(overrides)), sequence.intrinsics, init_object_mask)
    reports = [reconstructor.process(frame) for frame in sequence]
    reconstructor.finish()
    reconstructor.close()
    return SimpleNamespace(sequence=sequence, reconstructor=reconstructor, reports=reports)


@pytest.fixture(scope="module")
def jump_run(jump_sequence):
    return run(jump_sequence)


def test_moving_object_is_detected_within_three_frames(jump_sequence, jump_run):
    _, first_motion = true_object_poses(jump_sequence)
    created = [r.frame_index for r in jump_run.reports if r.objects_created]
    assert created, "no object map was created"
    # the first move (9 cm, 43 degrees) keeps the box largely within its old volume
    assert first_motion <= created[0] <= first_motion + 3
    assert not any(r.objects_created for r in jump_run.reports[:first_motion])  # nothing before it moved
    assert all(r.tracked for r in jump_run.reports)  # the camera is not dragged off by the object


def test_object_pose_follows_the_true_object(jump_sequence, jump_run):
    object_map = jump_run.reconstructor.object_maps[0]
    assert len(object_map.trajectory) >= 5
    error = tracked_pose_error(jump_run, jump_sequence, object_map)
    assert error.translation_rmse_cm < 2.0  # after removing the constant frame offset
    assert error.rotation_rmse_deg < 2.0


def _adjusted(object_map, adjustments):
    """Context: keyframe ``k``'s ``T_map_cam`` left-multiplied by ``adjustments[k]`` (what
    bundle adjustment would have done to it), restored afterwards."""
    import contextlib

    @contextlib.contextmanager
    def context():
        originals = [keyframe.T_map_cam.copy() for keyframe in object_map.keyframes]
        for keyframe, adjustment in zip(object_map.keyframes, adjustments):
            keyframe.T_map_cam = adjustment @ keyframe.T_map_cam
        try:
            yield
        finally:
            for keyframe, original in zip(object_map.keyframes, originals):
                keyframe.T_map_cam = original

    return context()


def test_object_trajectory_moves_with_its_bundle_adjusted_keyframes(jump_run):
    """The written object poses follow what bundle adjustment did to the object's keyframes:
    all of them when all moved alike; one rest of the object as a whole when one of its
    keyframes moved; frames nearer other keyframes not at all."""

    reconstructor = jump_run.reconstructor
    object_map = reconstructor.object_maps[0]
    assert len(object_map.keyframes) >= 3
    _, before = reconstructor.object_trajectory(object_map)
    adjustment = np.eye(4)  # in the object frame
    adjustment[:3, :3] = Rotation.from_rotvec([0.0, 0.03, 0.01]).as_matrix()
    adjustment[:3, 3] = [0.01, 0.0, -0.02]
    with _adjusted(object_map, [adjustment] * len(object_map.keyframes)):
        _, after = reconstructor.object_trajectory(object_map)
    # T_w_o = T_w_c inv(T_o_c): the adjustment of T_o_c is undone on the object's side
    np.testing.assert_allclose(after, before @ np.linalg.inv(adjustment), atol=1e-9)

    last = len(object_map.keyframes) - 1
    with _adjusted(object_map, [np.eye(4)] * last + [adjustment]):
        _, after = reconstructor.object_trajectory(object_map)
    changes = np.linalg.inv(before) @ after  # per frame, on the object's side
    moved = ~np.all(np.isclose(changes, np.eye(4), atol=1e-12), axis=(1, 2))
    frames = np.array([frame_index for frame_index, _, _ in object_map.trajectory])
    assert moved[frames == object_map.keyframes[last].frame_index].all()
    assert moved.any() and not moved.all()
    # the frames moved are one rest of the object (one world pose as tracked), moved as one
    tracked = np.array([T_w_o for _, _, T_w_o in object_map.trajectory])
    np.testing.assert_allclose(tracked[moved], np.broadcast_to(tracked[moved][0], tracked[moved].shape), atol=1e-9)
    np.testing.assert_allclose(changes[moved], np.broadcast_to(changes[moved][0], changes[moved].shape), atol=1e-9)



def test_object_trajectory_averages_the_corrections_of_one_rest(jump_run):
    """Within one rest of the object (one world pose as tracked) holding several keyframes,
    the written poses move by the mean of what bundle adjustment did to those keyframes."""

    reconstructor = jump_run.reconstructor
    object_map = reconstructor.object_maps[0]
    tracked = {frame_index: T_w_o for frame_index, _, T_w_o in object_map.trajectory}
    rests: dict[bytes, list[int]] = {}  # tracked world pose -> its keyframes (positions)
    for position, keyframe in enumerate(object_map.keyframes):
        if keyframe.frame_index in tracked:
            rests.setdefault(np.round(tracked[keyframe.frame_index], 9).tobytes(), []).append(position)
    rest = max(rests.values(), key=len)
    assert len(rest) >= 2, "the fixture needs a rest with two keyframes"
    adjustment = np.eye(4)
    adjustment[:3, :3] = Rotation.from_rotvec([0.02, -0.01, 0.04]).as_matrix()
    adjustment[:3, 3] = [0.006, -0.004, 0.01]
    # from the keyframes as tracked: no correction but this one adjustment of one keyframe
    as_tracked = [keyframe.T_map_cam_tracked @ np.linalg.inv(keyframe.T_map_cam) for keyframe in object_map.keyframes]
    with _adjusted(object_map, as_tracked):
        _, before = reconstructor.object_trajectory(object_map)
    with _adjusted(object_map, [adjustment @ T if position == rest[0] else T
                                for position, T in enumerate(as_tracked)]):
        _, after = reconstructor.object_trajectory(object_map)
    mean = np.eye(4)
    mean[:3, :3] = Rotation.from_matrix([adjustment[:3, :3]] + [np.eye(3)] * (len(rest) - 1)).mean().as_matrix()
    mean[:3, 3] = adjustment[:3, 3] / len(rest)
    rest_pose = tracked[object_map.keyframes[rest[0]].frame_index]
    in_rest = np.array([np.allclose(T_w_o, rest_pose, atol=1e-9) for _, _, T_w_o in object_map.trajectory])
    np.testing.assert_allclose(after[in_rest], before[in_rest] @ np.linalg.inv(mean), atol=1e-9)
    np.testing.assert_allclose(after[~in_rest], before[~in_rest], atol=1e-12)


def test_object_trajectory_counts_only_adjustments_made_after_a_frame_was_tracked(jump_run):
    """A frame whose rest holds no keyframe is corrected by what bundle adjustment did, after
    the frame was tracked, to the map's latest keyframe of that time: an adjustment from
    before (which its registration already saw) does not count twice."""

    reconstructor = jump_run.reconstructor
    object_map = reconstructor.object_maps[0]
    keyframe_at = {keyframe.frame_index: keyframe for keyframe in object_map.keyframes}
    poses = [T_w_o for _, _, T_w_o in object_map.trajectory]
    alone = [i for i in range(1, len(poses) - 1)  # a rest of one frame: the object moved before and after
             if not np.allclose(poses[i], poses[i - 1], atol=1e-9)
             and not np.allclose(poses[i], poses[i + 1], atol=1e-9)]
    # such a frame that is a keyframe, anchored to an earlier keyframe: without its own
    # keyframe it is a rest with none
    position = next(i for i in alone if object_map.trajectory[i][0] in keyframe_at
                    and object_map.trajectory_anchors[object_map.trajectory[i][0]][0].frame_index
                    < object_map.trajectory[i][0])
    frame = object_map.trajectory[position][0]
    anchor_keyframe, T_map_cam_then = object_map.trajectory_anchors[frame]
    adjustment = np.eye(4)
    adjustment[:3, :3] = Rotation.from_rotvec([-0.02, 0.03, 0.01]).as_matrix()
    adjustment[:3, 3] = [0.0, 0.01, 0.005]
    all_keyframes = object_map.keyframes
    object_map.keyframes = [keyframe for keyframe in all_keyframes if keyframe.frame_index != frame]
    try:
        _, before = reconstructor.object_trajectory(object_map)
        original = anchor_keyframe.T_map_cam.copy()
        anchor_keyframe.T_map_cam = adjustment @ original  # adjusted after the frame was tracked
        _, after = reconstructor.object_trajectory(object_map)
        np.testing.assert_allclose(after[position], before[position] @ np.linalg.inv(adjustment), atol=1e-9)
        # all of it done before the frame was tracked (its registration saw the keyframe where
        # it is now): T_o_c stays as tracked, whatever the keyframe's whole correction
        assert not np.allclose(anchor_keyframe.T_map_cam, anchor_keyframe.T_map_cam_tracked, atol=1e-6)
        object_map.trajectory_anchors[frame] = (anchor_keyframe, anchor_keyframe.T_map_cam.copy())
        _, seen = reconstructor.object_trajectory(object_map)
        report = next(report for report in reconstructor.reports if report.frame_index == frame)
        T_w_o_tracked = object_map.trajectory[position][2]
        np.testing.assert_allclose(
            seen[position], reconstructor.current_pose(report) @ np.linalg.inv(report.T_w_c) @ T_w_o_tracked,
            atol=1e-9)
    finally:
        anchor_keyframe.T_map_cam = original
        object_map.trajectory_anchors[frame] = (anchor_keyframe, T_map_cam_then)
        object_map.keyframes = all_keyframes

def test_masks_agree_with_labels(jump_sequence, jump_run):
    sequence = jump_run.sequence
    true_positive = predicted = actual = 0
    object_map = jump_run.reconstructor.object_maps[0]
    tracked_frames = {index for index, _, _ in object_map.trajectory}
    for report in jump_run.reports:
        if report.frame_index not in tracked_frames:
            continue
        labels = labels_of(jump_sequence, sequence[report.frame_index]) > 0
        mask = jump_run.reconstructor.keyframe_masks.get(report.frame_index)
        if mask is None:
            continue
        mask = mask > 0
        true_positive += int((mask & labels).sum())
        predicted += int(mask.sum())
        actual += int(labels.sum())
    assert predicted > 0
    assert true_positive / predicted > 0.85
    assert true_positive / actual > 0.6  # every face the box turns towards the camera, at 320x240


def first_observation_labels(reconstructor, map_, sequence, root):
    """Label (0 static, k object k) under the first observation of every active landmark."""
    labels = {}
    for keyframe in sorted(map_.keyframes, key=lambda k: k.frame_index):
        image = None
        for landmark, pixel in zip(keyframe.point_landmarks, keyframe.pixels):
            if landmark in labels or not map_.points.active[landmark]:
                continue
            if image is None:
                image = labels_of(root, sequence[keyframe.frame_index])
            u = int(np.clip(round(pixel[0]), 0, image.shape[1] - 1))
            v = int(np.clip(round(pixel[1]), 0, image.shape[0] - 1))
            labels[landmark] = int(image[v, u])
    return np.array(list(labels.values()))


def test_maps_are_not_contaminated(jump_sequence, jump_run):
    reconstructor = jump_run.reconstructor
    static = first_observation_labels(reconstructor, reconstructor.static_map, jump_run.sequence, jump_sequence)
    assert len(static) > 500
    # The box rests in view for the first frames: the static map took its features, and must
    # have retired them once it moved.
    assert np.mean(static > 0) < 0.02
    for object_map in reconstructor.object_maps:
        on_object = first_observation_labels(reconstructor, object_map, jump_run.sequence, jump_sequence)
        assert np.mean(on_object == 0) < 0.1


def test_objects_off_keeps_the_static_map_only(jump_sequence):
    result = run(jump_sequence, ["objects.enabled=false"], sequence=open_sequence(jump_sequence, max_frames=12))
    assert result.reconstructor.object_maps == []
    assert all(not r.objects_created for r in result.reports)


def test_object_out_of_view_is_relocalised(jump_sequence, tmp_path):
    """The box disappears (its pixels blanked) for three frames while it rests, then comes back:
    its map stops, then is relocalised against the whole map, and no second map is started."""
    root = tmp_path / "hidden"
    shutil.copytree(jump_sequence, root)
    sequence = open_sequence(root)
    _, first_motion = true_object_poses(root)
    hidden = range(first_motion + 3, first_motion + 6)
    for index in hidden:
        entry = sequence.entries[index]
        labels = labels_of(root, sequence[index]) > 0
        color = cv2.imread(str(entry.color_path))
        depth = cv2.imread(str(entry.depth_path), cv2.IMREAD_UNCHANGED)
        color[labels] = 0
        depth[labels] = 0
        cv2.imwrite(str(entry.color_path), color)
        cv2.imwrite(str(entry.depth_path), depth)
    # up to the next jump (8 frames after the first one), which may start a second map
    result = run(root, [AT_ONCE], sequence=open_sequence(root, max_frames=first_motion + 8))
    reports = result.reports
    assert len(reports[first_motion + 2].objects_tracked) == 1
    box = reports[first_motion + 2].objects_tracked[0]
    assert all(box not in reports[i].objects_tracked for i in hidden)
    after = reports[hidden[-1] + 1 :]
    assert any(box in r.objects_tracked for r in after)  # found again, by the same map
    assert not any(r.objects_created for r in reports[first_motion + 1 :])


def test_init_object_starts_a_map_on_the_first_frame(jump_sequence):
    sequence = open_sequence(jump_sequence, max_frames=12)
    labels = labels_of(jump_sequence, sequence[0]) > 0
    rows, cols = np.nonzero(labels)
    box = np.zeros_like(labels)
    box[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1] = True
    result = run(jump_sequence, [AT_ONCE], init_object_mask=box, sequence=sequence)
    reports = result.reports
    assert reports[0].objects_created == [1]
    object_map = result.reconstructor.object_maps[0]
    assert object_map.created_at_frame == 0
    # it is tracked while it rests and after it moved, by the same map
    _, first_motion = true_object_poses(jump_sequence)
    assert all(r.objects_tracked == [1] for r in reports[:first_motion])  # tracked while it rests
    # After the jump the box may show a side its map has not seen: a second map can start then
    # (merged into the first once both explain the same features), but the box stays tracked.
    assert len(result.reconstructor.object_maps) <= 2
    assert sum(bool(r.objects_tracked) for r in reports[first_motion:]) >= 3


def test_same_seed_same_objects(jump_sequence):
    sequence = open_sequence(jump_sequence, max_frames=18)
    first, second = run(jump_sequence, sequence=sequence), run(jump_sequence, sequence=sequence)
    a = first.reconstructor.object_maps
    b = second.reconstructor.object_maps
    assert len(a) == len(b) >= 1
    for map_a, map_b in zip(a, b):
        assert np.array_equal(map_a.points.positions, map_b.points.positions)
        assert all(np.array_equal(x[2], y[2]) for x, y in zip(map_a.trajectory, map_b.trajectory))


def test_reconstruct_writes_object_results(jump_sequence, tmp_path):
    import json

    from typer.testing import CliRunner

    from jsr.cli import app

    out = tmp_path / "out"
    frames = 18
    result = CliRunner().invoke(app, ["reconstruct", str(jump_sequence), "--out", str(out), "--max-frames",
                                      str(frames), "--save-masks", "-q"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["objects"]) >= 1
    first = summary["objects"][0]
    folder = out / "objects" / f"object_{first['id']}"
    for name in ("trajectory.tum", "keyframes.tum", "landmarks.ply"):
        assert (folder / name).is_file(), name
    trajectory = np.loadtxt(folder / "trajectory.tum")
    assert len(trajectory.reshape(-1, 8)) == first["frames_tracked"]
    assert len(list((out / "masks").glob("*.png"))) == frames
    rows = (out / "landmarks.csv").read_text().splitlines()
    assert any(f",object_{first['id']}," in row for row in rows)
    evaluated = CliRunner().invoke(app, ["evaluate", str(out), str(jump_sequence), "-q"])
    assert evaluated.exit_code == 0, evaluated.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["masks"]["precision"] > 0.8


# ----------------------------------------------------------------------------------------
# Building blocks


class _Noise:
    sigma_z_coefficient = 1.425e-3
    inlier_sigmas = 3.0
    min_inlier_threshold = 0.01


class _Segments:
    discontinuity_sigmas = 4.0
    min_discontinuity = 0.02


def test_free_space_violation_flags_what_moved_in():
    intrinsics = SimpleNamespace(fx=300.0, fy=300.0, cx=80.0, cy=60.0)
    wall = np.full((120, 160), 2.0, dtype=np.float32)
    view = DepthView(wall[::4, ::4].copy(), np.eye(4), 4)
    frame_depth = wall.copy()
    frame_depth[40:80, 40:80] = 1.0  # something now stands 1 m in front of the wall
    labels = np.zeros((120, 160), dtype=np.int32)
    labels[40:80, 40:80] = 1
    violations, consistent = free_space_violations(frame_depth, labels, np.eye(4), intrinsics, view, 2, _Noise(), 0.05)
    assert violations[1] == 100 and consistent[1] == 0  # every sampled pixel of the new thing
    assert violations[0] == 0 and consistent[0] > 900
    # the wall seen farther away than before (something left) is no violation
    violations, _ = free_space_violations(np.full_like(wall, 2.5), labels, np.eye(4), intrinsics, view, 2, _Noise(),
                                          0.05)
    assert violations.sum() == 0


def test_free_space_measured_only_needs_depth_all_around():
    """Beside a hole in the earlier view (a translucent object that returned no depth to it), a
    sample is seen through by the lenient test, used to detect, but not by the strict one,
    used to confirm."""
    intrinsics = SimpleNamespace(fx=300.0, fy=300.0, cx=80.0, cy=60.0)
    wall = np.full((120, 160), 2.0, dtype=np.float32)
    wall[40:80, 56:80] = 0.0  # the view measured no depth over the left part of the thing
    view = DepthView(wall[::4, ::4].copy(), np.eye(4), 4)
    frame_depth = np.full((120, 160), 2.0, dtype=np.float32)
    frame_depth[40:80, 40:80] = 1.0
    labels = np.zeros((120, 160), dtype=np.int32)
    labels[40:80, 40:80] = 1
    lenient, _ = free_space_violations(frame_depth, labels, np.eye(4), intrinsics, view, 2, _Noise(), 0.05)
    strict, _ = free_space_violations(frame_depth, labels, np.eye(4), intrinsics, view, 2, _Noise(), 0.05,
                                      measured_only=True)
    # 10 sampled columns: 4 over the wall (40-52), 6 over the hole; the column next to the
    # hole has depth, but a neighbour without
    assert lenient[1] == 4 * 10 and strict[1] == 3 * 10
    # samples at the image border have neighbours beyond it: not seen through when strict
    border_labels = np.zeros_like(labels)
    border_labels[:, :8] = 1
    near_border = np.full_like(frame_depth, 2.0)
    near_border[:, :8] = 1.0
    view = DepthView(np.full((30, 40), 2.0, dtype=np.float32), np.eye(4), 4)
    lenient, _ = free_space_violations(near_border, border_labels, np.eye(4), intrinsics, view, 2, _Noise(), 0.05)
    strict, _ = free_space_violations(near_border, border_labels, np.eye(4), intrinsics, view, 2, _Noise(), 0.05,
                                      measured_only=True)
    assert lenient[1] == 2 * 30 and strict[1] == 28  # the first column and the top and bottom rows drop out


def test_depth_adjacency_joins_edges_not_occlusions():
    depth = np.full((40, 60), 1.0, dtype=np.float32)
    labels = np.zeros((40, 60), dtype=np.int32)
    labels[:, 20:40] = 1  # continuous with 0: two faces meeting at an edge
    labels[:, 40:] = 2
    depth[:, 40:] = 2.0  # 2 lies 1 m behind 1: an occlusion boundary
    pairs = depth_adjacent_segments(labels, depth, _Noise(), _Segments())
    assert pairs.tolist() == [[0, 1]]


def test_grow_region_stays_within_candidates():
    adjacency = np.array([[0, 1], [1, 2], [2, 3], [0, 4]])
    candidates = np.array([False, True, True, False, True])
    assert grow_region([0], candidates, adjacency) == [0, 1, 2, 4]
    assert grow_region([3], candidates, adjacency) == [1, 2, 3]  # 4 only reachable through 0


def test_complete_segments_needs_a_majority_of_inliers():
    point_segment = np.array([0, 0, 0, 1, 1, 1, 1, 2])
    point_owner = np.array([5, 5, 5, 0, 0, 5, 5, 5])
    evidence = np.array([True, True, True, True, True, True, False, True])
    owners = complete_segments(point_segment, 3, point_owner, evidence, [5], min_votes=2)
    assert owners.tolist() == [5, 0, 0]  # segment 1: 1 object vote against 2 static; segment 2: too few


def _box_landmarks(rng, count=60):
    """``(count, 3)`` points on the faces of a 20 x 16 x 12 cm box centred at the origin."""
    half = np.array([0.10, 0.08, 0.06])
    points = rng.uniform(-1, 1, (count, 3)) * half
    face = rng.integers(0, 3, count)
    points[np.arange(count), face] = np.sign(rng.uniform(-1, 1, count)) * half[face]
    return points


def _object_map(object_id, positions, descriptors):
    from jsr.pipeline.measurements import PointMeasurements
    from jsr.pipeline.maps import ObjectMap

    count = len(positions)
    points = PointMeasurements(pixels=np.zeros((count, 2)), points=positions, has_depth=np.ones(count, bool),
                               bearings=positions / np.linalg.norm(positions, axis=1, keepdims=True),
                               sigma_z=np.full(count, 0.002), descriptors=descriptors.astype(np.float32))
    object_map = ObjectMap(object_id, created_at_frame=object_id * 10)
    object_map.add_keyframe(object_id * 10, float(object_id), np.eye(4), points, np.arange(count),
                            np.full(count, -1), np.zeros((count, 3), np.uint8))
    object_map.trajectory.append((object_id * 10, float(object_id), np.eye(4)))
    return object_map


def test_two_maps_of_one_object_merge_into_the_first_frame():
    """Merging map 2 into map 1 at ``T_1_2`` (map 1 <- map 2) brings its landmarks, its
    keyframe (both poses) and its frames' trajectory anchors into map 1's frame."""

    from jsr.pipeline.map_merging import merge_object_maps

    rng = np.random.default_rng(3)
    box = _box_landmarks(rng, 80) + [0.0, 0.0, 1.0]  # the box 1 m in front of map 1's camera
    descriptors = rng.random((80, 128))
    T_1_2 = np.eye(4)
    T_1_2[:3, :3] = Rotation.from_rotvec([0.1, 1.2, -0.2]).as_matrix()
    T_1_2[:3, 3] = [0.3, -0.1, 0.2]
    # map 2 saw landmarks 30-79 (its first view showed other faces first), in its own frame
    in_map_2 = (box[30:] - T_1_2[:3, 3]) @ T_1_2[:3, :3]
    first = _object_map(1, box[:60], descriptors[:60])
    second = _object_map(2, in_map_2, descriptors[30:])
    second.keyframes[0].T_map_cam_tracked = np.eye(4)  # as tracked; bundle adjustment moved it since
    second.keyframes[0].T_map_cam = T_1_2.copy()
    second.trajectory.append((21, 2.1, np.eye(4)))  # tracked after map 2's keyframe, then at T_1_2
    second.trajectory_anchors[21] = (second.keyframes[0], T_1_2.copy())
    first.trajectory_anchors[10] = (first.keyframes[0], np.eye(4))
    merge_object_maps(first, second, T_1_2)
    assert len(first.keyframes) == 2 and len(first.points) == 110
    moved_in = first.keyframes[1]  # map 2's keyframe (frame 20), after map 1's (frame 10)
    assert moved_in.frame_index == 20
    # both poses of the keyframe it brought are in map 1's frame now
    np.testing.assert_allclose(moved_in.T_map_cam_tracked, T_1_2, atol=1e-9)
    np.testing.assert_allclose(moved_in.T_map_cam, T_1_2 @ T_1_2, atol=1e-9)
    # its frames' anchors follow it: the keyframe in map 1, its pose then in map 1's frame
    assert [index for index, _, _ in first.trajectory] == [10, 20, 21]
    assert sorted(first.trajectory_anchors) == [10, 21]
    keyframe, T_map_cam_then = first.trajectory_anchors[21]
    assert keyframe is moved_in
    np.testing.assert_allclose(T_map_cam_then, T_1_2 @ T_1_2, atol=1e-9)
    assert first.trajectory_anchors[10][0] is first.keyframes[0]
    np.testing.assert_allclose(first.points.positions[60:], box[30:], atol=1e-9)  # in map 1's frame


def test_segments_inside_extent_take_faces_not_the_table():
    from jsr.pipeline.object_extent import extent_hull, segments_inside_extent

    rng = np.random.default_rng(4)
    intrinsics = SimpleNamespace(fx=300.0, fy=300.0, cx=80.0, cy=60.0)
    # a box front face at z = 1.0 (x, y in +-0.1) whose landmarks span 12 cm in depth
    landmarks = _box_landmarks(rng, 80) * [1.0, 1.25, 1.0] + [0.0, 0.0, 1.06]
    depth = np.full((120, 160), 1.0, dtype=np.float32)
    labels = np.full((120, 160), 1, dtype=np.int32)  # segment 1: a wall at 1 m, far wider than the box
    u, v = np.meshgrid(np.arange(160), np.arange(120))
    face = (np.abs(u - 80) < 28) & (np.abs(v - 60) < 28)  # |x|, |y| < 9.3 cm at 1 m
    labels[face] = 0
    hull = extent_hull(np.concatenate([landmarks, [[3.0, 3.0, 3.0]]]))  # a stray landmark far away is left out
    inside = segments_inside_extent(labels, depth, intrinsics, np.eye(4), hull, _Noise(), 2,
                                    margin=0.03, min_share=0.5)
    assert inside.tolist() == [True, False]
    # seen from an object frame in which the box is elsewhere, nothing is inside
    moved = np.eye(4)
    moved[:3, 3] = [0.5, 0.0, 0.0]
    assert not segments_inside_extent(labels, depth, intrinsics, moved, hull, _Noise(), 2, 0.03, 0.5).any()
    assert extent_hull(landmarks[:5]) is None  # too few landmarks: no extent


def test_pixels_inside_hull_agree_with_every_facet():
    """The few-facet prefilter only skips work: the verdict is that of testing every facet."""
    from jsr.geometry import backproject_pixels, inlier_threshold
    from jsr.pipeline.object_extent import extent_hull, pixels_inside_hull

    rng = np.random.default_rng(5)
    intrinsics = SimpleNamespace(fx=300.0, fy=300.0, cx=80.0, cy=60.0)
    rows, cols = (grid.ravel() for grid in np.mgrid[0:120:2, 0:160:2])
    for trial in range(6):
        landmarks = rng.normal(size=(150, 3)) * rng.uniform(0.02, 0.2, 3) + [0.0, 0.0, 1.2]
        hull = extent_hull(landmarks)
        depths = rng.uniform(0.6, 2.0, len(rows))
        depths[::2] = 1.2 + rng.normal(0.0, 0.1, len(depths[::2]))  # many pixels near the object
        inside = pixels_inside_hull(rows, cols, depths, intrinsics, np.eye(4), hull, _Noise(), 0.03)
        points = backproject_pixels(cols, rows, depths, 300.0, 300.0, 80.0, 60.0)
        distance = np.max(points @ hull.equations[:, :3].T + hull.equations[:, 3], axis=1)
        expected = distance <= inlier_threshold(depths, _Noise.sigma_z_coefficient, _Noise.inlier_sigmas, 0.03)
        assert expected.any() and not expected.all()
        np.testing.assert_array_equal(inside, expected)


def test_unlabelled_pixels_take_the_owner_of_most_neighbours():
    from jsr.pipeline.ownership import fill_unlabelled

    ownership = np.zeros((40, 40), dtype=np.uint8)
    ownership[10:30, 10:30] = 2
    unlabelled = np.zeros((40, 40), dtype=bool)
    unlabelled[20, 20] = unlabelled[5, 5] = True  # a dropout inside the object, one in the background
    unlabelled[10:30, 29:31] = True  # a strip along the object's right edge: half object, half not
    ownership[unlabelled] = 0
    filled = fill_unlabelled(ownership, unlabelled, radius=2)
    assert filled[20, 20] == 2 and filled[5, 5] == 0
    assert filled[20, 29] == 2 and filled[20, 30] == 0  # nearer the object: object; beyond: not
    assert np.array_equal(filled[~unlabelled], ownership[~unlabelled])


def test_merging_keeps_ids_masks_and_tracking_state_consistent():
    from jsr.io.camera import CameraIntrinsics

    rng = np.random.default_rng(5)
    reconstructor = Reconstructor(load_config(None, []), CameraIntrinsics(300.0, 300.0, 80.0, 60.0, 160, 120))
    try:
        box = _box_landmarks(rng, 40) + [0.0, 0.0, 1.0]
        first, second = _object_map(1, box, rng.random((40, 128))), _object_map(2, box, rng.random((40, 128)))
        state = reconstructor.state
        state.object_maps = [first, second]
        state.next_object_id = 3
        mask = np.zeros((120, 160), np.uint8)
        mask[10:20, 10:20] = 2
        state.keyframe_masks[20] = mask  # map 2's keyframe is frame 20
        second.last_T_o_c = np.eye(4)
        second.last_T_w_o = np.eye(4)
        T_1_2 = np.eye(4)
        T_1_2[:3, 3] = [0.1, 0.0, 0.0]
        merge_maps(state, first, second, T_1_2, 25, "test")
        assert reconstructor.object_maps == [first]
        assert reconstructor.merged_into == {2: 1}
        assert set(np.unique(reconstructor.keyframe_masks[20])) == {0, 1}  # map 2's pixels are map 1's now
        np.testing.assert_allclose(first.last_T_o_c, T_1_2)  # map 2 saw the object last: map 1 goes on from there
        assert [index for index, _, _ in first.trajectory] == [10, 20]
        assert state.next_object_id == 3  # a new map gets id 3, not the freed 2
    finally:
        reconstructor.close()


def test_object_surfaces_follow_the_object(jump_sequence):
    """With objects.shape_reidentify on, every object keyframe keeps a surface sample under a
    live map id, and the assembled surface model lies on the true object."""
    result = run(jump_sequence, ["objects.shape_reidentify=true"])
    reconstructor = result.reconstructor
    live = {m.object_id for m in reconstructor.object_maps}
    assert reconstructor.object_maps
    for samples in reconstructor.state.surfaces.samples.values():
        assert set(samples) <= live
    poses, _ = true_object_poses(jump_sequence)
    object_map = reconstructor.object_maps[0]
    model = reconstructor.state.surfaces.model(object_map)
    assert model is not None and len(model.points) > 100
    # The model, put in the world with the map's pose at its first frame, lies on the object:
    # in the object's true frame its points are within the box's half diagonal (plus noise).
    import yaml

    from jsr.geometry import pose_from_tum, transform_points

    frame_index, _, T_w_o_map = object_map.trajectory[0]
    T_gtworld_cam0 = pose_from_tum(np.loadtxt(jump_sequence / "groundtruth.txt")[0, 1:8])
    size = yaml.safe_load((jump_sequence / "synth.yaml").read_text())["objects"][0]["size"]
    object_points = transform_points(np.linalg.inv(poses[frame_index]) @ T_gtworld_cam0 @ T_w_o_map, model.points)
    inside = np.linalg.norm(object_points, axis=1) < 0.5 * np.linalg.norm(size) + 0.02
    assert inside.mean() > 0.95


def test_vacated_landmarks_are_retired_only_once_something_moved(jump_sequence):
    """objects.retire_after_vacated: static landmarks seen through (the measured surface far
    behind them) in that many frames in a row are retired, but only once an object was
    detected; before that, a surface seen through is a depth artefact."""
    result = run(jump_sequence, ["objects.retire_after_vacated=2"], sequence=open_sequence(jump_sequence, max_frames=4))
    reconstructor = result.reconstructor
    assert not reconstructor.object_maps
    T_w_c = result.reports[-1].T_w_c
    far = SimpleNamespace(depth=np.full((HEIGHT, WIDTH), 20.0, dtype=np.float32))  # everything seen through
    not_matched = SimpleNamespace(bridged=True)  # no registration inliers to spare
    active_before = reconstructor.static_map.points.active.copy()
    state = reconstructor.state
    for _ in range(3):
        retire_vacated_landmarks(state, far, T_w_c, not_matched)
    np.testing.assert_array_equal(reconstructor.static_map.points.active, active_before)
    state.next_object_id = 2  # as if object 1 had been detected
    retire_vacated_landmarks(state, far, T_w_c, not_matched)
    np.testing.assert_array_equal(reconstructor.static_map.points.active, active_before)  # once is not enough
    retire_vacated_landmarks(state, far, T_w_c, not_matched)
    retired = active_before & ~reconstructor.static_map.points.active
    assert retired.sum() > 50


def test_vacated_retirement_reaches_landmarks_of_old_keyframes(jump_sequence):
    """The vacated test looks at every active static landmark, not only those of the recent
    keyframes: an object's landmarks from before it moved are in keyframes that are no longer
    recent when its old place comes back into view."""
    overrides = ["objects.retire_after_vacated=2", "matching.recent_keyframes=1",
                 "objects.vacated_cluster_size=0"]  # old landmarks far apart count one by one
    result = run(jump_sequence, overrides, sequence=open_sequence(jump_sequence, max_frames=4))
    reconstructor = result.reconstructor
    static_map = reconstructor.static_map
    assert len(static_map.keyframes) >= 2
    recent = static_map.recent_point_landmarks(1)
    old_only = np.setdiff1d(np.flatnonzero(static_map.points.active), recent)
    assert len(old_only) > 20
    reconstructor.state.next_object_id = 2  # as if object 1 had been detected
    T_w_c = result.reports[-1].T_w_c
    far = SimpleNamespace(depth=np.full((HEIGHT, WIDTH), 20.0, dtype=np.float32))  # everything seen through
    in_view = _static_landmark_pixels(reconstructor, T_w_c)[0]
    old_in_view = np.intersect1d(old_only, in_view)
    assert len(old_in_view) > 20
    for _ in range(2):
        retire_vacated_landmarks(reconstructor.state, far, T_w_c, SimpleNamespace(bridged=True))
    assert not static_map.points.active[old_in_view].any()


def _static_landmark_pixels(reconstructor, T_w_c):
    """Ids, rounded pixels ``(N, 2)`` and depths ``(N,)`` of the active static landmarks (all
    of them: the vacated test looks at every one) in view from ``T_w_c``."""
    points = reconstructor.static_map.points
    ids = reconstructor.static_map.recent_point_landmarks(None)
    camera, (u, v), inside, _ = depth_at_map_points(points.positions[ids], T_w_c, np.zeros((HEIGHT, WIDTH)),
                                                     reconstructor.intrinsics)
    return ids[inside], np.stack([u[inside], v[inside]], axis=1), camera[inside, 2]


def test_map_points_are_read_in_a_depth_image_from_the_camera_pose():
    """free_space.depth_at_map_points: world points placed at chosen pixels and depths of a
    camera turned and moved in the world come back at those pixels, with the depth measured
    there; a point behind the camera, and one outside the image, are not inside."""
    intrinsics = SimpleNamespace(fx=300.0, fy=300.0, cx=WIDTH / 2, cy=HEIGHT / 2)
    T_w_c = make_transform(Rotation.from_euler("xyz", [10, -25, 5], degrees=True).as_matrix(), [0.3, -0.2, 1.1])
    pixels = np.array([[10, 20], [160, 120], [300, 230], [200, 50]])
    z = np.array([0.8, 2.0, 3.5, 1.2])
    camera = np.column_stack([(pixels[:, 0] - intrinsics.cx) / intrinsics.fx * z,
                              (pixels[:, 1] - intrinsics.cy) / intrinsics.fy * z, z])
    camera = np.vstack([camera, [0.0, 0.0, -1.0], [5.0, 0.0, 1.0]])  # behind; far off to the side
    world = transform_points(T_w_c, camera)
    depth = np.zeros((HEIGHT, WIDTH), np.float32)
    depth[pixels[:, 1], pixels[:, 0]] = z + 0.01  # measured 1 cm behind each
    seen, (u, v), inside, measured = depth_at_map_points(world, T_w_c, depth, intrinsics)
    np.testing.assert_allclose(seen, camera, atol=1e-9)
    assert inside.tolist() == [True, True, True, True, False, False]
    np.testing.assert_array_equal(np.stack([u[:4], v[:4]], axis=1), pixels)
    np.testing.assert_allclose(measured, np.r_[z + 0.01, 0.0, 0.0], atol=1e-6)


@pytest.mark.parametrize("window_px", [0, 5])
def test_vacated_retirement_spares_a_surface_beside_the_pixel(jump_sequence, window_px):
    """objects.vacated_window_px: a landmark whose surface is measured one pixel beside its
    projection (a depth edge, a colour/depth misregistration) is not taken for vacated."""
    overrides = ["objects.retire_after_vacated=2", f"objects.vacated_window_px={window_px}"]
    result = run(jump_sequence, overrides, sequence=open_sequence(jump_sequence, max_frames=4))
    reconstructor = result.reconstructor
    reconstructor.state.next_object_id = 2  # as if object 1 had been detected
    T_w_c = result.reports[-1].T_w_c
    ids, pixels, depths = _static_landmark_pixels(reconstructor, T_w_c)
    edge = np.full((HEIGHT, WIDTH), 20.0, dtype=np.float32)
    beside = np.clip(pixels[:, 0] + 1, 0, WIDTH - 1)
    edge[pixels[:, 1], beside] = depths
    edge[pixels[:, 1], pixels[:, 0]] = 20.0  # the pixel itself is seen through
    frame = SimpleNamespace(depth=edge)
    active_before = reconstructor.static_map.points.active.copy()
    for _ in range(2):
        retire_vacated_landmarks(reconstructor.state, frame, T_w_c, SimpleNamespace(bridged=True))
    retired = active_before & ~reconstructor.static_map.points.active
    if window_px:
        assert retired.sum() == 0
    else:
        assert retired.sum() > 0.5 * len(ids)


@pytest.mark.parametrize("cluster_size", [0, 5])
def test_vacated_retirement_needs_an_area_seen_through(jump_sequence, cluster_size):
    """objects.vacated_cluster_size: one landmark seen through on its own (a depth artefact)
    stays; the place an object left is many landmarks seen through together."""
    overrides = ["objects.retire_after_vacated=2", f"objects.vacated_cluster_size={cluster_size}",
                 "objects.vacated_window_px=0"]  # the cluster condition alone
    sequence = open_sequence(jump_sequence, max_frames=4)
    result = run(jump_sequence, overrides, sequence=sequence)
    reconstructor = result.reconstructor
    reconstructor.state.next_object_id = 2
    T_w_c = result.reports[-1].T_w_c
    ids, pixels, _ = _static_landmark_pixels(reconstructor, T_w_c)
    # the landmark farthest in the image from any other: a hole around it holds it alone
    gaps = np.linalg.norm(pixels[:, None, :] - pixels[None, :, :], axis=2) + np.eye(len(ids)) * 1e9
    alone = int(np.argmax(gaps.min(axis=1)))
    assert gaps[alone].min() > 4
    depth = list(sequence)[-1].depth.copy()
    u, v = pixels[alone]
    depth[max(v - 2, 0):v + 3, max(u - 2, 0):u + 3] = 20.0
    frame = SimpleNamespace(depth=depth)
    for _ in range(2):
        retire_vacated_landmarks(reconstructor.state, frame, T_w_c, SimpleNamespace(bridged=True))
    assert reconstructor.static_map.points.active[ids[alone]] == (cluster_size > 0)


def test_young_object_map_takes_in_the_rest_of_its_object():
    """objects.grow_keyframe_ratio: a frame holding at least that many times the map's
    landmarks in new 3D measurements of the object makes a keyframe, whatever the view."""
    config = load_config(None)
    object_map = SimpleNamespace(points=SimpleNamespace(active_count=26))
    points = SimpleNamespace(has_depth=np.ones(200, dtype=bool))
    own = np.arange(100)
    landmark_of = np.full(200, -1)
    landmark_of[:20] = np.arange(20)  # 20 matched, 80 new
    assert map_would_grow(config, object_map, points, own, landmark_of)
    landmark_of[:80] = np.arange(80)  # 20 new: fewer than the map's 26 landmarks
    assert not map_would_grow(config, object_map, points, own, landmark_of)
    points.has_depth[:] = False  # 2D measurements make no landmarks
    landmark_of[:] = -1
    assert not map_would_grow(config, object_map, points, own, landmark_of)
    points.has_depth[:] = True
    assert map_would_grow(config, object_map, points, own, landmark_of)
    assert not map_would_grow(load_config(None, ["objects.grow_keyframe_ratio=0"]), object_map, points, own,
                              landmark_of)


@pytest.fixture(scope="module")
def turning_sequence(tmp_path_factory):
    """Seed 2 of the smooth motion: the box turns about itself by 14-17 degrees a frame from
    frame 10 on, so its features stay within the guided search radius of where they were."""
    root = tmp_path_factory.mktemp("objects") / "turning"
    generate_sequence(root, full_size_options(objects=1, seed=2, motion="smooth"))
    return root


@pytest.mark.parametrize("turn_degrees", [0.0, 10.0])
def test_object_turning_about_itself_is_detected(turning_sequence, turn_degrees):
    """detection.in_place_turn_degrees: outlier landmarks found again near their projections
    veto a segment (a look-alike took their match), unless they agree on one large rigid turn."""
    _, first_motion = true_object_poses(turning_sequence)
    sequence = open_sequence(turning_sequence, max_frames=first_motion + 4)
    result = run(turning_sequence, [AT_ONCE, f"detection.in_place_turn_degrees={turn_degrees}"], sequence=sequence)
    created = [report.frame_index for report in result.reports if report.objects_created]
    if turn_degrees:
        assert created and created[0] - first_motion <= 3
    else:
        assert not created  # the in-place test alone vetoes it


def test_moving_region_too_poor_to_start_gets_detail_boxes(jump_sequence):
    """A moving region with too few 3D points to start a map is looked at closer (detail
    keypoints) in the next CANDIDATE_DETAIL_FRAMES frames, then forgotten."""
    sequence = open_sequence(jump_sequence, max_frames=1)
    reconstructor = Reconstructor(load_config(None, ["features.object_detail=true"]), sequence.intrinsics)
    state = reconstructor.state
    state.memory.candidate_boxes.append(((100, 80, 140, 120), 5 + CANDIDATE_DETAIL_FRAMES))
    margin = reconstructor.config.features.object_detail_margin
    grown = int(round(margin * 40))
    assert detail_boxes(state, 6) == [(100 - grown, 80 - grown, 140 + grown, 120 + grown)]
    assert detail_boxes(state, 5 + CANDIDATE_DETAIL_FRAMES) != []
    assert detail_boxes(state, 6 + CANDIDATE_DETAIL_FRAMES) == []
    assert not state.memory.candidate_boxes
    reconstructor.close()


@pytest.fixture(scope="module")
def resting_turn_sequence(tmp_path_factory):
    """Seed 3 of two jumping objects (60 frames; the tests use the first 25 or 50): at frame 19 the
    cylinder (18 cm across) turns 35 degrees about its axis and comes to rest 8 cm away. Only
    6-9 of its static landmarks are matched as outliers per frame, all found again near their
    projections."""
    root = tmp_path_factory.mktemp("objects") / "resting_turn"
    generate_sequence(root, full_size_options(objects=2, seed=3))
    return root


@pytest.mark.parametrize("memory_frames", [0, 3])
def test_object_that_turned_and_rests_is_detected(resting_turn_sequence, memory_frames):
    """detection.in_place_turn_memory_frames: too few agreeing outliers for one frame, but the
    same turn in two frames, starts the cylinder's map within 5 frames of its motion."""
    # Measured (the sequence as generated and 4 copies with +-1 grey level and +-1 depth unit on
    # 2% of the pixels): with the memory the map starts 2 or 3 frames after the motion (frame 21
    # or 22), without it not up to frame 26 (first + 7). The test used to stop at frame 22 and
    # allow 3 frames: a start one frame later would not have been seen.
    first_motion = first_motion_frame(resting_turn_sequence, 2)
    sequence = open_sequence(resting_turn_sequence, max_frames=first_motion + 6)
    # without detection by displaced landmarks, which finds the cylinder in other ways
    result = run(resting_turn_sequence, [AT_ONCE, f"detection.in_place_turn_memory_frames={memory_frames}",
                                         "detection.displaced_share=0"], sequence=sequence)
    cylinder_maps = frames_creating_maps_of(result, resting_turn_sequence, 2)
    if memory_frames:
        assert cylinder_maps and first_motion <= cylinder_maps[0] <= first_motion + 5
    else:
        assert not cylinder_maps


@pytest.fixture(scope="module")
def turned_over_its_place_sequence(tmp_path_factory):
    """Seed 3 of two objects jumping in the same frames (60 frames; the test uses the first
    14): at frame 10 the cylinder turns 35 degrees and comes to rest 8 cm away, over its old
    place. 2 of its 30 features match the static map (no outliers to detect it by), and the
    space it moved into lies behind its old surface (free space says nothing)."""
    root = tmp_path_factory.mktemp("objects") / "turned_over_its_place"
    generate_sequence(root, full_size_options(objects=2, seed=3, simultaneous=True))
    return root


@pytest.mark.parametrize("displaced_share", [0.0, 0.8])
def test_object_whose_landmarks_all_went_missing_is_detected(turned_over_its_place_sequence, displaced_share):
    """detection.displaced_share: the cylinder's static landmarks, inliers in frame 9, are
    neither matched nor at the measured depth in frame 10: its map starts at once. Without the
    test it starts only at its next jump (frame 19)."""
    root = turned_over_its_place_sequence
    first_motion = first_motion_frame(root, 2)
    sequence = open_sequence(root, max_frames=first_motion + 4)
    result = run(root, [AT_ONCE, f"detection.displaced_share={displaced_share}"], sequence=sequence)
    cylinder_maps = frames_creating_maps_of(result, root, 2)
    if displaced_share:
        assert cylinder_maps == [first_motion]
    else:
        assert not cylinder_maps


def test_object_whose_outliers_found_look_alikes_is_detected_by_its_displaced_landmarks(resting_turn_sequence):
    """At frame 19 the cylinder moves 8 cm and turns 35 degrees: all 7 of its outlier landmarks
    are found near their projections (on look-alikes in its own texture), which alone would
    veto it as in place, but 45 of its landmarks are displaced and the veto weighs them too:
    its map starts at once (3 frames later when only the outliers were weighed)."""
    first_motion = first_motion_frame(resting_turn_sequence, 2)
    result = run(resting_turn_sequence, [AT_ONCE], sequence=open_sequence(resting_turn_sequence, max_frames=first_motion + 2))
    assert frames_creating_maps_of(result, resting_turn_sequence, 2) == [first_motion]


def test_object_over_touching_segments_is_detected_by_their_displaced_landmarks(few_outliers_jump_sequence):
    """At frame 18 the cylinder jumps 8 cm and turns 43 degrees: none of its features matches
    the static map, and its displaced static landmarks fall 6 and 7 into two touching segments
    (its lit and shaded sides), each short of the 10 one segment needs. Counted together they
    start its map at once (20 frames later when each segment counted alone)."""
    root = few_outliers_jump_sequence
    first_motion = first_motion_frame(root, 2)
    result = run(root, [AT_ONCE], sequence=open_sequence(root, max_frames=first_motion + 2))
    assert frames_creating_maps_of(result, root, 2) == [first_motion]


@pytest.fixture(scope="module")
def small_move_sequence(tmp_path_factory):
    """Seed 4 of two objects jumping in the same frames (60 frames; the test uses the first
    13): at frame 10 the cylinder moves 8 cm and turns 43 degrees. Its 16 features match
    nothing static; 5 static landmarks are displaced in its one segment, 56% of whose pixels
    lie in space the static keyframes saw empty (free-space detection wants 60%), and the
    static registration outliers are too few to show it."""
    root = tmp_path_factory.mktemp("objects") / "small_move"
    generate_sequence(root, full_size_options(objects=2, seed=4, simultaneous=True))
    return root


@pytest.mark.parametrize("significance", [1e-9, 1e-6])
def test_few_displaced_landmarks_unlikely_by_chance_detect_an_object(small_move_sequence, significance):
    """detection.displaced_significance: 5 of 5 displaced landmarks, in a frame where few
    others are, are no chance (3e-7 at most): the cylinder's map starts at its first motion.
    Asked for 1e-9, which 5 landmarks cannot reach, the cylinder is not found in the next
    frames."""
    root = small_move_sequence
    first_motion = first_motion_frame(root, 2)
    result = run(root, [AT_ONCE, f"detection.displaced_significance={significance}"],
                 sequence=open_sequence(root, max_frames=first_motion + 3))
    cylinder_maps = frames_creating_maps_of(result, root, 2)
    if significance > 1e-9:
        assert cylinder_maps == [first_motion]
    else:
        assert not cylinder_maps


@pytest.fixture(scope="module")
def partial_view_jump_sequence(tmp_path_factory):
    """Seed 2 of two jumping objects (60 frames; the test uses the first 50): at frame 46 the
    box (object 1) jumps and shows old sides its landmarks do not match and, on a third of
    its pixels, a side its map never saw."""
    root = tmp_path_factory.mktemp("objects") / "partial_view_jump"
    generate_sequence(root, full_size_options(objects=2, seed=2))
    return root


@pytest.mark.parametrize("sequence_fixture", ["resting_turn_sequence", "partial_view_jump_sequence"])
def test_box_turned_to_unseen_sides_keeps_its_map(sequence_fixture, request):
    """objects.shape_reidentify: at frame 47 (seed 3) or 46 (seed 2) the box jumps and shows
    sides none of its landmarks match (seed 3: 34 matches, 0 inliers); its surface alone
    re-identifies it, so it keeps one map instead of starting a second. On seed 2 only two
    thirds of the region lie on the box's surface model."""
    root = request.getfixturevalue(sequence_fixture)
    sequence = open_sequence(root, max_frames=50)
    result = run(root, sequence=sequence)  # objects.shape_reidentify is on by default
    box_maps = maps_given_true_object(result, root, 1)
    assert len(box_maps) == 1
    assert box_maps <= set(result.reports[47].objects_tracked) and box_maps <= set(result.reports[49].objects_tracked)
    # and at the right pose: one constant offset explains the frames before and after the jump
    box = next(m for m in result.reconstructor.object_maps if m.object_id in box_maps)
    frames = [index for index, _, _ in box.trajectory]
    assert min(frames) < 40 and max(frames) == 49
    error = tracked_pose_error(result, root, box)
    assert error.translation_rmse_cm < 2.0 and error.rotation_rmse_deg < 2.0


def _maps_of_true_object(result, root, true_id, listed: str):
    """``(frame index, object id)`` of the maps in each report's ``listed`` ids
    (``objects_tracked`` or ``objects_created``) given pixels mostly of true object ``true_id``."""
    frames = list(result.sequence)
    found = []
    for report in result.reports:
        labels = labels_of(root, frames[report.frame_index])
        for object_id in getattr(report, listed):
            given = report.mask == object_id
            if given.any() and (labels[given] == true_id).mean() > 0.5:
                found.append((report.frame_index, object_id))
    return found


def maps_given_true_object(result, root, true_id):
    """Ids of the object maps given, in some frame, pixels mostly of true object ``true_id``."""
    return {object_id for _, object_id in _maps_of_true_object(result, root, true_id, "objects_tracked")}


def frames_creating_maps_of(result, root, true_id):
    """Frame indices in which a map was created on pixels mostly of true object ``true_id``."""
    return [frame for frame, _ in _maps_of_true_object(result, root, true_id, "objects_created")]


def tracked_pose_error(result, root, object_map, true_id: int = 1, only_frames=None):
    """Pose error of ``object_map`` against true object ``true_id`` over the frames it tracked
    (those of them in ``only_frames``, when given)."""
    true_poses, _ = true_object_poses(root, true_id)
    _, gt_cameras = result.sequence.groundtruth
    tracked = [(index, T_w_o) for index, _, T_w_o in object_map.trajectory
               if only_frames is None or index in only_frames]
    frames = [index for index, _ in tracked]
    estimated = np.array([T_w_o for _, T_w_o in tracked])
    cameras = np.array([result.reports[i].T_w_c for i in frames])
    return object_pose_error(cameras, estimated, gt_cameras[frames], true_poses[frames])


@pytest.fixture(scope="module")
def few_outliers_jump_sequence(tmp_path_factory):
    """Seed 4 of two jumping objects (60 frames; the test uses the first 14): at frame 10 the
    box (object 1) jumps and turns so that only 5-6 of its features still match its static
    landmarks, fewer than one frame needs to decide a motion."""
    root = tmp_path_factory.mktemp("objects") / "few_outliers_jump"
    generate_sequence(root, full_size_options(objects=2, seed=4))
    return root


@pytest.mark.parametrize("memory_frames", [0, 3])
def test_motion_with_few_agreeing_outliers_is_confirmed_by_a_recent_frame(few_outliers_jump_sequence,
                                                                          memory_frames):
    """detection.in_place_turn_memory_frames also confirms a region that moved away: too few
    agreeing outliers in one frame, the same motion in the next, and the box's map starts
    within 3 frames of its jump; without the memory, not in these frames."""
    root = few_outliers_jump_sequence
    # without detection by displaced landmarks, which finds the box in other ways
    result = run(root, [AT_ONCE, f"detection.in_place_turn_memory_frames={memory_frames}", "detection.displaced_share=0"],
                 sequence=open_sequence(root, max_frames=14))
    box_maps = frames_creating_maps_of(result, root, 1)
    if memory_frames:
        assert box_maps and 10 <= box_maps[0] <= 13
    else:
        assert not box_maps


def test_turn_is_confirmed_by_the_same_turn_in_a_recent_frame():
    """The remembered turn must move the region to the same old place by the same rotation,
    at most detection.in_place_turn_memory_frames frames earlier."""

    config = load_config(None)
    memory = DetectionMemory()
    rng = np.random.default_rng(0)
    camera_points = rng.uniform([-0.1, -0.1, 1.5], [0.1, 0.1, 1.7], (30, 3))
    points = SimpleNamespace(points=camera_points, has_depth=np.ones(30, dtype=bool))
    segments = SimpleNamespace(point_indices=[np.arange(30)])

    def measured(frame_index):
        return SimpleNamespace(points=points, segments=segments, frame_index=frame_index)

    T_w_c = np.eye(4)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("y", 35, degrees=True).as_matrix()
    turn[:3, 3] = [0.3, 0.0, -0.9]
    other = turn.copy()
    other[:3, 3] += [0.05, 0.0, 0.0]  # the same rotation, 5 cm elsewhere
    seen = lambda frame_index, T_w_old: turn_seen_before(config, memory, measured(frame_index), [0], T_w_c, T_w_old)
    assert not seen(10, turn)  # nothing remembered yet
    assert not seen(11, other)
    assert seen(12, turn)  # frame 10's turn
    about_centroid = np.eye(4)  # a further turn about the region's centroid: same old place
    centroid = camera_points.mean(axis=0)
    tolerance = TURN_MEMORY_DEGREES_FACTOR * config.detection.min_motion_degrees  # rotations fitted to few points

    def turned_about_centroid(degrees):
        about_centroid[:3, :3] = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
        about_centroid[:3, 3] = centroid - about_centroid[:3, :3] @ centroid
        return turn @ about_centroid

    memory.recent_turns = [(12, turn)]
    assert not seen(13, turned_about_centroid(1.5 * tolerance))  # the same old place, another rotation
    memory.recent_turns = [(12, turn)]
    assert seen(13, turned_about_centroid(0.75 * tolerance))  # the same turn, fitted again to a few points
    memory_frames = config.detection.in_place_turn_memory_frames
    memory.recent_turns = []
    assert not seen(20, turn)
    assert seen(20 + memory_frames, turn)  # just within the memory
    memory.recent_turns = []
    assert not seen(30, turn)
    assert not seen(30 + memory_frames + 1, turn)  # too long ago


def test_suspect_segments_give_the_static_keyframe_only_their_inliers():
    """objects.hold_back_suspects: points and planes of this frame's suspect segments that are
    no static inliers do not become static landmarks; all others do."""
    segments = SimpleNamespace(segment_of_points=lambda n: np.array([0, 0, 1, 1, 1, -1]),
                               plane_index=np.array([0, 1, -1]))  # plane 0 is segment 0, plane 1 segment 1
    measurements = SimpleNamespace(points=np.zeros(6), planes=np.zeros(2), segments=segments, frame_index=7)
    ctx = SimpleNamespace(suspects=[1], measurements=measurements, static_inliers=lambda: (
        np.array([True, False, True, False, False, False]), np.array([False, False])))
    points, planes = without_suspects(ctx, np.arange(6), np.arange(2))
    assert points.tolist() == [0, 1, 2, 5]
    assert planes.tolist() == [0]


def test_landmarks_in_space_seen_empty_are_phantoms():
    """FreeSpaceViews.in_free_space: a static landmark the latest static keyframe saw through
    (its wall 3 m away, the landmark at 2 m) is a phantom, whatever lies on or behind the
    wall, or outside the view, is not; nothing is with free-space tests off."""
    from jsr.synth.scene import synth_intrinsics

    intrinsics = synth_intrinsics(160, 120)
    keyframes = [SimpleNamespace(T_map_cam=np.eye(4))]  # the view's keyframe
    points = np.array([[0.0, 0.0, 2.0],  # in front of the wall: seen through
                       [0.1, 0.0, 2.95],  # on the wall
                       [0.0, 0.1, 3.5],  # behind it
                       [5.0, 0.0, 2.0]])  # outside the view
    for overrides, expected in (([], [True, False, False, False]),
                                (["objects.free_space_detection=false"], [False] * 4)):
        views = FreeSpaceViews(load_config(None, overrides), intrinsics)
        views.views.append((0, DepthView(np.full((30, 40), 3.0, dtype=np.float32), np.eye(4), 4)))
        assert views.in_free_space(keyframes, points).tolist() == expected


@pytest.fixture(scope="module")
def returning_sequence(tmp_path_factory):
    """Seed 2 of the jumping box (60 frames; the test uses the first 23): at frame 19 the box
    jumps back to 5 cm from where it stood before its first jump (frame 10), with the same
    rotation. Static landmarks of its first place that nothing retired are found again on it,
    8-10 px off, as if in place."""
    root = tmp_path_factory.mktemp("objects") / "returning"
    generate_sequence(root, full_size_options(objects=1, seed=2))
    return root


@pytest.fixture(scope="module")
def returning_run(returning_sequence):
    """The returning box's run up to 4 frames past its second jump (frame 19): frames 0-22."""
    second_jump = int(motion_frames(returning_sequence, 1)[1])
    return run(returning_sequence, sequence=open_sequence(returning_sequence, max_frames=second_jump + 4))


def test_object_back_at_its_old_place_is_detected(returning_sequence, returning_run):
    """The in-place test does not count landmarks lying in space the static keyframes saw
    empty (phantoms of the box's first place, found again on it as if in place): after its
    jump at frame 19 the box is lost for at most two frames, then tracked with its own
    pixels. (Until December 2026 a rule taking the segments where a just-lost object stood
    as that object kept it tracked from frame 19; it changed nothing on any real sequence or
    composite and was removed.)"""
    second_jump = int(motion_frames(returning_sequence, 1)[1])
    result = returning_run
    frames = list(result.sequence)
    for report in result.reports[second_jump + 2:]:
        labels = labels_of(returning_sequence, frames[report.frame_index])
        given = np.isin(report.mask, report.objects_tracked) & (report.mask > 0)
        assert report.objects_tracked and (labels[given] == 1).mean() > 0.9


class _FramePoints(SimpleNamespace):
    def __len__(self):
        return len(self.has_depth)


class _FrameSegments:
    """Just the segment interface :func:`~jsr.pipeline.region_growth.grow` reads."""

    def __init__(self, point_indices):
        self.point_indices = [np.asarray(indices, dtype=np.int64) for indices in point_indices]

    def __len__(self):
        return len(self.point_indices)

    def segment_of_points(self, count):
        owner = np.full(count, -1, dtype=np.int64)
        for segment, indices in enumerate(self.point_indices):
            owner[indices] = segment
        return owner



def _frame_context(measurements, **computed) -> FrameContext:
    """A frame context at the identity camera pose, bridged (no static matches), with the given
    per-frame values (``adjacency``, ``free_space``) already computed."""
    return FrameContext(frame=SimpleNamespace(depth=None), measurements=measurements,
                        report=SimpleNamespace(T_w_c=np.eye(4)),
                        timings={}, static=SimpleNamespace(bridged=True, by_depth=False), **computed)

@pytest.mark.parametrize("violations, grown", [(20, [0, 1]), (5, [0])])
def test_face_with_few_3d_features_grows_into_its_object_when_it_moved_in(violations, grown):
    """A face next to a tracked object seen at a grazing angle (10 features, 2 with depth)
    joins the object when at least objects.grow_violation_share of its sampled pixels lie in space
    the static keyframes saw empty; a segment like it where they saw a surface does not."""
    from jsr.synth.scene import synth_intrinsics

    reconstructor = Reconstructor(load_config(None), synth_intrinsics(640, 480))
    segments = _FrameSegments([np.arange(0, 20), np.arange(20, 30), np.arange(30, 40)])
    has_depth = np.ones(40, dtype=bool)
    has_depth[22:30] = False  # the grazing face: 2 of its 10 features have depth
    has_depth[32:40] = False  # ... and so has the segment beside it that stayed where it was
    measurements = SimpleNamespace(segments=segments, points=_FramePoints(has_depth=has_depth), frame_index=5)
    ctx = _frame_context(measurements, adjacency=np.array([[0, 1], [0, 2]]),
                         free_space=(np.array([0, violations, 0]), np.array([0, 40 - violations, 40])))
    owner = np.array([1, 0, 0])
    assert grow(reconstructor.state, ctx, [0], np.zeros(40, dtype=bool), owner) == grown
    reconstructor.close()


@pytest.mark.parametrize("object_width, grown", [(0.3, [0]), (1.0, [0, 1]), (None, [0, 1])])
def test_unsupported_segment_much_wider_than_its_object_stays_static(object_width, grown):
    """A segment beside an object, 20 3D features none of them a static inlier, where the static
    keyframes saw nothing: it joins the object as a face not matched yet, unless it is more
    than SIZE_FACTOR times wider than everything known of the object (a 1.2 m piece of floor
    beside a 0.3 m box: a real carpet with few static features)."""
    from jsr.synth.scene import synth_intrinsics

    intrinsics = synth_intrinsics(640, 480)
    reconstructor = Reconstructor(load_config(None), intrinsics)
    labels = np.full((480, 640), -1, dtype=np.int32)
    labels[200:280, 280:360] = 0  # the object's segment
    labels[300:480, 40:600] = 1  # 560 px wide at 1 m: about 1.2 m of floor
    segments = _FrameSegments([np.arange(0, 20), np.arange(20, 40)])
    segments.label_image = labels
    measurements = SimpleNamespace(segments=segments, points=_FramePoints(has_depth=np.ones(40, dtype=bool)),
                                   frame_index=5)
    ctx = _frame_context(measurements, adjacency=np.array([[0, 1]]),
                         free_space=(np.array([0, 0]), np.array([0, 0])))
    ctx.frame = SimpleNamespace(depth=np.ones((480, 640), dtype=np.float32))
    assert grow(reconstructor.state, ctx, [0], np.zeros(40, dtype=bool), np.array([1, 0]),
                object_width=object_width) == grown
    reconstructor.close()


@pytest.mark.parametrize("unseen_only, segment_2_pixels, grown", [
    (True, 960, [0, 1]),  # 40 of its 60 samples tested, all on a surface seen before: stays static
    (True, 1600, [0, 1, 2]),  # 40 of 100: the keyframes saw too little of it to tell
    (False, 960, [0, 1, 2]),
])
def test_segment_inside_the_extent_where_the_static_keyframes_saw_a_surface_stays_static(unseen_only,
                                                                                        segment_2_pixels, grown):
    """objects.grow_inside_extent: a featureless segment inside the object's extent joins the
    object, unless the static keyframes taken since its map began saw a surface where it lies
    (and its static matches did not move; objects.extent_unseen_only): the background a jumped
    object left, taken once into its map (synth_two_sim seed 1 at 320x240), stretched the extent
    over the scene, which then grew into one static segment after another (70% of the object's
    mask static by the end). Earlier keyframes saw the object's own faces as static; a segment
    they saw less than half of may be a face of the object that moved there."""
    from jsr.synth.scene import synth_intrinsics

    config = load_config(None, [f"objects.extent_unseen_only={str(unseen_only).lower()}"])
    reconstructor = Reconstructor(config, synth_intrinsics(640, 480))
    segments = _FrameSegments([np.arange(0, 20), np.arange(20, 30), np.arange(30, 40)])
    segments.pixel_counts = [960, 960, segment_2_pixels]  # free-space samples: every 4th pixel of every 4th row
    measurements = SimpleNamespace(segments=segments, points=_FramePoints(has_depth=np.ones(40, dtype=bool)),
                                   frame_index=30)
    # segment 1: too few samples for a free-space verdict; segment 2: all 40 tested on a surface
    # seen before ...
    counts = (np.array([0, 0, 0]), np.array([0, 2, 40]))
    ctx = _frame_context(measurements, adjacency=np.array([[0, 1], [0, 2]]), free_space=counts)
    # ... by the static keyframes taken since the object's map began (the object left out of them)
    since = []
    ctx.free_space_since = lambda state, after_frame: since.append(after_frame) or counts
    owner = np.array([1, 0, 0])
    inside = np.array([False, True, True])
    assert grow(reconstructor.state, ctx, [0], np.zeros(40, dtype=bool), owner, inside, known_since=7) == grown
    assert since == ([7] if unseen_only else [])
    reconstructor.close()


def test_free_space_since_a_frame_counts_only_later_keyframes():
    """FrameContext.free_space_since: the static keyframes of frames after the given one;
    when all the kept ones are, the frame's own (cached) counts, not computed again."""
    from jsr.synth.scene import synth_intrinsics

    reconstructor = Reconstructor(load_config(None), synth_intrinsics(640, 480))
    state = reconstructor.state
    state.static_map.keyframes = [SimpleNamespace(frame_index=5), SimpleNamespace(frame_index=9)]
    state.free_space.views = [(0, None), (1, None)]
    segments = _FrameSegments([])
    segments.label_image = None
    ctx = _frame_context(SimpleNamespace(segments=segments), free_space=("all views",))
    asked = []
    state.free_space.counts = lambda keyframes, depth, labels, count, T_w_c, after_frame=None, measured_only=False, \
        static_samples=None, surfaces=None: asked.append(after_frame) or ("later views",)
    assert ctx.free_space_since(state, 3) == ("all views",) and asked == []
    assert ctx.free_space_since(state, 7) == ("later views",) and asked == [7]
    reconstructor.close()


def test_landmarks_that_agree_from_two_far_fits_overrule_the_surface():
    """shape_reidentification.landmarks_agree_elsewhere: landmark registrations away from the surface
    fits that predicted them are trusted only when two fits far apart (beyond 20 cm or 30
    degrees of each other) led them to the same pose of the same object."""
    from jsr.geometry import make_transform, rotation_about_axis

    centre = np.array([0.0, 0.0, 1.0])
    up = [0.0, 0.0, 1.0]

    def about_centre(degrees, shift=(0.0, 0.0, 0.0)):
        rotation = rotation_about_axis(up, np.radians(degrees))
        return make_transform(rotation, centre - rotation @ centre + np.asarray(shift))

    def registration(T, inliers):
        return SimpleNamespace(transformation=T, num_inliers=inliers)

    truth = about_centre(20.0, (0.05, 0.0, 0.0))
    box, other_box = object(), object()
    first = (box, about_centre(180.0), "matches", registration(truth, 9))
    second = (box, about_centre(80.0), "matches", registration(about_centre(21.0, (0.052, 0.0, 0.0)), 11))
    agree = landmarks_agree_elsewhere
    assert agree([first, second], centre) is second  # the one with most inliers
    assert agree([first], centre) is None  # one registration away from its fit: maybe chance
    near_first = (box, about_centre(170.0), "matches", registration(truth, 12))
    assert agree([first, near_first], centre) is None  # two fits 10 degrees apart: one start
    assert agree([first, (other_box, *second[1:])], centre) is None  # two objects
    elsewhere = (box, about_centre(80.0), "matches", registration(about_centre(60.0), 11))
    assert agree([first, elsewhere], centre) is None  # the landmarks disagree with each other


def test_object_lost_in_its_jump_keeps_its_one_map(returning_sequence, returning_run):
    """At frame 19 the box jumps 8 cm and turns 57 degrees. Its map matches 6 inliers of 19
    and loses it; the static map's outliers on its new place are mostly found again near their
    projections and agree on no motion. It is lost for two frames, not taken for a new object
    nor into the static map: by frame 22 its one map follows it again, at the right pose.
    (A rule that took the segments where a just-lost object stood as that object, moved,
    kept it tracked in frames 19-20; it changed nothing on the composites, kitchen_box120 or
    the real sequences, and was removed.)"""
    root, result = returning_sequence, returning_run
    box_maps = maps_given_true_object(result, root, 1)
    assert len(box_maps) == 1
    assert box_maps <= set(result.reports[22].objects_tracked)
    box = next(m for m in result.reconstructor.object_maps if m.object_id in box_maps)
    error = tracked_pose_error(result, root, box)
    assert error.translation_rmse_cm < 2.0 and error.rotation_rmse_deg < 2.0


@pytest.fixture(scope="module")
def face_moved_in_sequence(tmp_path_factory):
    """Seed 7 of two jumping objects (60 frames; the tests use the first 14): at frame 10 the
    box (object 1) jumps, and without objects.grow_violation_share and objects.grow_unmatched a
    face of it goes to the static map (recall 0.61-0.65 in frames 10-13)."""
    root = tmp_path_factory.mktemp("objects") / "face_moved_in"
    generate_sequence(root, full_size_options(objects=2, seed=7))
    return root


# Seed 1 of two jumping objects, on which the two tests below ran before, sat at a knife edge:
# without either rule the box kept about half of its pixels (recall 0.53), or all of them (0.99)
# on 1 of 5 copies of it with +-1 grey level and +-1 depth unit on 2% of the pixels.


@pytest.mark.parametrize("violation_share", [0.0, 0.3])
def test_face_that_moved_in_is_grown_into_its_object(face_moved_in_sequence, partial_view_jump_sequence,
                                                     violation_share):
    """objects.grow_violation_share: a face of the box that jumped at frame 10, no static
    inlier among its keypoints and partly in space seen empty, joins the box's map; without
    the rule it goes to the static map (objects.grow_unmatched, which also takes it on seed 7
    from frame 12, off here)."""
    # Measured in frames 12-13 (frame 10 or 11 the box's map starts) on seeds 7 and 2, as
    # generated and on 4 copies with +-1 grey level and +-1 depth unit on 2% of the pixels (all
    # alike within 0.002): with the rule recall 0.95-0.97 (seed 7) and 0.98 (seed 2); without,
    # 0.63-0.65 (seed 7) and 0.77-0.78 (seed 2).
    for root in (face_moved_in_sequence, partial_view_jump_sequence):
        result = run(root, [f"objects.grow_violation_share={violation_share}", "objects.grow_unmatched=false"],
                     sequence=open_sequence(root, max_frames=14))
        recalls = object_recalls(result, root, 1, result.reports[12:])
        if violation_share:
            assert min(recalls) > 0.9, (root.name, recalls)
        else:
            assert max(recalls) < 0.85, (root.name, recalls)


@pytest.fixture(scope="module")
def sample_like_sequence(tmp_path_factory):
    """The bundled sample's options (sample_data/README.md: 40 frames, 320x240, seed 0)."""
    root = tmp_path_factory.mktemp("objects") / "sample_like"
    generate_sequence(root, SynthOptions(frames=40, objects=1, motion="jump", width=WIDTH, height=HEIGHT, seed=0))
    return root


def test_grazing_face_where_the_old_face_was_joins_its_object(sample_like_sequence):
    """At frame 10 the box jumps 9 cm and turns 43 degrees; its second face, seen at a grazing
    angle (3D keypoints only with features.slanted_max_incidence 70, off by default), lies
    where the static keyframes saw its old front face. Its 7 displaced static landmarks count
    with the front face's 11 (touching segments), so it joins the box's map at once; the box
    keeps one map through its next jump (frame 18: 20 cm, 38 degrees, now showing mostly the
    second face)."""
    root = sample_like_sequence
    result = run(root, [AT_ONCE, "features.slanted_max_incidence=70"], sequence=open_sequence(root, max_frames=20))
    recalls = object_recalls(result, root, 1, result.reports[10:17])
    assert np.median(recalls) > 0.9, recalls
    assert [report.objects_tracked for report in result.reports[10:]] == [[1]] * 10


@pytest.mark.parametrize("unmatched", [False, True])
def test_face_whose_features_match_nothing_static_is_grown(face_moved_in_sequence, unmatched):
    """objects.grow_unmatched: from frame 12 a face of the box that jumped at frame 10 (none
    of its features a static inlier, few matched at all, partly in space the static keyframes
    saw empty) joins the box's map even with objects.grow_violation_share off; without either
    rule the static map takes it."""
    # Measured in frames 12-13 as in the test above (seed 7; on seed 2 the rule changes nothing):
    # with the rule recall 0.95-0.97, without 0.63-0.65.
    root = face_moved_in_sequence
    result = run(root, [AT_ONCE, "objects.grow_violation_share=0", f"objects.grow_unmatched={str(unmatched).lower()}"],
                 sequence=open_sequence(root, max_frames=14))
    recalls = object_recalls(result, root, 1, result.reports[12:])
    if unmatched:
        assert min(recalls) > 0.9, recalls
    else:
        assert max(recalls) < 0.85, recalls


@pytest.fixture(scope="module")
def resting_cylinder_sequence(tmp_path_factory):
    """Seed 5 of two jumping objects (60 frames; the test uses the first 35): the cylinder
    (object 2) jumps at frame 18 and rests until frame 35. Its texture alone fixes its turn
    about its axis, and registered anew each frame it wandered by up to 2.6 degrees."""
    root = tmp_path_factory.mktemp("objects") / "resting_cylinder"
    generate_sequence(root, full_size_options(objects=2, seed=5))
    return root


@pytest.mark.parametrize("max_extra_cost", [0.0, 16.8])
def test_resting_object_keeps_its_world_pose(resting_cylinder_sequence, max_extra_cost):
    """objects.resting_max_extra_cost: while the cylinder rests, its world pose stays where it
    was (within 0.5 degrees and 5 mm over frames 20-34) and within a degree and 5 mm of the
    truth; registered anew each frame (0: off), it wanders by more than a degree."""
    root = resting_cylinder_sequence
    assert motion_frames(root, 2).tolist()[:2] == [18, 35]
    result = run(root, [f"objects.resting_max_extra_cost={max_extra_cost}"],
                 sequence=open_sequence(root, max_frames=35))
    (cylinder_id,) = maps_given_true_object(result, root, 2)
    (cylinder,) = [m for m in result.reconstructor.object_maps if m.object_id == cylinder_id]
    resting = [T_w_o for index, _, T_w_o in cylinder.trajectory if 20 <= index <= 34]
    assert len(resting) == 15
    turns = [rotation_angle(np.linalg.inv(resting[0])[:3, :3] @ T_w_o[:3, :3]) for T_w_o in resting]
    shifts = [np.linalg.norm(T_w_o[:3, 3] - resting[0][:3, 3]) for T_w_o in resting]
    error = tracked_pose_error(result, root, cylinder, true_id=2, only_frames=range(20, 35))
    if max_extra_cost > 0:
        assert np.degrees(max(turns)) < 0.5 and max(shifts) < 0.005
        assert error.rotation_max_deg < 1.0 and error.translation_max_cm < 0.5
    else:
        assert np.degrees(max(turns)) > 1.0 and error.rotation_max_deg > 1.0


@pytest.fixture(scope="module")
def side_face_sequence(tmp_path_factory):
    """Seed 1 of the jumping box at 320x240 (60 frames; the test uses the first 38): at frame 28
    it jumps and shows a side face whose keypoints mostly have no depth (too slanted for the
    5-pixel depth window)."""
    root = tmp_path_factory.mktemp("objects") / "side_face"
    generate_sequence(root, SynthOptions(frames=60, objects=1, motion="jump", width=WIDTH, height=HEIGHT, seed=1))
    return root


@pytest.mark.parametrize("hold_back, least, most", [("true", 0.9, 1.0), ("false", 0.0, 0.8)])
def test_face_beside_a_jumped_object_stays_out_of_the_static_map(side_face_sequence, hold_back, least, most):
    """In the frame of a jump, the segments beside the object that no static inlier supports
    give the static keyframe nothing (objects.hold_back_beside_moved): the box's side face is
    then grown into the box in the next frames (without the rule, the static keyframe of frame
    28 takes its features and depth, and it stays static: recall 0.6)."""
    jump = int(motion_frames(side_face_sequence, 1)[2])
    assert jump == 28
    # the extent spanning the surface samples takes the face as well: left out, to test this rule alone
    result = run(side_face_sequence, [AT_ONCE, f"objects.hold_back_beside_moved={hold_back}", "objects.extent_from_surface=false"],
                 sequence=open_sequence(side_face_sequence, max_frames=jump + 10))
    recall = np.mean(object_recalls(result, side_face_sequence, 1, result.reports[jump + 1:]))
    assert least <= recall <= most


@pytest.fixture(scope="module")
def hidden_face_sequences(tmp_path_factory):
    """Seeds 3 and 4 of the jumping box at 320x240 (60 frames; the test uses the first 20): at
    frame 10 the box jumps, and from frame 13 (seed 3) or 15 (seed 4) a face of it is inside
    its extent only with the surface samples."""
    roots = {}
    for seed in (3, 4):
        roots[seed] = tmp_path_factory.mktemp("objects") / f"hidden_face_{seed}"
        generate_sequence(roots[seed], SynthOptions(frames=60, objects=1, motion="jump", width=WIDTH, height=HEIGHT,
                                                    seed=seed))
    return roots


@pytest.mark.parametrize("from_surface", ["true", "false"])
def test_extent_spans_the_faces_without_3d_keypoints(hidden_face_sequences, from_surface):
    """Once the free-space views no longer see a face of the box move in, only the extent
    spanning the object's surface samples (objects.extent_from_surface) keeps giving it to the
    box: a face whose keypoints have no depth adds no landmark to the hull."""
    # Two seeds, each with a margin. One seed alone sat at a knife edge: seed 1 after its jump
    # at frame 46, without the samples, gave recall 0.74 and a second map, or 0.94 and one map
    # (as on another machine with the same versions), as the RANSAC seed or +-1 grey level on
    # 2% of the pixels decided. Measured on seeds 3 and 4, frames 11-19, on the sequences as
    # generated and on 4 copies with +-1 grey level and +-1 depth unit on 2% of the pixels (all
    # five alike within 0.025): with the samples recall 0.91-0.98 per frame (seed 3) and
    # 0.97-0.99 (seed 4); without, 7 frames at 0.46-0.55 (seed 3) and 4 at 0.67 (seed 4).
    for seed, root in hidden_face_sequences.items():
        jump = first_motion_frame(root, 1)
        assert jump == 10
        result = run(root, [f"objects.extent_from_surface={from_surface}"],
                     sequence=open_sequence(root, max_frames=jump + 10))
        recalls = object_recalls(result, root, 1, result.reports[jump + 1:])
        if from_surface == "true":
            assert min(recalls) > 0.85, (seed, recalls)
        else:  # the face lost for several frames
            assert sum(recall < 0.75 for recall in recalls) >= 3, (seed, recalls)


def test_surface_alignment_is_drawn_again_while_nothing_is_kept(monkeypatch):
    """objects.shape_attempts: a region that no alignment explains is aligned again (RANSAC may
    miss the right alignment once), and no more once one is kept; the region's surface is
    sampled once for all attempts."""
    from jsr.pipeline import shape_reidentification
    from jsr.synth.scene import synth_intrinsics

    labels = np.full((240, 320), -1, dtype=np.int32)
    labels[100:160, 120:200] = 3  # the moving region: segment 3, a flat patch 1 m away
    frame = SimpleNamespace(index=7, depth=np.ones((240, 320), dtype=np.float32),
                            color=np.full((240, 320, 3), 128, dtype=np.uint8))
    measurements = SimpleNamespace(segments=SimpleNamespace(label_image=labels))
    for attempts, results, calls, found in [(2, [False, True], 2, True), (1, [False, True], 1, False),
                                            (3, [True, False, False], 1, True), (2, [False, False], 2, False)]:
        reconstructor = Reconstructor(load_config(None, [f"objects.shape_attempts={attempts}"]),
                                      synth_intrinsics(320, 240))
        answers = iter(results)
        seen = []
        monkeypatch.setattr(shape_reidentification, "align_to_lost_objects",
                            lambda *args: seen.append(args) or next(answers))
        # one lost object whose surface could hold the region
        monkeypatch.setattr(reconstructor.state.surfaces, "model", lambda object_map: "its surface model")
        monkeypatch.setattr(shape_reidentification, "could_hold", lambda model, region: True)
        lost = [SimpleNamespace(object_id=1)]
        ctx = SimpleNamespace(frame=frame, measurements=measurements, surface_alignments=0)
        assert shape_reidentification.reidentify_by_shape(reconstructor.state, ctx, [3], None, lost, {},
                                                          attempts) is found
        assert len(seen) == calls
        assert all(args[4] is seen[0][4] for args in seen)  # one region model, reused
        reconstructor.close()


@pytest.mark.parametrize("in_place, grown", [(False, [0, 1]), (True, [0])])
def test_segment_of_outliers_grows_only_if_its_landmarks_left(monkeypatch, in_place, grown):
    """A segment beside an object where the static keyframes saw a surface, all 20 of its
    static matches outliers: the object's own face before it jumped, unless its outlier
    landmarks are still found in place (a carpet whose matches went to look-alikes)."""
    import jsr.pipeline.region_growth as region_growth
    from jsr.synth.scene import synth_intrinsics

    reconstructor = Reconstructor(load_config(None), synth_intrinsics(640, 480))
    asked = []
    monkeypatch.setattr(region_growth, "mostly_in_place",
                        lambda state, ctx, segment, inliers, minimum: asked.append(segment) or in_place)
    segments = _FrameSegments([np.arange(0, 20), np.arange(20, 40)])
    measurements = SimpleNamespace(segments=segments, points=_FramePoints(has_depth=np.ones(40, dtype=bool)),
                                   frame_index=5)
    ctx = _frame_context(measurements, adjacency=np.array([[0, 1]]),
                         free_space=(np.array([0, 0]), np.array([0, 60])))  # segment 1: a surface seen before
    ctx.static = SimpleNamespace(bridged=False, by_depth=False,
                                 matched=SimpleNamespace(point_measurements=np.arange(20, 40)))
    assert grow(reconstructor.state, ctx, [0], np.zeros(40, dtype=bool), np.array([1, 0])) == grown
    assert asked == [1]
    reconstructor.close()


def test_segment_much_wider_than_its_object_is_mixed():
    """classify.wider_than_object: a segment given to a 0.3 m object that spans 1.2 m of
    surface holds more than the object; one as wide as the object, or one given to an object
    with no extent yet, does not."""
    from scipy.spatial import ConvexHull

    from jsr.pipeline.classify import wider_than_object
    from jsr.synth.scene import synth_intrinsics

    intrinsics = synth_intrinsics(640, 480)
    labels = np.full((480, 640), -1, dtype=np.int32)
    labels[200:280, 280:360] = 0  # about 0.17 m wide at 1 m
    labels[300:480, 40:600] = 1  # about 1.2 m
    labels[0:100, 0:100] = 2  # given to an object without an extent
    corners = np.array([[x, y, z] for x in (0, 0.3) for y in (0, 0.2) for z in (0, 0.15)])
    hulls = {1: ConvexHull(corners), 2: None}
    wide = wider_than_object(labels, np.ones((480, 640), dtype=np.float32), intrinsics, np.array([1, 1, 2, 0]),
                             hulls)
    assert wide.tolist() == [False, True, False, False]


def test_forgetting_a_moved_objects_surface_blanks_it_in_the_views():
    """FreeSpaceViews.forget_surface: where a view saw the static landmarks of an object that
    has since moved (a 0.4 m face 2 m away in front of a wall at 3 m), its samples are blanked
    with a one-sample margin, so that the object coming back there is not "consistent" with
    the view; the wall around it, and a stray landmark matched on it, are untouched."""
    from jsr.synth.scene import synth_intrinsics

    intrinsics = synth_intrinsics(160, 120)
    depth = np.full((30, 40), 3.0, dtype=np.float32)
    views = FreeSpaceViews(load_config(None), intrinsics)
    keyframes = [SimpleNamespace(T_map_cam=np.eye(4))]
    rows, cols = np.mgrid[8:16, 12:20]  # the face's samples (stride 4)
    depth[rows, cols] = 2.0
    views.views.append((0, DepthView(depth.copy(), np.eye(4), 4)))
    u, v = cols.ravel() * 4.0, rows.ravel() * 4.0
    face = np.column_stack([(u - intrinsics.cx) / intrinsics.fx * 2.0, (v - intrinsics.cy) / intrinsics.fy * 2.0,
                            np.full(len(u), 2.0)])
    stray = np.array([[(130 - intrinsics.cx) / intrinsics.fx * 3.0, 0.0, 3.0]])  # on the wall, far off
    blanked = views.forget_surface(keyframes, np.vstack([face[[0, 7, 20, 35, 56, 63]], stray]))  # corners, inside
    view = views.views[0][1]
    expected = np.zeros((30, 40), dtype=bool)
    expected[7:17, 11:21] = True  # the hull of the face's landmarks, one sample wider
    assert blanked == expected.sum()
    assert (view.depth[expected] == 0).all() and (view.depth[~expected] == depth[~expected]).all()
    assert (view.near_depth[~expected] > 0).all()  # the lenient minimum ignores the blanked samples


def test_every_region_is_tried_by_features_before_any_by_surface(monkeypatch):
    """moving_regions.detect_moving_regions: a lost object that the features find in one moving
    region of the frame is not first aligned by surface to another region (0.5-2.3 s a draw;
    bonn_crowd_people seed 4, frame 20: a person map aligned twice to one region, then found by
    its landmarks in the next), and every region left has its first surface draw before any
    has its second. A region nothing explains starts a map; a later region does not grow into
    the segments an earlier one grew to."""
    import jsr.pipeline.moving_regions as moving_regions
    from jsr.synth.scene import synth_intrinsics

    reconstructor = Reconstructor(load_config(None, ["detection.in_place_turn_degrees=0", "objects.shape_attempts=2"]),
                                  synth_intrinsics(160, 120))
    state = reconstructor.state
    segments = _FrameSegments([np.arange(0, 30), np.arange(30, 60), np.arange(60, 90), np.arange(90, 120)])
    segments.label_image = np.repeat(np.repeat(np.arange(4), 10)[None], 10, axis=0)
    points = _FramePoints(has_depth=np.ones(120, dtype=bool))
    measurements = SimpleNamespace(segments=segments, points=points, frame_index=12)
    assignment = SimpleNamespace(segment_owner=np.zeros(4, dtype=np.int64), point_owner=np.zeros(120, dtype=np.int64))
    ctx = SimpleNamespace(registered=True, frame=SimpleNamespace(index=12), measurements=measurements,
                          report=SimpleNamespace(T_w_c=np.eye(4), objects_created=[], objects_tracked=[]),
                          assignment=assignment, static_matched=lambda: None, static_inliers=lambda: (None, None),
                          free_space_counts=lambda state: (np.zeros(4), np.zeros(4)), T_w_c=np.eye(4),
                          outcomes=[], suspects=[])
    for name in ("detect_moving_segments", "not_in_place", "rigidly_moved"):
        monkeypatch.setattr(moving_regions, name, lambda state_or_segments, *args, **kwargs: [0, 1, 2])
    monkeypatch.setattr(moving_regions, "free_space_segments", lambda *args: [])
    monkeypatch.setattr(moving_regions, "displaced_landmarks", lambda *args: [])
    monkeypatch.setattr(moving_regions, "merge_adjacent_moving_segments", lambda *args: [[0], [1], [2]])
    monkeypatch.setattr(moving_regions, "moved_as_before", lambda *args: False)
    monkeypatch.setattr(moving_regions, "outlier_landmarks", lambda *args: np.zeros(0, dtype=np.int64))
    grown_into = {}  # region -> the segments free for it to grow into

    def grow(state, ctx, group, inliers, owner):  # region 0 grows into segment 3 (not moving), if free
        grown_into[group[0]] = [s for s in range(4) if owner[s] == 0]
        return group + [3] if group == [0] and owner[3] == 0 else group

    monkeypatch.setattr(moving_regions, "grow", grow)
    calls = []

    def reidentify(state, ctx, group, group_points, outcomes, shape_draws=0):
        calls.append((group[0], shape_draws))
        # region 2 is a lost object found by its features, region 1 one found by its surface
        return (group == [2] and not shape_draws) or (group == [1] and shape_draws > 0)

    monkeypatch.setattr(moving_regions, "reidentify", reidentify)
    started = []
    monkeypatch.setattr(moving_regions, "start_object",
                        lambda state, ctx, group, T_w_c, evidence_landmarks: started.append(group))
    moving_regions.detect_moving_regions(state, ctx)
    # features on all three first; then one surface draw each on 0 and 1; a second on 0 only
    assert calls == [(0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (0, 1)]
    assert started == [[0, 3]]
    assert grown_into == {0: [0, 3], 1: [1], 2: [2]}  # 3 is region 0's before it is started
    reconstructor.close()


def test_surface_alignments_per_frame_are_bounded(monkeypatch):
    """shape_reidentification.reidentify_by_shape: a frame runs at most
    objects.shape_alignments_per_frame (region, lost object) alignments, however many regions,
    lost objects and draws ask for them (bonn_crowd_people seed 9, frame 85: 8 alignments of
    person surfaces, 13.4 s); the lost objects are aligned in the order given, and a region
    that finds the budget spent is not even sampled."""
    import jsr.pipeline.shape_reidentification as shape

    config = load_config(None, ["objects.shape_alignments_per_frame=5"])
    lost = [SimpleNamespace(object_id=k) for k in (4, 7, 9)]
    state = SimpleNamespace(config=config, intrinsics=None,
                            surfaces=SimpleNamespace(model=lambda object_map: f"model {object_map.object_id}"))
    ctx = SimpleNamespace(frame=SimpleNamespace(index=85, depth=None, color=None),
                          measurements=SimpleNamespace(segments=SimpleNamespace(label_image=np.zeros((4, 4), int))),
                          surface_alignments=0)
    sampled, aligned = [], []
    monkeypatch.setattr(shape, "sample_surface", lambda *args: sampled.append(1))
    monkeypatch.setattr(shape, "region_model", lambda sample, voxel: "region")
    monkeypatch.setattr(shape, "could_hold", lambda model, region: True)
    monkeypatch.setattr(shape, "align_to_lost_objects", lambda state, ctx, group, points, region, models, outcomes:
                        aligned.append([m.object_id for m, _ in models]) and False)
    for _ in range(2):  # as the detection draws: once for every region, then again: 18 alignments asked for
        for region in range(3):
            assert not shape.reidentify_by_shape(state, ctx, [region], np.zeros(0, int), lost, {}, draws=1)
    assert aligned == [[4, 7, 9], [4, 7]]  # region 0 against all three, region 1 against the first two
    assert ctx.surface_alignments == 5
    assert len(sampled) == 2  # later regions found the budget spent


def test_an_objects_surface_model_is_built_again_only_when_its_views_change(monkeypatch):
    """``ObjectSurfaces`` keeps an object's model and its own views' texture agreement while its
    keyframes (their samples and poses) stay the same, and builds them again when one moves or
    is added."""
    from jsr.pipeline.object_surfaces import ObjectSurfaces
    from jsr.pipeline.surfaces import SurfaceSample
    from jsr.synth.scene import synth_intrinsics

    surfaces = ObjectSurfaces(load_config(None), synth_intrinsics(320, 240))
    rng = np.random.default_rng(0)

    def sample():
        return SurfaceSample(rng.uniform(-0.1, 0.1, (400, 3)).astype(np.float32) + np.float32([0, 0, 1]),
                             rng.integers(0, 255, (400, 3)).astype(np.uint8))

    keyframes = [SimpleNamespace(frame_index=k, T_map_cam=np.eye(4)) for k in (3, 7)]
    object_map = SimpleNamespace(object_id=5, keyframes=keyframes)
    surfaces.samples = {3: {5: sample()}, 7: {5: sample()}}
    computed = []
    monkeypatch.setattr(surfaces, "own_texture", lambda m: computed.append(m.object_id) or 0.5)
    model = surfaces.model(object_map)
    assert model is not None and surfaces.model(object_map) is model
    assert surfaces.self_texture(object_map) == surfaces.self_texture(object_map) == 0.5 and computed == [5]
    keyframes[1].T_map_cam[0, 3] = 0.05  # bundle adjustment moved a keyframe (in place)
    moved = surfaces.model(object_map)
    assert moved is not model and surfaces.self_texture(object_map) == 0.5 and computed == [5, 5]
    keyframes.append(SimpleNamespace(frame_index=9, T_map_cam=np.eye(4)))
    assert surfaces.model(object_map) is moved  # no sample of frame 9: the same views
    surfaces.samples[9] = {5: sample()}
    assert surfaces.model(object_map) is not moved
