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

from jsr.geometry import (backproject_pixels, cross_matrices, make_transform, rotation_about_axis, rotation_angle,
                          transform_points)


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
RANKED_HYPOTHESES = 200  # the best-supported RANSAC hypotheses from which the ICP starts are chosen
FITTING_HYPOTHESES = 6  # ... besides the best-supported distinct ones, this many best-fitting distinct ones
FIT_SAMPLE = 150  # region points (evenly spread over its list) on which a hypothesis's fit is measured
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
         iterations: int = 15, anchors: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Point-to-plane ICP of ``region`` onto ``model`` from ``T`` (model <- region).
    ``anchors`` ``(K, 3)`` region-frame points and ``(K, 3)`` the model points they must land
    on (landmark matches) add point-to-point rows, which hold the motions that slide the
    surface along itself."""
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
        if anchors is not None and len(anchors[0]):
            # (p + w x p + t - q) = 0, three rows per anchor: w x p = -[p]x w
            anchored, targets = transform_points(T, anchors[0]), anchors[1]
            rows = np.concatenate([-cross_matrices(anchored), np.tile(np.eye(3), (len(anchored), 1, 1))], axis=2)
            rows = rows.reshape(-1, 6)  # (3K, 6)
            a, b = np.vstack([a, rows]), np.concatenate([b, (targets - anchored).ravel()])
        step, *_ = np.linalg.lstsq(a, b, rcond=None)
        angle = np.linalg.norm(step[:3])
        rotation = np.eye(3) if angle < 1e-12 else rotation_about_axis(step[:3] / angle, angle)
        T = make_transform(rotation, step[3:]) @ T
        if angle < 1e-5 and np.linalg.norm(step[3:]) < 1e-5:
            break
    return T


def refine_fit(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
               voxel: float, anchors: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``T`` (model <- region) refined by point-to-plane ICP: geometry alone, for a fit whose
    shape pins it (:func:`geometric_constraint`); coloured ICP's fits are pulled off by the
    shading of an object that turned. With ``anchors`` (region points ``(K, 3)``, model
    points ``(K, 3)``: landmark matches) the fit is refined on both, for a fit that only the
    anchors pin."""
    return _icp(region, model, model_tree, T, voxel, anchors=anchors)


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


def _kept_refinement(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, start: np.ndarray,
                     refined: np.ndarray, voxel: float) -> np.ndarray:
    """``refined`` unless it puts less of the region on the model surface and lines its
    texture up worse than ``start`` did: coloured ICP then diverged (synth_two seed 5, frame
    35: a cylinder's fit 0.2 cm and 3 degrees from the truth slid to 6 cm and 52 degrees,
    fitness 1.0 -> 0.55)."""
    if fitness(region, model_tree, refined, voxel) >= fitness(region, model_tree, start, voxel):
        return refined
    if texture_agreement(region, model, model_tree, refined, voxel) >= texture_agreement(
            region, model, model_tree, start, voxel):
        return refined
    return start


def fitness(region: SurfaceModel, model_tree: cKDTree, T: np.ndarray, voxel: float) -> float:
    """Share of the region's points within 1.5 voxels of the model under ``T``."""
    return _share_on_surface(region.points, model_tree, T, voxel)


def _share_on_surface(points: np.ndarray, model_tree: cKDTree, T: np.ndarray, voxel: float) -> float:
    """Share of ``points`` ``(N, 3)`` within 1.5 voxels of the model points in ``model_tree`` under ``T``."""
    distance, _ = model_tree.query(transform_points(T, points), distance_upper_bound=1.5 * voxel)
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
    ``hypotheses`` distinct alignments most pairs agree with, and :data:`FITTING_HYPOTHESES`
    more that put most of a sample of the region on the model surface. Each is also tried turned by 180 degrees about the
    axes of the aligned region (its near-symmetries: features must tell them apart), then
    refined by point-to-plane ICP, and each distinct fit covering ``min_fitness`` of the
    region once more by coloured ICP (undone when it loses both fit and texture). Returned: alignments with at least ``min_fitness`` of the region on the
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
    ranked = np.argsort(-support, kind="stable")[:RANKED_HYPOTHESES]
    transforms = [make_transform(rotations[index], translations[index]) for index in ranked]

    def keep_distinct(candidates, kept: list[int], limit: int) -> None:
        for position in candidates:
            if len(kept) == limit:
                break
            if all(not same_placement(transforms[position], transforms[k], centre, 0.05, 20.0) for k in kept):
                kept.append(int(position))

    order: list[int] = []  # positions in ``ranked`` of the best-supported distinct alignments
    keep_distinct(range(len(ranked)), order, hypotheses)
    # Feature support ranks poorly on flat faces, whose FPFH pairs are near random: the true
    # alignment can fall below the best-supported ones. The best-fitting ones (share of a
    # sample of the region on the model surface) join them.
    tree = cKDTree(model.points)
    sample = region.points[np.linspace(0, len(region.points) - 1, min(FIT_SAMPLE, len(region.points))).astype(int)]
    sample_fitness = np.array([_share_on_surface(sample, tree, T, voxel) for T in transforms])
    keep_distinct(np.argsort(-sample_fitness, kind="stable"), order, hypotheses + FITTING_HYPOTHESES)

    model_turns = _symmetry_axes(model.points, model.normals)
    starts = []
    for position in order:
        T = transforms[position]
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
        # a fit that turns freely (a cylinder) is also tried where its texture lines up best
        for coarse in list(refine):
            swept = texture_sweep(region, model, tree, coarse, voxel, min_fitness)
            if swept is not None and not any(same_placement(swept, other, centre, 0.05, 20.0) for other in refine):
                refine.append(swept)
        refined_fits = list(pool.map(lambda coarse: _colored_icp(region, model, coarse, voxel), refine))
    refined_fits = [_kept_refinement(region, model, tree, coarse, refined, voxel)
                    for coarse, refined in zip(refine, refined_fits)]
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


def _information(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
                 voxel: float) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The point-to-plane information matrix ``(6, 6)`` per point of the region points on the
    model under ``T`` (model <- region), rows ``[(p - c) x n / L, n]`` for aligned points
    ``p``, model normals ``n``; with the centroid ``c`` ``(3,)`` (model frame) and the RMS
    radius ``L`` about it. None when fewer than 10 region points lie on the model."""
    aligned = transform_points(T, region.points)
    distance, nearest = model_tree.query(aligned, distance_upper_bound=1.5 * voxel)
    on = np.isfinite(distance)
    if on.sum() < 10:
        return None
    p, n = aligned[on], model.normals[nearest[on]]
    centre = p.mean(axis=0)
    radius = max(float(np.sqrt(np.mean(np.sum((p - centre) ** 2, axis=1)))), 1e-9)
    jacobian = np.hstack([np.cross(p - centre, n) / radius, n])
    return jacobian.T @ jacobian / len(p), centre, radius


def geometric_constraint(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
                         voxel: float) -> float:
    """How well the region's shape alone pins the alignment ``T`` (model <- region): the
    smallest eigenvalue of the point-to-plane information matrix per point of the region
    points on the model (:func:`_information`; the stability measure of Gelfand et al.
    2003). Near 0 when some rigid motion slides the surface along itself: a cylinder's side
    turned about its axis, a plane, two faces of a box along their edge. A box seen on three
    faces gives 0.03-0.08. 0.0 when fewer than 10 region points lie on the model.
    """
    information = _information(region, model, model_tree, T, voxel)
    return 0.0 if information is None else float(np.linalg.eigvalsh(information[0])[0])


FREE_TURN_CONSTRAINT = 0.005  # a turn is free when the information along it is below this (a cylinder's side ~0.001)
FREE_TURN_ROTATION_SHARE = 0.5  # ... and it is a turn: this much of its twist (rotation scaled by the RMS radius L)
# is rotation; a turn about an axis d from the region's centroid has L / sqrt(L^2 + d^2): an arc of a cylinder 0.8-0.95
FREE_TURN_STEP_DEGREES = 15.0  # the free turn is swept in steps of this


def free_turn(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
              voxel: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The line ``(axis (3,), point (3,))`` (model frame) about which the region aligned by
    ``T`` (model <- region) turns freely along the model (a cylinder's side about its axis),
    or None: of the motions of :func:`_information` below FREE_TURN_CONSTRAINT (a cylinder's
    side has two: the turn and a slide along the axis), the one most a rotation, if mostly
    one (FREE_TURN_ROTATION_SHARE; a slide is none)."""
    information = _information(region, model, model_tree, T, voxel)
    if information is None:
        return None
    matrix, centre, radius = information
    values, vectors = np.linalg.eigh(matrix)
    free = vectors[:, values < FREE_TURN_CONSTRAINT]  # (6, k) twists (scaled rotation, translation)
    if free.shape[1] == 0:
        return None
    # the unit twist in their span with the largest rotation part
    share, mix = np.linalg.eigh(free[:3].T @ free[:3])
    twist = free @ mix[:, -1]
    if np.sqrt(max(share[-1], 0.0)) < FREE_TURN_ROTATION_SHARE:
        return None
    omega, velocity = twist[:3] / radius, twist[3:]  # velocity of a point x - c: omega x (x - c) + velocity
    # a turn about the line through a: omega x (x - a), so velocity = -omega x (a - c)
    point = centre + np.cross(omega, velocity) / float(omega @ omega)
    return omega / np.linalg.norm(omega), point


def texture_sweep(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray,
                  voxel: float, min_fitness: float) -> np.ndarray | None:
    """Along the free turn of the fit ``T`` (:func:`free_turn`), in steps of
    FREE_TURN_STEP_DEGREES, the turned fit whose texture lines up best
    (:func:`texture_agreement`), if better than ``T``'s and with ``min_fitness`` of the
    region on the model; None otherwise. The shape cannot tell where a cylinder turned to;
    its texture can, from far, where coloured ICP only slides a few degrees."""
    line = free_turn(region, model, model_tree, T, voxel)
    if line is None:
        return None
    axis, point = line
    best, best_texture = None, texture_agreement(region, model, model_tree, T, voxel)
    for angle in np.radians(np.arange(FREE_TURN_STEP_DEGREES, 360.0, FREE_TURN_STEP_DEGREES)):
        turned = _turn_about(axis, point, angle) @ T
        if fitness(region, model_tree, turned, voxel) < min_fitness:
            continue
        texture = texture_agreement(region, model, model_tree, turned, voxel)
        if texture > best_texture:
            best, best_texture = turned, texture
    return best


TEXTURE_PIN_METRES = 0.03  # a free motion is pinned by texture when moving the region this far (RMS) along it ...
TEXTURE_PIN_RATIO = 0.8  # ... either way drops the texture agreement to at most this share of its peak
TEXTURE_SEARCH_STEP_METRES = 0.002  # the peak is searched for in steps of this (RMS motion of the region)


def _free_motions(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray, voxel: float,
                  free_below: float) -> list[np.ndarray] | None:
    """The rigid motions that slide the region aligned by ``T`` (model <- region) along the
    model: ``(4, 4)`` twist matrices (model frame, about the origin) of the information
    eigenvalues below ``free_below`` (:func:`_information`), each scaled to move the region's
    points by 1 m RMS. None when fewer than 10 region points lie on the model."""
    information = _information(region, model, model_tree, T, voxel)
    if information is None:
        return None
    matrix, centre, radius = information
    values, vectors = np.linalg.eigh(matrix)
    offsets = transform_points(T, region.points) - centre
    motions = []
    for twist in vectors[:, values < free_below].T:
        omega, velocity = twist[:3] / radius, twist[3:]  # point velocity omega x (x - c) + velocity
        speed = np.sqrt(np.mean(np.sum((np.cross(omega, offsets) + velocity) ** 2, axis=1)))
        generator = np.zeros((4, 4))
        generator[:3, :3] = cross_matrices(omega / speed)
        generator[:3, 3] = (velocity - np.cross(omega, centre)) / speed  # about the model origin
        motions.append(generator)
    return motions


def anchors_pin(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray, voxel: float,
                free_below: float, anchor_points: np.ndarray, min_share: float) -> bool:
    """Whether ``anchor_points`` ``(K, 3)`` (region frame: landmark matches) pin the motions
    that the shape leaves free under ``T`` (:func:`_free_motions`): every such motion (and
    every mix of them) that moves the region by 1 cm RMS moves the anchors by at least
    ``min_share`` cm RMS. Anchors on a line parallel to a cylinder's axis pin its turn and
    its slide; anchors where the region turns about (its axis, far off them) do not."""
    motions = _free_motions(region, model, model_tree, T, voxel, free_below)
    if motions is None or not len(anchor_points):
        return False
    if not motions:
        return True
    anchored = np.hstack([transform_points(T, anchor_points), np.ones((len(anchor_points), 1))])
    # (3K, m): displacement of every anchor per unit of each free motion, RMS over the anchors
    displacement = np.stack([(anchored @ generator.T)[:, :3].ravel() for generator in motions], axis=1)
    displacement /= np.sqrt(len(anchor_points))
    return bool(np.linalg.svd(displacement, compute_uv=False)[-1] >= min_share)


def texture_pin(region: SurfaceModel, model: SurfaceModel, model_tree: cKDTree, T: np.ndarray, voxel: float,
                free_below: float, min_fitness: float) -> np.ndarray | None:
    """The fit ``T`` (model <- region) moved along the motions its shape leaves free
    (:func:`_free_motions`, information below ``free_below``) to where the texture lines up
    best (:func:`texture_agreement`; coordinate ascent, steps of TEXTURE_SEARCH_STEP_METRES
    within TEXTURE_PIN_METRES), if the texture pins it there: moving TEXTURE_PIN_METRES along
    any free motion, either way, drops the agreement to TEXTURE_PIN_RATIO of its peak or takes
    the region off the model (below ``min_fitness``). None otherwise (a flat texture along the
    motion, or none). Measured on synth_two seed 5, a cylinder turned about its axis: the
    agreement 0.85 at the right turn, 0.68-0.73 at 8 degrees (1 cm), 0.51-0.57 at 12."""
    from scipy.linalg import expm

    motions = _free_motions(region, model, model_tree, T, voxel, free_below)
    if motions is None:
        return None

    def moved(generator: np.ndarray, metres: float) -> np.ndarray:
        return expm(metres * generator) @ T

    def score(candidate: np.ndarray) -> float:
        if fitness(region, model_tree, candidate, voxel) < min_fitness:
            return -np.inf
        return texture_agreement(region, model, model_tree, candidate, voxel)

    steps = np.arange(-TEXTURE_PIN_METRES, TEXTURE_PIN_METRES + 1e-9, TEXTURE_SEARCH_STEP_METRES)
    peak = score(T)
    for _ in range(2):  # coordinate ascent over the free motions (a cylinder: its turn and its slide)
        for generator in motions:
            candidates = [moved(generator, metres) for metres in steps]
            scores = [score(candidate) for candidate in candidates]
            best = int(np.argmax(scores))
            if scores[best] > peak:
                T, peak = candidates[best], scores[best]
    if not np.isfinite(peak) or peak <= 0:
        return None
    for generator in motions:
        for metres in (-TEXTURE_PIN_METRES, TEXTURE_PIN_METRES):
            if score(moved(generator, metres)) > TEXTURE_PIN_RATIO * peak:
                return None
    return T


def seen_through_share(model: SurfaceModel, T_model_camera: np.ndarray, view, intrinsics, noise, margin: float,
                       sigmas: float, min_points: int = 20) -> float | None:
    """Share of the model's points that the current view saw through if the model sat at
    ``T_model_camera`` (model <- this camera): of the points facing the camera that project
    where ``view`` (a :class:`~jsr.pipeline.free_space.DepthView` of this frame, identity pose)
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


def _turn_about(axis: np.ndarray, centre: np.ndarray, angle: float) -> np.ndarray:
    """``(4, 4)`` rotation by ``angle`` (radians) about the line through ``centre`` along ``axis``."""
    turn = make_transform(rotation_about_axis(axis, angle), np.zeros(3))
    return make_transform(np.eye(3), centre) @ turn @ make_transform(np.eye(3), -centre)


def _half_turn(axis: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``(4, 4)`` rotation by 180 degrees about the line through ``centre`` along ``axis``."""
    return _turn_about(axis, centre, np.pi)


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
