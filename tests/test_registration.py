"""Mixed point/plane RANSAC registration on synthetic correspondences with known poses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsr.config import NoiseConfig, RansacConfig
from jsr.pipeline import correspondences, pose_refinement, registration
from jsr.pipeline.correspondences import Correspondences
from jsr.pipeline.pose_scoring import RegistrationProblem
from jsr.pipeline.registration import register

FX = FY = 525.0
CX, CY = 319.5, 239.5
PIXEL_SIGMA = 0.5
SIGMA_Z = 1.425e-3  # Kinect: sigma_Z = c Z^2


def _pose(rng: np.random.Generator) -> np.ndarray:
    axis = rng.normal(size=3)
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0.1, 0.6)).as_matrix()
    transform[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    return transform


def _camera_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points seen by a 640x480 camera, 0.8 to 4 m deep."""
    u, v, z = rng.uniform(0, 640, n), rng.uniform(0, 480, n), rng.uniform(0.8, 4.0, n)
    return np.column_stack([(u - CX) / FX * z, (v - CY) / FY * z, z])


def _observe_pixels(rng: np.random.Generator, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = points[:, 2]
    u = FX * points[:, 0] / z + CX + rng.normal(0.0, PIXEL_SIGMA, len(z))
    v = FY * points[:, 1] / z + CY + rng.normal(0.0, PIXEL_SIGMA, len(z))
    return u, v


def _measure_3d(rng: np.random.Generator, points: np.ndarray) -> np.ndarray:
    """Kinect-like measurement: pixel noise and axial depth noise sigma_Z = c Z^2."""
    u, v = _observe_pixels(rng, points)
    z = points[:, 2] + rng.normal(0.0, 1.0, len(points)) * SIGMA_Z * points[:, 2] ** 2
    return np.column_stack([(u - CX) / FX * z, (v - CY) / FY * z, z])


def _measure_bearings(rng: np.random.Generator, points: np.ndarray) -> np.ndarray:
    u, v = _observe_pixels(rng, points)
    rays = np.column_stack([(u - CX) / FX, (v - CY) / FY, np.ones(len(u))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _to_map(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _scene(
    seed: int,
    n3d: int = 0,
    n2d: int = 0,
    n_planes: int = 0,
    outlier_ratio: float = 0.5,
    plane_outliers: int = 0,
) -> tuple[Correspondences, np.ndarray, dict[str, np.ndarray]]:
    """Correspondences under a random pose; a fraction of each kind matched to wrong landmarks."""
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    fields: dict[str, np.ndarray] = {}
    outliers: dict[str, np.ndarray] = {}
    if n3d:
        points = _camera_points(rng, n3d)
        landmarks = _to_map(truth, points)
        wrong = rng.choice(n3d, int(round(outlier_ratio * n3d)), replace=False)
        landmarks[wrong] = _to_map(truth, _camera_points(rng, len(wrong)))
        measured = _measure_3d(rng, points)
        fields.update(frame_points=measured, map_points=landmarks, point_depths=measured[:, 2])
        outliers["point3d"] = wrong
    if n2d:
        points = _camera_points(rng, n2d)
        landmarks = _to_map(truth, points)
        wrong = rng.choice(n2d, int(round(outlier_ratio * n2d)), replace=False)
        landmarks[wrong] = _to_map(truth, _camera_points(rng, len(wrong)))
        fields.update(frame_bearings=_measure_bearings(rng, points), map_points_2d=landmarks)
        outliers["point2d"] = wrong
    if n_planes:
        normals = rng.normal(size=(n_planes, 3))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        offsets = rng.uniform(0.5, 3.0, n_planes)
        map_normals = normals @ truth[:3, :3].T
        map_offsets = offsets - map_normals @ truth[:3, 3]
        noisy = normals + rng.normal(0.0, 0.003, normals.shape)
        noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
        frame_planes = np.column_stack([noisy, offsets + rng.normal(0.0, 0.005, n_planes)])
        map_planes = np.column_stack([map_normals, map_offsets])
        map_planes[:plane_outliers] = map_planes[np.roll(np.arange(plane_outliers), 1)]
        fields.update(frame_planes=frame_planes, map_planes=map_planes)
        outliers["plane"] = np.arange(plane_outliers)
    return Correspondences(**fields), truth, outliers


def _errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    delta = np.linalg.inv(truth) @ estimate
    angle = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(delta[:3, 3])), float(angle)


def _check_pose(result, truth: np.ndarray) -> None:
    assert result.success, result.reason
    assert result.reason == ""
    translation_error, rotation_error = _errors(result.transformation, truth)
    assert translation_error < 0.005, translation_error
    assert rotation_error < 0.3, rotation_error


def _check_outliers_rejected(mask: np.ndarray, wrong: np.ndarray, min_recall: float = 0.95) -> None:
    """Wrong matches are outliers; nearly all right ones are inliers."""
    assert not mask[wrong].any()
    right = np.setdiff1d(np.arange(len(mask)), wrong)
    assert mask[right].mean() >= min_recall


RANSAC = RansacConfig()
NOISE = NoiseConfig()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_3d_points_with_half_outliers(seed: int) -> None:
    corr, truth, wrong = _scene(seed, n3d=400)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(seed))
    _check_pose(result, truth)
    _check_outliers_rejected(result.inliers_point3d, wrong["point3d"])
    assert result.num_matches == 400
    assert 0.45 <= result.fitness <= 0.55
    assert 0.0 < result.rmse < 0.03
    assert result.iterations <= RANSAC.max_iterations


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_2d_points_only_with_half_outliers(seed: int) -> None:
    corr, truth, wrong = _scene(seed, n2d=400)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(seed))
    _check_pose(result, truth)
    _check_outliers_rejected(result.inliers_point2d, wrong["point2d"])
    assert result.rmse == 0.0  # no 3D pairs


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mixed_points_and_planes_with_half_outliers(seed: int) -> None:
    corr, truth, wrong = _scene(seed, n3d=200, n2d=60, n_planes=6, plane_outliers=2)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(seed))
    _check_pose(result, truth)
    _check_outliers_rejected(result.inliers_point3d, wrong["point3d"])
    _check_outliers_rejected(result.inliers_point2d, wrong["point2d"], min_recall=0.9)
    np.testing.assert_array_equal(result.inliers_plane, [False, False, True, True, True, True])
    assert result.num_matches == 266


def test_scarce_3d_points_use_2d_matches() -> None:
    """Eight 3D matches (too few to sample from alone) and many 2D matches."""
    corr, truth, _ = _scene(5, n3d=8, n2d=300, outlier_ratio=0.3)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(5))
    _check_pose(result, truth)


def test_planes_and_few_points() -> None:
    """Hypotheses from plane mixes: three good planes and a handful of 3D points."""
    corr, truth, _ = _scene(6, n3d=12, n_planes=3, outlier_ratio=0.25)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(6))
    assert result.success, result.reason
    translation_error, rotation_error = _errors(result.transformation, truth)
    assert translation_error < 0.02 and rotation_error < 1.0
    assert result.inliers_plane.all()


def test_too_few_matches_fails_without_ransac() -> None:
    corr, _, _ = _scene(0, n3d=6, n_planes=3, outlier_ratio=0.0)  # 9 matches < 10
    result = register(corr, RANSAC, NOISE, np.random.default_rng(0))
    assert not result.success
    assert "too few matches" in result.reason and "min_matches" in result.reason
    assert result.iterations == 0
    assert result.num_matches == 9 and result.num_inliers == 0
    np.testing.assert_array_equal(result.transformation, np.eye(4))
    assert result.inliers_point3d.shape == (6,) and result.inliers_plane.shape == (3,)


def test_planes_count_as_matches() -> None:
    corr, _, _ = _scene(0, n3d=7, n_planes=3, outlier_ratio=0.0)  # 10 matches
    result = register(corr, RANSAC, NOISE, np.random.default_rng(0))
    assert result.num_matches == 10
    assert result.success, result.reason


def test_low_inlier_ratio_fails() -> None:
    corr, truth, wrong = _scene(3, n3d=300, outlier_ratio=0.7)  # 30% inliers < 0.4
    result = register(corr, RANSAC, NOISE, np.random.default_rng(3))
    assert not result.success
    assert "inlier ratio" in result.reason and "min_inlier_ratio" in result.reason
    assert result.fitness < RANSAC.min_inlier_ratio
    # the pose itself is still found; only the success rule rejects it
    assert _errors(result.transformation, truth)[0] < 0.01
    # with a lower required ratio the same data registers
    lenient = dataclasses.replace(RANSAC, min_inlier_ratio=0.25)
    assert register(corr, lenient, NOISE, np.random.default_rng(3)).success


def test_pure_outliers_fail() -> None:
    corr, _, _ = _scene(4, n3d=100, outlier_ratio=1.0)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(4))
    assert not result.success
    assert result.reason
    assert result.iterations == RANSAC.max_iterations


def test_same_seed_same_result() -> None:
    corr, _, _ = _scene(8, n3d=150, n2d=40, n_planes=4)
    first = register(corr, RANSAC, NOISE, np.random.default_rng(123))
    second = register(corr, RANSAC, NOISE, np.random.default_rng(123))
    np.testing.assert_array_equal(first.transformation, second.transformation)
    np.testing.assert_array_equal(first.inliers_point3d, second.inliers_point3d)
    np.testing.assert_array_equal(first.inliers_point2d, second.inliers_point2d)
    np.testing.assert_array_equal(first.inliers_plane, second.inliers_plane)
    assert first.iterations == second.iterations


def test_different_seeds_sample_differently() -> None:
    """The rng drives the sampling: without refinement the best sample differs by seed."""
    corr, _, _ = _scene(8, n3d=150)
    raw = dataclasses.replace(RANSAC, refine_rounds=0)
    first = register(corr, raw, NOISE, np.random.default_rng(1))
    second = register(corr, raw, NOISE, np.random.default_rng(2))
    assert not np.array_equal(first.transformation, second.transformation)


def test_initial_guess_is_scored_first() -> None:
    corr, truth, _ = _scene(9, n3d=200, outlier_ratio=0.2)
    # a single sampled hypothesis cannot be relied on; the initial guess carries the result
    one_sample = dataclasses.replace(RANSAC, max_iterations=1, refine_rounds=0)
    guided = register(corr, one_sample, NOISE, np.random.default_rng(0), initial_guess=truth)
    assert guided.success
    assert _errors(guided.transformation, truth)[0] < 1e-12
    # a good guess lets adaptive stopping end after a few samples (0.8^3 -> ~10 samples)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(0), initial_guess=truth)
    _check_pose(result, truth)
    assert result.iterations < 20


def test_bad_initial_guess_is_overruled() -> None:
    corr, truth, _ = _scene(10, n3d=300)
    wrong_guess = truth.copy()
    wrong_guess[:3, 3] += [0.5, 0.0, 0.0]
    result = register(corr, RANSAC, NOISE, np.random.default_rng(0), initial_guess=wrong_guess)
    _check_pose(result, truth)


def test_initial_guess_returned_when_too_few_matches() -> None:
    corr, truth, _ = _scene(0, n3d=4, outlier_ratio=0.0)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(0), initial_guess=truth)
    assert not result.success
    np.testing.assert_array_equal(result.transformation, truth)


def test_inlier_functions_agree_with_result() -> None:
    corr, _, _ = _scene(11, n3d=120, n2d=50, n_planes=5, plane_outliers=1)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(0))
    pose = result.transformation
    np.testing.assert_array_equal(correspondences.point_inliers(pose, corr, NOISE), result.inliers_point3d)
    np.testing.assert_array_equal(correspondences.point2d_inliers(pose, corr, NOISE), result.inliers_point2d)
    np.testing.assert_array_equal(correspondences.plane_inliers(pose, corr, RANSAC), result.inliers_plane)
    evaluated = registration.evaluate_pose(pose, corr, RANSAC, NOISE)
    assert evaluated.num_inliers == result.num_inliers
    assert evaluated.success == result.success


def test_depth_dependent_threshold() -> None:
    """A 3 cm error is an inlier at 4 m (3 sigma_Z = 6.8 cm) but not at 1 m (1 cm floor)."""
    frame = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 4.0]])
    corr = Correspondences(frame_points=frame, map_points=frame + [0.03, 0.0, 0.0])
    np.testing.assert_array_equal(correspondences.point_inliers(np.eye(4), corr, NOISE), [False, True])


def test_surface_pose_result_links_landmarks_only_when_enough_agree() -> None:
    """A pose from a surface alignment alone succeeds whatever the matches say; the matches
    agreeing with it stay inliers (linking old landmarks) only from min_links on."""
    rng = np.random.default_rng(3)
    frame = rng.uniform([-0.2, -0.2, 1.0], [0.2, 0.2, 1.5], (10, 3))
    landmarks = frame + rng.uniform(0.1, 0.3, (10, 3))  # wrong matches ...
    landmarks[:6] = frame[:6]  # ... but six agree with the pose
    corr = Correspondences(frame_points=frame, map_points=landmarks)
    linked = registration.surface_pose_result(np.eye(4), corr, RANSAC, NOISE, min_links=5)
    assert linked.success and linked.num_inliers == 6 and linked.inliers_point3d[:6].all()
    unlinked = registration.surface_pose_result(np.eye(4), corr, RANSAC, NOISE, min_links=7)
    assert unlinked.success and unlinked.num_inliers == 0 and not unlinked.inliers_point3d.any()
    np.testing.assert_array_equal(unlinked.transformation, np.eye(4))
    assert unlinked.reason  # says where the pose came from
    # fewer matches than ransac.min_matches (too few to register) link all the same
    few = corr.subset(np.arange(6), np.zeros(0, dtype=int), np.zeros(0, dtype=int))
    assert few.num_matches < RANSAC.min_matches
    assert registration.surface_pose_result(np.eye(4), few, RANSAC, NOISE, min_links=5).num_inliers == 6
    empty = registration.surface_pose_result(np.eye(4), Correspondences(), RANSAC, NOISE, min_links=5)
    assert empty.success and empty.num_inliers == 0


def test_2d_landmark_behind_the_camera_is_an_outlier() -> None:
    bearing = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    landmarks = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0]])
    corr = Correspondences(frame_bearings=bearing, map_points_2d=landmarks)
    np.testing.assert_array_equal(correspondences.point2d_inliers(np.eye(4), corr, NOISE), [True, False])


def test_ids_are_carried_through_subset() -> None:
    corr, _, _ = _scene(12, n3d=20, n_planes=2)
    corr.landmark_ids = np.arange(100, 120)
    corr.frame_point_ids = np.arange(20)
    corr.frame_plane_ids = np.array([5, 6])
    part = corr.subset(point3d=np.arange(20) % 2 == 0, plane=[1])
    np.testing.assert_array_equal(part.landmark_ids, np.arange(100, 120, 2))
    np.testing.assert_array_equal(part.frame_plane_ids, [6])
    assert part.num_point3d == 10 and part.num_plane == 1
    assert len(part.point_depths) == 10


def test_mismatched_lengths_are_rejected() -> None:
    with pytest.raises(ValueError):
        Correspondences(frame_points=np.zeros((3, 3)), map_points=np.zeros((2, 3)))


def test_nan_rows_do_not_break_registration() -> None:
    corr, truth, _ = _scene(13, n3d=200)
    corr.frame_points[:10] = np.nan  # e.g. keypoints whose depth lookup failed
    corr.point_depths[:10] = np.nan
    result = register(corr, RANSAC, NOISE, np.random.default_rng(0))
    _check_pose(result, truth)
    assert not result.inliers_point3d[:10].any()


def test_depth_fallback_keeps_far_matches_with_biased_depth() -> None:
    """Image mode: far 3D matches whose pixel is right but whose depth is off by twice the
    threshold (a systematic sensor error) stay inliers with ransac.depth_fallback and do not
    bias the pose; near matches with a depth 3 cm off and gross mismatches stay outliers."""
    rng = np.random.default_rng(7)
    truth = _pose(rng)
    far = _camera_points(rng, 300)
    far[:, :] *= (rng.uniform(2.0, 4.0, 300) / far[:, 2])[:, None]
    near = _camera_points(rng, 100)
    near[:, :] *= (rng.uniform(0.6, 1.2, 100) / near[:, 2])[:, None]
    points = np.concatenate([far, near])
    measured = _measure_3d(rng, points)
    biased_far = np.arange(0, 90)  # 30% of the far points: depth 6 sigma_Z too deep
    biased_near = np.arange(300, 330)  # 30% of the near points: 3 cm too deep
    scale = np.ones(len(points))
    scale[biased_far] = 1.0 + 6.0 * SIGMA_Z * points[biased_far, 2]
    scale[biased_near] = 1.0 + 0.03 / points[biased_near, 2]
    measured *= scale[:, None]  # along the ray: the pixel is unchanged
    landmarks = _to_map(truth, points)
    wrong = np.arange(330, 360)
    landmarks[wrong] = _to_map(truth, _camera_points(rng, len(wrong)))
    corr = Correspondences(frame_points=measured, map_points=landmarks, focal_length=FX)

    with_fallback = register(corr, dataclasses.replace(RANSAC, depth_fallback=3.0), NOISE, np.random.default_rng(0))
    _check_pose(with_fallback, truth)
    assert with_fallback.inliers_point3d[biased_far].mean() > 0.95
    assert not with_fallback.inliers_point3d[biased_near].any()
    assert not with_fallback.inliers_point3d[wrong].any()

    strict = register(corr, dataclasses.replace(RANSAC, depth_fallback=0.0), NOISE, np.random.default_rng(0))
    _check_pose(strict, truth)
    assert strict.inliers_point3d[biased_far].mean() < 0.05
    assert not strict.inliers_point3d[biased_near].any()


def _image_space_setup(seed: int):
    """Inliers of a mixed scene (3D and 2D points, planes) under image-space refinement, and a
    start pose 2 cm / 1 degree off the truth."""
    corr, truth, _ = _scene(seed, n3d=150, n2d=50, n_planes=4, outlier_ratio=0.2)
    corr = dataclasses.replace(corr, focal_length=FX)
    problem = RegistrationProblem(corr, RANSAC, NOISE)
    _, _, masks = problem.score_one(truth)
    rng = np.random.default_rng(seed)
    start = truth.copy()
    start[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.01, 3)).as_matrix() @ start[:3, :3]
    start[:3, 3] += rng.normal(0.0, 0.02, 3)
    return problem, masks, start, truth


@pytest.mark.parametrize("seed", [0, 1])
def test_image_space_jacobian_matches_finite_differences(seed: int) -> None:
    problem, masks, start, truth = _image_space_setup(seed)
    linearised = pose_refinement.image_space_terms(problem, start, masks, FX)
    # 5 degrees from the start, where the Jacobian was not built
    rotation = Rotation.from_rotvec([0.0, 0.0, np.deg2rad(5.0)]).as_matrix() @ start[:3, :3]
    translation = start[:3, 3]
    residuals, jacobian = linearised(rotation, translation)
    assert jacobian.shape == (len(residuals), 6)
    step = 1e-6
    for k in range(6):
        increment = np.zeros(6)
        increment[k] = step
        ahead, _ = linearised(Rotation.from_rotvec(increment[:3]).as_matrix() @ rotation, translation + increment[3:])
        behind, _ = linearised(Rotation.from_rotvec(-increment[:3]).as_matrix() @ rotation,
                               translation - increment[3:])
        numeric = (ahead - behind) / (2 * step)
        np.testing.assert_allclose(jacobian[:, k], numeric, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_image_space_refinement_reaches_the_huber_minimum(seed: int) -> None:
    """Our Levenberg-Marquardt ends where scipy's robust least squares on the same residuals
    does (to a micrometre and a thousandth of a degree)."""
    from scipy.optimize import least_squares

    problem, masks, start, truth = _image_space_setup(seed)
    refined = pose_refinement.refine_pose_image_space(problem, start, masks, FX)
    linearised = pose_refinement.image_space_terms(problem, start, masks, FX)

    def residuals(x: np.ndarray) -> np.ndarray:
        return linearised(Rotation.from_rotvec(x[:3]).as_matrix() @ start[:3, :3], start[:3, 3] + x[3:])[0]

    solution = least_squares(residuals, np.zeros(6), method="trf", loss="huber",
                             f_scale=pose_refinement.HUBER_SCALE, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    reference = np.eye(4)
    reference[:3, :3] = Rotation.from_rotvec(solution.x[:3]).as_matrix() @ start[:3, :3]
    reference[:3, 3] = start[:3, 3] + solution.x[3:]
    distance, angle = _errors(refined, reference)
    assert distance < 1e-6 and angle < 1e-3
    moved, _ = _errors(start, truth)
    assert _errors(refined, truth)[0] < 0.2 * moved  # and it did move towards the truth


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pose_cost_tells_noise_from_motion(seed: int) -> None:
    """The resting test of object tracking (objects.resting_max_extra_cost = 16.8): the true
    pose costs little more than the registered one (at most 3 here, below the chi-square
    bound the noise model would give); a pose 5 mm or 0.3 degrees off costs over twice the
    bound; a wildly wrong pose costs each inlier its capped share."""
    corr, truth, _ = _scene(seed, n3d=150, n2d=50, n_planes=3, outlier_ratio=0.3)
    result = register(corr, RANSAC, NOISE, np.random.default_rng(seed))
    assert result.success
    registered = registration.pose_cost(result.transformation, result, RANSAC, NOISE)
    assert 0.0 <= registered
    assert registration.pose_cost(truth, result, RANSAC, NOISE) - registered < 3.0
    shifted = truth.copy()
    shifted[:3, 3] += [0.005, 0.0, 0.0]
    turned = truth.copy()
    turned[:3, :3] = truth[:3, :3] @ Rotation.from_rotvec([0.0, np.radians(0.3), 0.0]).as_matrix()
    for moved in (shifted, turned):
        assert registration.pose_cost(moved, result, RANSAC, NOISE) - registered > 2 * 16.8
    far = _pose(np.random.default_rng(seed + 100))
    far[:3, 3] += 5.0
    capped_terms = result.num_inliers + int(result.inliers_plane.sum())  # a plane: normal and offset
    assert registration.pose_cost(far, result, RANSAC, NOISE) == pytest.approx(
        capped_terms * NOISE.inlier_sigmas**2 / 2.0)
