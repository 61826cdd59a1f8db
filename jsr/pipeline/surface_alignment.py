"""Shape-based alignment of a region's surface to an object's surface model.

Features alone cannot find an object again after a jump that turned it far: the new view
shares few SIFT matches with its map that pass the ratio test (on kitchen_box120, 2-6 between
the maps of one box). Its *shape* still fits the object's surface, seen from another side.
This module aligns a region's surface to an object's model (:mod:`jsr.pipeline.surfaces`,
a subsampled coloured surface per object keyframe): FPFH correspondences (Rusu et al. 2009,
via Open3D), a seeded RANSAC of our own (so runs are reproducible), the region's 180-degree
self-symmetries (a box face fits its model four ways), point-to-plane ICP and coloured ICP.
What makes a fit certain is :mod:`jsr.pipeline.surface_evidence`.

Frames: ``camera`` is the frame of the view a sample was taken in; ``model`` is the object
map's frame. Transforms are ``(4, 4)`` and map points of the right-hand frame into the left.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from jsr.geometry import cross_matrices, make_transform, rotation_about_axis, transform_points
from jsr.pipeline.surface_evidence import (color_residual, fitness, same_placement, share_on_surface, texture_agreement,
                                           texture_sweep, turn_about)
from jsr.pipeline.surfaces import SurfaceModel, thinned


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
REFINED_FITS = 32  # coloured ICP refines at most this many distinct point-to-plane fits, those of best colour agreement
ICP_STARTS = 48  # ICP runs from at most this many starts, those that fit the sample best (bounds the cost)
# Surfaces with more points are aligned at a coarser voxel, the same for both (their FPFH must be
# comparable), so that neither has more than this many: ICP's cost grows with the points, and a
# person-sized model (44000 points at 1 cm) made single frames take 10-50 s on bonn_crowd_people.
# Objects of 20-30 cm have 900-1900 points at 1 cm and are aligned at full resolution.
MAX_ALIGNED_POINTS = 2000
# A large model's alignment voxel follows the region's size (alignment_voxel), so a lost
# person-sized model would keep one thinned copy per voxel it met, for as long as it lives.
CACHED_VOXELS = 4
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


def _model_at(model: SurfaceModel, voxel: float, thin: bool) -> tuple[SurfaceModel, np.ndarray]:
    """``model`` (thinned to ``voxel`` if ``thin``) and its :func:`_features`, kept in
    ``model.derived``: a lost object's model is aligned to the moving regions of many frames."""
    key = ("aligned at", voxel, thin)
    if key not in model.derived:
        cached = [k for k in model.derived if isinstance(k, tuple) and k[0] == "aligned at"]
        for old in cached[: max(len(cached) - CACHED_VOXELS + 1, 0)]:
            del model.derived[old]  # the oldest first (dicts keep insertion order)
        at = thinned(model, voxel) if thin else model
        model.derived[key] = (at, _features(at, voxel))
    return model.derived[key]


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
    region once more by coloured ICP (undone when it loses both fit and texture), at most
    :data:`REFINED_FITS` of them. Large surfaces are aligned at a coarser voxel
    (:func:`alignment_voxel`), their fitness measured at it. Returned: alignments with at least
    ``min_fitness`` of the region on the model surface, at most ``max_candidates``, no two
    within 2 cm and 10 degrees, ordered by their colour residual.
    """
    if len(region.points) < 20 or len(model.points) < 20:
        return []
    coarser = alignment_voxel(region, model, voxel)
    thin = coarser > voxel  # (at their own voxel thinning keeps every point)
    voxel = coarser
    region = thinned(region, voxel) if thin else region
    region_features = _features(region, voxel)
    model, model_features = _model_at(model, voxel, thin)
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
    sample_fitness = np.array([share_on_surface(sample, tree, T, voxel) for T in transforms])
    keep_distinct(np.argsort(-sample_fitness, kind="stable"), order, hypotheses + FITTING_HYPOTHESES)

    model_turns = _symmetry_axes(model.points, model.normals)
    starts = []
    for position in order:
        T = transforms[position]
        aligned = transform_points(T, region.points)
        aligned_normals = region.normals @ T[:3, :3].T
        starts += [T] + [_half_turn(axis, through) @ T
                         for axis, through in _symmetry_axes(aligned, aligned_normals) + model_turns]
    # 18 hypotheses with ~10 turns each make ~200 starts, most far off: ICP from all took
    # 3-6 s in one frame of a real kitchen. Those that already put most of the sample on the
    # model are where ICP converges to a fit.
    start_fitness = np.array([share_on_surface(sample, tree, T, voxel) for T in starts])
    starts = [starts[k] for k in np.sort(np.argsort(-start_fitness, kind="stable")[:ICP_STARTS])]
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
        # Coloured ICP is most of the cost, and a large surface fits a region in dozens of
        # distinct places (a person: 40-50, 3-4 s a frame). The best-coloured are refined: the
        # alignments are chosen by colour. Boxes gave 10-28 distinct fits on kitchen_box120.
        if len(refine) > REFINED_FITS:
            residuals = [color_residual(region, model, tree, coarse, voxel) for coarse in refine]
            refine = [refine[k] for k in np.sort(np.argsort(residuals, kind="stable")[:REFINED_FITS])]
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


def alignment_voxel(region: SurfaceModel, model: SurfaceModel, voxel: float) -> float:
    """The voxel at which ``region`` and ``model`` (thinned at ``voxel``) are aligned:
    ``voxel``, coarsened until neither keeps more than :data:`MAX_ALIGNED_POINTS` points, so that
    an alignment's work is bounded whatever the surfaces' size. A sheet's count falls with the
    voxel's area; a thick surface's falls slower (a person's map, views of a body that moved:
    25748 points at 1 cm kept 3723 at the 3.6 cm that the area predicts, and its alignments took
    3 s), so the count is measured again at each coarser voxel."""
    aligned = voxel
    count = max(len(region.points), len(model.points))
    while count > MAX_ALIGNED_POINTS:
        aligned *= max(1.05, float(np.sqrt(count / MAX_ALIGNED_POINTS)))
        count = max(len(thinned(region, aligned).points), len(thinned(model, aligned).points))
    return aligned


def _half_turn(axis: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``(4, 4)`` rotation by 180 degrees about the line through ``centre`` along ``axis``."""
    return turn_about(axis, centre, np.pi)


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
