"""The noise of bundle adjustment's observations, estimated from their own residuals.

Bundle adjustment (:mod:`jsr.pipeline.bundle`) divides each residual by a sigma from the
configured noise model: pixels over ``bundle_adjustment.pixel_sigma``, depth over the sensor's
``sigma_Z = c Z^2``, planes over their two sigmas. The model is the sensor's random noise; on
real footage the residuals also carry what it leaves out (colour and depth not registered
exactly, depth bias far from the optical centre, a keypoint's depth looked up beside an edge).
At the solution of a window on ``bonn_crowd200``, the depth residuals spread 2.4-3.6 times their
model sigma and the reprojections half theirs: the solve then trusts the depth it should doubt,
and moves the keyframes away from the truth (camera ATE 2.5-3.7 cm with bundle adjustment off,
4.3-4.5 cm with it on).

The cure is the classic one of adjustment theory: a *variance component* per kind of
observation, estimated from the residuals (Helmert; here robustly). Each solve measures, per
group of residuals, their spread in current sigmas (the median absolute deviation, scaled to a
standard deviation and corrected for the degrees of freedom the fit took), divides the group's
weights by it and solves again while a component still moves by more than
:data:`TOLERANCE` (at most :data:`MAX_PASSES` solves). They are the sensor's: the static map's
next run starts from them (:class:`~jsr.pipeline.bundle_scheduler.BundleScheduler`), so later
runs usually need one or two solves, and object maps' runs use them as they are.
"""

from __future__ import annotations

import numpy as np

GROUPS = ("reprojection", "depth", "pixel_2d", "plane_normal", "plane_offset")
"""The kinds of residual that get their own component: the image position of a point with
depth, its depth, a point without depth, a plane's normal and a plane's offset."""

MIN_RESIDUALS = 30
"""A group with fewer residuals keeps its component: the spread of fewer is too loose (the
median absolute deviation of 30 normal samples has a standard error of about 20%). Nothing is
estimated from a problem with fewer residuals than parameters plus this: its residuals are
mostly fitted away."""

TOLERANCE = 0.1
"""Another solve follows while a component changed by more than this share."""

MAX_PASSES = 3
"""Solves per bundle adjustment run at most. The first run of a sequence starts from the
configured sigmas and needs all three on real footage; later runs start from the estimate."""

BOUNDS = (0.1, 10.0)
"""A component stays within these multiples of the configured sigma."""


def group_residuals(problem, residuals: np.ndarray) -> dict[str, np.ndarray]:
    """Split a :class:`~jsr.pipeline.bundle.BundleProblem`'s whitened residual vector (3D points,
    2D points, planes; see its ``residuals``) into the :data:`GROUPS`. Planes seen by one
    keyframe of the problem are left out: their landmark fits them exactly."""
    n3, n2, n_planes = len(problem.obs3_keyframe), len(problem.obs2_keyframe), len(problem.obsp_keyframe)
    points3 = residuals[: 3 * n3].reshape(-1, 3)
    points2 = residuals[3 * n3 : 3 * n3 + 2 * n2]
    planes = residuals[3 * n3 + 2 * n2 :].reshape(-1, 4)
    seen_twice = np.bincount(problem.obsp_plane, minlength=len(problem.plane_ids))[problem.obsp_plane] >= 2
    planes = planes[seen_twice] if n_planes else planes
    return {
        "reprojection": points3[:, :2].ravel(),
        "depth": points3[:, 2],
        "pixel_2d": points2,
        "plane_normal": planes[:, :3].ravel(),
        "plane_offset": planes[:, 3],
    }


def measured_spread(problem, x: np.ndarray) -> np.ndarray:
    """``(5,)`` the spread of each group's whitened residuals at the increments ``x``, in
    current sigmas (1 where the weights are right; NaN for a group with fewer than
    :data:`MIN_RESIDUALS`): ``1.4826 * median |r|`` (a standard deviation robust to the
    outliers the Huber loss discounts), times ``sqrt(m / (m - p))`` for the ``p`` parameters
    fitted to the ``m`` residuals (which shrink the residuals below the noise)."""
    spread = np.full(len(GROUPS), np.nan)
    used = problem.num_residuals
    if used - problem.num_parameters < MIN_RESIDUALS:
        return spread
    groups = group_residuals(problem, problem.residuals(x))
    redundancy = np.sqrt(used / (used - problem.num_parameters))
    for index, name in enumerate(GROUPS):
        values = groups[name]
        if len(values) >= MIN_RESIDUALS:
            spread[index] = 1.4826 * float(np.median(np.abs(values))) * redundancy
    return spread


def weights(problem) -> tuple:
    """The problem's residual weights, one per group (``obs3_weight`` an array): to put back
    with :func:`restore` after a solve has reweighed them."""
    return (problem.pixel_weight, problem.obs3_weight, problem.pixel2d_weight, problem.normal_weight,
            problem.offset_weight)


def restore(problem, saved: tuple) -> None:
    """Put back the weights :func:`weights` saved."""
    (problem.pixel_weight, problem.obs3_weight, problem.pixel2d_weight, problem.normal_weight,
     problem.offset_weight) = saved


def reweigh(problem, factors: np.ndarray) -> None:
    """Multiply each group's sigma by ``factors`` ``(5,)``: its weights are divided by them."""
    reprojection, depth, pixel_2d, plane_normal, plane_offset = np.asarray(factors, dtype=float)
    problem.pixel_weight = problem.pixel_weight / reprojection
    problem.obs3_weight = problem.obs3_weight / depth
    problem.pixel2d_weight = problem.pixel2d_weight / pixel_2d
    problem.normal_weight = problem.normal_weight / plane_normal
    problem.offset_weight = problem.offset_weight / plane_offset


def update(components: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """The components ``(5,)`` after a solve that measured ``spread`` with them: each times its
    spread (NaN or non-positive: unchanged), within :data:`BOUNDS`."""
    factors = np.where(np.isfinite(spread) & (spread > 0), spread, 1.0)
    return np.clip(components * factors, *BOUNDS)
