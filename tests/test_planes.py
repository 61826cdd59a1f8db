"""Plane extraction (jsr.pipeline.planes) against exact ground truth.

Two sources of frames: an analytic room (ray-box intersections, written here, so these tests
do not depend on the synthetic generator) and frames of ``jsr.synth``. A ground-truth face
counts if it is visible over enough pixels; it must be found with its normal within 2 degrees
and its offset within 1 cm, and no extracted plane may be far from every true face.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from jsr.config import Config
from jsr.geometry import KINECT_SIGMA_Z_COEFFICIENT, invert_transform, look_at, make_transform, rotation_about_axis
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline import plane_fitting
from jsr.pipeline.plane_fitting import fit_planes_from_moments, fit_scalar
from jsr.pipeline.planes import extract_planes

ANGLE_TOLERANCE_DEGREES = 2.0
OFFSET_TOLERANCE = 0.01


# --------------------------------------------------------------------------------------
# Analytic scene: a room (seen from inside) with a table top and a rotated box on the floor.


@dataclass
class Box:
    name: str
    centre: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0

    @property
    def pose(self) -> np.ndarray:
        return make_transform(rotation_about_axis(np.array([0.0, 0.0, 1.0]), self.yaw), self.centre)


ROOM = Box("room", (0.0, 0.25, 1.3), (4.0, 4.5, 2.6))
SOLIDS = [
    Box("box", (0.45, 0.75, 0.2), (0.5, 0.4, 0.4), math.radians(25.0)),
    Box("table top", (-0.65, 0.95, 0.73), (0.9, 0.6, 0.04), math.radians(-10.0)),
]
INTRINSICS = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


def _slabs(origins: np.ndarray, directions: np.ndarray, box: Box) -> tuple[np.ndarray, ...]:
    """Entry/exit ray parameters and the axes and signs of the entry/exit faces of ``box``."""
    pose_inv = invert_transform(box.pose)
    o = origins @ pose_inv[:3, :3].T + pose_inv[:3, 3]
    d = directions @ pose_inv[:3, :3].T
    half = np.asarray(box.size) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) / d
        t2 = (half - o) / d
    t_low, t_high = np.minimum(t1, t2), np.maximum(t1, t2)
    entry_axis = np.argmax(t_low, axis=1)
    exit_axis = np.argmin(t_high, axis=1)
    t_entry = t_low.max(axis=1)
    t_exit = t_high.min(axis=1)
    rows = np.arange(len(d))
    entry_sign = np.where(d[rows, entry_axis] > 0, -1, 1)  # the face on the side the ray comes from
    exit_sign = np.where(d[rows, exit_axis] > 0, 1, -1)
    return t_entry, t_exit, entry_axis, entry_sign, exit_axis, exit_sign


def face_plane(box: Box, axis: int, sign: int, T_c_w: np.ndarray, inward: bool = False) -> tuple[np.ndarray, float]:
    """Camera-frame ``(normal, d)`` of a box face, ``n . x + d = 0``, normal towards the camera."""
    pose = box.pose
    normal_w = pose[:3, axis] * sign * (-1 if inward else 1)
    point_w = pose[:3, 3] + pose[:3, axis] * sign * box.size[axis] / 2.0
    normal_c = T_c_w[:3, :3] @ normal_w
    point_c = T_c_w[:3, :3] @ point_w + T_c_w[:3, 3]
    d = -float(normal_c @ point_c)
    if d < 0:
        normal_c, d = -normal_c, -d
    return normal_c, d


def render_analytic(seed: int = 0, noise: bool = True, eye=(0.6, -0.9, 1.55), target=(-0.1, 0.9, 0.4)):
    """Depth ``(H, W)`` float32 (quantised to 1/5000 m), face ids ``(H, W)`` and face planes."""
    T_w_c = look_at(np.array(eye), np.array(target))
    T_c_w = invert_transform(T_w_c)
    h, w = INTRINSICS.height, INTRINSICS.width
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays_c = np.stack([(u - INTRINSICS.cx) / INTRINSICS.fx, (v - INTRINSICS.cy) / INTRINSICS.fy, np.ones_like(u)], -1)
    directions = rays_c.reshape(-1, 3) @ T_w_c[:3, :3].T  # camera z component 1: t is the depth
    origins = np.broadcast_to(T_w_c[:3, 3], directions.shape)
    _, t_room, _, _, axis_room, sign_room = _slabs(origins, directions, ROOM)
    depth = t_room.copy()
    face = axis_room * 2 + (sign_room > 0)  # room faces 0..5
    planes = {int(f): face_plane(ROOM, f // 2, 1 if f % 2 else -1, T_c_w, inward=True) for f in range(6)}
    for index, solid in enumerate(SOLIDS, start=1):
        t_entry, t_exit, axis, sign, _, _ = _slabs(origins, directions, solid)
        hit = (t_entry < t_exit) & (t_entry > 0) & (t_entry < depth)
        depth = np.where(hit, t_entry, depth)
        face = np.where(hit, index * 6 + axis * 2 + (sign > 0), face)
        for f in range(6):
            planes[index * 6 + f] = face_plane(solid, f // 2, 1 if f % 2 else -1, T_c_w)
    depth = depth.reshape(h, w)
    if noise:
        rng = np.random.default_rng(seed)
        depth = depth + rng.standard_normal(depth.shape) * KINECT_SIGMA_Z_COEFFICIENT * depth**2
    depth = np.round(depth * 5000.0) / 5000.0
    return depth.astype(np.float32), face.reshape(h, w), planes


def face_names() -> dict[int, str]:
    names = {0: "wall -x", 1: "wall +x", 2: "wall -y", 3: "wall +y", 4: "floor", 5: "ceiling"}
    for index, solid in enumerate(SOLIDS, start=1):
        for f in range(6):
            names[index * 6 + f] = f"{solid.name} face {'xyz'[f // 2]}{'+' if f % 2 else '-'}"
    return names


# --------------------------------------------------------------------------------------
# Matching extracted planes to ground-truth faces


def plane_errors(normal: np.ndarray, offset: float, true_normal: np.ndarray, true_offset: float) -> tuple[float, float]:
    angle = math.degrees(math.acos(min(1.0, abs(float(normal @ true_normal)))))
    sign = 1.0 if normal @ true_normal >= 0 else -1.0
    return angle, abs(offset - sign * true_offset)


def oracle_errors(depth: np.ndarray, intrinsics: CameraIntrinsics, mask: np.ndarray, truth) -> tuple[float, float]:
    """Errors of a least-squares plane fitted to the true pixels of a face (the noise floor)."""
    v, u = np.nonzero(mask & (depth > 0))
    z = depth[v, u].astype(np.float64)
    points = np.column_stack([(u - intrinsics.cx) / intrinsics.fx * z, (v - intrinsics.cy) / intrinsics.fy * z, z])
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    normal = -normal if normal @ centre > 0 else normal
    return plane_errors(normal, -float(normal @ centre), *truth)


def whole_blocks(face_ids: np.ndarray, face: int, block: int = 10) -> int:
    """Blocks of the extraction grid lying entirely on ``face``."""
    h, w = face_ids.shape
    on = (face_ids[: h // block * block, : w // block * block] == face).reshape(h // block, block, w // block, block)
    return int(on.all(axis=(1, 3)).sum())


def match_report(result, face_ids, truth, names, depth, intrinsics, strict_spurious=True, partners=None):
    """Faces that must be found, those missed, spurious planes, and a report of all errors.

    A face must be found if it holds at least 20 whole blocks (the size of the smallest plane)
    and a least-squares fit to its true pixels (the noise floor) is within half the
    tolerances. ``truth`` maps a face to its plane; a plane matching a face of ``partners``
    (a parallel face less than 3 cm away, such as a picture on a wall: a relief below the
    depth noise) also counts. Spurious: a plane near no true face (5 deg / 3 cm); with ``strict_spurious``
    off, only planes of at least 10000 pixels are checked.
    """
    visible, lines, missed = [], [], []
    for f in truth:
        if whole_blocks(face_ids, f) < 20:
            continue
        oracle = oracle_errors(depth, intrinsics, face_ids == f, truth[f])
        if oracle[0] > ANGLE_TOLERANCE_DEGREES / 2 or oracle[1] > OFFSET_TOLERANCE / 2:
            lines.append(f"({names.get(f, f)}: noise floor {oracle[0]:.2f} deg, {100 * oracle[1]:.2f} cm, not required)")
            continue
        visible.append(f)
        errors = [plane_errors(result.normals[p], result.offsets[p], *truth[f]) for p in range(len(result))]
        for g in (partners or {}).get(f, ()):
            errors += [plane_errors(result.normals[p], result.offsets[p], *truth[g]) for p in range(len(result))]
        good = [e for e in errors if e[0] < ANGLE_TOLERANCE_DEGREES and e[1] < OFFSET_TOLERANCE]
        best = min(good or errors or [(math.inf, math.inf)], key=lambda e: e[0] + 100 * e[1])
        lines.append(f"{names.get(f, f)} ({int((face_ids == f).sum())} px): {best[0]:.2f} deg, {100 * best[1]:.2f} cm")
        if not good:
            missed.append(names.get(f, str(f)))
    spurious = []
    for p in range(len(result)):
        if not strict_spurious and result.point_counts[p] < 10000:
            continue
        errors = [plane_errors(result.normals[p], result.offsets[p], *truth[f]) for f in truth]
        if not any(a < 5.0 and o < 0.03 for a, o in errors):
            spurious.append(
                f"plane {p} ({result.point_counts[p]} px, n={np.round(result.normals[p], 3)}, d={result.offsets[p]:.3f})"
            )
    return visible, missed, spurious, "; ".join(lines)


# --------------------------------------------------------------------------------------
# Tests on the analytic room


@pytest.fixture(scope="module")
def config() -> Config:
    return Config()


@pytest.mark.parametrize("seed, eye", [(0, (0.6, -0.9, 1.55)), (1, (-1.0, -0.8, 1.7)), (2, (1.3, -1.2, 1.3))])
def test_room_planes_are_found_accurately(config, seed, eye):
    depth, face_ids, truth = render_analytic(seed=seed, eye=eye)
    result = extract_planes(depth, INTRINSICS, config.planes, config.noise)
    visible, missed, spurious, report = match_report(result, face_ids, truth, face_names(), depth, INTRINSICS)
    assert len(visible) >= 5, report
    assert not missed, f"faces not found within 2 deg / 1 cm: {missed}. {report}"
    assert not spurious, f"planes matching no true face: {spurious}. {report}"


def test_plane_pixels_lie_on_their_face(config):
    depth, face_ids, truth = render_analytic(seed=2)
    result = extract_planes(depth, INTRINSICS, config.planes, config.noise)
    assert len(result) >= 6
    for p in range(len(result)):
        mask = result.label_image == p
        assert mask.sum() == result.point_counts[p]
        majority = np.bincount(face_ids[mask]).argmax()
        purity = float((face_ids[mask] == majority).mean())
        solid_purity = float((face_ids[mask] // 6 == majority // 6).mean())
        coverage = float(mask[face_ids == majority].mean())
        # Pixels of a neighbouring face within the noise of the plane join it at a crease
        # (refinement by distance, as in Feng et al.); never pixels of another solid.
        assert solid_purity > 0.98, f"plane {p}: only {solid_purity:.3f} of its pixels on one solid"
        assert purity > 0.85, f"plane {p}: only {purity:.3f} of its pixels on one face"
        # Blocks at the border of a face are refined pixel by pixel: most of the face is kept.
        if (face_ids == majority).sum() > 10000:
            assert coverage > 0.85, f"plane {p}: covers only {coverage:.3f} of face {majority}"


def test_normals_face_the_camera_and_offsets_are_positive(config):
    depth, _, _ = render_analytic(seed=3)
    result = extract_planes(depth, INTRINSICS, config.planes, config.noise)
    assert len(result) > 0
    assert np.all(result.offsets > 0)
    assert np.all(np.einsum("ij,ij->i", result.normals, result.centroids) < 0)
    np.testing.assert_allclose(np.linalg.norm(result.normals, axis=1), 1.0, atol=1e-9)
    residual = np.einsum("ij,ij->i", result.normals, result.centroids) + result.offsets
    np.testing.assert_allclose(residual, 0.0, atol=1e-9)
    # Fit RMSE is close to the depth noise of the plane, not to a bad fit.
    assert np.all(result.fit_rmse < 3 * KINECT_SIGMA_Z_COEFFICIENT * 4.5**2)


def test_noise_free_room_is_exact(config):
    depth, face_ids, truth = render_analytic(seed=0, noise=False)
    result = extract_planes(depth, INTRINSICS, config.planes, config.noise)
    visible, missed, spurious, report = match_report(result, face_ids, truth, face_names(), depth, INTRINSICS)
    assert not missed and not spurious, report
    for f in visible:
        errors = [plane_errors(result.normals[p], result.offsets[p], *truth[f]) for p in range(len(result))]
        angle, offset = min(errors, key=lambda e: e[0] + 100 * e[1])
        assert angle < 0.5 and offset < OFFSET_TOLERANCE, report


def test_missing_depth_and_disabled_extraction(config):
    depth, _, _ = render_analytic(seed=4)
    holes = depth.copy()
    holes[:, :200] = 0.0  # a third of the image without depth
    result = extract_planes(holes, INTRINSICS, config.planes, config.noise)
    assert np.all(result.label_image[:, :200] == -1)
    assert len(result) > 0
    config_off = Config()
    config_off.planes.enabled = False
    off = extract_planes(depth, INTRINSICS, config_off.planes, config_off.noise)
    assert len(off) == 0 and off.label_image.shape == depth.shape and np.all(off.label_image == -1)
    empty = extract_planes(np.zeros_like(depth), INTRINSICS, config.planes, config.noise)
    assert len(empty) == 0


def test_without_refinement_labels_are_whole_blocks(config):
    depth, face_ids, truth = render_analytic(seed=5)
    config_coarse = Config()
    config_coarse.planes.refine = False
    result = extract_planes(depth, INTRINSICS, config_coarse.planes, config_coarse.noise)
    assert len(result) >= 5
    blocks = np.where(depth > 0, result.label_image, -2).reshape(48, 10, 64, 10)
    for label in range(len(result)):
        on = (blocks == label).any(axis=(1, 3))
        assert np.all(((blocks == label) | (blocks == -2)).all(axis=(1, 3))[on]), "a label covers part of a block"
    # Coarse planes include the blocks straddling creases: only the large faces are required.
    for f in (0, 3, 4):  # wall -x, wall +y, floor
        errors = [plane_errors(result.normals[p], result.offsets[p], *truth[f]) for p in range(len(result))]
        angle, offset = min(errors, key=lambda e: e[0] + 100 * e[1])
        assert angle < ANGLE_TOLERANCE_DEGREES and offset < OFFSET_TOLERANCE, (f, angle, offset)


def test_distorted_camera_labels_the_raw_image(config):
    """With lens distortion the planes are fitted in ideal pinhole geometry."""
    distorted = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480, 5000.0, (0.08, -0.12, 0.0, 0.0, 0.0))
    depth, face_ids, truth = render_analytic(seed=6)
    # Resample the pinhole rendering onto the distorted sensor grid: raw pixel -> ideal pixel.
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    ideal = distorted.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]))
    iu = np.clip(np.rint(ideal[:, 0]).astype(int), 0, 639)
    iv = np.clip(np.rint(ideal[:, 1]).astype(int), 0, 479)
    raw_depth = depth[iv, iu].reshape(480, 640)
    raw_faces = face_ids[iv, iu].reshape(480, 640)
    result = extract_planes(raw_depth, distorted, config.planes, config.noise, undistort=True)
    visible, missed, spurious, report = match_report(result, raw_faces, truth, face_names(), depth, INTRINSICS)
    assert not missed and not spurious, report
    for p in range(len(result)):
        mask = result.label_image == p
        majority = np.bincount(raw_faces[mask]).argmax()
        assert (raw_faces[mask] // 6 == majority // 6).mean() > 0.98
        assert (raw_faces[mask] == majority).mean() > 0.85


def test_fit_from_moments_matches_eigh():
    rng = np.random.default_rng(7)
    rows = []
    for _ in range(200):
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        points = rng.normal(size=(80, 3)) * 0.1 + np.array([0.0, 0.0, 2.0])
        points -= np.outer(points @ normal - 1.0, normal)
        points += rng.normal(size=(80, 3)) * 1e-3
        x, y, z = points.T
        rows.append([80, x.sum(), y.sum(), z.sum(), x @ x, x @ y, x @ z, y @ y, y @ z, z @ z, (z**4).sum()])
    moments = np.array(rows)
    normals, offsets, centroids, mse = fit_planes_from_moments(moments)
    mean, covariance = plane_fitting._covariances(moments)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    reference = eigenvectors[:, :, 0] * np.where(np.einsum("ij,ij->i", eigenvectors[:, :, 0], mean) > 0, -1, 1)[:, None]
    np.testing.assert_allclose(normals, reference, atol=1e-9)
    np.testing.assert_allclose(mse, eigenvalues[:, 0], rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(centroids, mean)
    np.testing.assert_allclose(offsets, -np.einsum("ij,ij->i", normals, mean))
    for row, normal, error in zip(rows[:20], normals, mse):
        fitted = fit_scalar(list(map(float, row)), True)
        assert fitted[0] == pytest.approx(error, rel=1e-6, abs=1e-15)
        np.testing.assert_allclose(fitted[3:], normal, atol=1e-9)


# --------------------------------------------------------------------------------------
# Tests on jsr.synth frames (exact geometry of the generator's scene)


def _synth_face_truth(plan, frame_index: int, depth_clean: np.ndarray):
    """Camera-frame planes of all box faces and the visible pixels of each (from exact depth)."""
    T_w_c = plan.camera_poses[frame_index]
    T_c_w = invert_transform(T_w_c)
    intrinsics = plan.intrinsics
    h, w = depth_clean.shape
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    z = depth_clean.ravel()
    valid = z > 0
    points_c = np.column_stack([(u.ravel() - intrinsics.cx) / intrinsics.fx * z, (v.ravel() - intrinsics.cy) / intrinsics.fy * z, z])
    points_w = points_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    poses = plan.shape_poses(frame_index)
    face_ids = np.full(h * w, -1)
    truth = {}
    names = {}
    for s, (shape, pose) in enumerate(zip(plan.shapes, poses)):
        if shape.kind != "box":
            continue
        local = (points_w - pose[:3, 3]) @ pose[:3, :3]
        half = np.asarray(shape.size) / 2.0
        inside = np.all(np.abs(local) <= half + 0.002, axis=1) & valid
        for axis in range(3):
            for sign in (-1, 1):
                fid = s * 6 + axis * 2 + (sign > 0)
                on_face = inside & (np.abs(local[:, axis] - sign * half[axis]) < 0.002)
                face_ids[on_face] = fid
                normal_w = pose[:3, axis] * sign
                point_w = pose[:3, 3] + pose[:3, axis] * sign * half[axis]
                normal_c = T_c_w[:3, :3] @ normal_w
                point_c = T_c_w[:3, :3] @ point_w + T_c_w[:3, 3]
                d = -float(normal_c @ point_c)
                if d < 0:
                    normal_c, d = -normal_c, -d
                truth[fid] = (normal_c, d)
                names[fid] = f"{shape.name} {'xyz'[axis]}{'+' if sign > 0 else '-'}"
    return face_ids.reshape(h, w), truth, names


@pytest.fixture(scope="module")
def synth_frames():
    from jsr.synth.options import SynthOptions
    from jsr.synth.render import SynthRenderer
    from jsr.synth.scene import build_scene_plan

    options = SynthOptions(frames=30, objects=2, width=640, height=480, seed=5)
    plan = build_scene_plan(options)
    renderer = SynthRenderer(plan)
    frames = {index: renderer.render(index) for index in (0, 14, 29)}
    return plan, frames


@pytest.mark.parametrize("frame_index", [0, 14, 29])
def test_synth_planes_match_box_faces(config, synth_frames, frame_index):
    plan, frames = synth_frames
    frame = frames[frame_index]
    depth = (np.round(frame.depth * 5000.0) / 5000.0).astype(np.float32)
    result = extract_planes(depth, plan.intrinsics, config.planes, config.noise)
    face_ids, truth, names = _synth_face_truth(plan, frame_index, frame.depth_clean)
    # Planar faces of the scene's cylinders (caps) are not in ``truth``: allow planes near them.
    partners = {
        f: [
            g
            for g in truth
            if g != f
            and plane_errors(truth[f][0], truth[f][1], *truth[g])[0] < 1.0
            and plane_errors(truth[f][0], truth[f][1], *truth[g])[1] < 0.03
        ]
        for f in truth
    }
    visible, missed, spurious, report = match_report(
        result, face_ids, truth, names, depth, plan.intrinsics, strict_spurious=False, partners=partners
    )
    assert len(visible) >= 4, report
    assert not missed, f"faces not found within 2 deg / 1 cm: {missed}. {report}"
    assert not spurious, f"planes matching no true face: {spurious}. {report}"


def test_pixels_beyond_the_block_grid_are_labelled(config):
    """Image sides that are not multiples of the block size (here 64 x 47 with 10 px blocks)."""
    intrinsics = CameraIntrinsics(100.0, 100.0, 31.5, 23.0, 64, 47)
    v, u = np.mgrid[0:47, 0:64].astype(float)
    # A tilted plane z = 2 + 0.1 x, i.e. depth = 2 / (1 - 0.1 (u - cx) / fx).
    depth = (2.0 / (1.0 - 0.1 * (u - intrinsics.cx) / intrinsics.fx)).astype(np.float32)
    result = extract_planes(depth, intrinsics, config.planes, config.noise)
    assert len(result) == 1
    assert np.all(result.label_image == 0)
    assert result.point_counts[0] == 64 * 47
    expected = np.array([0.1, 0.0, -1.0]) / np.linalg.norm([0.1, 0.0, -1.0])
    np.testing.assert_allclose(result.normals[0], expected, atol=1e-4)
    assert result.offsets[0] == pytest.approx(2.0 / np.linalg.norm([0.1, 0.0, -1.0]), abs=1e-4)
