"""Shape-based alignment of object surfaces (jsr.pipeline.surfaces)."""

import numpy as np

from jsr.geometry import make_transform, rotation_about_axis, transform_points
from scipy.spatial import cKDTree

from jsr.pipeline.surfaces import SurfaceSample, align_surfaces, build_model, geometric_constraint, sample_surface

VOXEL = 0.01


def _box_faces(size=(0.24, 0.18, 0.12), spacing=0.004, seed=0):
    """Points ``(N, 3)`` and colours ``(N, 3)`` uint8 of three faces of a box centred at the
    origin (+x, +y, +z), each with its own colour and a blotchy texture."""
    rng = np.random.default_rng(seed)
    half = np.asarray(size) / 2
    points, colors = [], []
    base = {0: (200, 40, 40), 1: (40, 180, 60), 2: (40, 60, 200)}
    blobs = rng.uniform(-0.12, 0.12, size=(12, 3))
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        u = np.arange(-half[others[0]], half[others[0]], spacing)
        v = np.arange(-half[others[1]], half[others[1]], spacing)
        uu, vv = np.meshgrid(u, v)
        face = np.zeros((uu.size, 3))
        face[:, axis] = half[axis]
        face[:, others[0]], face[:, others[1]] = uu.ravel(), vv.ravel()
        color = np.tile(np.asarray(base[axis], float), (len(face), 1))
        near_blob = np.min(np.linalg.norm(face[:, None] - blobs[None], axis=2), axis=1) < 0.03
        color[near_blob] = 255 - color[near_blob]
        points.append(face)
        colors.append(color.astype(np.uint8))
    return np.concatenate(points), np.concatenate(colors)


def _view(points, colors, T_model_camera):
    """The box as sampled from a camera at ``T_model_camera`` (camera-frame points)."""
    camera_points = transform_points(np.linalg.inv(T_model_camera), points)
    return SurfaceSample(camera_points.astype(np.float32), colors)


def test_alignment_recovers_a_turned_textured_box():
    points, colors = _box_faces()
    T_model_camera = make_transform(np.eye(3), [0.0, 0.0, 0.8])  # camera in front of +z, facing it
    T_model_camera[:3, :3] = rotation_about_axis([1.0, 0.0, 0.0], np.pi)  # looking along -z
    model = build_model([(T_model_camera, _view(points, colors, T_model_camera))], VOXEL)
    # The region: the box turned by 100 degrees about z and shifted, seen from the same camera
    # (its +x and +y faces swap places, a view its features would not match)
    T_true = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.radians(100)), [0.05, -0.03, 0.0])
    region_points = transform_points(T_true, points)
    region = build_model([(T_model_camera, _view(region_points, colors, T_model_camera))], VOXEL)
    alignments = align_surfaces(region, model, VOXEL, np.random.default_rng(0))
    assert alignments, "no alignment found"
    best = alignments[0]
    error = best.T_model_region @ T_true  # region frame = model frame here: should be identity
    angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert np.linalg.norm(error[:3, 3]) < 0.02 and angle < 3.0
    assert best.fitness > 0.8


def test_alignment_is_reproducible():
    points, colors = _box_faces(seed=3)
    T = make_transform(np.eye(3), [0.0, 0.0, 1.0])
    model = build_model([(T, _view(points, colors, T))], VOXEL)
    turned = transform_points(make_transform(rotation_about_axis([0, 0, 1], 0.7), [0.02, 0, 0]), points)
    region = build_model([(T, _view(turned, colors, T))], VOXEL)
    first = align_surfaces(region, model, VOXEL, np.random.default_rng(5))
    second = align_surfaces(region, model, VOXEL, np.random.default_rng(5))
    assert len(first) == len(second)
    for a, b in zip(first, second):
        np.testing.assert_allclose(a.T_model_region, b.T_model_region, atol=1e-9)


def test_sample_surface_keeps_mask_pixels_with_depth():
    class Intrinsics:
        fx = fy = 500.0
        cx, cy = 32.0, 24.0

    depth = np.full((48, 64), 1.0, dtype=np.float32)
    depth[:, :10] = 0.0
    mask = np.zeros((48, 64), dtype=bool)
    mask[10:30, 5:40] = True
    color = np.zeros((48, 64, 3), dtype=np.uint8)
    sample = sample_surface(depth, color, mask, Intrinsics(), stride=2, voxel=1e-4)
    assert len(sample.points) == 10 * 15  # rows 10..28 step 2, columns 10..38 step 2
    np.testing.assert_allclose(sample.points[:, 2], 1.0)


def _cylinder_side(radius=0.06, height=0.25, spacing=0.004, arc_degrees=150.0):
    """Points ``(N, 3)`` on an arc of a cylinder's side about the z axis, and grey colours."""
    angles = np.radians(np.arange(-arc_degrees / 2, arc_degrees / 2, np.degrees(spacing / radius)))
    heights = np.arange(-height / 2, height / 2, spacing)
    aa, hh = np.meshgrid(angles, heights)
    points = np.stack([radius * np.cos(aa.ravel()), radius * np.sin(aa.ravel()), hh.ravel()], axis=1)
    return points, np.full((len(points), 3), 128, dtype=np.uint8)


def _constraint_of(points, colors):
    """geometric_constraint of a surface against itself, seen from a camera on +x+y+z."""
    T = make_transform(np.eye(3), [0.8, 0.6, 0.7])
    model = build_model([(T, _view(points, colors, T))], VOXEL)
    return geometric_constraint(model, model, cKDTree(model.points), np.eye(4), VOXEL)


def test_geometric_constraint_tells_a_box_corner_from_sliding_surfaces():
    box_points, box_colors = _box_faces()
    corner = _constraint_of(box_points, box_colors)
    # three faces pin every motion; a cylinder's side turns about its axis, a plane slides
    cylinder = _constraint_of(*_cylinder_side())
    plane = box_points[:, 2] == box_points[:, 2].max()
    flat = _constraint_of(box_points[plane], box_colors[plane])
    assert corner > 0.03
    assert cylinder < 0.005 and flat < 0.005


def test_shape_alone_needs_a_complete_pinned_unrivalled_fit_in_the_objects_own_colours():
    """Reconstructor._shape_alone: the rules that let a surface alignment re-identify a lost
    object without landmark matches."""
    from types import SimpleNamespace

    from jsr.config import load_config
    from jsr.pipeline.reconstruct import Reconstructor
    from jsr.pipeline.surfaces import Alignment

    config = load_config(None)
    owner = SimpleNamespace(config=config, _surface_self_residual=lambda object_map: 0.05)
    camera = make_transform(np.eye(3), [0.8, 0.6, 0.7])
    box = build_model([(camera, _view(*_box_faces(), camera))], VOXEL)
    turned = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.pi), np.zeros(3))
    shifted = make_transform(np.eye(3), [0.03, 0.0, 0.0])

    def alone(alignments, region=box, model=box):
        return Reconstructor._shape_alone(owner, SimpleNamespace(object_id=1), region, model, alignments)

    right = Alignment(np.eye(4), 0.98, 0.07)
    assert alone([right]) is right
    assert alone([Alignment(np.eye(4), 0.8, 0.07)]) is None  # too little of the region on the model
    too_colourful = 1.2 * config.objects.shape_max_color_ratio * 0.05
    assert alone([Alignment(np.eye(4), 0.98, too_colourful)]) is None  # beyond the object's own views' agreement
    assert alone([right, Alignment(turned, 0.95, 0.09)]) is None  # a turned fit nearly as good: ambiguous
    assert alone([right, Alignment(turned, 0.95, 0.2)]) is right  # the turned fit's colours disagree
    assert alone([right, Alignment(shifted, 0.97, 0.07)]) is right  # 3 cm apart: the same fit
    cylinder = build_model([(camera, _view(*_cylinder_side(), camera))], VOXEL)
    assert alone([right], cylinder, cylinder) is None  # turns about its axis: shape does not pin it
    owner._surface_self_residual = lambda object_map: None
    assert alone([right]) is None  # one view of the object: nothing to compare colours with
    owner._surface_self_residual = lambda object_map: 0.05
    owner.config = load_config(None, ["objects.shape_max_color_ratio=0"])
    assert alone([right]) is None  # switched off: only fits that landmarks confirm


def test_same_placement_compares_alignments_at_the_region():
    """Two alignments of a region 1.2 m in front of its camera (the region frame's origin):
    an 8-degree turn about the region is a small change, though it moves the camera 17 cm; a
    turn about the camera moves the region far."""
    from jsr.pipeline.surfaces import same_placement

    centre = np.array([0.0, 0.0, 1.2])
    turn = rotation_about_axis([0.0, 1.0, 0.0], np.radians(8))
    about_region = make_transform(turn, centre - turn @ centre)
    assert same_placement(np.eye(4), about_region, centre, 0.1, 15.0)
    assert not same_placement(np.eye(4), make_transform(rotation_about_axis([0.0, 1.0, 0.0], np.radians(14)),
                                                         np.zeros(3)), centre, 0.1, 15.0)  # 29 cm at the region
