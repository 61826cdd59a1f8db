"""Dense surface samples of object maps, and shape-based alignment of a region to them.

Features alone cannot find an object again after a jump that turned it far: the new view
shares few SIFT matches with its map that pass the ratio test (on kitchen_box120, 2-6 between
the maps of one box). Its *shape* still fits the object's surface, seen from another side. This module keeps a
subsampled coloured surface per object keyframe and aligns a region's surface to an object's
model: FPFH correspondences (Rusu et al. 2009, via Open3D), a seeded RANSAC of our own (so
runs are reproducible), the region's 180-degree self-symmetries (a box face fits its model
four ways), and point-to-plane ICP. The candidate alignments it returns are pose
*predictions*: the reconstructor accepts one when the object's landmarks confirm it by
prediction-based feature matching and registration, or, when no landmarks match (the jump
showed the object from a view too far from its map's for SIFT), when the surface alone is
certain: at least half of the region on the model (``objects.shape_min_fitness``; the rest may
be sides the map never saw), a model that, so placed, the view does not see through
(:func:`seen_through_share`), a texture that lines up nearly as well as the object's own
views line up with each other (:func:`texture_agreement`), a shape that pins the fit
(:func:`geometric_constraint`), and no rival fit (``objects.shape_*``).

Frames: ``camera`` is the frame of the view a sample was taken in; ``model`` is the object
map's frame. Transforms are ``(4, 4)`` and map points of the right-hand frame into the left.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from jsr.geometry import backproject_pixels, make_transform, rotation_about_axis, rotation_angle, transform_points


@dataclass
class SurfaceSample:
    """Object pixels of one view: ``points`` ``(N, 3)`` camera frame (float32), ``colors``
    ``(N, 3)`` uint8 RGB."""

    points: np.ndarray
    colors: np.ndarray


@dataclass
class SurfaceModel:
    """An object's surface in its map frame: ``points`` ``(N, 3)``, ``normals`` ``(N, 3)``
    (unit, facing the cameras that saw them), ``colors`` ``(N, 3)`` float in [0, 1]."""

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray


def sample_surface(depth: np.ndarray, color: np.ndarray, mask: np.ndarray, intrinsics, stride: int,
                   voxel: float) -> SurfaceSample:
    """The pixels of ``mask`` ``(H, W)`` bool with valid ``depth`` ``(H, W)`` metres, every
    ``stride``-th row and column, back-projected and thinned to one point per ``voxel`` cube."""
    sub_mask = mask[::stride, ::stride] & (depth[::stride, ::stride] > 0)
    rows, cols = np.nonzero(sub_mask)
    z = depth[::stride, ::stride][rows, cols].astype(np.float64)
    points = backproject_pixels(cols * stride, rows * stride, z, intrinsics.fx, intrinsics.fy, intrinsics.cx,
                                intrinsics.cy)
    colors = color[rows * stride, cols * stride] if color.ndim == 3 else np.repeat(
        color[rows * stride, cols * stride, None], 3, axis=1)
    keep = _one_per_voxel(points, voxel)
    return SurfaceSample(points[keep].astype(np.float32), np.asarray(colors[keep], dtype=np.uint8))


def _one_per_voxel(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of the first point in each occupied ``voxel`` cube (in input order: deterministic)."""
    if not len(points):
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def build_model(views: list[tuple[np.ndarray, SurfaceSample]], voxel: float) -> SurfaceModel | None:
    """One surface from samples ``[(T_model_camera, sample), ...]``, thinned to ``voxel``;
    None when fewer than 20 points remain."""
    points, colors, centres = [], [], []
    for T_model_camera, sample in views:
        if not len(sample.points):
            continue
        points.append(transform_points(T_model_camera, sample.points.astype(np.float64)))
        colors.append(sample.colors)
        centres.append(np.repeat(T_model_camera[None, :3, 3], len(sample.points), axis=0))
    if not points:
        return None
    points, colors, centres = np.concatenate(points), np.concatenate(colors), np.concatenate(centres)
    keep = _one_per_voxel(points, voxel)
    if len(keep) < 20:
        return None
    points, colors, centres = points[keep], colors[keep], centres[keep]
    normals = _normals(points, voxel)
    # face the camera each point was seen from (FPFH depends on the normals' sign)
    flip = np.einsum("ij,ij->i", normals, centres - points) < 0
    normals[flip] *= -1
    return SurfaceModel(points, normals, colors.astype(np.float64) / 255.0)


def region_model(sample: SurfaceSample, voxel: float) -> SurfaceModel | None:
    """A region of the current frame as a :class:`SurfaceModel` in its camera frame."""
    return build_model([(np.eye(4), sample)], voxel)


def _normals(points: np.ndarray, voxel: float) -> np.ndarray:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    return np.asarray(cloud.normals).copy()


def _fpfh(model: SurfaceModel, voxel: float) -> np.ndarray:
    """``(N, 33)`` FPFH descriptors of the model's points."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.points))
    cloud.normals = o3d.utility.Vector3dVector(model.normals)
    feature = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return np.asarray(feature.data).T.copy()


SUPPORT_CHUNK = 256  # RANSAC hypotheses scored together (bounds the memory of the scoring)
COLOR_WEIGHT = 1.0  # weight of the neighbourhood colour (RGB in [0, 1]) against FPFH (histograms summing to 1)


def _features(model: SurfaceModel, voxel: float) -> np.ndarray:
    """``(N, 36)`` point descriptors: FPFH (shape) and the mean colour within 3 voxels. Shape
    alone cannot tell the faces of a box apart; their colours mostly can."""
    fpfh = _fpfh(model, voxel) / 100.0
    tree = cKDTree(model.points)
    weights = tree.sparse_distance_matrix(tree, 3 * voxel, output_type="coo_matrix").tocsr()
    weights.data[:] = 1.0  # neighbours count equally, whatever their distance
    weights.setdiag(1.0)
    counts = np.asarray(weights.sum(axis=1)).ravel()
    mean_color = (weights @ model.colors) / counts[:, None]
    features = np.hstack([fpfh, COLOR_WEIGHT * mean_color])
    features[~fpfh.any(axis=1)] = 0.0  # no shape descriptor: not used
    return features


def _kabsch(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched least-squares rotations and translations: ``source``, ``target`` ``(B, K, 3)``
    -> ``R`` ``(B, 3, 3)``, ``t`` ``(B, 3)`` with ``target ~ R @ source + t``."""
    source_mean, target_mean = source.mean(axis=1), target.mean(axis=1)
    covariance = np.einsum("bki,bkj->bij", target - target_mean[:, None], source - source_mean[:, None])
    u, _, vt = np.linalg.svd(covariance)
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, 2] *= d[:, None]
    rotation = u @ vt
    translation = target_mean - np.einsum("bij,bj->bi", rotation, source_mean)
    return rotation, translation


def _icp(region: SurfaceModel, model: SurfaceModel, tree: cKDTree, T: np.ndarray, voxel: float,
         iterations: int = 15) -> np.ndarray:
    """Point-to-plane ICP of ``region`` onto ``model`` from ``T`` (model <- region)."""
    for iteration in range(iterations):
        moved = transform_points(T, region.points)
        radius = (4.0 if iteration < 5 else 2.0) * voxel
        distance, nearest = tree.query(moved, distance_upper_bound=radius)
        pairs = np.isfinite(distance)
        if pairs.sum() < 10:
            break
        p, q, n = moved[pairs], model.points[nearest[pairs]], model.normals[nearest[pairs]]
        # linearised: (p + w x p + t - q) . n = 0 for the small rotation w and translation t
        a = np.hstack([np.cross(p, n), n])
        b = -np.einsum("ij,ij->i", p - q, n)
        step, *_ = np.linalg.lstsq(a, b, rcond=None)
        angle = np.linalg.norm(step[:3])
        rotation = np.eye(3) if angle < 1e-12 else rotation_about_axis(step[:3] / angle, angle)
        T = make_transform(rotation, step[3:]) @ T
        if angle < 1e-5 and np.linalg.norm(step[3:]) < 1e-5:
            break
    return T


def refine_fit(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
               voxel: float) -> np.ndarray:
    """``T`` (model <- region) refined by point-to-plane ICP: geometry alone, for a fit whose
    shape pins it (:func:`geometric_constraint`); coloured ICP's fits are pulled off by the
    shading of an object that turned."""
    return _icp(region, model, model_tree, T, voxel)


ICP_WORKERS = 2  # ICP runs from independent starts run on this many threads (results kept in order)


@contextmanager
def _open3d_one_thread():
    """Open3D with one thread per call inside the block (the limit is process-wide): its ICP
    sums the normal equations over points in parallel, in whatever order the threads finish, so
    that with two threads the same input gave fits differing by 1e-14, which grew into object
    poses 1 cm apart by the end of kitchen_box120. Runs must be reproducible; the calls run
    side by side instead (:data:`ICP_WORKERS`)."""
    import open3d as o3d

    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield o3d
    finally:
        o3d.utility.set_max_threads(threads)


def _colored_icp(region: SurfaceModel, model: SurfaceModel, T: np.ndarray, voxel: float) -> np.ndarray:
    """Open3D's coloured ICP (Park et al. 2017) from ``T``: geometry and colour together slide
    a flat face into place, which point-to-plane ICP cannot. Call it inside
    :func:`_open3d_one_thread`, for reproducible results."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    clouds = []
    for surface in (region, model):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(surface.points))
        cloud.normals = o3d.utility.Vector3dVector(surface.normals)
        cloud.colors = o3d.utility.Vector3dVector(surface.colors)
        clouds.append(cloud)
    for radius in (4 * voxel, 2 * voxel):
        try:
            result = registration.registration_colored_icp(
                clouds[0], clouds[1], radius, T,
                registration.TransformationEstimationForColoredICP(lambda_geometric=0.9),
                registration.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=30))
        except RuntimeError:  # no correspondences within the radius: keep the start
            break
        if result.fitness > 0:
            T = np.asarray(result.transformation).copy()
    return T


def fitness(region: SurfaceModel, model_tree: cKDTree, T: np.ndarray, voxel: float) -> float:
    """Share of the region's points within 1.5 voxels of the model under ``T``."""
    distance, _ = model_tree.query(transform_points(T, region.points), distance_upper_bound=1.5 * voxel)
    return float(np.isfinite(distance).mean())


@dataclass
class Alignment:
    """A candidate alignment: ``T_model_region`` ``(4, 4)``, the share of the region on the
    model surface (``fitness``) and the mean colour difference there (``color_residual``)."""

    T_model_region: np.ndarray
    fitness: float
    color_residual: float


def align_surfaces(region: SurfaceModel, model: SurfaceModel, voxel: float, rng: np.random.Generator,
                   iterations: int = 20000, hypotheses: int = 12, min_fitness: float = 0.3,
                   max_candidates: int = 8) -> list[Alignment]:
    """Candidate ``T_model_region`` alignments of ``region`` onto ``model``, best fit first.

    Nearest neighbours in FPFH and neighbourhood colour give point pairs; RANSAC draws ``iterations`` triples from them
    (triangles whose side lengths disagree by over 10% are skipped) and keeps the
    ``hypotheses`` distinct alignments most pairs agree with. Each is also tried turned by 180 degrees about the
    axes of the aligned region (its near-symmetries: features must tell them apart), then
    refined by point-to-plane ICP, and each distinct fit covering ``min_fitness`` of the
    region once more by coloured ICP. Returned: alignments with at least ``min_fitness`` of the region on the
    model surface, at most ``max_candidates``, no two within 2 cm and 10 degrees, ordered by
    their colour residual.
    """
    if len(region.points) < 20 or len(model.points) < 20:
        return []
    region_features, model_features = _features(region, voxel), _features(model, voxel)
    valid_region = np.flatnonzero(region_features.any(axis=1))
    valid_model = np.flatnonzero(model_features.any(axis=1))
    if len(valid_region) < 3 or len(valid_model) < 3:
        return []
    model_index = cKDTree(model_features[valid_model])
    _, nearest = model_index.query(region_features[valid_region])
    source = region.points[valid_region]
    target = model.points[valid_model[nearest]]

    centre = region.points.mean(axis=0)  # where alignments are compared (same_placement)
    samples = rng.integers(0, len(source), size=(iterations, 3))
    a, b = source[samples], target[samples]
    edges_a = np.linalg.norm(a - np.roll(a, 1, axis=1), axis=2)
    edges_b = np.linalg.norm(b - np.roll(b, 1, axis=1), axis=2)
    similar = np.all(np.abs(edges_a - edges_b) <= 0.1 * np.maximum(edges_a, edges_b), axis=1)
    similar &= np.all(edges_a > 2 * voxel, axis=1)
    if not similar.any():
        return []
    rotations, translations = _kabsch(a[similar], b[similar])
    support = np.zeros(len(rotations), dtype=np.int64)
    for start in range(0, len(rotations), SUPPORT_CHUNK):  # (chunk, K, 3) at a time, not (B, K, 3)
        chunk = slice(start, start + SUPPORT_CHUNK)
        moved = np.einsum("bij,kj->bki", rotations[chunk], source) + translations[chunk, None]
        support[chunk] = (np.linalg.norm(moved - target[None], axis=2) < 1.5 * voxel).sum(axis=1)
    ranked = np.argsort(-support, kind="stable")
    order: list[int] = []  # the best-supported distinct alignments
    for index in ranked[:200]:
        T = make_transform(rotations[index], translations[index])
        if all(not same_placement(T, make_transform(rotations[k], translations[k]), centre, 0.05, 20.0)
               for k in order):
            order.append(int(index))
        if len(order) == hypotheses:
            break

    tree = cKDTree(model.points)
    model_turns = _symmetry_axes(model.points, model.normals)
    starts = []
    for index in order:
        T = make_transform(rotations[index], translations[index])
        aligned = transform_points(T, region.points)
        aligned_normals = region.normals @ T[:3, :3].T
        starts += [T] + [_half_turn(axis, through) @ T
                         for axis, through in _symmetry_axes(aligned, aligned_normals) + model_turns]
    # Each ICP depends on its start only: the runs go side by side, their results in order.
    with _open3d_one_thread(), ThreadPoolExecutor(ICP_WORKERS) as pool:
        coarse_fits = list(pool.map(lambda start: _icp(region, model, tree, start, voxel), starts))
        refine: list[np.ndarray] = []  # the point-to-plane fits that coloured ICP refines
        for coarse in coarse_fits:
            if fitness(region, tree, coarse, voxel) < min_fitness:
                continue  # not a fit: the slower coloured ICP (most of the time here) would not make it one
            if any(same_placement(coarse, other, centre, 0.05, 20.0) for other in refine):
                continue  # many starts converge to one fit (within 5 cm and 20 degrees): refine it once
            refine.append(coarse)
        refined_fits = list(pool.map(lambda coarse: _colored_icp(region, model, coarse, voxel), refine))
    candidates = [(score, refined) for refined in refined_fits
                  if (score := fitness(region, tree, refined, voxel)) >= min_fitness]
    # best colour agreement first: shape fits a box several ways, its texture only one
    scored = sorted(((color_residual(region, model, tree, T, voxel), -score, index, T)
                     for index, (score, T) in enumerate(candidates)), key=lambda item: item[:3])
    distinct: list[Alignment] = []
    for residual, negative_fitness, _, T in scored:
        if all(not same_placement(T, other.T_model_region, centre) for other in distinct):
            distinct.append(Alignment(T, -negative_fitness, residual))
        if len(distinct) == max_candidates:
            break
    return distinct


def color_residual(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
                   voxel: float) -> float:
    """Mean absolute RGB difference (in [0, 1]) between the region's points on the model
    surface under ``T`` and their nearest model points (1.0 when none is on it)."""
    distance, nearest = model_tree.query(transform_points(T, region.points), distance_upper_bound=1.5 * voxel)
    on = np.isfinite(distance)
    if not on.any():
        return 1.0
    return float(np.abs(region.colors[on] - model.colors[nearest[on]]).mean())


UNIFORM_COLOR_POWER = (1.0 / 255) ** 2  # colours spread less than one level of 255 about their mean are uniform


def texture_agreement(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
                      voxel: float) -> float:
    """Normalised cross-correlation of the colours of the region's points on the model
    surface under ``T`` (model <- region) with their nearest model points: each RGB channel
    less its mean over those points, correlated over all three channels at once. 1: the
    texture lines up; about 0: it does not (or there is none). Unlike the colour residual it
    ignores a shift and a common gain of the colours, which a turned object's shading
    changes. 0.0 when fewer than 10 region points lie on the model or either side is uniform."""
    distance, nearest = model_tree.query(transform_points(T, region.points), distance_upper_bound=1.5 * voxel)
    on = np.isfinite(distance)
    if on.sum() < 10:
        return 0.0
    ours = region.colors[on] - region.colors[on].mean(axis=0)
    theirs = model.colors[nearest[on]] - model.colors[nearest[on]].mean(axis=0)
    ours_power, theirs_power = float(np.sum(ours ** 2)), float(np.sum(theirs ** 2))
    if min(ours_power, theirs_power) < UNIFORM_COLOR_POWER * len(ours):  # spread below a grey level: uniform
        return 0.0
    return float(np.sum(ours * theirs) / np.sqrt(ours_power * theirs_power))


def geometric_constraint(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
                         voxel: float) -> float:
    """How well the region's shape alone pins the alignment ``T`` (model <- region): the
    smallest eigenvalue, per point, of the point-to-plane information matrix of the region
    points on the model (rows ``[(p - c) x n / L, n]`` for aligned points ``p``, model
    normals ``n``, centroid ``c``, RMS radius ``L``; the stability measure of Gelfand et al.
    2003). Near 0 when some rigid motion slides the surface along itself: a cylinder's side
    turned about its axis, a plane, two faces of a box along their edge. A box seen on three
    faces gives 0.03-0.08. 0.0 when fewer than 10 region points lie on the model.
    """
    aligned = transform_points(T, region.points)
    distance, nearest = model_tree.query(aligned, distance_upper_bound=1.5 * voxel)
    on = np.isfinite(distance)
    if on.sum() < 10:
        return 0.0
    p, n = aligned[on], model.normals[nearest[on]]
    centre = p.mean(axis=0)
    radius = float(np.sqrt(np.mean(np.sum((p - centre) ** 2, axis=1))))
    jacobian = np.hstack([np.cross(p - centre, n) / max(radius, 1e-9), n])
    return float(np.linalg.eigvalsh(jacobian.T @ jacobian)[0] / len(p))


def seen_through_share(model: SurfaceModel, T_model_camera: np.ndarray, view, intrinsics, noise, margin: float,
                       sigmas: float, min_points: int = 20) -> float | None:
    """Share of the model's points that the current view saw through if the model sat at
    ``T_model_camera`` (model <- this camera): of the points facing the camera that project
    where ``view`` (a :class:`~jsr.pipeline.objects.DepthView` of this frame, identity pose)
    measured depth, those in front of all the depth around them by more than ``max(margin,
    sigmas * sigma_Z)``. A right fit puts the model where the view sees a surface or behind one
    (occluded), whatever part of the object the region shows; a wrong one puts some of it in
    space the view saw empty. None when fewer than ``min_points`` can be checked."""
    T_camera_model = np.linalg.inv(T_model_camera)
    points = transform_points(T_camera_model, model.points)
    normals = model.normals @ T_camera_model[:3, :3].T
    facing = np.einsum("ij,ij->i", points, normals) < 0  # the side of the surface the camera sees
    measured, through, _ = view.seen_through(points[facing], intrinsics, noise, margin, sigmas)
    if measured.sum() < max(min_points, 1):
        return None
    return float(through.sum() / measured.sum())


def _half_turn(axis: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``(4, 4)`` rotation by 180 degrees about the line through ``centre`` along ``axis``."""
    turn = make_transform(rotation_about_axis(axis, np.pi), np.zeros(3))
    return make_transform(np.eye(3), centre) @ turn @ make_transform(np.eye(3), -centre)


def _symmetry_axes(points: np.ndarray, normals: np.ndarray, faces: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
    """Lines ``(axis, centre)`` about which a surface may look the same turned by 180 degrees:
    its principal axes through its centroid, and the normals of its ``faces`` largest flat
    parts through their centroids (a box face turned about its normal fits itself)."""
    centre = points.mean(axis=0)
    _, principal = np.linalg.eigh(np.cov((points - centre).T))
    lines = [(principal[:, k], centre) for k in range(3)]
    remaining = np.ones(len(points), dtype=bool)
    for _ in range(faces):
        candidates = np.flatnonzero(remaining)
        if len(candidates) < 20:
            break
        probes = candidates[:: max(1, len(candidates) // 100)]
        agreement = normals[probes] @ normals[candidates].T > np.cos(np.radians(20))
        best = probes[int(np.argmax(agreement.sum(axis=1)))]
        members = candidates[normals[candidates] @ normals[best] > np.cos(np.radians(20))]
        if len(members) < 20:
            break
        axis = normals[members].mean(axis=0)
        lines.append((axis / np.linalg.norm(axis), points[members].mean(axis=0)))
        remaining[candidates[normals[candidates] @ normals[best] > np.cos(np.radians(30))]] = False
    return lines


def same_placement(T_a: np.ndarray, T_b: np.ndarray, centre: np.ndarray, metres: float = 0.02,
                   degrees: float = 10.0) -> bool:
    """Whether two ``(4, 4)`` alignments (model <- region) place the region alike: its
    ``centre`` ``(3,)`` (region frame) within ``metres``, and the rotations within ``degrees``.
    Measured at the region, not at the region frame's origin (the camera, 1-3 m away, where a
    small turn reads as a long shift)."""
    shift = np.linalg.norm(transform_points(T_a, centre[None]) - transform_points(T_b, centre[None]))
    return bool(shift < metres and np.degrees(rotation_angle(T_a[:3, :3].T @ T_b[:3, :3])) < degrees)
