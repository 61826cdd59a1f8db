"""Shape-based alignment of object surfaces (jsr.pipeline.surfaces, jsr.pipeline.surface_alignment,
jsr.pipeline.surface_evidence)."""

import numpy as np

from jsr.geometry import make_transform, rotation_about_axis, transform_points
from scipy.spatial import cKDTree

from jsr.pipeline.surface_alignment import CACHED_VOXELS, MAX_ALIGNED_POINTS, _model_at, align_surfaces, alignment_voxel
from jsr.pipeline.surface_evidence import geometric_constraint, texture_agreement
from jsr.pipeline.surfaces import SurfaceSample, build_model, sample_surface, thinned

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


def test_a_large_surface_is_aligned_at_a_coarser_voxel():
    """A person-sized surface (three faces of a 1.0 x 0.8 x 0.5 m box, ~17000 points at 1 cm) is
    aligned at a voxel that leaves neither surface more than MAX_ALIGNED_POINTS points (bounded
    cost), and the turn is still found; a box of 24 cm keeps the full resolution."""
    points, colors = _box_faces(size=(1.0, 0.8, 0.5), spacing=0.008)
    T_model_camera = make_transform(rotation_about_axis([1.0, 0.0, 0.0], np.pi), [0.0, 0.0, 2.5])
    model = build_model([(T_model_camera, _view(points, colors, T_model_camera))], VOXEL)
    T_true = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.radians(100)), [0.05, -0.03, 0.0])
    region = build_model([(T_model_camera, _view(transform_points(T_true, points), colors, T_model_camera))], VOXEL)
    assert len(model.points) > 4 * MAX_ALIGNED_POINTS
    coarser = alignment_voxel(region, model, VOXEL)
    assert coarser > 2 * VOXEL
    assert max(len(thinned(region, coarser).points), len(thinned(model, coarser).points)) <= MAX_ALIGNED_POINTS
    small, small_colors = _box_faces(size=(0.24, 0.2, 0.15), spacing=0.008)
    small_model = build_model([(T_model_camera, _view(small, small_colors, T_model_camera))], VOXEL)
    assert len(small_model.points) < MAX_ALIGNED_POINTS
    assert alignment_voxel(small_model, small_model, VOXEL) == VOXEL
    alignments = align_surfaces(region, model, VOXEL, np.random.default_rng(0))
    assert alignments, "no alignment found"
    error = alignments[0].T_model_region @ T_true
    angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert np.linalg.norm(error[:3, 3]) < 0.03 and angle < 3.0


def test_alignment_is_reproducible():
    points, colors = _box_faces(seed=3)
    T = make_transform(np.eye(3), [0.0, 0.0, 1.0])
    model = build_model([(T, _view(points, colors, T))], VOXEL)
    turned = transform_points(make_transform(rotation_about_axis([0, 0, 1], 0.7), [0.02, 0, 0]), points)
    region = build_model([(T, _view(turned, colors, T))], VOXEL)
    first = align_surfaces(region, model, VOXEL, np.random.default_rng(5))
    for _ in range(3):  # Open3D's multi-threaded ICP differed in the last bits from run to run
        again = align_surfaces(region, model, VOXEL, np.random.default_rng(5))
        assert len(again) == len(first)
        for a, b in zip(first, again):
            np.testing.assert_array_equal(a.T_model_region, b.T_model_region)  # bit for bit


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


class _Intrinsics:
    fx = fy = 300.0
    cx, cy = 160.0, 120.0


def _depth_view(camera_points, wall_depth=None, shape=(240, 320)):
    """A :class:`~jsr.pipeline.free_space.DepthView` (stride 2, camera frame) of ``(N, 3)``
    camera-frame points rendered into a z-buffer, in front of a wall at ``wall_depth`` m
    (None: no depth elsewhere)."""
    from jsr.geometry import project_points
    from jsr.pipeline.free_space import DepthView

    depth = np.full(shape, np.inf if wall_depth is None else wall_depth, dtype=np.float64)
    uv = np.round(project_points(camera_points, _Intrinsics.fx, _Intrinsics.fy, _Intrinsics.cx,
                                 _Intrinsics.cy)).astype(int)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < shape[0])
    np.minimum.at(depth, (uv[inside, 1], uv[inside, 0]), camera_points[inside, 2])
    depth[~np.isfinite(depth)] = 0.0
    return DepthView(depth[::2, ::2].astype(np.float32), np.eye(4), 2)


def _box_camera():
    """``T_model_camera`` of a camera 0.8 m from the box centre on +x+y+z, looking at it."""
    from jsr.geometry import look_at

    return look_at(np.array([0.45, 0.4, 0.5]), np.zeros(3))


def _box_scene():
    """The box seen from :func:`_box_camera` in front of a wall 1.6 m away: ``camera``
    (``T_model_camera``), the view's sample, the box's model, the region (the sample as a
    model, camera frame) and the view's depth."""
    from jsr.pipeline.surfaces import region_model

    points, colors = _box_faces()
    camera = _box_camera()
    seen = _view(points, colors, camera)
    return (camera, seen, build_model([(camera, seen)], VOXEL), region_model(seen, VOXEL),
            _depth_view(seen.points.astype(float), wall_depth=1.6))


def _seen_through_in(view, model):
    """A function of a placement ``T_model_camera`` of ``model``: its
    :func:`~jsr.pipeline.surface_evidence.seen_through_share` in ``view`` (margins 3 cm and 3
    sigmas, None when too little can be checked)."""
    from jsr.config import load_config
    from jsr.pipeline.surface_evidence import seen_through_share

    noise = load_config(None).noise
    return lambda T_model_camera: seen_through_share(model, T_model_camera, view, _Intrinsics(), noise, 0.03, 3.0)


def test_seen_through_share_finds_a_model_placed_in_seen_empty_space():
    """A right placement puts the model on the surface the view measured; one 10 cm towards
    the camera, or 15 cm aside against a wall behind the box, puts it in space seen empty."""
    points, colors = _box_faces()
    camera = _box_camera()
    model = build_model([(camera, _view(points, colors, camera))], VOXEL)
    share = _seen_through_in(_depth_view(_view(points, colors, camera).points.astype(float), wall_depth=1.6), model)

    assert share(camera) < 0.01
    towards = make_transform(np.eye(3), [0.0, 0.0, -0.1])  # in the camera frame: 10 cm nearer
    assert share(camera @ np.linalg.inv(towards)) > 0.9
    aside = make_transform(np.eye(3), [0.15, 0.0, 0.0])
    assert share(camera @ np.linalg.inv(aside)) > 0.3
    behind = make_transform(np.eye(3), [0.0, 0.0, 0.1])  # occluded by the box: not seen through
    assert share(camera @ np.linalg.inv(behind)) < 0.01
    # no depth where the model falls: nothing to check
    assert _seen_through_in(_depth_view(np.zeros((0, 3))), model)(camera) is None


def test_seen_through_share_leaves_out_a_face_seen_edge_on():
    """A face seen nearly edge-on (83-85 degrees from face-on) returns no depth to a sensor,
    which measures the wall behind it there: at the right placement it is not counted as seen
    through (the share was 0.20 when it counted), and a placement 10 cm nearer still is."""
    from jsr.config import load_config
    from jsr.geometry import look_at

    points, colors = _box_faces()
    model = build_model([(_box_camera(), _view(points, colors, _box_camera()))], VOXEL)
    camera = look_at(np.array([0.2, 0.45, 0.6]), np.zeros(3))  # the +x face 83-85 degrees from face-on
    measured_faces = points[:, 0] < 0.119  # the depth sensor returns the +y and +z faces only
    view = _depth_view(_view(points[measured_faces], colors[measured_faces], camera).points.astype(float),
                       wall_depth=1.6)
    share = _seen_through_in(view, model)

    assert share(camera) < load_config(None).objects.shape_max_seen_through
    towards = make_transform(np.eye(3), [0.0, 0.0, -0.1])
    assert share(camera @ np.linalg.inv(towards)) > 0.9


def _textured(points, seed=1):
    """Blotchy colours ``(N, 3)`` uint8 for any surface ``points`` ``(N, 3)``: grey, with
    dark blotches of 3 cm around random centres."""
    rng = np.random.default_rng(seed)
    centres = points[rng.choice(len(points), size=12, replace=False)]
    near = np.min(np.linalg.norm(points[:, None] - centres[None], axis=2), axis=1) < 0.03
    colors = np.full((len(points), 3), 200, dtype=np.uint8)
    colors[near] = 50
    return colors


def _rings(points, width=0.05):
    """Colours ``(N, 3)`` uint8 in bands of ``width`` m along z: a texture that a turn about
    the z axis leaves as it is."""
    colors = np.full((len(points), 3), 200, dtype=np.uint8)
    colors[np.floor(points[:, 2] / width).astype(int) % 2 == 0] = 50
    return colors


def test_texture_agreement_sees_whether_the_texture_lines_up():
    from jsr.pipeline.surfaces import region_model

    points, colors = _box_faces()
    camera = _box_camera()
    seen = _view(points, colors, camera)
    box = build_model([(camera, seen)], VOXEL)
    region = region_model(seen, VOXEL)
    tree = cKDTree(box.points)
    assert texture_agreement(region, box, tree, camera, VOXEL) > 0.95
    darker = region_model(SurfaceSample(seen.points, (0.6 * seen.colors + 20).astype(np.uint8)), VOXEL)
    assert texture_agreement(darker, box, tree, camera, VOXEL) > 0.95  # shading: a gain and a shift
    shuffled = region_model(SurfaceSample(seen.points, np.random.default_rng(0).permutation(seen.colors)), VOXEL)
    assert abs(texture_agreement(shuffled, box, tree, camera, VOXEL)) < 0.1  # another object's colours
    uniform = region_model(SurfaceSample(seen.points, np.full_like(seen.colors, 128)), VOXEL)
    assert texture_agreement(uniform, box, tree, camera, VOXEL) == 0.0  # no texture to line up
    far = make_transform(np.eye(3), [1.0, 0.0, 0.0]) @ camera
    assert texture_agreement(region, box, tree, far, VOXEL) == 0.0  # nothing on the model


def test_shape_alone_needs_a_pinned_unrivalled_fit_whose_texture_lines_up_where_the_view_allows_it():
    """shape_reidentification.shape_alone: the rules that let a surface alignment re-identify a lost
    object without landmark matches. The region is the box seen from ``camera``; the right
    alignment is ``camera`` (model <- region camera). The object's own views are stubbed to
    line up perfectly (texture agreement 1.0)."""
    from types import SimpleNamespace

    from jsr.config import load_config
    from jsr.pipeline.shape_reidentification import shape_alone
    from jsr.pipeline.surface_alignment import Alignment
    from jsr.pipeline.surface_evidence import same_placement
    from jsr.pipeline.surfaces import region_model

    config = load_config(None)
    state = SimpleNamespace(config=config, intrinsics=_Intrinsics())
    own_texture = 1.0  # how well the object's own views line up
    camera, seen, box, region, view = _box_scene()
    turned = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.pi), np.zeros(3)) @ camera
    shifted = make_transform(np.eye(3), [0.03, 0.0, 0.0]) @ camera

    def alone(alignments, region=region, model=box, view=view):
        """The fit shape_alone returns, as ``right``, ``"other"`` (another placement) or None."""
        chosen = shape_alone(state, SimpleNamespace(object_id=1), region, model, alignments, view,
                                            own_texture)
        if chosen is None:
            return None
        centre = region.points.mean(axis=0)
        return right if same_placement(chosen.T_model_region, camera, centre, 0.005, 0.5) else "other"

    right = Alignment(camera, 0.98, 0.07)
    assert alone([right]) is right
    # a fit a few millimetres off, pinned by the box's shape, is polished by point-to-plane ICP
    nudge = make_transform(rotation_about_axis([0.0, 1.0, 0.0], np.radians(2.0)), [0.004, 0.0, 0.0])
    assert alone([Alignment(nudge @ camera, 0.98, 0.07)]) is right
    assert alone([Alignment(camera, 0.6, 0.07)]) is not None  # the rest of the region: sides never seen
    assert alone([Alignment(camera, 0.4, 0.07)]) is None  # too little of the region on the model
    shuffled = region_model(SurfaceSample(seen.points, np.random.default_rng(0).permutation(seen.colors)), VOXEL)
    assert alone([right], region=shuffled) is None  # the shape fits, the texture does not
    # a turned fit listed first (better colour residual) and as complete: its texture does not line up
    assert alone([Alignment(turned, 0.95, 0.05), right]) is right
    assert alone([right, Alignment(shifted, 0.97, 0.07)]) is right  # 3 cm apart: the same fit
    # a model holding the box twice, 0.6 m apart, and a view with depth on the region only: a
    # fit onto the other copy lines up as well, and nothing rules it out
    copy = make_transform(np.eye(3), [0.6, 0.0, 0.0])
    twice = build_model([(camera, seen), (copy @ camera, seen)], VOXEL)
    region_only = _depth_view(seen.points.astype(float))
    assert alone([right], model=twice, view=region_only) is right
    assert alone([right, Alignment(copy @ camera, 0.98, 0.07)], model=twice, view=region_only) is None
    # the other copy's texture lines up too, but clearly worse (more than 0.2 of the own
    # views' agreement below the choice): not ambiguous; nearly as well (within 0.2): ambiguous
    blend = np.random.default_rng(1).integers(0, 256, seen.colors.shape)
    for weight, rival_is_ambiguous in ((0.5, False), (0.95, True)):
        smudged = SurfaceSample(seen.points, (weight * seen.colors + (1 - weight) * blend).astype(np.uint8))
        unlike = build_model([(camera, seen), (copy @ camera, smudged)], VOXEL)
        tree = cKDTree(unlike.points)
        agreements = [texture_agreement(region, unlike, tree, T, VOXEL) for T in (camera, copy @ camera)]
        assert agreements[1] >= 0.5  # the rival passes the texture test on its own
        assert (agreements[1] >= agreements[0] - 0.2) == rival_is_ambiguous
        expected = None if rival_is_ambiguous else right
        assert alone([right, Alignment(copy @ camera, 0.98, 0.07)], model=unlike, view=region_only) is expected
    # 15 cm nearer the camera, in space the view saw empty: neither the choice nor a rival
    nearer = camera @ np.linalg.inv(make_transform(np.eye(3), [0.0, 0.0, -0.15]))
    assert alone([Alignment(nearer, 0.97, 0.06), right]) is right
    # the same fit, but the frame saw 20 cm past the box: the model would float in empty space
    farther = _depth_view(seen.points.astype(float) * (1 + 0.2 / np.linalg.norm(seen.points, axis=1))[:, None],
                          wall_depth=1.6)
    assert alone([right], view=farther) is None
    assert alone([right], view=_depth_view(np.zeros((0, 3)))) is None  # no depth to check it against
    # the object's own views: the region must line up at least half as well as they do
    own_texture = 0.4
    assert alone([right]) is right
    blend = np.random.default_rng(1).integers(0, 256, seen.colors.shape)
    noisy = region_model(SurfaceSample(seen.points, (0.3 * seen.colors + 0.7 * blend).astype(np.uint8)), VOXEL)
    noisy_agreement = texture_agreement(noisy, box, cKDTree(box.points), camera, VOXEL)
    assert 0.25 < noisy_agreement < 0.6
    assert alone([right], region=noisy) is right  # within half of how well the own views line up
    own_texture = 1.0
    assert alone([right], region=noisy) is None
    own_texture = 0.1
    assert alone([right]) is None  # the object's own views hardly line up (one colour): nothing to trust
    own_texture = None
    assert alone([right]) is None  # one view of the object: nothing to compare with
    own_texture = 1.0
    # a cylinder's side turns about its axis: its shape does not pin the fit; painted in rings,
    # its texture, though it lines up, does not either (it is the same all along the turn)
    cylinder_points, _ = _cylinder_side()
    cylinder_seen = _view(cylinder_points, _rings(cylinder_points), camera)
    cylinder = build_model([(camera, cylinder_seen)], VOXEL)
    cylinder_region = region_model(cylinder_seen, VOXEL)
    assert texture_agreement(cylinder_region, cylinder, cKDTree(cylinder.points), camera, VOXEL) > 0.7
    assert alone([right], cylinder_region, cylinder, _depth_view(cylinder_seen.points.astype(float))) is None
    # blotchy, its texture peaks at the right turn: a fit 6 degrees off is moved there
    cylinder_seen = _view(cylinder_points, _textured(cylinder_points), camera)
    cylinder = build_model([(camera, cylinder_seen)], VOXEL)
    cylinder_region = region_model(cylinder_seen, VOXEL)
    off = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.radians(6.0)), np.zeros(3)) @ camera
    pinned = shape_alone(state, SimpleNamespace(object_id=1), cylinder_region, cylinder,
                                        [Alignment(off, 0.98, 0.07)], _depth_view(cylinder_seen.points.astype(float)),
                                        own_texture)
    assert pinned is not None
    assert same_placement(pinned.T_model_region, camera, cylinder_region.points.mean(axis=0), 0.005, 1.5)
    state.config = load_config(None, ["objects.shape_min_texture_ratio=0"])
    assert alone([right]) is None  # switched off: only fits that landmarks confirm


def test_shape_alone_lets_agreeing_landmark_matches_pin_a_fit_that_the_shape_leaves_free():
    """shape_reidentification.shape_alone with ``anchors_of``: a cylinder's side painted in
    rings, its fit turned 6 degrees about the axis (free for its shape and texture), and
    keypoints on it matched to landmarks at their true places. Five spread matches that agree
    with the fit pin it and refine it onto the truth; four do not."""
    from types import SimpleNamespace

    from jsr.config import load_config
    from jsr.pipeline.shape_reidentification import shape_alone
    from jsr.pipeline.surface_alignment import Alignment
    from jsr.pipeline.surface_evidence import same_placement
    from jsr.pipeline.surfaces import region_model

    config = load_config(None)
    state = SimpleNamespace(config=config, intrinsics=_Intrinsics())
    own_texture = 1.0  # how well the object's own views line up
    camera = _box_camera()
    cylinder_points, _ = _cylinder_side()
    seen = _view(cylinder_points, _rings(cylinder_points), camera)
    cylinder, region = build_model([(camera, seen)], VOXEL), region_model(seen, VOXEL)
    view = _depth_view(seen.points.astype(float))
    turned = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.radians(6.0)), np.zeros(3)) @ camera
    fit = Alignment(turned, 0.95, 0.07)
    centre = region.points.mean(axis=0)
    # keypoints: region points (camera frame) at spread heights and angles of the side
    rng = np.random.default_rng(3)
    spread = region.points[rng.choice(len(region.points), size=5, replace=False)]

    def anchors_from(keypoints, matched_keypoints=None):
        """Landmarks at the true places of ``keypoints``, matched to ``matched_keypoints``
        (default: the same keypoints, the right matches)."""
        landmarks = transform_points(camera, keypoints)
        keypoints = keypoints if matched_keypoints is None else matched_keypoints

        def anchors(T):
            agree = np.linalg.norm(transform_points(T, keypoints) - landmarks, axis=1) <= 0.015
            return keypoints[agree], landmarks[agree]
        return anchors

    def alone(anchors):
        return shape_alone(state, SimpleNamespace(object_id=1), region, cylinder, [fit], view,
                                          own_texture, anchors)

    assert alone(None) is None  # the shape alone leaves the turn free
    pinned = alone(anchors_from(spread))
    assert pinned is not None
    assert same_placement(pinned.T_model_region, camera, centre, 0.003, 0.5)  # refined onto the truth
    assert alone(anchors_from(spread[:4])) is None  # fewer than detection.min_segment_features
    # a refinement that loses texture agreement (the surface model pulls it off) is not kept:
    # the fit itself, pinned by the matches, is
    import jsr.pipeline.shape_reidentification as reidentification

    refine = reidentification.refine_fit
    astray = make_transform(np.eye(3), [0.0, 0.0, 0.03]) @ camera
    try:
        reidentification.refine_fit = lambda *args, **kwargs: astray
        kept = alone(anchors_from(spread))
    finally:
        reidentification.refine_fit = refine
    assert kept is not None and np.allclose(kept.T_model_region, turned)
    assert alone(anchors_from(spread, spread[::-1])) is None  # wrong matches: none agree with the fit


def test_refine_fit_holds_a_sliding_surface_by_its_anchors():
    """refine_fit: a flat face slid 2 cm along itself stays slid under point-to-plane ICP;
    three landmark matches (anchors) bring it back."""
    from jsr.pipeline.surface_alignment import refine_fit
    from jsr.pipeline.surfaces import region_model

    points, colors = _box_faces()
    face = points[:, 2] == points[:, 2].max()
    camera = _box_camera()
    seen = _view(points[face], colors[face], camera)
    model, region = build_model([(camera, seen)], VOXEL), region_model(seen, VOXEL)
    slid = make_transform(np.eye(3), [0.02, 0.0, 0.0]) @ camera
    tree = cKDTree(model.points)
    geometry_only = refine_fit(region, model, tree, slid, VOXEL)
    assert np.linalg.norm(geometry_only[:3, 3] - camera[:3, 3]) > 0.015
    keypoints = region.points[[0, len(region.points) // 2, len(region.points) - 1]]
    anchored = refine_fit(region, model, tree, slid, VOXEL, anchors=(keypoints, transform_points(camera, keypoints)))
    assert np.allclose(anchored, camera, atol=1e-3)


def test_surface_agrees_with_a_landmark_pose_where_it_lies_on_the_model_the_view_allows_it_and_texture_lines_up():
    """shape_reidentification.surface_agrees: a pose the landmarks found, checked by the surface."""
    from types import SimpleNamespace

    from jsr.config import load_config
    from jsr.pipeline.shape_reidentification import surface_agrees
    from jsr.pipeline.surfaces import region_model

    state = SimpleNamespace(config=load_config(None), intrinsics=_Intrinsics())
    own_texture = 1.0  # how well the object's own views line up
    camera, seen, box, region, view = _box_scene()

    def agrees(T, region=region):
        return surface_agrees(state, SimpleNamespace(object_id=1), region, box, T, view,
                                             own_texture)

    assert agrees(camera)
    assert not agrees(camera @ np.linalg.inv(make_transform(np.eye(3), [0.0, 0.0, -0.15])))  # seen through
    assert not agrees(make_transform(np.eye(3), [0.5, 0.0, 0.0]) @ camera)  # off the model
    shuffled = region_model(SurfaceSample(seen.points, np.random.default_rng(0).permutation(seen.colors)), VOXEL)
    assert not agrees(camera, region=shuffled)  # the texture does not line up
    own_texture = None
    assert not agrees(camera)  # nothing to compare the texture with


def test_same_placement_compares_alignments_at_the_region():
    """Two alignments of a region 1.2 m in front of its camera (the region frame's origin):
    an 8-degree turn about the region is a small change, though it moves the camera 17 cm; a
    turn about the camera moves the region far."""
    from jsr.pipeline.surface_evidence import same_placement

    centre = np.array([0.0, 0.0, 1.2])
    turn = rotation_about_axis([0.0, 1.0, 0.0], np.radians(8))
    about_region = make_transform(turn, centre - turn @ centre)
    assert same_placement(np.eye(4), about_region, centre, 0.1, 15.0)
    assert not same_placement(np.eye(4), make_transform(rotation_about_axis([0.0, 1.0, 0.0], np.radians(14)),
                                                         np.zeros(3)), centre, 0.1, 15.0)  # 29 cm at the region


def test_texture_sweep_finds_where_a_cylinder_turned_about_its_axis():
    """free_turn finds a cylinder side's axis; texture_sweep turns a fit 100 degrees off about
    it back to within a sweep step of the truth, and leaves a box corner (no free turn) alone."""
    from jsr.pipeline.surface_evidence import free_turn, texture_sweep
    from jsr.pipeline.surfaces import region_model

    camera = _box_camera()
    points, _ = _cylinder_side(arc_degrees=200.0)
    seen = _view(points, _textured(points), camera)
    cylinder, region = build_model([(camera, seen)], VOXEL), region_model(seen, VOXEL)
    tree = cKDTree(cylinder.points)
    axis, point = free_turn(region, cylinder, tree, camera, VOXEL)
    assert abs(axis[2]) > 0.99 and np.linalg.norm(point[:2]) < VOXEL  # the z axis through the origin
    off = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.radians(100.0)), np.zeros(3)) @ camera
    swept = texture_sweep(region, cylinder, tree, off, VOXEL, 0.3)
    assert swept is not None
    error = np.degrees(np.arccos(np.clip((np.trace(swept[:3, :3].T @ camera[:3, :3]) - 1) / 2, -1, 1)))
    assert error <= 15.0  # within a step: coloured ICP and the landmarks take it from there
    box_points, box_colors = _box_faces()
    box_seen = _view(box_points, box_colors, camera)
    box = build_model([(camera, box_seen)], VOXEL)
    assert free_turn(region_model(box_seen, VOXEL), box, cKDTree(box.points), camera, VOXEL) is None


def test_anchors_pin_the_motions_a_surface_leaves_free():
    """anchors_pin: on a flat face (free: two slides and the turn about its normal) anchors
    spread over it pin the fit, anchors at one spot leave the turn about them free; on a
    cylinder's side (free: its turn and its slide) one spot pins both; a box corner has no
    free motion to pin."""
    from jsr.pipeline.surface_evidence import anchors_pin
    from jsr.pipeline.surfaces import region_model

    camera = _box_camera()
    points, colors = _box_faces()
    face = points[:, 2] == points[:, 2].max()

    def pins(surface_points, surface_colors, anchors):
        seen = _view(surface_points, surface_colors, camera)
        model, region = build_model([(camera, seen)], VOXEL), region_model(seen, VOXEL)
        return anchors_pin(region, model, cKDTree(model.points), camera, VOXEL, 0.015,
                           transform_points(np.linalg.inv(camera), anchors), 0.5)

    spread = np.array([[0.1, 0.08, 0.06], [-0.1, 0.08, 0.06], [0.0, -0.08, 0.06]])
    spot = np.array([[0.05, 0.02, 0.06], [0.052, 0.021, 0.06], [0.049, 0.018, 0.06]])
    assert pins(points[face], colors[face], spread)
    assert not pins(points[face], colors[face], spot)
    cylinder_points, _ = _cylinder_side()
    on_cylinder = cylinder_points[[0, 1, 2]]
    assert pins(cylinder_points, _textured(cylinder_points), on_cylinder)
    assert pins(points, colors, spot)


def test_a_refinement_that_loses_fit_and_texture_is_not_kept():
    """Coloured ICP that slides a right fit away (less of the region on the model, texture
    lined up worse) is undone; one that improves either is kept."""
    from jsr.pipeline.surface_alignment import _kept_refinement
    from jsr.pipeline.surfaces import region_model

    camera = _box_camera()
    points, _ = _cylinder_side(arc_degrees=200.0)
    seen = _view(points, _textured(points), camera)
    cylinder, region = build_model([(camera, seen)], VOXEL), region_model(seen, VOXEL)
    tree = cKDTree(cylinder.points)
    slid = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.radians(50.0)), [0.0, 0.0, 0.03]) @ camera
    np.testing.assert_array_equal(_kept_refinement(region, cylinder, tree, camera, slid, VOXEL), camera)
    np.testing.assert_array_equal(_kept_refinement(region, cylinder, tree, slid, camera, VOXEL), camera)


def test_segments_off_the_object_surface_are_found():
    """A region re-identified as one object whose segments include another object (two objects
    moved side by side): the segment off the object's surface is named, the ones on it are not,
    and nothing is named when no other object is lost."""
    from types import SimpleNamespace

    from jsr.config import load_config
    from jsr.geometry import backproject_pixels
    from jsr.pipeline.object_registration import ObjectTrackingResult
    from jsr.pipeline.reidentification import off_surface
    from jsr.pipeline.surfaces import SurfaceModel
    from jsr.synth.scene import synth_intrinsics

    intrinsics = synth_intrinsics(160, 120)
    depth = np.zeros((120, 160), dtype=np.float32)
    labels = np.full((120, 160), -1, dtype=np.int32)
    depth[30:90, 20:70], labels[30:90, 20:70] = 1.0, 0  # the object's face, on its model
    depth[30:90, 70:80], labels[30:90, 70:80] = 1.0, 1  # a strip of the same face
    depth[30:90, 95:140], labels[30:90, 95:140] = 0.8, 2  # another object beside it
    rows, cols = np.nonzero((labels == 0) | (labels == 1))
    points = backproject_pixels(cols, rows, depth[rows, cols].astype(np.float64), intrinsics.fx, intrinsics.fy,
                                intrinsics.cx, intrinsics.cy)
    model = SurfaceModel(points, np.tile([0.0, 0.0, -1.0], (len(points), 1)), np.full((len(points), 3), 0.5))
    first = SimpleNamespace(object_id=1, confirmed=True, dormant=False)
    second = SimpleNamespace(object_id=2, confirmed=True, dormant=True)
    state = SimpleNamespace(config=load_config(None, []), intrinsics=intrinsics, object_maps=[first, second],
                            surfaces=SimpleNamespace(model=lambda object_map: model))
    outcome = ObjectTrackingResult(first, frame_result=SimpleNamespace(success=True, transformation=np.eye(4)))
    ctx = SimpleNamespace(frame=SimpleNamespace(depth=depth, color=np.zeros((120, 160, 3), np.uint8)),
                          measurements=SimpleNamespace(segments=SimpleNamespace(label_image=labels)))
    outcomes = {1: outcome}
    assert off_surface(state, ctx, [0, 1, 2], outcome, outcomes) == [2]
    second.dormant = False  # the other object is tracked in this frame: no one else to find there
    outcomes[2] = SimpleNamespace(object_map=second, success=True)
    assert off_surface(state, ctx, [0, 1, 2], outcome, outcomes) == []


def test_a_models_alignment_descriptors_are_kept_and_give_the_same_alignments():
    """The model's descriptors are computed once per alignment voxel (a lost object's model is
    aligned to the moving regions of many frames) and kept on the model; aligning with them gives
    what a fresh copy of the model gives."""
    points, colors = _box_faces()
    T_model_camera = make_transform(rotation_about_axis([1.0, 0.0, 0.0], np.pi), [0.0, 0.0, 0.8])
    model = build_model([(T_model_camera, _view(points, colors, T_model_camera))], VOXEL)
    fresh = build_model([(T_model_camera, _view(points, colors, T_model_camera))], VOXEL)
    T_true = make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.radians(40)), [0.02, 0.01, 0.0])
    region = build_model([(T_model_camera, _view(transform_points(T_true, points), colors, T_model_camera))], VOXEL)
    first = align_surfaces(region, model, VOXEL, np.random.default_rng(3))
    assert len(model.derived) == 1 and not fresh.derived
    kept = next(iter(model.derived.values()))
    again = align_surfaces(region, model, VOXEL, np.random.default_rng(3))
    assert next(iter(model.derived.values())) is kept  # not computed again
    for alignments in (again, align_surfaces(region, fresh, VOXEL, np.random.default_rng(3))):
        assert len(alignments) == len(first) > 0
        for a, b in zip(alignments, first):
            np.testing.assert_array_equal(a.T_model_region, b.T_model_region)


def test_a_model_keeps_its_descriptors_at_a_few_voxels_only():
    """A long-lived model aligned at many voxels (the region decides a large model's voxel)
    keeps the latest CACHED_VOXELS of them, and other derived values untouched."""
    points, colors = _box_faces()
    T_model_camera = make_transform(rotation_about_axis([1.0, 0.0, 0.0], np.pi), [0.0, 0.0, 0.8])
    model = build_model([(T_model_camera, _view(points, colors, T_model_camera))], VOXEL)
    model.derived["other"] = 1
    voxels = [VOXEL * (1.0 + 0.25 * k) for k in range(CACHED_VOXELS + 3)]
    for voxel in voxels:
        _model_at(model, voxel, thin=True)
    kept = sorted(key[1] for key in model.derived if key != "other")
    assert kept == voxels[-CACHED_VOXELS:] and model.derived["other"] == 1
