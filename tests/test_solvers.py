"""Minimal pose solvers: exact on noise-free data, degenerate input rejected without crashing."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsr.geometry import umeyama_alignment
from jsr.pipeline import solvers

SEEDS = range(8)


def _pose(rng: np.random.Generator) -> np.ndarray:
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    transform[:3, 3] = rng.uniform(-2.0, 2.0, 3)
    return transform


def _camera_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points in front of a camera with a 60 degree field of view, 0.8 to 4 m away."""
    z = rng.uniform(0.8, 4.0, n)
    xy = rng.uniform(-0.55, 0.55, (n, 2)) * z[:, None]
    return np.column_stack([xy, z])


def _to_map(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _planes(rng: np.random.Generator, n: int, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.uniform(0.5, 3.0, n)
    map_normals = normals @ transform[:3, :3].T
    map_offsets = offsets - map_normals @ transform[:3, 3]
    return np.column_stack([normals, offsets]), np.column_stack([map_normals, map_offsets])


def _bearings(points: np.ndarray) -> np.ndarray:
    return points / np.linalg.norm(points, axis=-1, keepdims=True)


def _closest_error(candidates: list[np.ndarray], truth: np.ndarray) -> float:
    assert candidates, "the solver returned no candidate"
    for candidate in candidates:
        assert candidate.shape == (4, 4)
        np.testing.assert_allclose(candidate[3], [0, 0, 0, 1])
        np.testing.assert_allclose(candidate[:3, :3] @ candidate[:3, :3].T, np.eye(3), atol=1e-10)
    return min(float(np.abs(candidate - truth).max()) for candidate in candidates)


@pytest.mark.parametrize("seed", SEEDS)
def test_three_3d_points_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    points = _camera_points(rng, 3)
    candidates = solvers.solve_points3d(points, _to_map(truth, points))
    assert len(candidates) == 1
    assert _closest_error(candidates, truth) < 1e-8


@pytest.mark.parametrize("seed", SEEDS)
def test_p3p_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    points = _camera_points(rng, 3)
    candidates = solvers.solve_p3p(_bearings(points), _to_map(truth, points))
    assert 1 <= len(candidates) <= 4
    assert _closest_error(candidates, truth) < 1e-8


def test_p3p_exact_on_many_random_configurations() -> None:
    """Over many random configurations the true pose is always among the candidates."""
    rng = np.random.default_rng(42)
    errors = []
    for _ in range(300):
        truth = _pose(rng)
        points = _camera_points(rng, 3)
        errors.append(_closest_error(solvers.solve_p3p(_bearings(points), _to_map(truth, points)), truth))
    assert max(errors) < 1e-8


@pytest.mark.parametrize("seed", SEEDS)
def test_two_3d_one_2d_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    points = _camera_points(rng, 3)
    world = _to_map(truth, points)
    candidates = solvers.solve_2pt3d_1pt2d(points[:2], world[:2], _bearings(points[2]), world[2])
    assert 1 <= len(candidates) <= 2
    assert _closest_error(candidates, truth) < 1e-8


@pytest.mark.parametrize("seed", SEEDS)
def test_one_3d_two_2d_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    points = _camera_points(rng, 3)
    world = _to_map(truth, points)
    candidates = solvers.solve_1pt3d_2pt2d(points[0], world[0], _bearings(points[1:]), world[1:])
    assert 1 <= len(candidates) <= 2
    assert _closest_error(candidates, truth) < 1e-8


@pytest.mark.parametrize("seed", SEEDS)
def test_three_planes_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    frame_planes, map_planes = _planes(rng, 3, truth)
    candidates = solvers.solve_3planes(frame_planes, map_planes)
    assert len(candidates) == 1
    assert _closest_error(candidates, truth) < 1e-8


@pytest.mark.parametrize("seed", SEEDS)
def test_two_planes_one_point_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    frame_planes, map_planes = _planes(rng, 2, truth)
    point = _camera_points(rng, 1)[0]
    candidates = solvers.solve_2planes_1pt(frame_planes, map_planes, point, _to_map(truth, point[None])[0])
    assert len(candidates) == 1
    assert _closest_error(candidates, truth) < 1e-8


@pytest.mark.parametrize("seed", SEEDS)
def test_one_plane_two_points_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _pose(rng)
    frame_planes, map_planes = _planes(rng, 1, truth)
    points = _camera_points(rng, 2)
    candidates = solvers.solve_1plane_2pts(frame_planes[0], map_planes[0], points, _to_map(truth, points))
    assert len(candidates) == 1
    assert _closest_error(candidates, truth) < 1e-8


def test_batched_solvers_match_single_sample_forms() -> None:
    rng = np.random.default_rng(7)
    count = 16
    truths = np.stack([_pose(rng) for _ in range(count)])
    points = np.stack([_camera_points(rng, 3) for _ in range(count)])
    world = np.einsum("hij,hnj->hni", truths[:, :3, :3], points) + truths[:, None, :3, 3]
    transforms, index = solvers.solve_points3d_batch(points, world)
    np.testing.assert_array_equal(index, np.arange(count))
    np.testing.assert_allclose(transforms, truths, atol=1e-8)
    transforms, index = solvers.solve_p3p_batch(_bearings(points), world)
    for h in range(count):
        assert _closest_error(list(transforms[index == h]), truths[h]) < 1e-8


def test_kabsch_batch_equals_umeyama_on_noisy_points() -> None:
    rng = np.random.default_rng(3)
    truth = _pose(rng)
    points = _camera_points(rng, 50)
    world = _to_map(truth, points) + rng.normal(0.0, 0.01, (50, 3))
    expected, _ = umeyama_alignment(points, world)
    np.testing.assert_allclose(solvers.kabsch_batch(points[None], world[None])[0], expected, atol=1e-10)


# ---------------------------------------------------------------------- degenerate input


def test_collinear_points_give_no_candidate() -> None:
    line = np.array([[0.0, 0.0, 1.0], [0.1, 0.1, 1.5], [0.2, 0.2, 2.0]])
    world = line + [1.0, 2.0, 3.0]
    assert solvers.solve_points3d(line, world) == []
    assert solvers.solve_p3p(_bearings(line + [0.5, 0.0, 0.0]), world) == []
    # the 2D point lies on the line of the two 3D points
    assert solvers.solve_2pt3d_1pt2d(line[:2], world[:2], _bearings(line[2]), world[2]) == []


def test_coincident_points_give_no_candidate() -> None:
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.3, 0.1, 2.0]])
    assert solvers.solve_points3d(points, points) == []


def test_parallel_planes_give_no_candidate() -> None:
    normal = np.array([0.0, 0.0, -1.0])
    planes = np.array([[*normal, 1.0], [*normal, 2.0], [*normal, 3.0]])
    assert solvers.solve_3planes(planes, planes) == []
    point = np.array([0.0, 0.0, 1.0])
    assert solvers.solve_2planes_1pt(planes[:2], planes[:2], point, point) == []
    # three normals in one plane (a "corridor" without floor) do not fix the translation
    coplanar = np.array([[1.0, 0, 0, 1.0], [0, 1.0, 0, 1.0], [np.sqrt(0.5), np.sqrt(0.5), 0, 2.0]])
    assert solvers.solve_3planes(coplanar, coplanar) == []


def test_plane_with_points_along_its_normal_gives_no_candidate() -> None:
    plane = np.array([0.0, 0.0, -1.0, 2.0])
    points = np.array([[0.1, 0.2, 1.0], [0.1, 0.2, 1.5]])  # the segment is parallel to the normal
    assert solvers.solve_1plane_2pts(plane, plane, points, points) == []


def test_nan_input_does_not_crash() -> None:
    points = np.full((3, 3), np.nan)
    planes = np.full((3, 4), np.nan)
    assert solvers.solve_points3d(points, points) == []
    assert solvers.solve_p3p(points, points) == []
    assert solvers.solve_2pt3d_1pt2d(points[:2], points[:2], points[2], points[2]) == []
    assert solvers.solve_1pt3d_2pt2d(points[0], points[0], points[1:], points[1:]) == []
    assert solvers.solve_3planes(planes, planes) == []
    assert solvers.solve_2planes_1pt(planes[:2], planes[:2], points[0], points[0]) == []
    assert solvers.solve_1plane_2pts(planes[0], planes[0], points[:2], points[:2]) == []


def test_batch_mixes_degenerate_and_valid_samples() -> None:
    rng = np.random.default_rng(11)
    truth = _pose(rng)
    good = _camera_points(rng, 3)
    line = np.array([[0.0, 0.0, 1.0], [0.1, 0.1, 1.5], [0.2, 0.2, 2.0]])
    frame = np.stack([line, good, line])
    transforms, index = solvers.solve_points3d_batch(frame, np.stack([_to_map(truth, f) for f in frame]))
    np.testing.assert_array_equal(index, [1])
    np.testing.assert_allclose(transforms[0], truth, atol=1e-8)
