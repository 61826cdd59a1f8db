import numpy as np
from scipy.spatial.transform import Rotation

from jsr.geometry import (
    backproject_depth,
    backproject_pixels,
    inlier_threshold,
    invert_transform,
    look_at,
    make_transform,
    project_points,
    rotation_angle,
    transform_points,
    umeyama_alignment,
)


def test_invert_and_transform():
    rng = np.random.default_rng(0)
    transform = make_transform(Rotation.random(random_state=1).as_matrix(), rng.normal(size=3))
    assert np.allclose(invert_transform(transform) @ transform, np.eye(4))
    points = rng.normal(size=(10, 3))
    assert np.allclose(transform_points(invert_transform(transform), transform_points(transform, points)), points)
    stack = np.stack([transform, np.eye(4)])
    assert np.allclose(invert_transform(stack)[0], np.linalg.inv(transform))


def test_umeyama_recovers_rigid_and_similarity():
    rng = np.random.default_rng(2)
    source = rng.normal(size=(30, 3))
    truth = make_transform(Rotation.random(random_state=3).as_matrix(), [1.0, -2.0, 0.5])
    target = transform_points(truth, source)
    estimate, scale = umeyama_alignment(source, target)
    assert np.allclose(estimate, truth, atol=1e-10) and scale == 1.0
    estimate, scale = umeyama_alignment(source, 2.5 * target, with_scale=True)
    assert np.isclose(scale, 2.5)


def test_rotation_angle():
    rotation = Rotation.from_rotvec([0, 0, 0.3]).as_matrix()
    assert np.isclose(rotation_angle(rotation), 0.3)


def test_inlier_threshold_is_paper_sigma():
    # sigma = max(1 cm, 3 * 1.425e-3 Z^2): 1 cm up to Z = 1.53 m, then grows
    assert np.isclose(inlier_threshold(1.0), 0.01)
    assert np.isclose(inlier_threshold(3.0), 3 * 1.425e-3 * 9)


def test_backprojection_and_projection_agree():
    depth = np.full((4, 5), 2.0, dtype=np.float32)
    cloud = backproject_depth(depth, 100.0, 100.0, 2.0, 1.5)
    pixels = project_points(cloud.reshape(-1, 3), 100.0, 100.0, 2.0, 1.5)
    u, v = np.meshgrid(np.arange(5), np.arange(4))
    assert np.allclose(pixels, np.column_stack([u.ravel(), v.ravel()]))
    assert np.allclose(backproject_pixels(u.ravel(), v.ravel(), depth.ravel(), 100, 100, 2.0, 1.5), cloud.reshape(-1, 3))


def test_look_at_points_camera_z_at_target():
    pose = look_at([2.0, 0.0, 1.0], [0.0, 0.0, 1.0])
    assert np.allclose(pose[:3, 2], [-1, 0, 0])
    assert np.allclose(pose[:3, 1], [0, 0, -1])  # image down is world down
    assert np.isclose(np.linalg.det(pose[:3, :3]), 1.0)


def test_cross_matrices_multiply_as_the_cross_product():
    from jsr.geometry import cross_matrices

    rng = np.random.default_rng(0)
    v, u = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", cross_matrices(v), u), np.cross(v, u), atol=1e-12)
    np.testing.assert_allclose(cross_matrices(v[0]) @ u[0], np.cross(v[0], u[0]), atol=1e-12)
