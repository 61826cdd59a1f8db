"""Bundle adjustment on hand-built maps of a synthetic scene (no image pipeline involved)."""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from jsr.config import BundleAdjustmentConfig, NoiseConfig
from jsr.geometry import (
    KINECT_SIGMA_Z_COEFFICIENT,
    backproject_pixels,
    invert_transform,
    look_at,
    make_transform,
    rotation_angle,
    transform_points,
)
from jsr.pipeline.bundle import BundleProblem, bundle_adjust
from jsr.pipeline.bundle_solution import apply_solution
from jsr.pipeline.bundle_jacobian import jacobian_sparsity
from jsr.pipeline.bundle_noise import BOUNDS, GROUPS, update
from jsr.pipeline.bundle_scheduler import BundleScheduler
from jsr.geometry import transform_planes
from jsr.pipeline.maps import Keyframe, Map, ObjectMap
from jsr.pipeline.robust_loss import huber_loss

FX = FY = 525.0
CX, CY = 319.5, 239.5
WIDTH, HEIGHT = 640, 480
K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
NOISE = NoiseConfig()

# world: z up; floor z = 0, back wall y = 1, side wall x = -1 (normals towards the cameras)
WORLD_PLANES = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 1.0]])


@dataclass
class Observation:
    landmarks: np.ndarray  # (K,) true landmark indices
    camera_points: np.ndarray  # (K, 3), NaN rows for 2D observations
    pixels: np.ndarray
    sigma_z: np.ndarray
    camera_planes: np.ndarray  # (P, 4), one per WORLD_PLANES row


@dataclass
class Scene:
    poses: np.ndarray  # (N, 4, 4) true T_map_cam
    landmarks: np.ndarray  # (L, 3) true positions
    planes: np.ndarray  # (P, 4)
    observations: list[Observation]


def make_scene(rng, keyframes=8, landmarks=300, fraction_2d=0.15, arc_degrees=40.0, max_per_keyframe=None,
               planes=3, depth_noise=1.0):
    """Cameras on an arc 2.5 m from the scene, landmarks on the floor, the back wall and in between.
    Keypoints are 0.5 px off; depths ``depth_noise`` times the sensor's sigma_Z (which the
    observations state as their sigma either way)."""
    angles = np.radians(np.linspace(-arc_degrees / 2, arc_degrees / 2, keyframes))
    poses = []
    for angle in angles:
        eye = np.array([2.5 * np.sin(angle), -2.5 * np.cos(angle), 0.8]) + rng.normal(0, 0.02, 3)
        poses.append(look_at(eye, np.array([0.0, 0.3, 0.4]) + rng.normal(0, 0.05, 3)))
    poses = np.stack(poses)
    third = landmarks // 3
    floor = np.column_stack([rng.uniform(-1, 1, third), rng.uniform(-0.6, 1, third), np.zeros(third)])
    wall = np.column_stack([rng.uniform(-1, 1, third), np.ones(third), rng.uniform(0, 1.2, third)])
    rest = landmarks - 2 * third
    volume = np.column_stack([rng.uniform(-0.8, 0.8, rest), rng.uniform(-0.5, 0.8, rest), rng.uniform(0.1, 1.0, rest)])
    points = np.vstack([floor, wall, volume])
    world_planes = WORLD_PLANES[:planes]

    observations = []
    for pose in poses:
        local = transform_points(invert_transform(pose), points)
        z = local[:, 2]
        u = FX * local[:, 0] / z + CX
        v = FY * local[:, 1] / z + CY
        visible = np.flatnonzero((z > 0.3) & (u >= 0) & (u < WIDTH) & (v >= 0) & (v < HEIGHT))
        if max_per_keyframe is not None and len(visible) > max_per_keyframe:
            visible = np.sort(rng.choice(visible, max_per_keyframe, replace=False))
        pixels = np.column_stack([u[visible], v[visible]]) + rng.normal(0, 0.5, (len(visible), 2))
        sigma_z = KINECT_SIGMA_Z_COEFFICIENT * z[visible] ** 2
        depth = z[visible] + rng.normal(0, 1, len(visible)) * sigma_z * depth_noise
        camera_points = backproject_pixels(pixels[:, 0], pixels[:, 1], depth, FX, FY, CX, CY)
        is_2d = rng.random(len(visible)) < fraction_2d
        camera_points[is_2d] = np.nan
        sigma_z[is_2d] = 0.0
        camera_planes = transform_planes(invert_transform(pose), world_planes)
        camera_planes[camera_planes[:, 3] < 0] *= -1.0  # normals towards the camera
        tilt = Rotation.from_rotvec(rng.normal(0, np.radians(0.2), (len(camera_planes), 3))).as_matrix()
        camera_planes[:, :3] = np.einsum("qij,qj->qi", tilt, camera_planes[:, :3])
        camera_planes[:, 3] += rng.normal(0, 0.002, len(camera_planes))
        observations.append(Observation(visible, camera_points, pixels, sigma_z, camera_planes))
    # every landmark needs a 3D observation somewhere (in the pipeline 3D measurements create them):
    # give the first observation of a landmark seen only in 2D its depth back
    has_3d = np.zeros(len(points), dtype=bool)
    for o in observations:
        has_3d[o.landmarks[~np.isnan(o.camera_points[:, 0])]] = True
    for k, o in enumerate(observations):
        rows = np.flatnonzero(~has_3d[o.landmarks])
        if len(rows):
            local = transform_points(invert_transform(poses[k]), points[o.landmarks[rows]])
            o.camera_points[rows] = local
            o.sigma_z[rows] = KINECT_SIGMA_Z_COEFFICIENT * local[:, 2] ** 2
            has_3d[o.landmarks[rows]] = True
    return Scene(poses, points, world_planes, observations)


def perturb_poses(rng, poses, translation=0.02, degrees=1.0):
    """Every pose but the first moved by ``translation`` metres and rotated by ``degrees``."""
    perturbed = poses.copy()
    for k in range(1, len(poses)):
        axis = rng.normal(size=3)
        direction = rng.normal(size=3)
        rotation = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(degrees)).as_matrix()
        perturbed[k, :3, :3] = rotation @ poses[k, :3, :3]
        perturbed[k, :3, 3] += translation * direction / np.linalg.norm(direction)
    return perturbed


def perturb_planes(rng, planes, degrees=1.0, offset=0.01):
    out = planes.copy()
    rotvec = rng.normal(size=(len(planes), 3))
    rotvec *= np.radians(degrees) / np.linalg.norm(rotvec, axis=1, keepdims=True)
    out[:, :3] = Rotation.from_rotvec(rotvec).apply(planes[:, :3])
    out[:, 3] += offset * rng.choice([-1.0, 1.0], len(planes))
    return out


def keyframe_of(scene, k, pose, landmark_ids):
    o = scene.observations[k]
    return Keyframe(
        keyframe_id=k, frame_index=10 * k, timestamp=float(k), T_map_cam=pose.copy(),
        point_measurements=np.arange(len(o.landmarks)), point_landmarks=landmark_ids[o.landmarks],
        camera_points=o.camera_points.copy(), pixels=o.pixels.copy(), sigma_z=o.sigma_z.copy(),
        plane_landmarks=np.arange(len(o.camera_planes)), camera_planes=o.camera_planes.copy(),
    )


def build_map(scene, rng, perturb=True):
    """All landmarks first (in id order), then the keyframes; poses/landmarks/planes perturbed."""
    poses = perturb_poses(rng, scene.poses) if perturb else scene.poses.copy()
    positions = scene.landmarks + (rng.normal(0, 0.01, scene.landmarks.shape) if perturb else 0.0)
    planes = perturb_planes(rng, scene.planes) if perturb else scene.planes.copy()
    the_map = Map("static")
    count = len(positions)
    ids = the_map.points.add(positions, np.zeros((count, 128), np.float32), np.full(count, 0.005),
                             np.zeros((count, 3), np.uint8))
    the_map.planes.add(planes, np.zeros((len(planes), 3)), np.full(len(planes), 1000.0))
    for k in range(len(scene.poses)):
        the_map.keyframes.append(keyframe_of(scene, k, poses[k], ids))
    return the_map


def pose_errors(the_map, scene):
    """Translation (m) and rotation (deg) errors of every keyframe relative to the first one."""
    estimated = invert_transform(the_map.keyframes[0].T_map_cam) @ the_map.keyframe_poses
    truth = invert_transform(scene.poses[0]) @ scene.poses
    error = invert_transform(truth) @ estimated
    return np.linalg.norm(error[:, :3, 3], axis=1), np.degrees(rotation_angle(error[:, :3, :3]))


def landmark_rmse(the_map, scene):
    return float(np.sqrt(np.mean(np.sum((the_map.points.positions - scene.landmarks) ** 2, axis=1))))


def plane_errors(the_map, scene):
    """Normal angle (deg) and offset (m) errors of the plane landmarks."""
    planes = the_map.planes.planes
    cosine = np.clip(np.sum(planes[:, :3] * scene.planes[:, :3], axis=1), -1, 1)
    return np.degrees(np.arccos(cosine)), planes[:, 3] - scene.planes[:, 3]


def snapshot(the_map):
    return (the_map.keyframe_poses.copy(), the_map.points.positions.copy(), the_map.planes.planes.copy(),
            the_map.planes.centroids.copy())


def assert_same_state(a, b):
    for x, y in zip(snapshot(a), snapshot(b)):
        assert x.shape == y.shape and np.array_equal(x, y)


# ---------------------------------------------------------------------------------------------


def test_bundle_adjustment_reduces_pose_and_landmark_errors():
    rng = np.random.default_rng(1)
    scene = make_scene(rng, keyframes=8, landmarks=300)
    scene.observations[2].camera_planes[1] *= -1.0  # same plane seen with the opposite orientation
    the_map = build_map(scene, rng)
    first_pose = the_map.keyframes[0].T_map_cam.copy()
    translation_before, rotation_before = pose_errors(the_map, scene)
    rmse_before = landmark_rmse(the_map, scene)
    normal_before, offset_before = plane_errors(the_map, scene)

    result = bundle_adjust(the_map, BundleAdjustmentConfig(enabled=True), NOISE, K)

    translation_after, rotation_after = pose_errors(the_map, scene)
    rmse_after = landmark_rmse(the_map, scene)
    assert result.success, result.message
    assert result.final_cost < result.initial_cost
    assert result.keyframes_optimised == 7 and result.keyframes_fixed == 1
    assert result.landmarks_optimised == 300 and result.planes_optimised == 3
    assert np.array_equal(the_map.keyframes[0].T_map_cam, first_pose)
    # >= 3x smaller pose errors (relative to the fixed first keyframe), landmarks closer
    assert translation_after[1:].max() * 3 <= translation_before[1:].min()
    assert rotation_after[1:].max() * 3 <= rotation_before[1:].min()
    assert rmse_after < 0.5 * rmse_before
    # planes moved back towards the truth
    normal_after, offset_after = plane_errors(the_map, scene)
    assert normal_after.max() * 3 < normal_before.min()
    assert np.sqrt(np.mean(offset_after**2)) < 0.6 * np.sqrt(np.mean(offset_before**2))
    # every plane observation agrees with its landmark afterwards, the flipped one included
    problem = BundleProblem.from_map(the_map, BundleAdjustmentConfig(enabled=True), NOISE, K)
    plane_rows = 3 * len(problem.obs3_keyframe) + 2 * len(problem.obs2_keyframe)
    assert np.abs(problem.residuals(np.zeros(problem.num_parameters))[plane_rows:]).max() < 3.0
    # centroids were moved onto the refined planes
    planes = the_map.planes.planes
    assert np.allclose(np.sum(the_map.planes.centroids * planes[:, :3], 1) + planes[:, 3], 0, atol=1e-12)
    # refined rotations stay rotations
    rotations = the_map.keyframe_poses[:, :3, :3]
    assert np.allclose(rotations @ np.swapaxes(rotations, 1, 2), np.eye(3), atol=1e-10)


def test_two_dimensional_observations_constrain_the_pose():
    """A keyframe observing landmarks only through 2D points is still corrected."""
    rng = np.random.default_rng(2)
    scene = make_scene(rng, keyframes=6, landmarks=300, fraction_2d=0.1, planes=0)
    o = scene.observations[3]
    o.camera_points[:] = np.nan  # keyframe 3 has no depth at all
    o.sigma_z[:] = 0.0
    the_map = build_map(scene, rng)
    before, _ = pose_errors(the_map, scene)
    result = bundle_adjust(the_map, BundleAdjustmentConfig(enabled=True), NOISE, K)
    after, _ = pose_errors(the_map, scene)
    assert result.success
    assert after[3] * 3 < before[3]


def test_window_holds_older_keyframes_fixed():
    rng = np.random.default_rng(3)
    scene = make_scene(rng, keyframes=8, landmarks=300, planes=0)
    the_map = build_map(scene, rng)
    before = the_map.keyframe_poses.copy()
    result = bundle_adjust(the_map, BundleAdjustmentConfig(enabled=True), NOISE, K, window=3)
    after = the_map.keyframe_poses
    window_landmarks = np.unique(np.concatenate([o.landmarks for o in scene.observations[5:]]))
    assert result.keyframes_optimised == 3 and result.landmarks_optimised == len(window_landmarks)
    assert result.keyframes_fixed == 5  # all older keyframes observe landmarks of the window
    assert result.observations == sum(np.isin(o.landmarks, window_landmarks).sum() for o in scene.observations)
    assert np.array_equal(before[:5], after[:5])
    assert not np.allclose(before[5:], after[5:])


def island_map(rng, shared: int, clustered: bool = False):
    """8 keyframes (no planes) whose last 3 observe their own copies of the landmarks, but for
    ``shared`` landmarks they keep in common with the first 5: a group of keyframes that a jump
    of an object left tied to the rest of its map by a few landmarks. ``clustered``: those
    nearest to one landmark, else any."""
    scene = make_scene(rng, keyframes=8, landmarks=300, planes=0)
    the_map = build_map(scene, rng)
    count = len(scene.landmarks)
    copies = the_map.points.add(scene.landmarks.copy(), np.zeros((count, 128), np.float32), np.full(count, 0.005),
                                np.zeros((count, 3), np.uint8))
    early = np.unique(np.concatenate([o.landmarks for o in scene.observations[:5]]))
    late = np.unique(np.concatenate([o.landmarks for o in scene.observations[5:]]))
    kept = np.intersect1d(early, late)
    if clustered:
        kept = kept[np.argsort(np.linalg.norm(scene.landmarks[kept] - scene.landmarks[kept[0]], axis=1))]
    kept = kept[:shared]
    for keyframe in the_map.keyframes[5:]:
        island = ~np.isin(keyframe.point_landmarks, kept)
        keyframe.point_landmarks = np.where(island, copies[keyframe.point_landmarks], keyframe.point_landmarks)
    return the_map


@pytest.mark.parametrize("shared, island_pinned", [(1, True), (2, True), (3, False), (20, False)])
def test_a_group_of_free_keyframes_barely_tied_to_the_rest_keeps_its_oldest_fixed(shared, island_pinned):
    the_map = island_map(np.random.default_rng(4), shared)
    config = BundleAdjustmentConfig(enabled=True, min_shared_landmarks=3, link_max_spread=0.0)  # by the count
    problem = BundleProblem.from_map(the_map, config, NOISE, K, window=4)
    free = {int(k): int(slot) >= 0 for k, slot in zip(problem.keyframe_indices, problem.free_index)}
    assert free[4] and free[6] and free[7]  # keyframe 4 shares hundreds with the fixed ones
    assert free[5] is not island_pinned
    # with min_shared_landmarks 1 and no pinning test, one common landmark links
    lenient = BundleProblem.from_map(the_map, replace(config, min_shared_landmarks=1, link_max_spread=0.0), NOISE, K,
                                     window=4)
    assert np.all(lenient.free_index[np.isin(lenient.keyframe_indices, [4, 5, 6, 7])] >= 0)
    # the pinned group is still adjusted within itself
    before = the_map.keyframe_poses.copy()
    result = bundle_adjust(the_map, config, NOISE, K, window=4)
    after = the_map.keyframe_poses
    assert result.success and result.keyframes_fixed == 4 + int(island_pinned)
    assert bool(np.array_equal(before[5], after[5])) is island_pinned
    assert not np.allclose(before[6:], after[6:])


def test_shared_landmarks_link_keyframes_only_where_they_pin_them():
    """3 landmarks spread over the scene (1.8 m) link the island to the rest; the 3 nearest to
    one landmark (a patch of 11 cm, which hardly holds the turns about it) do not: its oldest
    keyframe is held fixed, as with too few."""
    config = BundleAdjustmentConfig(enabled=True)
    assert config.min_shared_landmarks == 3 and config.link_max_spread > 0
    for clustered in (False, True):
        the_map = island_map(np.random.default_rng(4), 3, clustered=clustered)
        problem = BundleProblem.from_map(the_map, config, NOISE, K, window=4)
        free = {int(k): int(slot) >= 0 for k, slot in zip(problem.keyframe_indices, problem.free_index)}
        assert free[4] and free[6] and free[7]
        assert free[5] is not clustered


def test_link_spread_of_a_patch_and_the_floor_against_points_across_the_view():
    """bonn_crowd_people's case: 5 points within 15 cm at 3 m and the floor leave the turn
    about the vertical through the points to the points alone; 30 points across the view pin
    the keyframe. Spread in inlier thresholds, over the keyframe's own landmarks."""
    from jsr.pipeline.bundle_links import link_spread

    rng = np.random.default_rng(0)
    pose = np.eye(4)  # camera at the origin looking along +z, y down
    own = np.column_stack([rng.uniform(-2, 2, 200), rng.uniform(-1, 1.2, 200), rng.uniform(1.5, 4, 200)])
    patch = np.array([0.0, -1.0, 3.0]) + rng.uniform(-0.075, 0.075, size=(5, 3))
    floor = np.array([[0.0, -1.0, 0.0]])
    config = BundleAdjustmentConfig()
    loose = link_spread(patch, floor, own, pose, NOISE, config)
    across = link_spread(own[:30], floor, own, pose, NOISE, config)
    assert loose > 5.0 and across < 0.5
    assert link_spread(patch[:2], np.zeros((0, 3)), own, pose, NOISE, config) == float("inf")  # a turn left free


def test_linked_groups_count_points_and_planes_apart():
    from jsr.pipeline.bundle_links import linked_groups as _linked_groups

    none = np.zeros(0, dtype=np.int64)
    assert _linked_groups(3, none, none, none, none, 1).tolist() == [0, 1, 2]  # nothing observed: no links
    # keyframes 0 and 1 share planes 0-2; point 0 and plane 0 are different landmarks
    planes_frames, planes = np.array([0, 0, 0, 1, 1, 1, 2]), np.array([0, 1, 2, 0, 1, 2, 5])
    groups = _linked_groups(3, none, none, planes_frames, planes, 3)
    assert groups[0] == groups[1] != groups[2]
    groups = _linked_groups(3, np.array([0, 2, 2]), np.array([0, 0, 0]), planes_frames, planes, 3)
    assert groups[0] == groups[1] != groups[2]  # keyframe 2 sees point 0 twice: one shared landmark with none
    assert len(set(_linked_groups(3, np.array([0, 2]), np.array([0, 0]), planes_frames, planes, 1))) == 1


def test_huber_loss_has_scipys_huber_cost():
    residuals = np.array([0.1, -0.5, 1.9, -2.5, 7.0, 40.0])
    costs = [least_squares(lambda x: residuals + 0 * x, np.zeros(1), loss=loss, f_scale=2.0).cost
             for loss in ("huber", huber_loss)]
    assert costs[0] == pytest.approx(costs[1], rel=1e-12)
    assert costs[0] == pytest.approx(0.5 * np.sum(np.where(np.abs(residuals) <= 2, residuals**2,
                                                           2 * 2 * np.abs(residuals) - 4)), rel=1e-12)


def tiny_problem():
    rng = np.random.default_rng(4)
    scene = make_scene(rng, keyframes=4, landmarks=12, fraction_2d=0.3, planes=2)
    the_map = build_map(scene, rng)
    problem = BundleProblem.from_map(the_map, BundleAdjustmentConfig(enabled=True), NOISE, K, window=2)
    return problem


def test_jacobian_sparsity_matches_dense_numeric_jacobian():
    problem = tiny_problem()
    assert problem.num_free_keyframes == 2
    assert len(problem.obs2_keyframe) > 0 and len(problem.obsp_keyframe) > 0
    # keyframe 1 is out of the window but observes its landmarks: present and fixed
    assert list(problem.keyframe_indices) == [0, 1, 2, 3] and list(problem.free_index) == [-1, -1, 0, 1]
    rng = np.random.default_rng(5)
    x = rng.normal(0, 1e-2, problem.num_parameters)  # away from 0: all couplings show
    step = 1e-6
    dense = np.zeros((problem.num_residuals, problem.num_parameters))
    for column in range(problem.num_parameters):
        delta = np.zeros(problem.num_parameters)
        delta[column] = step
        dense[:, column] = (problem.residuals(x + delta) - problem.residuals(x - delta)) / (2 * step)
    pattern = jacobian_sparsity(problem).toarray() != 0
    nonzero = np.abs(dense) > 1e-9
    # no derivative outside the declared pattern ...
    assert not np.any(nonzero & ~pattern)
    # ... and, block by block (residual block x parameter block), nothing declared that is not there
    row_blocks = np.concatenate([np.repeat(np.arange(n), w) + offset for n, w, offset in (
        (len(problem.obs3_keyframe), 3, 0),
        (len(problem.obs2_keyframe), 2, len(problem.obs3_keyframe)),
        (len(problem.obsp_keyframe), 4, len(problem.obs3_keyframe) + len(problem.obs2_keyframe)))])
    free = problem.num_free_keyframes
    column_blocks = np.concatenate([np.repeat(np.arange(free), 6),
                                    free + np.repeat(np.arange(len(problem.point_ids) + len(problem.plane_ids)), 3)])
    blocks = (problem.num_observations, free + len(problem.point_ids) + len(problem.plane_ids))
    declared = np.zeros(blocks, dtype=bool)
    found = np.zeros(blocks, dtype=bool)
    rows, cols = np.nonzero(pattern)
    declared[row_blocks[rows], column_blocks[cols]] = True
    rows, cols = np.nonzero(nonzero)
    found[row_blocks[rows], column_blocks[cols]] = True
    assert np.array_equal(declared, found)
    # the sparse finite differences scipy computes agree with the dense ones
    from scipy.optimize._numdiff import approx_derivative

    sparse = approx_derivative(problem.residuals, x, method="2-point", sparsity=jacobian_sparsity(problem))
    assert np.allclose(sparse.toarray(), dense, atol=1e-4 * np.abs(dense).max())
    # the analytic Jacobian the solver uses is the derivative, entry by entry
    analytic = problem.jacobian(x)
    assert analytic.shape == dense.shape
    assert np.allclose(analytic.toarray(), dense, rtol=1e-5, atol=1e-6 * np.abs(dense).max())


def test_points_seen_by_one_keyframe_move_with_it_as_a_full_solve_would(monkeypatch):
    """Points observed once are left out of the solve and carried by their keyframe's
    correction: keyframe poses and every landmark end where solving for all points puts them."""
    rng = np.random.default_rng(21)
    scene = make_scene(rng, keyframes=6, landmarks=900, max_per_keyframe=120, planes=2)
    the_map = build_map(scene, rng)
    # (the noise is estimated from the residuals, which the points seen once would change)
    config = BundleAdjustmentConfig(enabled=True, max_iterations=200, estimate_noise=False)
    problem = BundleProblem.from_map(the_map, config, NOISE, K)
    carried = problem.carried_point_ids
    assert len(carried) > 100 and not np.isin(carried, problem.point_ids).any()
    observed = np.concatenate([kf.point_landmarks for kf in the_map.keyframes])
    ids, counts = np.unique(observed, return_counts=True)
    assert np.array_equal(np.sort(carried), ids[(counts == 1) & np.isin(ids, carried)])
    assert set(ids[counts >= 2]) <= set(problem.point_ids)

    full_map = copy.deepcopy(the_map)
    poses_before, positions_before = the_map.keyframe_poses.copy(), the_map.points.positions.copy()
    reduced = bundle_adjust(the_map, config, NOISE, K)
    monkeypatch.setattr(BundleProblem, "_carry_single_view_points", lambda self: None)
    full = bundle_adjust(full_map, config, NOISE, K)
    assert reduced.success and full.success
    assert reduced.landmarks_optimised + len(carried) == full.landmarks_optimised
    difference = invert_transform(full_map.keyframe_poses) @ the_map.keyframe_poses
    assert np.abs(difference[:, :3, 3]).max() < 1e-4  # 0.1 mm
    assert np.degrees(rotation_angle(difference[:, :3, :3])).max() < 0.01
    solved = np.setdiff1d(np.arange(len(positions_before)), carried)
    assert np.linalg.norm(the_map.points.positions[solved] - full_map.points.positions[solved], axis=1).max() < 1e-3
    # a carried point keeps its place in its keyframe's camera (the full solve also fits its
    # observation there, but gives up what the map knew of it beyond that one view)
    owner = {int(i): k for k, kf in enumerate(the_map.keyframes) for i in kf.point_landmarks}
    moved = 0.0
    for point in carried:
        k = owner[int(point)]
        before = transform_points(invert_transform(poses_before[k]), positions_before[point][None])
        after = transform_points(invert_transform(the_map.keyframe_poses[k]), the_map.points.positions[point][None])
        assert np.allclose(before, after, atol=1e-9)
        moved = max(moved, float(np.linalg.norm(the_map.points.positions[point] - positions_before[point])))
    assert moved > 1e-3  # their keyframes moved, and they with them


def test_first_keyframe_is_fixed_even_inside_the_window():
    problem = tiny_problem()
    assert problem.free_index[0] == -1
    rng = np.random.default_rng(6)
    scene = make_scene(rng, keyframes=3, landmarks=60)
    the_map = build_map(scene, rng)
    first = the_map.keyframes[0].T_map_cam.copy()
    result = bundle_adjust(the_map, BundleAdjustmentConfig(enabled=True, window_keyframes=10), NOISE, K)
    assert result.success and result.keyframes_optimised == 2
    assert np.array_equal(the_map.keyframes[0].T_map_cam, first)


def test_disabled_config_changes_nothing():
    rng = np.random.default_rng(7)
    scene = make_scene(rng, keyframes=6, landmarks=200)
    the_map = build_map(scene, rng)
    reference = copy.deepcopy(the_map)
    config = BundleAdjustmentConfig(enabled=False, every_keyframes=1)
    result = bundle_adjust(the_map, config, NOISE, K)
    assert not result.success and result.message == "disabled"
    with BundleScheduler(config, NOISE, K) as scheduler:
        assert not scheduler.maybe_start(the_map)
        assert scheduler.apply_finished(the_map) is None
        assert scheduler.finish(the_map) is None
    assert_same_state(the_map, reference)


def test_apply_keeps_changes_made_meanwhile():
    """Landmarks fused after the snapshot keep their change; later keyframes and landmarks
    follow the newest keyframe's correction."""
    rng = np.random.default_rng(8)
    scene = make_scene(rng, keyframes=7, landmarks=300)
    the_map = build_map(scene, rng)
    problem = BundleProblem.from_map(the_map, BundleAdjustmentConfig(enabled=True), NOISE, K)
    solution = problem.solve(BundleAdjustmentConfig(enabled=True))
    # meanwhile: landmark 5 is fused, a keyframe and a landmark are added
    shift = np.array([0.003, -0.002, 0.001])
    the_map.points.positions[5] += shift
    new_pose = the_map.keyframes[-1].T_map_cam @ make_transform(np.eye(3), [0.05, 0, 0])
    the_map.keyframes.append(replace(the_map.keyframes[-1], keyframe_id=7, T_map_cam=new_pose.copy()))
    new_id = the_map.points.add(np.array([[0.1, 0.2, 0.3]]), np.zeros((1, 128), np.float32), [0.005],
                                np.zeros((1, 3), np.uint8))[0]
    apply_solution(the_map, solution)
    index = list(solution.point_ids).index(5)
    assert np.allclose(the_map.points.positions[5], solution.positions_after[index] + shift, atol=1e-12)
    others = np.setdiff1d(solution.point_ids, [5])
    assert np.allclose(the_map.points.positions[others], solution.positions_after[np.searchsorted(solution.point_ids, others)],
                       atol=1e-12)
    correction = solution.result.correction
    assert not np.allclose(correction, np.eye(4))
    assert np.allclose(the_map.keyframes[-1].T_map_cam, correction @ new_pose, atol=1e-12)
    assert np.allclose(the_map.points.positions[new_id], transform_points(correction, np.array([[0.1, 0.2, 0.3]]))[0])
    assert np.allclose(the_map.keyframe_poses[1:7], solution.poses_after, atol=1e-12)


def run_incremental(asynchronous: bool, seed: int = 9, slow_worker: bool = False):
    """Feed keyframes one by one like the tracker does: landmarks created when first seen,
    fused when seen again; BA every 2 keyframes, applied after the next keyframe was added."""
    rng = np.random.default_rng(seed)
    scene = make_scene(rng, keyframes=10, landmarks=300)
    poses = perturb_poses(rng, scene.poses)
    initial = scene.landmarks + rng.normal(0, 0.01, scene.landmarks.shape)
    planes = perturb_planes(rng, scene.planes)
    config = BundleAdjustmentConfig(enabled=True, every_keyframes=2, window_keyframes=4, asynchronous=asynchronous)
    the_map = Map("static")
    ids = np.full(len(scene.landmarks), -1)
    the_map.planes.add(planes, np.zeros((3, 3)), np.full(3, 1000.0))
    results = []
    with BundleScheduler(config, NOISE, K) as scheduler:
        if slow_worker:
            original = BundleProblem.solve

            def slow_solve(self, *args):
                time.sleep(0.05)
                return original(self, *args)

            BundleProblem.solve = slow_solve
        try:
            for k, o in enumerate(scene.observations):
                pose = poses[k] if k == 0 else the_map.keyframes[-1].T_map_cam @ (
                    invert_transform(poses[k - 1]) @ poses[k])  # "tracked" against the current map
                has_depth = ~np.isnan(o.camera_points[:, 0])
                new = (ids[o.landmarks] < 0) & has_depth
                seen = (ids[o.landmarks] >= 0) & has_depth
                count = int(new.sum())
                ids[o.landmarks[new]] = the_map.points.add(
                    initial[o.landmarks[new]], np.zeros((count, 128), np.float32), o.sigma_z[new],
                    np.zeros((count, 3), np.uint8))
                the_map.points.fuse(ids[o.landmarks[seen]], transform_points(pose, o.camera_points[seen]),
                                    np.zeros((int(seen.sum()), 128), np.float32), o.sigma_z[seen])
                keep = ids[o.landmarks] >= 0
                keyframe = keyframe_of(scene, k, pose, ids)
                keyframe.point_landmarks = keyframe.point_landmarks[keep]
                keyframe.camera_points = keyframe.camera_points[keep]
                keyframe.pixels = keyframe.pixels[keep]
                keyframe.sigma_z = keyframe.sigma_z[keep]
                keyframe.point_measurements = keyframe.point_measurements[keep]
                the_map.keyframes.append(keyframe)
                applied = scheduler.apply_finished(the_map, wait=True)
                if applied is not None:
                    results.append(applied)
                scheduler.maybe_start(the_map)
            final = scheduler.finish(the_map)
            if final is not None:
                results.append(final)
        finally:
            if slow_worker:
                BundleProblem.solve = original
    return the_map, results, scene


def test_scheduler_is_deterministic_across_modes():
    sync_map, sync_results, scene = run_incremental(asynchronous=False)
    async_map, async_results, _ = run_incremental(asynchronous=True)
    slow_map, slow_results, _ = run_incremental(asynchronous=True, slow_worker=True)
    assert len(sync_results) == 5 and all(r.success for r in sync_results)
    assert [r.final_cost for r in sync_results] == [r.final_cost for r in async_results]
    assert [r.final_cost for r in sync_results] == [r.final_cost for r in slow_results]
    assert_same_state(sync_map, async_map)
    assert_same_state(sync_map, slow_map)
    # and the runs did improve the map
    translation, _ = pose_errors(sync_map, scene)
    assert np.sqrt(np.mean(translation[1:] ** 2)) < 0.01


def test_scheduler_starts_every_n_keyframes_and_waits_before_restarting():
    rng = np.random.default_rng(10)
    scene = make_scene(rng, keyframes=8, landmarks=200)
    full = build_map(scene, rng)
    the_map = Map("static")
    the_map.points = full.points
    the_map.planes = full.planes
    config = BundleAdjustmentConfig(enabled=True, every_keyframes=3, asynchronous=True)
    started = []
    with BundleScheduler(config, NOISE, K) as scheduler:
        for keyframe in full.keyframes:
            the_map.keyframes.append(keyframe)
            if scheduler.maybe_start(the_map):
                started.append(len(the_map.keyframes))
                assert scheduler.pending(the_map)
        assert started == [3, 6]
        # the job started at 3 was applied (waiting) before the one at 6 was started
        assert len(scheduler.results) == 1
        assert scheduler.finish(the_map).success
        assert not scheduler.pending(the_map) and len(scheduler.results) == 2


def test_window_of_ten_keyframes_with_5000_observations():
    rng = np.random.default_rng(11)
    scene = make_scene(rng, keyframes=10, landmarks=1500, max_per_keyframe=500, arc_degrees=30.0)
    the_map = build_map(scene, rng)
    bundle_adjust(build_map(scene, np.random.default_rng(12)), BundleAdjustmentConfig(enabled=True), NOISE, K)  # warm-up
    result = bundle_adjust(the_map, BundleAdjustmentConfig(enabled=True, window_keyframes=10), NOISE, K)
    assert result.success
    assert 4500 <= result.observations <= 5500
    # (its speed is a benchmark figure, not a test assertion)
    translation, _ = pose_errors(the_map, scene)
    assert translation[1:].max() < 0.005


def test_noise_components_are_estimated_from_the_residuals():
    """Depths four times noisier than the sigma they state, keypoints half the configured
    pixel sigma off: the run finds both from its residuals and weighs by them, which puts the
    landmarks nearer the truth than the configured sigmas do. The plane offsets (24 residuals)
    are too few to estimate and keep theirs."""
    rng = np.random.default_rng(3)
    scene = make_scene(rng, keyframes=8, landmarks=600, depth_noise=4.0)
    estimated = build_map(scene, rng)
    configured = copy.deepcopy(estimated)
    result = bundle_adjust(estimated, BundleAdjustmentConfig(enabled=True), NOISE, K)
    fixed = bundle_adjust(configured, BundleAdjustmentConfig(enabled=True, estimate_noise=False), NOISE, K)
    assert result.success and fixed.success and fixed.passes == 1
    assert np.array_equal(fixed.noise_components, np.ones(len(GROUPS)))
    components = dict(zip(GROUPS, result.noise_components))
    assert 0.4 < components["reprojection"] < 0.6 and 0.4 < components["pixel_2d"] < 0.6
    assert 3.5 < components["depth"] < 5.0
    assert components["plane_offset"] == 1.0
    assert 2 <= result.passes <= 3
    assert landmark_rmse(estimated, scene) < 0.6 * landmark_rmse(configured, scene)


def test_a_solve_leaves_the_problems_weights_as_they_were():
    """Solving reweighs the residuals, then puts the configured weights back: solving the same
    problem twice gives the same answer."""
    rng = np.random.default_rng(4)
    scene = make_scene(rng, keyframes=6, landmarks=300, depth_noise=4.0)
    problem = BundleProblem.from_map(build_map(scene, rng), BundleAdjustmentConfig(enabled=True), NOISE, K)
    before = (problem.pixel_weight, problem.obs3_weight.copy(), problem.pixel2d_weight, problem.normal_weight,
              problem.offset_weight)
    first = problem.solve(BundleAdjustmentConfig(enabled=True), np.full(len(GROUPS), 2.0))
    assert first.result.success and first.result.passes >= 2
    after = (problem.pixel_weight, problem.obs3_weight, problem.pixel2d_weight, problem.normal_weight,
             problem.offset_weight)
    assert all(np.array_equal(a, b) for a, b in zip(before, after))
    second = problem.solve(BundleAdjustmentConfig(enabled=True), np.full(len(GROUPS), 2.0))
    assert np.array_equal(first.poses_after, second.poses_after)
    assert np.array_equal(first.result.noise_components, second.result.noise_components)


def test_components_are_updated_within_bounds():
    components = np.array([1.0, 2.0, 1.0, 0.5, 1.0])
    spread = np.array([0.5, 1.5, np.nan, 0.0, 100.0])
    assert np.allclose(update(components, spread), [0.5, 3.0, 1.0, 0.5, BOUNDS[1]])


def test_the_static_maps_estimate_carries_to_its_next_run_and_to_object_maps(monkeypatch):
    """The static map's runs estimate the sensor's noise, each from where the last applied one
    ended; an object map's run uses that estimate as it is (one solve, not re-estimated)."""
    rng = np.random.default_rng(10)
    scene = make_scene(rng, keyframes=8, landmarks=400, depth_noise=4.0)
    full = build_map(scene, rng)
    static_map, object_map = Map("static"), ObjectMap(1, 0)
    for the_map in (static_map, object_map):
        the_map.points, the_map.planes = copy.deepcopy(full.points), copy.deepcopy(full.planes)
    calls = []
    original = BundleProblem.solve

    def recording_solve(self, config, noise_components=None, estimate=None):
        calls.append((self.map_name, None if noise_components is None else noise_components.copy(), estimate))
        return original(self, config, noise_components, estimate)

    monkeypatch.setattr(BundleProblem, "solve", recording_solve)
    config = BundleAdjustmentConfig(enabled=True, every_keyframes=3, asynchronous=False)
    with BundleScheduler(config, NOISE, K) as scheduler:
        for keyframe in full.keyframes[:6]:
            static_map.keyframes.append(keyframe)
            scheduler.maybe_start(static_map)
        scheduler.finish(static_map)
        for keyframe in full.keyframes[:3]:
            object_map.keyframes.append(copy.deepcopy(keyframe))
        scheduler.maybe_start(object_map)
        object_result = scheduler.finish(object_map)
    first, second = scheduler.results[:2]
    assert [(name, estimate) for name, _, estimate in calls] == [("static", True), ("static", True),
                                                                 ("object_1", False)]
    assert calls[0][1] is None and np.array_equal(calls[1][1], first.noise_components)
    assert first.noise_components[1] > 2.0  # the depth is noisier than stated
    assert second.passes <= first.passes
    assert np.array_equal(calls[2][1], second.noise_components)
    assert object_result.passes == 1 and np.array_equal(object_result.noise_components, second.noise_components)



@pytest.mark.parametrize("seed", [21, 22])
def test_a_run_over_the_whole_map_corrects_every_keyframe(seed):
    """``bundle_adjustment.final_global``: after the last frame one run frees all keyframes but
    the first. On a map whose keyframes are all 2 cm / 1 degree off, it brings every one near
    the truth, where a windowed run corrects only its window (and the keyframes that see the
    same landmarks stay fixed)."""
    rng = np.random.default_rng(seed)
    scene = make_scene(rng, keyframes=12, landmarks=600, arc_degrees=60.0)
    whole = build_map(scene, rng)
    windowed = copy.deepcopy(whole)
    first = whole.keyframes[0].T_map_cam.copy()
    config = BundleAdjustmentConfig(enabled=True, window_keyframes=4, asynchronous=False)
    with BundleScheduler(config, NOISE, K) as scheduler:
        result = scheduler.run_global(whole)
        assert scheduler.maybe_start(windowed, window=config.window_keyframes)
        scheduler.finish(windowed)
    assert result is not None and result.success
    assert result.keyframes_optimised == 11 and result.keyframes_fixed == 1
    assert np.array_equal(whole.keyframes[0].T_map_cam, first)
    translation, rotation = pose_errors(whole, scene)
    assert translation.max() < 0.004 and rotation.max() < 0.1
    translation_windowed, _ = pose_errors(windowed, scene)
    assert np.all(translation_windowed[1:8] > 0.01)  # outside the window: as they were (2 cm)
    assert landmark_rmse(whole, scene) < landmark_rmse(windowed, scene)


def test_a_run_over_the_whole_map_is_skipped_when_bundle_adjustment_is_off():
    rng = np.random.default_rng(21)
    the_map = build_map(make_scene(rng, keyframes=4, landmarks=200), rng)
    before = copy.deepcopy(the_map)
    config = BundleAdjustmentConfig(enabled=False, asynchronous=False)
    with BundleScheduler(config, NOISE, K) as scheduler:
        assert scheduler.run_global(the_map) is None
    assert_same_state(before, the_map)
