"""The dense term of static tracking: keyframe depth sampled with normals, a frame's depth
aligned to it point-to-plane (alone, and beside feature residuals), and the checks that keep a
poorly constrained alignment out."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsr.config import load_config
from jsr.geometry import invert_transform, make_transform, rotation_angle
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline.dense_alignment import (align_depth, carries, depth_surface, depth_target, disagreement,
                                          frame_samples, point_to_plane_terms, trusted)

INTRINSICS = CameraIntrinsics(fx=240.0, fy=240.0, cx=159.5, cy=119.5, width=320, height=240)
CONFIG = load_config(None)


def quad(corner, along_u, along_v):
    """Two triangles spanning ``corner + s u + t v`` (s, t in [0, 1])."""
    corner, along_u, along_v = (np.asarray(x, dtype=np.float32) for x in (corner, along_u, along_v))
    vertices = np.stack([corner, corner + along_u, corner + along_v, corner + along_u + along_v])
    return vertices, np.array([[0, 1, 2], [1, 3, 2]], dtype=np.uint32)


def room():
    """A floor, two walls meeting in a corner and a box on the floor (world frame: y down,
    the camera at the origin looks along +z)."""
    quads = [quad([-3, 1, 0.5], [6, 0, 0], [0, 0, 5]),  # floor at y = 1
             quad([-3, -2, 4], [6, 0, 0], [0, 3, 0]),  # back wall at z = 4
             quad([-1.5, -2, 0.5], [0, 0, 5], [0, 3, 0])]  # side wall at x = -1.5
    lo, hi = np.array([0.2, 0.6, 2.0]), np.array([0.6, 1.0, 2.4])  # a box standing on the floor
    size = hi - lo
    quads += [quad(lo, [size[0], 0, 0], [0, size[1], 0]), quad(lo, [0, 0, size[2]], [0, size[1], 0]),
              quad(lo, [size[0], 0, 0], [0, 0, size[2]]), quad([hi[0], lo[1], lo[2]], [0, 0, size[2]], [0, size[1], 0])]
    return quads


def render_depth(quads, T_w_c, noise_rng=None) -> np.ndarray:
    """``(H, W)`` depth (metres along the optical axis) seen from ``T_w_c``, with the axial
    noise of the default config when ``noise_rng`` is given."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for vertices, triangles in quads:
        scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
    v, u = np.mgrid[0:INTRINSICS.height, 0:INTRINSICS.width]
    rays_c = np.stack([(u - INTRINSICS.cx) / INTRINSICS.fx, (v - INTRINSICS.cy) / INTRINSICS.fy,
                       np.ones_like(u, dtype=float)], axis=-1).reshape(-1, 3)
    rays = np.concatenate([np.broadcast_to(T_w_c[:3, 3], rays_c.shape), rays_c @ T_w_c[:3, :3].T], axis=1)
    hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy().astype(np.float64)
    depth = np.where(np.isfinite(hit), hit, 0.0).reshape(INTRINSICS.height, INTRINSICS.width)  # rays have z = 1
    if noise_rng is not None:
        sigma = CONFIG.noise.sigma_z_coefficient * depth**2
        depth = np.where(depth > 0, depth + noise_rng.normal(0.0, 1.0, depth.shape) * sigma, 0.0)
    return depth.astype(np.float32)


def moved(T, degrees, axis, translation):
    return T @ make_transform(Rotation.from_rotvec(np.deg2rad(degrees) * np.asarray(axis, float)).as_matrix(),
                              translation)


def pose_error(a, b) -> tuple[float, float]:
    relative = invert_transform(a) @ b
    return float(np.linalg.norm(relative[:3, 3])), float(np.rad2deg(rotation_angle(relative[:3, :3])))


def test_keyframe_surface_normals_fit_the_planes_and_face_the_camera():
    depth = render_depth(room(), np.eye(4))
    surface = depth_surface(depth, np.ones(depth.shape, bool), INTRINSICS, CONFIG.dense, CONFIG.noise)
    assert len(surface.points) > 500
    assert np.allclose(np.linalg.norm(surface.normals, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", surface.normals, surface.points) < 0)  # towards the camera
    # samples on the back wall (z = 4, away from its edges) have the normal (0, 0, -1)
    wall = (np.abs(surface.points[:, 2] - 4.0) < 1e-3) & (surface.points[:, 0] > -1.2) & (surface.points[:, 1] < 0.7)
    assert wall.sum() > 50
    assert np.all(surface.normals[wall] @ [0, 0, -1] > np.cos(np.deg2rad(1.0)))
    # the sigma is the axial noise at the sample's depth
    assert np.allclose(surface.sigma[wall], CONFIG.noise.sigma_z_coefficient * 16.0, rtol=1e-3)
    # every surface is axis-aligned: only samples on a crease (two faces within their
    # neighbours) have a normal between two axes; none takes one across the box's silhouette
    off_axis = np.abs(surface.normals).max(axis=1) < np.cos(np.deg2rad(5.0))
    assert off_axis.mean() < 0.08
    kept_out = np.zeros(depth.shape, bool)
    kept_out[:, :160] = True
    half = depth_surface(depth, ~kept_out, INTRINSICS, CONFIG.dense, CONFIG.noise)
    assert len(half.points) < 0.6 * len(surface.points)
    assert np.all(half.points[:, 0] / half.points[:, 2] * INTRINSICS.fx + INTRINSICS.cx >= 159.0)


def two_keyframes_of_the_room(rng):
    """The room's noisy depth from the origin and from a view 16 cm and 6 degrees away, as a
    :class:`DepthTarget`."""
    keyframes = [np.eye(4), moved(np.eye(4), 6.0, [0, 1, 0], [0.15, 0.0, 0.05])]
    return depth_target([(T, depth_surface(render_depth(room(), T, rng), np.ones((240, 320), bool), INTRINSICS,
                                           CONFIG.dense, CONFIG.noise)) for T in keyframes])


def test_depth_alone_recovers_a_pose_predicted_centimetres_off():
    rng = np.random.default_rng(0)
    target = two_keyframes_of_the_room(rng)
    truth = moved(np.eye(4), 4.0, [0.3, 1, 0], [0.08, -0.03, 0.1])
    source, sigma = frame_samples(render_depth(room(), truth, rng), None, INTRINSICS, CONFIG.dense, CONFIG.noise)
    predicted = moved(truth, 1.5, [1, 0, 0.5], [0.02, 0.015, -0.02])
    assert pose_error(predicted, truth)[0] > 0.03
    fit = align_depth(source, sigma, target, predicted, CONFIG.dense)
    assert carries(fit, CONFIG.dense)
    translation, degrees = pose_error(fit.pose, truth)
    assert translation < 0.003 and degrees < 0.15
    assert fit.overlap > 0.9 and fit.normal_spread > 0.1


@pytest.mark.parametrize("distance", [1.5, 3.0])
def test_depth_alone_refuses_a_single_wall(distance):
    """A wall fixes depth and two rotations; sliding along it is free. With the sensor's noise
    the normals scatter (about 12 degrees at 3 m), which must not pass for constraint."""
    rng = np.random.default_rng(1)
    wall = [quad([-6, -4, distance], [12, 0, 0], [0, 8, 0])]
    target = depth_target([(np.eye(4), depth_surface(render_depth(wall, np.eye(4), rng), np.ones((240, 320), bool),
                                                     INTRINSICS, CONFIG.dense, CONFIG.noise))])
    truth = moved(np.eye(4), 0.0, [0, 1, 0], [0.05, 0.0, 0.0])
    source, sigma = frame_samples(render_depth(wall, truth, rng), None, INTRINSICS, CONFIG.dense, CONFIG.noise)
    fit = align_depth(source, sigma, target, moved(truth, 0.0, [0, 1, 0], [0.03, 0.02, 0.0]), CONFIG.dense)
    assert fit is not None and fit.overlap > 0.9
    assert not carries(fit, CONFIG.dense)


def test_normals_stay_off_a_thin_strip_before_a_wall():
    """A sample's normal comes from neighbours on its own surface: a 45-degree strip 1 m before
    a wall keeps its own normal, none taken from the wall behind it."""
    strip = quad([-0.05, -1.0, 0.95], [0.1, 0, 0.1], [0, 2.0, 0])
    wall = quad([-3, -2, 2.0], [6, 0, 0], [0, 4, 0])
    depth = render_depth([strip, wall], np.eye(4))
    surface = depth_surface(depth, np.ones(depth.shape, bool), INTRINSICS, CONFIG.dense, CONFIG.noise)
    on_strip = surface.points[:, 2] < 1.5
    assert on_strip.sum() > 5
    expected = np.array([-1.0, 0.0, 1.0]) / np.sqrt(2.0)
    assert np.all(np.abs(surface.normals[on_strip] @ expected) > np.cos(np.deg2rad(5.0)))


def test_features_and_depth_together_fix_what_depth_alone_leaves_free():
    """A single wall leaves three directions free; three feature points off the wall's plane,
    given as residuals of their own (a ``linearised`` like the image-space feature terms),
    fix them, and the depth still sets the distance to the wall."""
    wall = [quad([-3, -2, 3], [6, 0, 0], [0, 4, 0])]
    target = depth_target([(np.eye(4), depth_surface(render_depth(wall, np.eye(4)), np.ones((240, 320), bool),
                                                     INTRINSICS, CONFIG.dense, CONFIG.noise))])
    truth = moved(np.eye(4), 2.0, [0, 1, 0], [0.05, 0.02, 0.0])
    source, sigma = frame_samples(render_depth(wall, truth), None, INTRINSICS, CONFIG.dense, CONFIG.noise)
    # three world points known in the camera frame, as point-to-plane pairs along x, y and z
    world = np.array([[0.5, 0.2, 2.0], [-0.4, -0.3, 2.5], [0.1, 0.5, 1.5]])
    in_camera = (world - truth[:3, 3]) @ truth[:3, :3]
    p = np.repeat(in_camera, 3, axis=0)
    q = np.repeat(world, 3, axis=0)
    n = np.tile(np.eye(3), (3, 1))
    features = point_to_plane_terms(p, q, n, np.full(len(p), 0.002))
    start = moved(truth, 0.5, [0, 0, 1], [0.01, -0.01, 0.01])
    fit = align_depth(source, sigma, target, start, CONFIG.dense, features)
    translation, degrees = pose_error(fit.pose, truth)
    assert translation < 0.002 and degrees < 0.1


def test_disagreement_is_how_far_the_depth_moves_a_feature_pose():
    """A keyframe's features placed it exactly: its depth alone hardly moves it (the noise).
    Placed 3 cm off: the depth moves its samples back by about that. On a single wall the depth
    cannot place a frame, and says nothing."""
    rng = np.random.default_rng(1)
    target = two_keyframes_of_the_room(rng)
    truth = moved(np.eye(4), 3.0, [0.3, 1, 0], [0.06, -0.02, 0.08])
    source, sigma = frame_samples(render_depth(room(), truth, rng), None, INTRINSICS, CONFIG.dense, CONFIG.noise)
    assert disagreement(source, sigma, target, truth, CONFIG.dense) < 0.003
    off = moved(truth, 0.0, [1, 0, 0], [0.03, 0.0, 0.0])
    assert abs(disagreement(source, sigma, target, off, CONFIG.dense) - 0.03) < 0.005
    wall = [quad([-3, -2, 2.0], [6, 0, 0], [0, 4, 0])]
    wall_target = depth_target([(np.eye(4), depth_surface(render_depth(wall, np.eye(4), rng), np.ones((240, 320), bool),
                                                          INTRINSICS, CONFIG.dense, CONFIG.noise))])
    wall_source, wall_sigma = frame_samples(render_depth(wall, truth, rng), None, INTRINSICS, CONFIG.dense,
                                            CONFIG.noise)
    assert disagreement(wall_source, wall_sigma, wall_target, truth, CONFIG.dense) is None


def test_the_depth_is_trusted_by_the_median_of_the_latest_disagreements():
    config = load_config(None, ["dense.trust_within=0.02", "dense.trust_keyframes=3"]).dense
    assert not trusted([], config)  # nothing measured yet
    assert trusted([0.01, 0.05, 0.015], config)
    assert not trusted([0.01, 0.05, 0.015, 0.03], config)  # the latest three: median 0.03
    assert trusted([0.09], load_config(None, ["dense.trust_within=0"]).dense)  # 0: always


def test_free_space_judged_on_the_depth_registration_not_the_keyframe_pose():
    """FreeSpaceViews.counts with the frame's static samples: the frame is placed on each view
    by its depth first. A keyframe pose 2 degrees off puts the standing box's samples in front
    of the wall the view saw behind it (free space "violated" by a static thing); placed by the
    depth, the box agrees with the view. A box that did move 35 cm towards the camera still
    violates free space."""
    from types import SimpleNamespace

    from jsr.pipeline.free_space import FreeSpaceViews

    rng = np.random.default_rng(3)
    view_pose = moved(np.eye(4), 6.0, [0, 1, 0], [0.15, 0.0, 0.05])
    stored_pose = moved(view_pose, 2.0, [0.2, 1, 0], [0.01, 0.0, 0.0])  # the keyframe's pose, off
    keyframes = [SimpleNamespace(keyframe_id=0, frame_index=0, T_map_cam=stored_pose)]
    views = FreeSpaceViews(CONFIG, INTRINSICS)
    view_depth = render_depth(room(), view_pose, rng)
    views.remember(keyframes[0], view_depth, np.zeros((240, 320), bool))
    surfaces = {0: depth_surface(view_depth, np.ones((240, 320), bool), INTRINSICS, CONFIG.dense, CONFIG.noise)}

    def counts(quads, box_lo, box_hi, registered):
        depth = render_depth(quads, np.eye(4), rng)
        # the box's segment: pixels whose point lies within the box (2 cm margin)
        v, u = np.mgrid[0:240, 0:320]
        points = np.stack([(u - INTRINSICS.cx) / INTRINSICS.fx * depth, (v - INTRINSICS.cy) / INTRINSICS.fy * depth,
                           depth], axis=-1)
        on_box = np.all((points > np.asarray(box_lo) - 0.02) & (points < np.asarray(box_hi) + 0.02), axis=-1)
        labels = on_box.astype(np.int32)
        samples = frame_samples(depth, ~on_box, INTRINSICS, CONFIG.dense, CONFIG.noise) if registered else None
        violations, consistent = views.counts(keyframes, depth, labels, 2, np.eye(4), measured_only=True,
                                              static_samples=samples, surfaces=surfaces)
        return violations[1], consistent[1]

    lo, hi = [0.2, 0.6, 2.0], [0.6, 1.0, 2.4]
    violated, agreeing = counts(room(), lo, hi, registered=False)
    assert violated >= 10  # the pose error alone makes the static box look moved in
    violated, agreeing = counts(room(), lo, hi, registered=True)
    assert violated <= 1 and agreeing > 100
    # the box moved 35 cm towards the camera: in space the view saw empty, with or without
    shift = np.array([0.0, 0.0, -0.35])
    moved_room = room()[:3]
    size = np.subtract(hi, lo)
    low = np.add(lo, shift)
    high = low + size
    moved_room += [quad(low, [size[0], 0, 0], [0, size[1], 0]), quad(low, [0, 0, size[2]], [0, size[1], 0]),
                   quad(low, [size[0], 0, 0], [0, 0, size[2]]), quad([high[0], low[1], low[2]], [0, 0, size[2]],
                                                                     [0, size[1], 0])]
    violated, agreeing = counts(moved_room, low, high, registered=True)
    assert violated > 100 and agreeing <= 0.1 * violated
    # a pose error the view's neighbourhood absorbs (under near_radius samples in the view)
    # leaves the feature pose as it is
    _, view = views.views[0]
    view.T_w_c = moved(view_pose, 0.3, [0.2, 1, 0], [0.002, 0.0, 0.0])
    samples = frame_samples(render_depth(room(), np.eye(4), rng), None, INTRINSICS, CONFIG.dense, CONFIG.noise)
    assert views.registered_pose(view, surfaces[0], np.eye(4), samples) is not None
    assert np.array_equal(views.registered_pose(view, surfaces[0], np.eye(4), samples), np.eye(4))
    # with the view's pose off by 2 degrees, the frame is placed where the view sees it truly
    view.T_w_c = stored_pose
    translation, degrees = pose_error(views.registered_pose(view, surfaces[0], np.eye(4), samples),
                                      stored_pose @ invert_transform(view_pose))
    assert translation < 0.005 and degrees < 0.2
