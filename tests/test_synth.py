"""The synthetic sequence generator: layout, exact ground truth, determinism, noise, motion."""

import json

import cv2
import numpy as np
import pytest
import yaml

from jsr.errors import InputError, OutputError
from jsr.geometry import KINECT_SIGMA_Z_COEFFICIENT, backproject_depth, invert_transform, transform_points
from jsr.io.dataset import open_sequence
from jsr.io.trajectory import read_tum_trajectory
from jsr.synth.options import SynthOptions
from jsr.synth.render import SynthRenderer
from jsr.synth.scene import TABLE_SIZE, TABLE_TOP, build_scene_plan
from jsr.synth.write import generate_sequence


def _options_of(root):
    """The SynthOptions recorded in a generated sequence's synth.yaml."""
    return SynthOptions(**yaml.safe_load((root / "synth.yaml").read_text())["options"])


def _read_labels(path):
    labels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert labels is not None and labels.dtype == np.uint8 and labels.ndim == 2
    return labels


@pytest.fixture(scope="module")
def clean_and_noisy(tmp_path_factory):
    """The same two-object scene rendered without and with depth noise (no random dropouts)."""
    root = tmp_path_factory.mktemp("synth_noise")
    common = dict(frames=4, objects=2, width=160, height=120, seed=5, dropout=0.0)
    generate_sequence(root / "clean", SynthOptions(depth_noise=False, **common))
    generate_sequence(root / "noisy", SynthOptions(depth_noise=True, **common))
    return root / "clean", root / "noisy", SynthOptions(depth_noise=False, **common)


def test_sequence_loads_with_open_sequence(synth_sequence):
    options = _options_of(synth_sequence)
    sequence = open_sequence(synth_sequence)
    assert len(sequence) == options.frames
    assert sequence.kind == "tum"
    intrinsics = sequence.intrinsics
    assert (intrinsics.width, intrinsics.height) == (options.width, options.height)
    assert intrinsics.fx == pytest.approx(525.0 * options.width / 640.0)
    assert intrinsics.fy == pytest.approx(525.0 * options.width / 640.0)
    assert intrinsics.cx == pytest.approx((options.width - 1) / 2.0)
    assert intrinsics.cy == pytest.approx((options.height - 1) / 2.0)
    assert intrinsics.depth_scale == 5000.0
    np.testing.assert_allclose(sequence.timestamps, 1000.0 + np.arange(options.frames) / options.fps, atol=1e-6)
    for frame in (sequence[0], sequence[-1]):
        assert frame.color.shape == (options.height, options.width, 3) and frame.color.dtype == np.uint8
        assert frame.depth.shape == (options.height, options.width) and frame.depth.dtype == np.float32
        valid = frame.depth[frame.depth > 0]
        assert valid.size > 0.8 * frame.depth.size
        assert 0.3 <= valid.min() and valid.max() <= 6.0
        assert frame.color.std() > 20  # textured, not flat
        labels = _read_labels(synth_sequence / "labels" / f"{frame.name}.png")
        assert labels.shape == frame.depth.shape
        assert set(np.unique(labels)) <= {0, 1}
    assert sequence.groundtruth is not None and len(sequence.groundtruth[0]) == options.frames
    for line in (synth_sequence / "rgb.txt").read_text().splitlines():
        assert line.startswith("#") or line.split()[1].startswith("rgb/")


def test_ground_truth_round_trips(synth_sequence):
    options = _options_of(synth_sequence)
    plan = build_scene_plan(options)
    timestamps, camera_poses = read_tum_trajectory(synth_sequence / "groundtruth.txt")
    np.testing.assert_array_equal(timestamps, plan.timestamps)
    np.testing.assert_allclose(camera_poses, plan.camera_poses, rtol=0, atol=1e-12)
    assert plan.object_poses.shape == (options.objects, options.frames, 4, 4)
    for k in range(options.objects):
        object_times, object_poses = read_tum_trajectory(synth_sequence / "objects" / f"object_{k + 1}.txt")
        np.testing.assert_array_equal(object_times, plan.timestamps)
        np.testing.assert_allclose(object_poses, plan.object_poses[k], rtol=0, atol=1e-12)
    names = [line.split()[0] for line in (synth_sequence / "depth.txt").read_text().splitlines() if line[0] != "#"]
    assert names == plan.names == [f"{t:.6f}" for t in timestamps]


def test_same_seed_gives_identical_files_and_another_seed_differs(tmp_path):
    options = SynthOptions(frames=3, objects=1, width=96, height=72, seed=11)
    generate_sequence(tmp_path / "a", options)
    generate_sequence(tmp_path / "b", options)
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) == 3 * 3 + 6
    for relative in files_a:
        assert (tmp_path / "a" / relative).read_bytes() == (tmp_path / "b" / relative).read_bytes(), relative

    generate_sequence(tmp_path / "c", SynthOptions(frames=3, objects=1, width=96, height=72, seed=12))
    first = sorted((tmp_path / "a" / "rgb").iterdir())[0].name
    colour_a = cv2.imread(str(tmp_path / "a" / "rgb" / first))
    colour_c = cv2.imread(str(tmp_path / "c" / "rgb" / first))
    assert np.mean(np.abs(colour_a.astype(int) - colour_c.astype(int))) > 10
    assert (tmp_path / "a" / "groundtruth.txt").read_text() != (tmp_path / "c" / "groundtruth.txt").read_text()


def test_frames_do_not_depend_on_render_order():
    plan = build_scene_plan(SynthOptions(frames=3, objects=1, width=64, height=48, seed=2))
    forward = [SynthRenderer(plan).render(i) for i in range(3)]
    renderer = SynthRenderer(plan)
    backward = [renderer.render(i) for i in (2, 1, 0)][::-1]
    for a, b in zip(forward, backward):
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.labels, b.labels)


def test_object_texture_moves_with_the_object():
    """Translate object and camera together: the object's pixels keep their colours
    (textures are looked up in the object's frame), the room's pixels do not."""
    plan = build_scene_plan(SynthOptions(frames=2, objects=1, motion="static", width=160, height=120, seed=6))
    shift = np.eye(4)
    shift[:3, 3] = [0.06, -0.04, 0.0]
    plan.object_poses[0, 1] = shift @ plan.object_poses[0, 0]
    plan.camera_poses[1] = shift @ plan.camera_poses[0]
    renderer = SynthRenderer(plan)
    before, after = renderer.render(0, depth_noise=False, dropout=0.0), renderer.render(1, depth_noise=False, dropout=0.0)
    on_object = (before.labels == 1) & (after.labels == 1)
    assert on_object.sum() > 200
    np.testing.assert_allclose(before.depth_clean[on_object], after.depth_clean[on_object], atol=1e-5)
    difference = np.abs(before.color.astype(int) - after.color.astype(int))
    assert np.percentile(difference[on_object], 99) <= 2
    static = (before.labels == 0) & (after.labels == 0)
    assert difference[static].mean() > 10


def test_noise_free_depth_lies_on_the_true_surfaces(clean_and_noisy):
    clean, _, options = clean_and_noisy
    plan = build_scene_plan(options)
    sequence = open_sequence(clean)
    K = sequence.intrinsics
    object_pixels = np.zeros(options.objects, dtype=int)
    for index, frame in enumerate(sequence):
        labels = _read_labels(clean / "labels" / f"{frame.name}.png")
        valid = frame.depth > 0
        assert valid.mean() > 0.9  # only grazing angles and range limits remove depth
        points_camera = backproject_depth(frame.depth, K.fx, K.fy, K.cx, K.cy)
        points_world = transform_points(plan.camera_poses[index], points_camera.reshape(-1, 3)).reshape(
            points_camera.shape
        )
        for k, shape in enumerate(plan.object_shapes, start=1):
            mask = valid & (labels == k)
            object_pixels[k - 1] += mask.sum()
            local = transform_points(invert_transform(plan.object_poses[k - 1, index]), points_world[mask])
            distance = np.abs(shape.signed_distance(local))
            assert distance.size == 0 or distance.max() < 2e-3, (k, distance.max())
        static = valid & (labels == 0)
        points = points_world[static]
        nearest = np.full(len(points), np.inf)
        for shape in plan.static_shapes:
            local = transform_points(invert_transform(shape.pose), points)
            nearest = np.minimum(nearest, np.abs(shape.signed_distance(local)))
        assert nearest.max() < 2e-3, nearest.max()
        # Labels of object k cover exactly where the rendered surface belongs to it.
        assert labels.max() <= options.objects
    assert np.all(object_pixels > 50), object_pixels


def test_object_box_surface_check_can_fail(clean_and_noisy):
    """The same check with a wrong object pose puts the points well off the box."""
    clean, _, options = clean_and_noisy
    plan = build_scene_plan(options)
    frame = open_sequence(clean)[0]
    labels = _read_labels(clean / "labels" / f"{frame.name}.png")
    K = frame.intrinsics
    mask = (frame.depth > 0) & (labels == 1)
    points = transform_points(
        plan.camera_poses[0], backproject_depth(frame.depth, K.fx, K.fy, K.cx, K.cy)[mask]
    )
    wrong = plan.object_poses[0, 0].copy()
    wrong[:3, 3] += [0.0, 0.0, 0.01]
    local = transform_points(invert_transform(wrong), points)
    assert np.abs(plan.object_shapes[0].signed_distance(local)).max() > 5e-3


def test_depth_noise_follows_the_kinect_model(clean_and_noisy):
    clean, noisy, _ = clean_and_noisy
    clean_sequence, noisy_sequence = open_sequence(clean), open_sequence(noisy)
    residuals = []
    for a, b in zip(clean_sequence, noisy_sequence):
        np.testing.assert_array_equal(a.color, b.color)
        both = (a.depth > 0) & (b.depth > 0)
        assert both.sum() > 0.8 * a.depth.size
        z = a.depth[both].astype(np.float64)
        residuals.append((b.depth[both] - z) / (KINECT_SIGMA_Z_COEFFICIENT * z**2))
        labels_a = _read_labels(clean / "labels" / f"{a.name}.png")
        labels_b = _read_labels(noisy / "labels" / f"{b.name}.png")
        np.testing.assert_array_equal(labels_a, labels_b)
    normalised = np.concatenate(residuals)
    assert abs(normalised.std() - 1.0) < 0.2, normalised.std()
    assert abs(normalised.mean()) < 0.1


def test_dropouts_remove_about_the_requested_fraction():
    plan = build_scene_plan(SynthOptions(frames=2, objects=1, width=160, height=120, seed=3, dropout=0.1))
    renderer = SynthRenderer(plan)
    with_dropout = renderer.render(0)
    without = renderer.render(0, dropout=0.0)
    assert np.all(with_dropout.labels == without.labels)
    valid_before = without.depth > 0
    dropped = valid_before & (with_dropout.depth == 0)
    assert 0.09 < dropped.sum() / valid_before.sum() < 0.2
    # Systematic dropouts stay even with dropout = 0: the sensor range is 0.3 - 6 m.
    assert np.all((without.depth == 0) | ((without.depth >= 0.29) & (without.depth <= 6.01)))


def _changes(poses):
    """Frames f >= 1 whose pose differs from frame f - 1."""
    return [f for f in range(1, len(poses)) if np.abs(poses[f] - poses[f - 1]).max() > 1e-12]


def test_jump_motion_rests_then_moves_and_objects_stay_on_the_table(synth_sequence):
    options = _options_of(synth_sequence)
    plan = build_scene_plan(options)
    changes = _changes(plan.object_poses[0])
    assert changes and changes == plan.moving_frames[0]
    assert changes[0] >= min(10, options.frames // 4) and changes[0] == plan.first_motion_frames[0]
    for before, after in zip(changes, changes[1:]):
        assert after - before >= 2  # jumps, separated by rests
    for f in changes:
        step = invert_transform(plan.object_poses[0, f - 1]) @ plan.object_poses[0, f]
        assert 0.05 - 1e-9 <= np.linalg.norm(step[:2, 3]) <= 0.2 + 1e-9
        assert np.radians(10) - 1e-9 <= np.arccos(np.clip(step[0, 0], -1, 1)) <= np.radians(60) + 1e-9
    # The object is in view: labelled pixels in (almost) every frame.
    names = [line.split()[0] for line in (synth_sequence / "rgb.txt").read_text().splitlines() if line[0] != "#"]
    visible = [np.count_nonzero(_read_labels(synth_sequence / "labels" / f"{n}.png") == 1) for n in names]
    assert sum(v > 30 for v in visible) >= 0.8 * len(visible), visible
    _assert_on_table(plan)


def _footprint(shape):
    """Radius of the object's footprint for any rotation about the vertical."""
    return 0.5 * np.hypot(*shape.size[:2]) if shape.kind == "box" else 0.5 * shape.size[0]


def _assert_on_table(plan):
    for k, shape in enumerate(plan.object_shapes):
        poses = plan.object_poses[k]
        np.testing.assert_allclose(poses[:, 2, 3] - shape.size[2] / 2, TABLE_TOP, atol=1e-12)
        np.testing.assert_allclose(poses[:, :3, 2], np.tile([0.0, 0.0, 1.0], (len(poses), 1)), atol=1e-12)
        assert np.all(np.abs(poses[:, 0, 3]) + _footprint(shape) <= TABLE_SIZE[0] / 2)
        assert np.all(np.abs(poses[:, 1, 3]) + _footprint(shape) <= TABLE_SIZE[1] / 2)
    for a in range(len(plan.object_shapes)):
        for b in range(a + 1, len(plan.object_shapes)):
            gap = np.linalg.norm(plan.object_poses[a, :, :2, 3] - plan.object_poses[b, :, :2, 3], axis=1)
            reach = _footprint(plan.object_shapes[a]) + _footprint(plan.object_shapes[b])
            assert gap.min() >= reach, "objects intersect"


def test_static_motion_never_moves():
    plan = build_scene_plan(SynthOptions(frames=20, objects=2, motion="static", seed=4))
    for k in range(2):
        assert _changes(plan.object_poses[k]) == [] and plan.first_motion_frames[k] is None


@pytest.mark.parametrize("motion", ["jump", "smooth"])
def test_simultaneous_and_separate_moves(motion):
    together = build_scene_plan(SynthOptions(frames=20, objects=2, motion=motion, simultaneous=True, seed=1))
    shared = set(_changes(together.object_poses[0])) & set(_changes(together.object_poses[1]))
    assert shared, "simultaneous objects never moved in the same frame"
    _assert_on_table(together)

    apart = build_scene_plan(SynthOptions(frames=20, objects=2, motion=motion, simultaneous=False, seed=1))
    first, second = _changes(apart.object_poses[0]), _changes(apart.object_poses[1])
    assert first and second
    assert not set(first) & set(second)
    assert min(second) > min(first)
    # Object 2 starts after object 1 has come to rest again.
    assert min(second) > max(f for f in first if f < min(second)) + 1
    _assert_on_table(apart)


def test_smooth_motion_is_continuous():
    plan = build_scene_plan(SynthOptions(frames=40, objects=1, motion="smooth", seed=0))
    changes = _changes(plan.object_poses[0])
    runs = np.split(np.array(changes), np.flatnonzero(np.diff(changes) > 1) + 1)
    assert len(runs) >= 2 and all(len(run) >= 3 for run in runs)
    steps = np.linalg.norm(np.diff(plan.object_poses[0, :, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.1
    assert changes[0] >= 10


def test_camera_is_hand_held_and_looks_at_the_table():
    plan = build_scene_plan(SynthOptions(frames=60, objects=1, seed=0))
    centres = plan.camera_poses[:, :3, 3]
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert steps.max() < 0.08 and steps.min() > 0.0
    table_in_camera = np.einsum("nji,nj->ni", plan.camera_poses[:, :3, :3], [0.0, 0.0, TABLE_TOP] - centres)
    distance = np.linalg.norm(table_in_camera, axis=1)
    assert np.all((distance > 1.0) & (distance < 3.0))
    assert np.all(table_in_camera[:, 2] / distance > np.cos(np.radians(15)))  # table near the image centre


def test_overwrite_protection_and_cleanup(tmp_path):
    out = tmp_path / "seq"
    small = dict(objects=1, width=64, height=48, seed=0)
    generate_sequence(out, SynthOptions(frames=4, **small))
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="--overwrite"):
        generate_sequence(out, SynthOptions(frames=2, **small))
    calls = []
    summary = generate_sequence(out, SynthOptions(frames=2, **small), overwrite=True, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 2), (2, 2)]
    assert (out / "notes.txt").read_text() == "mine"
    assert len(list((out / "rgb").iterdir())) == 2 and len(list((out / "depth").iterdir())) == 2
    assert len(list((out / "labels").iterdir())) == 2
    assert len(open_sequence(out)) == 2
    json.dumps(summary)
    assert summary["frames"] == 2 and summary["first_motion_frame"] == [1]
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError):
        generate_sequence(tmp_path / "file", SynthOptions(frames=2, **small))


def test_jpg_colour_and_static_scene(tmp_path):
    generate_sequence(tmp_path, SynthOptions(frames=2, objects=0, width=64, height=48, image_format="jpg"))
    sequence = open_sequence(tmp_path)
    assert sequence[0].color_path.suffix == ".jpg" and len(sequence) == 2
    assert not (tmp_path / "objects").exists() or not any((tmp_path / "objects").iterdir())
    assert not np.any(_read_labels(tmp_path / "labels" / f"{sequence[0].name}.png"))


@pytest.mark.parametrize(
    "changes",
    [
        dict(frames=1),
        dict(objects=-1),
        dict(objects=50),
        dict(motion="teleport"),
        dict(width=8),
        dict(height=10),
        dict(dropout=1.5),
        dict(dropout=-0.1),
        dict(fps=0.0),
        dict(fps=1e7),
        dict(seed=-1),
        dict(image_format="bmp"),
        dict(frames=2.5),
    ],
)
def test_invalid_options_raise_input_error(tmp_path, changes):
    with pytest.raises(InputError):
        generate_sequence(tmp_path / "out", SynthOptions(**changes))
    assert not (tmp_path / "out").exists()
