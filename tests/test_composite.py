"""Composites (jsr synth --background): depth test, labels against object poses, objects resting
on the background's surface, determinism, and errors for a background that cannot be used.

Most tests use a tiny fake background written here: a floor (z = 0, world z up) and a wall
(y = 1.2), seen by a camera with lens distortion moving at constant velocity, so that its pose at
any time is known exactly; colour and depth timestamps differ by 8 ms, as on real sensors.
"""

import dataclasses
import math

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from jsr.cli import app
from jsr.errors import InputError, OutputError
from jsr.geometry import invert_transform, look_at, make_transform, rotation_about_axis, transform_points
from jsr.io.camera import CameraIntrinsics, load_camera_yaml, write_camera_yaml
from jsr.io.dataset import open_sequence
from jsr.io.trajectory import interpolate_poses, read_tum_trajectory, write_tum_trajectory
from jsr.synth.background import open_background
from jsr.synth.composite import Compositor, build_composite_plan, generate_composite
from jsr.synth.options import CompositeOptions
from jsr.synth.scene import Shape, footprint_radius
from jsr.synth.support import BackgroundViews

runner = CliRunner()

WIDTH, HEIGHT = 160, 120
INTRINSICS = CameraIntrinsics(140.0, 140.0, 79.5, 59.5, WIDTH, HEIGHT, 5000.0, (0.05, -0.04, 0.0, 0.0, 0.0))
WALL_Y = 1.2
COLOUR_T0, FPS, DEPTH_DELAY = 100.0, 30.0, 0.008


def camera_pose(time: float) -> np.ndarray:
    """``T_w_c`` of the fake background's camera: constant velocity and turn rate."""
    elapsed = time - COLOUR_T0
    start = look_at(np.array([0.0, -1.5, 1.1]), np.array([0.0, 0.2, 0.0]))
    turn = rotation_about_axis(np.array([0.0, 0.0, 1.0]), 0.15 * elapsed)
    return make_transform(turn @ start[:3, :3], start[:3, 3] + np.array([0.3, 0.1, 0.0]) * elapsed)


def ideal_rays() -> np.ndarray:
    """``(H, W, 3)`` camera rays (z = 1) through the pixels of ``INTRINSICS``, distortion undone
    with OpenCV directly (independent of the code under test)."""
    u, v = np.meshgrid(np.arange(WIDTH, dtype=float), np.arange(HEIGHT, dtype=float))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    normalised = cv2.undistortPoints(pixels, INTRINSICS.matrix, INTRINSICS.distortion_coefficients).reshape(-1, 2)
    return np.column_stack([normalised, np.ones(len(normalised))]).reshape(HEIGHT, WIDTH, 3)


def fake_depth(T_w_c: np.ndarray) -> np.ndarray:
    """``(H, W)`` metres of the floor and the wall seen from ``T_w_c``."""
    directions = ideal_rays() @ T_w_c[:3, :3].T
    origin = T_w_c[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        floor = np.where(directions[..., 2] < 0, -origin[2] / directions[..., 2], np.inf)
        wall = np.where(directions[..., 1] > 0, (WALL_Y - origin[1]) / directions[..., 1], np.inf)
    depth = np.minimum(floor, wall)
    return np.where(np.isfinite(depth), depth, 0.0)


def write_fake_background(root, frames=10, ground_truth=True, camera=True):
    """A TUM-layout background folder; returns it."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    rgb_lines, depth_lines = ["# timestamp filename"], ["# timestamp filename"]
    for i in range(frames):
        colour_time = COLOUR_T0 + i / FPS
        depth_time = colour_time + DEPTH_DELAY
        colour = cv2.GaussianBlur(rng.integers(60, 200, (HEIGHT, WIDTH, 3)).astype(np.uint8), (0, 0), 1.0)
        cv2.imwrite(str(root / "rgb" / f"{colour_time:.6f}.png"), colour)
        depth = np.round(fake_depth(camera_pose(depth_time)) * 5000.0).astype(np.uint16)
        cv2.imwrite(str(root / "depth" / f"{depth_time:.6f}.png"), depth)
        rgb_lines.append(f"{colour_time:.6f} rgb/{colour_time:.6f}.png")
        depth_lines.append(f"{depth_time:.6f} depth/{depth_time:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if ground_truth:  # sampled at its own times, as a motion-capture system does
        times = COLOUR_T0 - 1.0 / FPS + 0.004 + np.arange(frames + 2) / FPS
        write_tum_trajectory(root / "groundtruth.txt", times, np.stack([camera_pose(t) for t in times]))
    if camera:
        write_camera_yaml(root / "camera.yaml", INTRINSICS)
    return root


@pytest.fixture(scope="module")
def background(tmp_path_factory):
    return write_fake_background(tmp_path_factory.mktemp("composite") / "background")


def _options(background, **changes):
    values = dict(background=str(background), frames=10, objects=2, motion="jump", seed=3, period=3)
    values.update(changes)
    return CompositeOptions(**values)


@pytest.fixture(scope="module")
def clean_composite(background, tmp_path_factory):
    """Two objects jumping, without depth noise or dropouts."""
    out = tmp_path_factory.mktemp("composite") / "clean"
    generate_composite(out, _options(background, depth_noise=False, dropout=0.0))
    return out


def _labels(root, name):
    return cv2.imread(str(root / "labels" / f"{name}.png"), cv2.IMREAD_UNCHANGED)


def _shapes(root):
    objects = yaml.safe_load((root / "synth.yaml").read_text())["objects"]
    return [Shape(f"object {o['id']}", o["shape"], tuple(o["size"]), np.eye(4), o["id"], 0.0025, "object", 0)
            for o in objects]


def test_composite_is_a_sequence_like_synth_writes(clean_composite, background):
    sequence = open_sequence(clean_composite)
    source = open_sequence(background)
    assert len(sequence) == 10
    assert [entry.depth_path.name for entry in sequence.entries] == [e.depth_path.name for e in source.entries]
    assert sequence.intrinsics == load_camera_yaml(background / "camera.yaml")  # distortion kept
    times, poses = read_tum_trajectory(clean_composite / "groundtruth.txt")
    np.testing.assert_allclose(times, source.timestamps)
    for time, pose in zip(times, poses):  # the camera at each colour timestamp
        np.testing.assert_allclose(pose, camera_pose(time), atol=1e-6)
    metadata = yaml.safe_load((clean_composite / "synth.yaml").read_text())
    assert metadata["generator"] == "jsr synth --background" and metadata["version"]
    assert metadata["options"]["seed"] == 3 and metadata["background"]["frames"] == 10
    assert len(metadata["objects"]) == 2 and all(o["moving_frames"] for o in metadata["objects"])
    for record in metadata["objects"]:
        assert record["frames_in_view"] >= 8 and set(record["moving_frames_in_view"]) <= set(record["moving_frames"])
    for k in (1, 2):
        object_times, _ = read_tum_trajectory(clean_composite / "objects" / f"object_{k}.txt")
        np.testing.assert_array_equal(object_times, times)
    seen = [np.unique(_labels(clean_composite, frame.name)) for frame in sequence]
    assert all(set(values) <= {0, 1, 2} for values in seen)
    assert sum(1 in values for values in seen) >= 8 and sum(2 in values for values in seen) >= 8


def test_object_pixels_only_where_the_object_is_nearer(clean_composite, background):
    composite, source = open_sequence(clean_composite), open_sequence(background)
    object_pixels = colour_only = 0
    for mixed, real in zip(composite, source):
        labels = _labels(clean_composite, mixed.name)
        static = labels == 0
        np.testing.assert_array_equal(mixed.depth[static], real.depth[static])  # the real scene untouched
        # Colour is rendered from the camera at the colour timestamp (8 ms earlier): away from
        # the labels by more than that motion, the real colour is untouched.
        near = cv2.dilate((labels > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        np.testing.assert_array_equal(mixed.color[~near], real.color[~near])
        colour_only += np.count_nonzero(np.any(mixed.color[near & static] != real.color[near & static], axis=1))
        on_object = labels > 0
        object_pixels += on_object.sum()
        # Nearer (equal after the 0.2 mm quantisation only where the object touches the floor).
        assert np.all(mixed.depth[on_object] <= real.depth[on_object])
        assert np.mean(mixed.depth[on_object] < real.depth[on_object] - 0.01) > 0.8
        assert np.any(mixed.color[on_object] != real.color[on_object])
    assert object_pixels > 500 and colour_only > 0


def test_nearer_real_surfaces_hide_objects_and_holes_do_not(background, tmp_path):
    plan = build_composite_plan(_options(background, depth_noise=False, dropout=0.0))
    before = Compositor(plan).composite(0)
    rows, cols = np.nonzero(before.labels > 0)
    assert len(rows) > 100
    middle = int(np.median(cols))
    # The same frame with a real thing 0.5 m from the camera over the left half of the object,
    # and no real depth over the right half.
    depth = cv2.imread(str(plan.background.frames[0].depth_path), cv2.IMREAD_UNCHANGED)
    top, bottom = rows.min() - 3, rows.max() + 4
    depth[top:bottom, cols.min() - 3 : middle] = 2500
    depth[top:bottom, middle + 4 : cols.max() + 4] = 0
    changed = tmp_path / "depth.png"
    cv2.imwrite(str(changed), depth)
    frames = [dataclasses.replace(plan.background.frames[0], depth_path=changed), *plan.background.frames[1:]]
    plan.background = dataclasses.replace(plan.background, frames=frames)
    after = Compositor(plan).composite(0)
    left, right = np.zeros_like(after.labels, dtype=bool), np.zeros_like(after.labels, dtype=bool)
    left[:, : middle] = True
    right[:, middle + 4 :] = True
    assert not np.any(after.labels[left]) and np.all(after.depth[left & (before.labels > 0)] == 2500)
    np.testing.assert_array_equal(after.labels[right], before.labels[right])
    was_object = right & (before.labels > 0)
    np.testing.assert_array_equal(after.depth[was_object], before.depth[was_object])


def test_labelled_pixels_lie_on_the_object_at_its_pose(clean_composite):
    """Back-projected with the true camera (at the depth timestamp), every labelled pixel lies on
    its object's surface at the pose in objects/ (depth quantisation: 0.2 mm)."""
    shapes = _shapes(clean_composite)
    poses = [read_tum_trajectory(clean_composite / "objects" / f"object_{k}.txt")[1] for k in (1, 2)]
    rays = ideal_rays()
    checked = 0
    for index, frame in enumerate(open_sequence(clean_composite)):
        labels = _labels(clean_composite, frame.name)
        T_w_c = camera_pose(float(frame.depth_path.stem))
        for k, shape in enumerate(shapes):
            mask = (labels == k + 1) & (frame.depth > 0)
            world = transform_points(T_w_c, rays[mask] * frame.depth[mask, None])
            local = transform_points(invert_transform(poses[k][index]), world)
            assert len(local) == 0 or np.abs(shape.signed_distance(local)).max() < 2e-3
            checked += len(local)
            # The wrong object's pose does not fit: the check can fail.
            other = transform_points(invert_transform(poses[1 - k][index]), world)
            assert len(local) < 20 or np.median(np.abs(shapes[1 - k].signed_distance(other))) > 0.02
    assert checked > 500


def test_objects_rest_on_the_floor_apart(clean_composite):
    shapes = _shapes(clean_composite)
    poses = np.stack([read_tum_trajectory(clean_composite / "objects" / f"object_{k}.txt")[1] for k in (1, 2)])
    for k, shape in enumerate(shapes):
        # Upright on the floor z = 0: centre half a height up, local z along world z.
        np.testing.assert_allclose(poses[k, :, 2, 3], shape.size[2] / 2, atol=4e-3)
        assert np.all(poses[k, :, 2, 2] > math.cos(math.radians(1.0)))
        assert np.all(poses[k, :, 1, 3] < WALL_Y - footprint_radius(shape))  # not in the wall
    gaps = np.linalg.norm(poses[0, :, :2, 3] - poses[1, :, :2, 3], axis=1)
    assert np.all(gaps >= footprint_radius(shapes[0]) + footprint_radius(shapes[1]))
    moved = np.linalg.norm(np.diff(poses[:, :, :3, 3], axis=1), axis=2) > 0.04
    assert moved.any(axis=1).all()  # both jump


def test_same_seed_gives_identical_files(background, tmp_path):
    options = _options(background, frames=4, objects=1, seed=5)
    generate_composite(tmp_path / "a", options)
    generate_composite(tmp_path / "b", options)
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert len(files) == 4 * 3 + 6
    for relative in files:
        assert (tmp_path / "a" / relative).read_bytes() == (tmp_path / "b" / relative).read_bytes(), relative
    generate_composite(tmp_path / "c", dataclasses.replace(options, seed=6))
    assert (tmp_path / "a" / "objects" / "object_1.txt").read_text() != (
        tmp_path / "c" / "objects" / "object_1.txt"
    ).read_text()


def test_ground_truth_is_interpolated_between_its_samples():
    times = np.array([0.0, 1.0, 2.0])
    poses = np.stack([camera_pose(COLOUR_T0 + t) for t in times])
    query = np.array([0.25, 1.5, 2.02])  # the last one just past the end: extrapolated
    result = interpolate_poses(times, poses, query)
    for time, pose in zip(query, result):
        np.testing.assert_allclose(pose, camera_pose(COLOUR_T0 + time), atol=1e-9)


def test_places_outside_the_field_of_view_are_not_visible_through_the_distortion(background):
    """OpenCV's distortion polynomial folds points far outside the view back into the image;
    such a place must not count as visible (objects had been placed out of view so)."""
    loaded = open_background(background, 0, 2)
    views = BackgroundViews(loaded, 4, np.full((2, HEIGHT // 4, WIDTH // 4), np.inf, np.float32))
    inside_camera = np.array([[0.1, 0.05, 1.5]])
    outside_camera = np.array([[2.3 * 1.5, 0.0, 1.5]])  # 66 degrees off the axis, the image spans 30
    folded, _ = cv2.projectPoints(outside_camera, np.zeros(3), np.zeros(3), INTRINSICS.matrix,
                                  INTRINSICS.distortion_coefficients)
    assert 0 <= folded[0, 0, 0] < WIDTH and 0 <= folded[0, 0, 1] < HEIGHT  # what made the check needed
    T_w_c = loaded.depth_poses[0]
    assert views.visible(transform_points(T_w_c, inside_camera), 0)[0]
    assert not views.visible(transform_points(T_w_c, outside_camera), 0)[0]


@pytest.mark.parametrize(
    "broken, message",
    [
        ("no_ground_truth", "has no groundtruth.txt"),
        ("no_camera", "has no camera.yaml"),
        ("short_ground_truth", "has no ground-truth pose near it"),
        ("not_tum", "has no rgb.txt"),
    ],
)
def test_a_background_that_cannot_be_used_is_one_error_line(tmp_path, broken, message):
    root = write_fake_background(
        tmp_path / "bg", frames=4, ground_truth=broken != "no_ground_truth", camera=broken != "no_camera"
    )
    if broken == "short_ground_truth":
        times, poses = read_tum_trajectory(root / "groundtruth.txt")
        write_tum_trajectory(root / "groundtruth.txt", times[:3], poses[:3])
    if broken == "not_tum":
        (root / "rgb.txt").unlink()
    with pytest.raises(InputError, match=message):
        open_background(root, 0, 4)
    result = runner.invoke(app, ["synth", str(tmp_path / "out"), "--background", str(root), "--frames", "4"])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert lines[-1].startswith("error:") and message in result.output.replace("\n", " ")
    assert not (tmp_path / "out").exists()


def test_cli_rejects_options_that_do_not_fit_a_background(background, tmp_path):
    for arguments, message in (
        (["--frames", "11"], "needs 11 frames"),
        (["--width", "320"], "cannot be used with --background"),
        (["--period", "1"], "--period must be >= 2"),
    ):
        result = runner.invoke(app, ["synth", str(tmp_path / "out"), "--background", str(background), *arguments])
        assert result.exit_code == 2 and message in result.output.replace("\n", " "), result.output
    result = runner.invoke(app, ["synth", str(tmp_path / "out"), "--start", "3"])
    assert result.exit_code == 2 and "--start needs --background" in result.output
    with pytest.raises(OutputError, match="inside the background"):
        generate_composite(background / "out", _options(background))


@pytest.mark.real
def test_real_background_objects_stand_on_its_floor(shared_data, tmp_path):
    """On redkitchen300, the real depth around an object's footprint is the surface it stands
    on (within the sensor noise and the ground truth's error), and the objects are seen."""
    out = tmp_path / "kitchen"
    generate_composite(out, CompositeOptions(str(shared_data / "redkitchen300"), frames=16, objects=2, seed=2, period=5))
    metadata = yaml.safe_load((out / "synth.yaml").read_text())
    T_s_w = invert_transform(np.array(metadata["surface"]["T_w_s"]))
    sequence = open_sequence(out)
    rays = sequence.intrinsics  # pinhole: redkitchen has no distortion
    times, cameras = read_tum_trajectory(out / "groundtruth.txt")
    poses = [read_tum_trajectory(out / "objects" / f"object_{k}.txt")[1] for k in (1, 2)]
    shapes = _shapes(out)
    heights, seen = [], 0
    for index, frame in enumerate(sequence):
        labels = _labels(out, frame.name)
        seen += int(np.count_nonzero(labels == 1) > 100) + int(np.count_nonzero(labels == 2) > 100)
        v, u = np.nonzero((labels == 0) & (frame.depth > 0))
        z = frame.depth[v, u]
        camera_points = np.column_stack([(u - rays.cx) / rays.fx * z, (v - rays.cy) / rays.fy * z, z])
        local = transform_points(T_s_w @ cameras[index], camera_points)
        for k, shape in enumerate(shapes):
            centre = transform_points(T_s_w, poses[k][index][:3, 3][None])[0]
            radius = footprint_radius(shape)
            ring = np.linalg.norm(local[:, :2] - centre[:2], axis=1)
            near = (ring > radius) & (ring < radius + 0.08) & (np.abs(local[:, 2]) < 0.1)
            if np.count_nonzero(near) > 50:
                heights.append(np.median(local[near, 2]))
    assert seen >= 0.8 * 2 * len(sequence)
    assert len(heights) > 10 and np.max(np.abs(heights)) < 0.015, heights
