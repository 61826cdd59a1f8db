"""Mixed point/plane RANSAC registration (after Pinpoint SLAM, Ataer-Cansizoglu et al. 2016).

A frame is registered to a map from 3D-3D, 2D-3D and plane correspondences; their residuals,
noise-model thresholds and the counting rule of a success are in
:mod:`jsr.pipeline.correspondences`, the batched scoring of hypotheses (with the depth
fallback of image mode) in :mod:`jsr.pipeline.pose_scoring`.

RANSAC draws minimal samples of three correspondences from a pool: the 3D points and planes
when at least ``ransac.sample_2d_below`` of them exist, otherwise all correspondences. The
mix of each sample follows from drawing three distinct pool elements uniformly; each mix has
its solver in :mod:`jsr.pipeline.solvers` (mixes of 2D points with planes have none and are
never drawn). Samples are drawn, solved and scored ``ransac.batch_size`` at a time, the
scores of all hypotheses of a batch computed at once. The best hypothesis minimises the
truncated quadratic (MSAC) cost, each residual scaled by its threshold. Stopping is adaptive:
``ceil(log(1 - confidence) / log(1 - w^3))`` samples for the best pool inlier ratio ``w``,
at most ``ransac.max_iterations``. Then least squares on the inliers of all three types
(Levenberg-Marquardt over an increment of the pose, :mod:`jsr.pipeline.pose_refinement`: with
analytic derivatives in image mode, ``scipy.optimize.least_squares`` in metric mode) and inlier
re-selection alternate for up to ``ransac.refine_rounds`` rounds.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time

import numpy as np

from jsr.config import NoiseConfig, RansacConfig
from jsr.pipeline import solvers
from jsr.pipeline.correspondences import (Correspondences, RegistrationResult, depth_thresholds, min_inliers,
                                          plane_residuals, point2d_residuals, point3d_residuals,
                                          point3d_thresholds)
from jsr.pipeline.pose_refinement import refine_pose, refine_pose_image_space
from jsr.pipeline.pose_scoring import RegistrationProblem

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------

# (3D points, 2D points, planes) in a minimal sample, for every mix that has a solver.
_MIXES = ((3, 0, 0), (2, 1, 0), (1, 2, 0), (0, 3, 0), (2, 0, 1), (1, 0, 2), (0, 0, 3))


def _sample_distinct(rng: np.random.Generator, n: int, k: int, count: int) -> np.ndarray:
    """``(count, k)`` rows of ``k`` distinct indices in ``[0, n)``, each row uniform."""
    out = np.empty((count, k), dtype=np.int64)
    if k == 0:
        return out
    first = rng.integers(0, n, count)
    out[:, 0] = first
    if k >= 2:
        second = rng.integers(0, n - 1, count)
        second += second >= first
        out[:, 1] = second
    if k >= 3:
        low = np.minimum(out[:, 0], out[:, 1])
        high = np.maximum(out[:, 0], out[:, 1])
        third = rng.integers(0, n - 2, count)
        third += third >= low
        third += third >= high
        out[:, 2] = third
    return out


def _mix_probabilities(pool: tuple[int, int, int]) -> np.ndarray:
    """Probability of each mix in :data:`_MIXES` when drawing 3 of the pool, renormalised."""
    weights = np.array(
        [math.comb(pool[0], m[0]) * math.comb(pool[1], m[1]) * math.comb(pool[2], m[2]) for m in _MIXES],
        dtype=float,
    )
    total = weights.sum()
    return weights / total if total > 0 else weights


def _solve_mix(
    problem: RegistrationProblem, mix: tuple[int, int, int], i3: np.ndarray, i2: np.ndarray, ip: np.ndarray
) -> np.ndarray:
    """Candidate transforms ``(K, 4, 4)`` of a batch of samples of one mix."""
    p, q, bearings, x2 = problem.p, problem.q, problem.bearings, problem.x2
    pc, pm = problem.planes_c, problem.planes_m
    if mix == (3, 0, 0):
        result = solvers.solve_points3d_batch(p[i3], q[i3])
    elif mix == (2, 1, 0):
        result = solvers.solve_2pt3d_1pt2d_batch(p[i3], q[i3], bearings[i2[:, 0]], x2[i2[:, 0]])
    elif mix == (1, 2, 0):
        result = solvers.solve_1pt3d_2pt2d_batch(p[i3[:, 0]], q[i3[:, 0]], bearings[i2], x2[i2])
    elif mix == (0, 3, 0):
        result = solvers.solve_p3p_batch(bearings[i2], x2[i2])
    elif mix == (2, 0, 1):
        result = solvers.solve_1plane_2pts_batch(pc[ip[:, 0]], pm[ip[:, 0]], p[i3], q[i3])
    elif mix == (1, 0, 2):
        result = solvers.solve_2planes_1pt_batch(pc[ip], pm[ip], p[i3[:, 0]], q[i3[:, 0]])
    else:
        result = solvers.solve_3planes_batch(pc[ip], pm[ip])
    return result[0]


def _required_samples(inlier_ratio: float, confidence: float) -> float:
    if inlier_ratio <= 0.0:
        return math.inf
    all_inliers = inlier_ratio**3
    if all_inliers >= 1.0:
        return 0.0
    return math.log(1.0 - confidence) / math.log(1.0 - all_inliers)


# --------------------------------------------------------------------------------------
# Registration
# --------------------------------------------------------------------------------------


def _result(
    problem: RegistrationProblem | None,
    corr: Correspondences,
    ransac_cfg: RansacConfig,
    transform: np.ndarray,
    masks: list[np.ndarray] | None,
    iterations: int,
    reason: str,
    started: float,
) -> RegistrationResult:
    a, b, c = corr.num_point3d, corr.num_point2d, corr.num_plane
    if masks is None:
        masks = [np.zeros(a, dtype=bool), np.zeros(b, dtype=bool), np.zeros(c, dtype=bool)]
    num_matches = corr.num_matches
    num_inliers = int(sum(int(m.sum()) for m in masks))
    fitness = num_inliers / num_matches if num_matches else 0.0
    rmse = 0.0
    if problem is not None and masks[0].any():
        rmse = float(np.sqrt(np.mean(point3d_residuals(transform, corr)[masks[0]] ** 2)))
    if not reason:
        if fitness < ransac_cfg.min_inlier_ratio:
            reason = (
                f"inlier ratio {fitness:.3f} ({num_inliers}/{num_matches}) is below "
                f"ransac.min_inlier_ratio = {ransac_cfg.min_inlier_ratio}"
            )
        elif num_inliers < min_inliers(ransac_cfg):
            reason = f"only {num_inliers} inliers, at least {min_inliers(ransac_cfg)} are needed"
    return RegistrationResult(
        transformation=np.array(transform, dtype=float),
        success=not reason,
        inliers_point3d=masks[0],
        inliers_point2d=masks[1],
        inliers_plane=masks[2],
        num_matches=num_matches,
        num_inliers=num_inliers,
        fitness=fitness,
        rmse=rmse,
        iterations=iterations,
        reason=reason,
        time_ms=(time.perf_counter() - started) * 1e3,
        correspondences=corr,
    )


def evaluate_pose(
    transform: np.ndarray, corr: Correspondences, ransac_cfg: RansacConfig, noise_cfg: NoiseConfig
) -> RegistrationResult:
    """Inliers and success of a given pose, without RANSAC or refinement."""
    started = time.perf_counter()
    transform = np.asarray(transform, dtype=float)
    if corr.num_matches < ransac_cfg.min_matches:
        return _result(None, corr, ransac_cfg, transform, None, 0, _too_few(corr, ransac_cfg), started)
    problem = RegistrationProblem(corr, ransac_cfg, noise_cfg)
    _, _, masks = problem.score_one(transform)
    return _result(problem, corr, ransac_cfg, transform, masks, 0, "", started)


def scaled_residuals(transform: np.ndarray, corr: Correspondences, ransac_cfg: RansacConfig,
                     noise_cfg: NoiseConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """How far ``transform`` (``T_map_cam``, 4x4) leaves every correspondence from agreeing, as
    residual over inlier threshold, capped at 1 (a pair the pose makes an outlier): ``(A,)``
    3D-3D, ``(B,)`` 2D-3D (1 for a landmark behind the camera), ``(C,)`` plane normal angles and
    ``(C,)`` plane offsets."""
    transform = np.asarray(transform, dtype=float)
    points3d = point3d_residuals(transform, corr) / point3d_thresholds(corr, noise_cfg)
    distance, depth, along = point2d_residuals(transform, corr)
    in_front = (along > 0) & (depth > 0)
    points2d = np.where(in_front, distance / depth_thresholds(np.abs(depth), noise_cfg), 1.0)
    angle, offset = plane_residuals(transform, corr)
    return (np.minimum(points3d, 1.0), np.minimum(points2d, 1.0),
            np.minimum(angle / np.deg2rad(ransac_cfg.plane_inlier_angle_degrees), 1.0),
            np.minimum(offset / ransac_cfg.plane_inlier_distance, 1.0))


def squared_cost(scaled: np.ndarray, noise_cfg: NoiseConfig) -> np.ndarray:
    """Squared residuals in noise sigmas from residuals over inlier threshold (capped at 1,
    :func:`scaled_residuals`): a residual's sigma is its threshold over ``noise.inlier_sigmas``,
    times sqrt(2) (the landmark is about as noisy as the measurement)."""
    return np.asarray(scaled) ** 2 * noise_cfg.inlier_sigmas**2 / 2.0


def pose_cost(transform: np.ndarray, result: RegistrationResult, ransac_cfg: RansacConfig,
              noise_cfg: NoiseConfig) -> float:
    """How badly ``transform`` (``T_map_cam``, 4x4) explains the inliers of ``result``: the sum
    over them of squared residuals in noise sigmas, each residual capped at its inlier
    threshold (a pair that ``transform`` makes an outlier costs the most a pair can;
    :func:`scaled_residuals`, :func:`squared_cost`).

    A residual's sigma is its inlier threshold over ``noise.inlier_sigmas`` (3D and 2D points:
    the axial depth noise at their depth, at least ``noise.min_inlier_threshold`` over it;
    planes: the angle and offset thresholds), times sqrt(2): the landmark is about as noisy as
    the measurement. Were residuals Gaussian with these sigmas, the cost of the true pose would
    exceed that of the least-squares pose by a chi-square with 6 degrees of freedom (99% below
    16.8). They are smaller (the sigmas are the axial depth noise, and most of a residual is
    lateral): on seeded scenes of points 0.8-4 m away the true pose costs 0.3-1.4 more, and a
    pose 5 mm off 50-70 more.
    """
    corr = result.correspondences
    if corr is None:
        raise ValueError("pose_cost needs a result that carries its correspondences")
    points3d, points2d, angles, offsets = scaled_residuals(transform, corr, ransac_cfg, noise_cfg)
    in_thresholds = np.concatenate([points3d[result.inliers_point3d], points2d[result.inliers_point2d],
                                    angles[result.inliers_plane], offsets[result.inliers_plane]])
    return float((in_thresholds**2).sum() * noise_cfg.inlier_sigmas**2 / 2.0)


def surface_pose_result(transform: np.ndarray, corr: Correspondences, ransac_cfg: RansacConfig,
                        noise_cfg: NoiseConfig, min_links: int) -> RegistrationResult:
    """A successful result at a pose that a surface alignment alone decided (shape-based
    re-identification): ``transform`` is ``T_map_cam``. The ``corr`` matches that agree with
    it (the inlier tests of :func:`evaluate_pose`, here also below ``ransac.min_matches``)
    stay inliers, linking the view to old landmarks, only when at least ``min_links`` of them
    agree: fewer may agree by chance. ``reason`` says where the pose came from."""
    started = time.perf_counter()
    transform = np.asarray(transform, dtype=float)
    if corr.num_matches:
        problem = RegistrationProblem(corr, ransac_cfg, noise_cfg)
        _, _, masks = problem.score_one(transform)
        evaluated = _result(problem, corr, ransac_cfg, transform, masks, 0, "", started)
    else:
        evaluated = _result(None, corr, ransac_cfg, transform, None, 0, "no matches", started)
    masks = [evaluated.inliers_point3d, evaluated.inliers_point2d, evaluated.inliers_plane]
    if evaluated.num_inliers < min_links:
        masks = [np.zeros_like(mask, dtype=bool) for mask in masks]
    num_inliers = int(sum(int(np.sum(mask)) for mask in masks))
    return dataclasses.replace(
        evaluated, success=True, inliers_point3d=masks[0], inliers_point2d=masks[1], inliers_plane=masks[2],
        num_inliers=num_inliers, fitness=num_inliers / corr.num_matches if corr.num_matches else 0.0,
        rmse=evaluated.rmse if num_inliers else 0.0, reason="pose from a surface alignment alone")


def _too_few(corr: Correspondences, ransac_cfg: RansacConfig) -> str:
    return (
        f"too few matches: {corr.num_matches} (3D {corr.num_point3d}, 2D {corr.num_point2d}, "
        f"planes {corr.num_plane}) < ransac.min_matches = {ransac_cfg.min_matches}"
    )


def register(
    corr: Correspondences,
    ransac_cfg: RansacConfig,
    noise_cfg: NoiseConfig,
    rng: np.random.Generator,
    initial_guess: np.ndarray | None = None,
) -> RegistrationResult:
    """Estimate ``T_map_cam`` from mixed correspondences by RANSAC and least squares.

    Deterministic for a given ``rng`` state. ``initial_guess`` (e.g. a predicted pose) is
    scored as the first hypothesis, so RANSAC keeps it unless a sample explains more.
    """
    started = time.perf_counter()
    fallback = np.eye(4) if initial_guess is None else np.asarray(initial_guess, dtype=float)
    if corr.num_matches < ransac_cfg.min_matches:
        return _result(None, corr, ransac_cfg, fallback, None, 0, _too_few(corr, ransac_cfg), started)
    problem = RegistrationProblem(corr, ransac_cfg, noise_cfg)

    # The sampling pool: 3D points and planes, plus 2D points when 3D is scarce.
    n3, n2, npl = len(problem.finite3), len(problem.finite2), len(problem.finitep)
    use_2d = n3 + npl < ransac_cfg.sample_2d_below
    pool = (n3, n2 if use_2d else 0, npl)
    pool_size = sum(pool)
    probabilities = _mix_probabilities(pool)
    pool_kinds = np.array([1, 1 if use_2d else 0, 1])

    best_cost, best_transform, best_pool_inliers = math.inf, None, 0
    if initial_guess is not None:
        cost, counts = problem.score(fallback[None])
        best_cost, best_transform = float(cost[0]), fallback
        best_pool_inliers = int(counts[0] @ pool_kinds)

    iterations = 0
    if probabilities.sum() > 0:
        while iterations < ransac_cfg.max_iterations:
            required = _required_samples(best_pool_inliers / pool_size, ransac_cfg.confidence)
            if iterations >= required:
                break
            remaining = ransac_cfg.max_iterations - iterations
            if math.isfinite(required):
                remaining = min(remaining, math.ceil(required) - iterations)
            batch = max(1, min(ransac_cfg.batch_size, remaining))
            per_mix = rng.multinomial(batch, probabilities)
            candidates = []
            for mix, count in zip(_MIXES, per_mix):
                if count == 0:
                    continue
                i3 = problem.finite3[_sample_distinct(rng, n3, mix[0], count)]
                i2 = problem.finite2[_sample_distinct(rng, n2, mix[1], count)]
                ip = problem.finitep[_sample_distinct(rng, npl, mix[2], count)]
                candidates.append(_solve_mix(problem, mix, i3, i2, ip))
            iterations += batch
            hypotheses = np.concatenate(candidates, axis=0) if candidates else np.zeros((0, 4, 4))
            hypotheses = hypotheses[np.isfinite(hypotheses).all(axis=(1, 2))]
            if len(hypotheses) == 0:
                continue
            cost, counts = problem.score(hypotheses)
            best = int(np.argmin(cost))
            if cost[best] < best_cost:
                best_cost, best_transform = float(cost[best]), hypotheses[best]
                best_pool_inliers = int(counts[best] @ pool_kinds)

    if best_transform is None:
        reason = "no valid pose hypothesis (all minimal samples were degenerate)"
        if probabilities.sum() == 0:
            reason = "no minimal sample can be drawn from these matches (no solver for the mix)"
        return _result(problem, corr, ransac_cfg, fallback, None, iterations, reason, started)

    transform = best_transform
    cost, _, masks = problem.score_one(transform)
    refine = refine_pose if corr.focal_length is None else functools.partial(
        refine_pose_image_space, focal_length=corr.focal_length)
    for _ in range(ransac_cfg.refine_rounds):
        refined = refine(problem, transform, masks)
        if refined is None:
            break
        new_cost, _, new_masks = problem.score_one(refined)
        if not new_cost <= cost + 1e-9:
            break
        unchanged = all(np.array_equal(m, n) for m, n in zip(masks, new_masks))
        transform, cost, masks = refined, new_cost, new_masks
        if unchanged:
            break

    result = _result(problem, corr, ransac_cfg, transform, masks, iterations, "", started)
    logger.debug(
        "registration: %d matches (3D %d, 2D %d, planes %d), %d inliers, %d samples, %.1f ms%s",
        result.num_matches,
        corr.num_point3d,
        corr.num_point2d,
        corr.num_plane,
        result.num_inliers,
        iterations,
        result.time_ms,
        "" if result.success else f", failed: {result.reason}",
    )
    return result


__all__ = [
    "evaluate_pose",
    "pose_cost",
    "register",
    "surface_pose_result",
]
