"""Mixed point/plane RANSAC registration (after Pinpoint SLAM, Ataer-Cansizoglu et al. 2016).

A frame is registered to a map from three kinds of correspondences (paper, Section 2.2):

* 3D-3D points: a camera-frame point ``p`` and a map landmark ``q``; distance ``|T p - q|``;
* 2D-3D points: a bearing ray ``b`` of a keypoint without depth and a map landmark ``X``;
  distance from ``T^-1 X`` (the landmark in the camera) to the ray, and the landmark must be
  in front of the camera;
* planes: ``[n, d]`` in the camera and ``[m, e]`` in the map; the frame plane moved into the
  map must have a normal within ``ransac.plane_inlier_angle_degrees`` of ``m`` and an offset
  within ``ransac.plane_inlier_distance`` of ``e``.

Point thresholds follow the paper, ``sigma = max(noise.min_inlier_threshold,
noise.inlier_sigmas * sigma_Z(Z))`` with ``sigma_Z = noise.sigma_z_coefficient * Z^2``, ``Z``
the depth of the 3D measurement or, for 2D-3D pairs, of the landmark moved into the camera.

Depth fallback (image mode, ``ransac.depth_fallback`` = ``k > 0``). The noise model gives the
random error of a structured-light sensor; beyond about 1.5 m, where ``3 sigma_Z`` exceeds the
1 cm floor, the sensor's systematic depth error (which varies over the image and grows with
range) is of the same size, so a correct match seen from another viewpoint often fails the
depth test while its pixel agrees. Such a 3D match, with a depth error below ``k`` thresholds,
stays an inlier but constrains the pose like a 2D-3D match: through its reprojection only.
Nearer matches, whose 1 cm threshold already leaves a wide margin over the noise, keep the
strict inlier test. With the fallback on, the MSAC cost of every 3D pair weighs its pixel and
its depth agreement half each (a pair consistent in both beats one consistent in its pixel).
Measured on bonn_crowd200 (200 frames, 3 seeds): camera ATE 9.6 cm without, 4.5 cm with;
redkitchen300 (300 frames, 5 seeds): 2.46 cm without, 2.68 cm with.

Counting rule. Every correspondence counts as one match, a plane pair included (a plane is
one measurement of the frame even though it summarises many pixels), so
``num_matches = A + B + C``. RANSAC is not run when ``num_matches < ransac.min_matches``.
The registration succeeds when ``num_inliers / num_matches >= ransac.min_inlier_ratio`` and
``num_inliers >= max(3, ransac.min_inliers, ceil(ransac.min_matches * ransac.min_inlier_ratio))``.
The paper's 10 matches at 0.4 alone would accept 4 inliers, one more than a minimal sample:
on real data that happens by chance (a lost object map "found" on four 2D points of the
kitchen, 1.2 m off, in kitchen_box120), hence ``ransac.min_inliers`` (8).

RANSAC draws minimal samples of three correspondences from a pool: the 3D points and planes
when at least ``ransac.sample_2d_below`` of them exist, otherwise all correspondences. The
mix of each sample follows from drawing three distinct pool elements uniformly; each mix has
its solver in :mod:`jsr.pipeline.solvers` (mixes of 2D points with planes have none and are
never drawn). Samples are drawn, solved and scored ``ransac.batch_size`` at a time, the
scores of all hypotheses of a batch computed at once. The best hypothesis minimises the
truncated quadratic (MSAC) cost, each residual scaled by its threshold. Stopping is adaptive:
``ceil(log(1 - confidence) / log(1 - w^3))`` samples for the best pool inlier ratio ``w``,
at most ``ransac.max_iterations``. Then least squares on the inliers of all three types
(Levenberg-Marquardt over an increment of the pose: :func:`_minimise_huber` with analytic
derivatives in image mode, ``scipy.optimize.least_squares`` in metric mode) and inlier
re-selection alternate for up to ``ransac.refine_rounds`` rounds.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from jsr.config import NoiseConfig, RansacConfig
from jsr.geometry import cross_matrices, inlier_threshold
from jsr.pipeline import solvers
from jsr.pipeline.robust_loss import huber_cost

logger = logging.getLogger(__name__)

_ID_FIELDS = {
    "point3d": ("frame_point_ids", "landmark_ids"),
    "point2d": ("frame_point_ids_2d", "landmark_ids_2d"),
    "plane": ("frame_plane_ids", "landmark_plane_ids"),
}


def _array(values: np.ndarray | None, columns: int) -> np.ndarray:
    if values is None:
        return np.zeros((0, columns))
    return np.asarray(values, dtype=float).reshape(-1, columns)


@dataclass
class Correspondences:
    """Matches between frame measurements and map landmarks, one row per match.

    ``frame_points`` ``(A, 3)`` camera-frame 3D points and ``map_points`` ``(A, 3)`` their
    landmarks; ``point_depths`` ``(A,)`` camera depth of the 3D points (defaults to their z).
    ``frame_bearings`` ``(B, 3)`` unit rays of 2D points and ``map_points_2d`` ``(B, 3)``.
    ``frame_planes`` ``(C, 4)`` ``[n, d]`` in the camera and ``map_planes`` ``(C, 4)`` in the map.
    The optional id arrays (frame measurement indices, landmark ids) are not used here and are
    carried through :meth:`subset` unchanged, so that callers can map inliers back.
    ``focal_length`` (pixels), when given, switches the final least squares to image-space
    residuals (see :func:`_refine_pose_image_space`).
    """

    frame_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    map_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    frame_bearings: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    map_points_2d: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    frame_planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    map_planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    point_depths: np.ndarray | None = None
    frame_point_ids: np.ndarray | None = None
    landmark_ids: np.ndarray | None = None
    frame_point_ids_2d: np.ndarray | None = None
    landmark_ids_2d: np.ndarray | None = None
    frame_plane_ids: np.ndarray | None = None
    landmark_plane_ids: np.ndarray | None = None
    focal_length: float | None = None

    def __post_init__(self) -> None:
        self.frame_points = _array(self.frame_points, 3)
        self.map_points = _array(self.map_points, 3)
        self.frame_bearings = _array(self.frame_bearings, 3)
        self.map_points_2d = _array(self.map_points_2d, 3)
        self.frame_planes = _array(self.frame_planes, 4)
        self.map_planes = _array(self.map_planes, 4)
        pairs = [
            ("frame_points", "map_points"),
            ("frame_bearings", "map_points_2d"),
            ("frame_planes", "map_planes"),
        ]
        for a, b in pairs:
            if len(getattr(self, a)) != len(getattr(self, b)):
                raise ValueError(f"Correspondences: {a} and {b} differ in length")
        if self.point_depths is None:
            self.point_depths = self.frame_points[:, 2].copy()
        else:
            self.point_depths = np.asarray(self.point_depths, dtype=float).reshape(-1)
            if len(self.point_depths) != self.num_point3d:
                raise ValueError("Correspondences: point_depths must have one value per 3D point")
        sizes = {"point3d": self.num_point3d, "point2d": self.num_point2d, "plane": self.num_plane}
        for kind, names in _ID_FIELDS.items():
            for name in names:
                values = getattr(self, name)
                if values is not None:
                    values = np.asarray(values)
                    if len(values) != sizes[kind]:
                        raise ValueError(f"Correspondences: {name} must have {sizes[kind]} rows")
                    setattr(self, name, values)

    @property
    def num_point3d(self) -> int:
        return len(self.frame_points)

    @property
    def num_point2d(self) -> int:
        return len(self.frame_bearings)

    @property
    def num_plane(self) -> int:
        return len(self.frame_planes)

    @property
    def num_matches(self) -> int:
        """All correspondences; a plane pair counts as one match."""
        return self.num_point3d + self.num_point2d + self.num_plane

    def subset(
        self,
        point3d: np.ndarray | None = None,
        point2d: np.ndarray | None = None,
        plane: np.ndarray | None = None,
    ) -> "Correspondences":
        """The correspondences selected by index arrays or masks (None keeps all of a kind)."""

        def pick(values: np.ndarray | None, selection: np.ndarray | None) -> np.ndarray | None:
            if values is None or selection is None:
                return values
            return values[selection]

        return Correspondences(
            frame_points=pick(self.frame_points, point3d),
            map_points=pick(self.map_points, point3d),
            frame_bearings=pick(self.frame_bearings, point2d),
            map_points_2d=pick(self.map_points_2d, point2d),
            frame_planes=pick(self.frame_planes, plane),
            map_planes=pick(self.map_planes, plane),
            point_depths=pick(self.point_depths, point3d),
            frame_point_ids=pick(self.frame_point_ids, point3d),
            landmark_ids=pick(self.landmark_ids, point3d),
            frame_point_ids_2d=pick(self.frame_point_ids_2d, point2d),
            landmark_ids_2d=pick(self.landmark_ids_2d, point2d),
            frame_plane_ids=pick(self.frame_plane_ids, plane),
            landmark_plane_ids=pick(self.landmark_plane_ids, plane),
            focal_length=self.focal_length,
        )


@dataclass
class RegistrationResult:
    """Outcome of :func:`register` (or :func:`evaluate_pose`).

    ``transformation``: ``T_map_cam``. On failure it is the best pose found (or the initial
    guess / identity when RANSAC did not run) and must not be trusted; ``reason`` says why
    (on a success it is empty, except for :func:`surface_pose_result`).
    ``fitness`` is ``num_inliers / num_matches``; ``rmse`` the RMS distance of the inlier 3D
    point pairs in metres (0.0 when there are none); ``iterations`` the minimal samples drawn
    (an initial guess is scored in addition to them).
    """

    transformation: np.ndarray
    success: bool
    inliers_point3d: np.ndarray
    inliers_point2d: np.ndarray
    inliers_plane: np.ndarray
    num_matches: int
    num_inliers: int
    fitness: float
    rmse: float
    iterations: int
    reason: str = ""
    time_ms: float = 0.0
    correspondences: Correspondences | None = field(default=None, repr=False)


# --------------------------------------------------------------------------------------
# Residuals and inlier tests
# --------------------------------------------------------------------------------------


def point3d_thresholds(corr: Correspondences, noise_cfg: NoiseConfig) -> np.ndarray:
    """``(A,)`` inlier thresholds of the 3D-3D pairs from the depth of the frame points."""
    return depth_thresholds(corr.point_depths, noise_cfg)


def depth_thresholds(depth: np.ndarray, noise_cfg: NoiseConfig) -> np.ndarray:
    """Inlier thresholds (m) of points at ``depth`` (m, any shape): the paper's
    ``max(noise.min_inlier_threshold, noise.inlier_sigmas * sigma_Z(Z))``."""
    return inlier_threshold(
        np.abs(depth),
        coefficient=noise_cfg.sigma_z_coefficient,
        sigma_multiple=noise_cfg.inlier_sigmas,
        minimum=noise_cfg.min_inlier_threshold,
    )


def point3d_residuals(transform: np.ndarray, corr: Correspondences) -> np.ndarray:
    """``(A,)`` distances ``|T p - q|`` in metres."""
    moved = corr.frame_points @ transform[:3, :3].T + transform[:3, 3]
    return np.linalg.norm(moved - corr.map_points, axis=1)


def point2d_residuals(
    transform: np.ndarray, corr: Correspondences
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the 2D-3D pairs: ``(distance to the ray, landmark depth z, distance along the ray)``.

    The landmark is moved into the camera, ``T^-1 X``; each output is ``(B,)``.
    """
    camera = (corr.map_points_2d - transform[:3, 3]) @ transform[:3, :3]
    bearings = _unit_rows(corr.frame_bearings)
    along = np.einsum("bi,bi->b", camera, bearings)
    distance = np.linalg.norm(camera - along[:, None] * bearings, axis=1)
    return distance, camera[:, 2], along


def plane_residuals(transform: np.ndarray, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """For the plane pairs: ``(normal angle in radians, |offset difference| in metres)``."""
    normals = _unit_rows(corr.frame_planes[:, :3]) @ transform[:3, :3].T
    offsets = corr.frame_planes[:, 3] - normals @ transform[:3, 3]
    cosine = np.einsum("ci,ci->c", normals, _unit_rows(corr.map_planes[:, :3]))
    return np.arccos(np.clip(cosine, -1.0, 1.0)), np.abs(offsets - corr.map_planes[:, 3])


def point_inliers(transform: np.ndarray, corr: Correspondences, noise_cfg: NoiseConfig) -> np.ndarray:
    """``(A,)`` bool: 3D-3D pairs closer than their depth-dependent threshold under ``T``."""
    return point3d_residuals(transform, corr) < point3d_thresholds(corr, noise_cfg)


def point2d_inliers(transform: np.ndarray, corr: Correspondences, noise_cfg: NoiseConfig) -> np.ndarray:
    """``(B,)`` bool: landmarks in front of the camera and close to their bearing ray."""
    distance, depth, along = point2d_residuals(transform, corr)
    return (along > 0) & (depth > 0) & (distance < depth_thresholds(depth, noise_cfg))


def plane_inliers(transform: np.ndarray, corr: Correspondences, ransac_cfg: RansacConfig) -> np.ndarray:
    """``(C,)`` bool: plane pairs within the angle and offset thresholds under ``T``."""
    angle, offset = plane_residuals(transform, corr)
    return (angle < np.deg2rad(ransac_cfg.plane_inlier_angle_degrees)) & (
        offset < ransac_cfg.plane_inlier_distance
    )


def _unit_rows(vectors: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.where(norm > 0, norm, 1.0)


def min_inliers(ransac_cfg: RansacConfig) -> int:
    """Fewest inliers a successful registration needs (see the module docstring)."""
    return max(3, ransac_cfg.min_inliers, math.ceil(ransac_cfg.min_matches * ransac_cfg.min_inlier_ratio - 1e-9))


# --------------------------------------------------------------------------------------
# The problem: arrays, thresholds and batched scoring
# --------------------------------------------------------------------------------------


class _Problem:
    """Correspondences as contiguous arrays with their thresholds, scored in batches."""

    def __init__(self, corr: Correspondences, ransac_cfg: RansacConfig, noise_cfg: NoiseConfig):
        self.noise = noise_cfg
        self.p = np.ascontiguousarray(corr.frame_points)
        self.q = np.ascontiguousarray(corr.map_points)
        self.threshold3 = point3d_thresholds(corr, noise_cfg)
        # With a focal length, points are tested in the image: reprojection error against
        # inlier_sigmas * pixel_sigma pixels, and (3D points) the depth error against the
        # paper's sigma = max(1 cm, 3 sigma_Z). Without one, the paper's 3D distance test.
        self.focal_length = corr.focal_length
        self.pixel_threshold = noise_cfg.inlier_sigmas * noise_cfg.pixel_sigma
        # Depth-error bound (in thresholds) up to which a 3D pair may fall back to its
        # reprojection: ransac.depth_fallback beyond the 1 cm floor, 1 (no fallback) within it.
        beyond_floor = self.threshold3 > noise_cfg.min_inlier_threshold * (1.0 + 1e-9)
        fallback = ransac_cfg.depth_fallback if ransac_cfg.depth_fallback > 0 else 1.0
        self.depth_bound = np.where(beyond_floor, max(fallback, 1.0), 1.0)
        self.depth_fallback = fallback > 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            self.measured_uv = self.p[:, :2] / self.p[:, 2:3]
        self.bearings = _unit_rows(corr.frame_bearings)
        self.x2 = np.ascontiguousarray(corr.map_points_2d)
        self.planes_c = np.concatenate(
            [_unit_rows(corr.frame_planes[:, :3]), corr.frame_planes[:, 3:]], axis=1
        )
        self.planes_m = np.concatenate(
            [_unit_rows(corr.map_planes[:, :3]), corr.map_planes[:, 3:]], axis=1
        )
        self.angle_threshold = np.deg2rad(ransac_cfg.plane_inlier_angle_degrees)
        self.distance_threshold = ransac_cfg.plane_inlier_distance
        self.cos_threshold = np.cos(self.angle_threshold)
        self.sizes = (len(self.p), len(self.x2), len(self.planes_c))
        # Per-correspondence factors of the expanded squared residuals (see score()).
        self.features3 = np.concatenate(
            [
                np.einsum("ai,aj->aij", self.q, self.p).reshape(-1, 9),
                self.p,
                self.q,
                np.ones((len(self.p), 1)),
            ],
            axis=1,
        )
        self.norms3 = np.einsum("ai,ai->a", self.p, self.p) + np.einsum("ai,ai->a", self.q, self.q)
        self.features2 = np.einsum("bi,bj->bij", self.x2, self.bearings).reshape(-1, 9)
        self.norms2 = np.einsum("bi,bi->b", self.x2, self.x2)
        # Rows with NaN/inf never enter a minimal sample (they can still not be inliers).
        self.finite3 = np.flatnonzero(
            np.isfinite(self.p).all(1) & np.isfinite(self.q).all(1) & np.isfinite(self.threshold3)
        )
        self.finite2 = np.flatnonzero(np.isfinite(self.bearings).all(1) & np.isfinite(self.x2).all(1))
        self.finitep = np.flatnonzero(
            np.isfinite(self.planes_c).all(1) & np.isfinite(self.planes_m).all(1)
        )

    def score(self, transforms: np.ndarray, with_masks: bool = False):
        """MSAC cost ``(K,)`` and per-kind inlier counts ``(K, 3)`` of ``K`` poses.

        With ``with_masks`` also the inlier masks ``(K, A)``, ``(K, B)``, ``(K, C)``.
        """
        k = len(transforms)
        rotations = transforms[:, :3, :3]
        translations = transforms[:, :3, 3]
        cost = np.zeros(k)
        counts = np.zeros((k, 3), dtype=np.int64)
        masks = []
        a, b, c = self.sizes
        flat_rotations = rotations.reshape(k, 9).T  # (9, K), row-major R_ij
        rt_t = np.einsum("kji,kj->ki", rotations, translations)  # R^T t, (K, 3)
        t_sq = np.einsum("ki,ki->k", translations, translations)
        if a and self.focal_length is not None:
            camera = np.einsum("ai,kij->kaj", self.q, rotations) - rt_t[:, None, :]  # R^T (q - t), (K, A, 3)
            z = camera[:, :, 2]
            front = z > 1e-6
            uv = camera[:, :, :2] / np.where(front, z, 1.0)[:, :, None]
            reprojection = np.linalg.norm(uv - self.measured_uv[None], axis=2) * (self.focal_length / self.pixel_threshold)
            depth_error = np.abs(z - self.p[None, :, 2]) / self.threshold3[None, :]
            if self.depth_fallback:
                # inlier: the pixel agrees and the depth is within its (fallback) bound; the
                # cost weighs pixel and depth agreement half each, so a pair consistent in
                # both beats one consistent in its pixel only
                reprojection = np.where(front & (depth_error < self.depth_bound[None, :]), reprojection, np.inf)
                inliers = reprojection < 1.0
                cost += 0.5 * (np.fmin(reprojection**2, 1.0) + np.fmin(depth_error**2, 1.0)).sum(axis=1)
            else:
                scaled = np.where(front, np.maximum(reprojection, depth_error), np.inf)
                inliers = scaled < 1.0
                cost += np.fmin(scaled * scaled, 1.0).sum(axis=1)
            counts[:, 0] = inliers.sum(axis=1)
            masks.append(inliers)
        elif a:
            # |R p + t - q|^2 expanded into one matrix product over all hypotheses.
            squared = self.features3 @ np.concatenate(
                [-2.0 * flat_rotations, 2.0 * rt_t.T, -2.0 * translations.T, t_sq[None]], axis=0
            )
            squared += self.norms3[:, None]
            scaled = (np.sqrt(np.maximum(squared, 0.0)) / self.threshold3[:, None]).T  # (K, A)
            inliers = scaled < 1.0
            cost += np.fmin(scaled * scaled, 1.0).sum(axis=1)
            counts[:, 0] = inliers.sum(axis=1)
            masks.append(inliers)
        else:
            masks.append(np.zeros((k, 0), dtype=bool))
        if b:
            # Landmark in the camera c = R^T (X - t): along-ray b.c = X^T R b - (R^T t).b,
            # |c|^2 = |X - t|^2, depth = R[:, 2].(X - t); distance^2 = |c|^2 - (b.c)^2.
            along = self.features2 @ flat_rotations - self.bearings @ rt_t.T  # (B, K)
            norm_sq = self.norms2[:, None] - 2.0 * (self.x2 @ translations.T) + t_sq[None]
            depth = self.x2 @ rotations[:, :, 2].T - np.einsum("ki,ki->k", rotations[:, :, 2], translations)
            distance = np.sqrt(np.maximum(norm_sq - along * along, 0.0))
            if self.focal_length is None:
                scaled = (distance / depth_thresholds(depth, self.noise)).T
            else:
                # distance / along is the tangent of the angle to the ray: pixels at focal length f.
                scaled = (distance / np.maximum(along, 1e-9) * (self.focal_length / self.pixel_threshold)).T
            front = ((along > 0) & (depth > 0)).T
            inliers = front & (scaled < 1.0)
            cost += np.where(front, np.fmin(scaled * scaled, 1.0), 1.0).sum(axis=1)
            counts[:, 1] = inliers.sum(axis=1)
            masks.append(inliers)
        else:
            masks.append(np.zeros((k, 0), dtype=bool))
        if c:
            normals = np.matmul(self.planes_c[:, :3], rotations.transpose(0, 2, 1))
            cosine = np.einsum("kci,ci->kc", normals, self.planes_m[:, :3])
            offsets = self.planes_c[:, 3] - np.einsum("kci,ki->kc", normals, translations)
            angle = np.arccos(np.clip(cosine, -1.0, 1.0))
            scaled = np.maximum(
                angle / self.angle_threshold,
                np.abs(offsets - self.planes_m[:, 3]) / self.distance_threshold,
            )
            inliers = scaled < 1.0
            cost += np.fmin(scaled * scaled, 1.0).sum(axis=1)
            counts[:, 2] = inliers.sum(axis=1)
            masks.append(inliers)
        else:
            masks.append(np.zeros((k, 0), dtype=bool))
        if with_masks:
            return cost, counts, masks
        return cost, counts

    def score_one(self, transform: np.ndarray):
        cost, counts, masks = self.score(transform[None], with_masks=True)
        return float(cost[0]), counts[0], [m[0] for m in masks]


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
    problem: _Problem, mix: tuple[int, int, int], i3: np.ndarray, i2: np.ndarray, ip: np.ndarray
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
# Least-squares refinement
# --------------------------------------------------------------------------------------


def _exp_and_left_jacobian(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SO(3) exponential of a rotation vector and its left Jacobian."""
    angle = float(np.linalg.norm(omega))
    w = cross_matrices(omega)
    w2 = w @ w
    if angle < 1e-6:
        a, b, c = 1.0 - angle**2 / 6.0, 0.5 - angle**2 / 24.0, 1.0 / 6.0 - angle**2 / 120.0
    else:
        a = math.sin(angle) / angle
        b = (1.0 - math.cos(angle)) / angle**2
        c = (angle - math.sin(angle)) / angle**3
    eye = np.eye(3)
    return eye + a * w + b * w2, eye + b * w + c * w2


def _refine_pose(
    problem: _Problem, transform: np.ndarray, masks: list[np.ndarray]
) -> np.ndarray | None:
    """Least squares on the inliers; the pose is ``[Exp(w) R0 | t0 + v]`` over ``x = (w, v)``."""
    m3, m2, mp = masks
    p, q, s3 = problem.p[m3], problem.q[m3], problem.threshold3[m3]
    bearings, x2 = problem.bearings[m2], problem.x2[m2]
    pc, pm = problem.planes_c[mp], problem.planes_m[mp]
    rows = 3 * len(p) + 3 * len(x2) + 4 * len(pc)
    if rows < 6:
        return None
    r0, t0 = transform[:3, :3], transform[:3, 3]
    # 2D thresholds depend on the landmark depth; fixed at the start pose for a smooth cost.
    depth = ((x2 - t0) @ r0)[:, 2]
    s2 = depth_thresholds(depth, problem.noise)
    projector = np.eye(3) - bearings[:, :, None] * bearings[:, None, :]
    sa, sd = problem.angle_threshold, problem.distance_threshold

    def pose(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rotation_increment, left_jacobian = _exp_and_left_jacobian(x[:3])
        return rotation_increment @ r0, t0 + x[3:], left_jacobian

    def residuals(x: np.ndarray) -> np.ndarray:
        rotation, translation, _ = pose(x)
        parts = [((p @ rotation.T + translation - q) / s3[:, None]).ravel()]
        camera = (x2 - translation) @ rotation
        parts.append((np.einsum("bij,bj->bi", projector, camera) / s2[:, None]).ravel())
        normals = pc[:, :3] @ rotation.T
        plane = np.concatenate(
            [
                (normals - pm[:, :3]) / sa,
                ((pc[:, 3] - normals @ translation - pm[:, 3]) / sd)[:, None],
            ],
            axis=1,
        )
        parts.append(plane.ravel())
        return np.concatenate(parts)

    def jacobian(x: np.ndarray) -> np.ndarray:
        rotation, translation, left = pose(x)
        blocks = []
        if len(p):
            j = np.zeros((len(p), 3, 6))
            j[:, :, :3] = -cross_matrices(p @ rotation.T) @ left
            j[:, :, 3:] = np.eye(3)
            blocks.append((j / s3[:, None, None]).reshape(-1, 6))
        if len(x2):
            j = np.zeros((len(x2), 3, 6))
            j[:, :, :3] = rotation.T @ cross_matrices(x2 - translation) @ left
            j[:, :, 3:] = -rotation.T
            j = np.matmul(projector, j) / s2[:, None, None]
            blocks.append(j.reshape(-1, 6))
        if len(pc):
            normals = pc[:, :3] @ rotation.T
            d_normals = -cross_matrices(normals) @ left  # (C, 3, 3)
            j = np.zeros((len(pc), 4, 6))
            j[:, :3, :3] = d_normals / sa
            j[:, 3, :3] = -np.einsum("i,cij->cj", translation, d_normals) / sd
            j[:, 3, 3:] = -normals / sd
            blocks.append(j.reshape(-1, 6))
        return np.concatenate(blocks, axis=0)

    solution = least_squares(
        residuals, np.zeros(6), jac=jacobian, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=50
    )
    if not np.all(np.isfinite(solution.x)):
        return None
    rotation, translation, _ = pose(solution.x)
    refined = np.eye(4)
    refined[:3, :3] = rotation
    refined[:3, 3] = translation
    return refined


def _refine_pose_image_space(
    problem: _Problem,
    transform: np.ndarray,
    masks: list[np.ndarray],
    focal_length: float,
    prior: np.ndarray | None = None,
    prior_sigmas: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray | None:
    """Least squares on the inliers with residuals shaped like the sensor's noise
    (:func:`_image_space_terms`), minimised with a Huber loss (scale 2 sigma) by
    :func:`_minimise_huber` from ``transform``. None when too few residuals constrain the pose."""
    linearised = _image_space_terms(problem, transform, masks, focal_length, prior, prior_sigmas)
    if linearised is None:
        return None
    refined = _minimise_huber(linearised, transform[:3, :3], transform[:3, 3], HUBER_SCALE, max_iterations=50)
    if refined is None:
        return None
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = refined
    return pose


def _image_space_terms(
    problem: _Problem,
    transform: np.ndarray,
    masks: list[np.ndarray],
    focal_length: float,
    prior: np.ndarray | None,
    prior_sigmas: tuple[float, float],
) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None:
    """The residuals of the inliers ``masks`` as a function ``linearised(rotation (3, 3),
    translation (3,)) -> (residuals (M,), jacobian (M, 6))`` of the pose ``T_map_cam``; None
    when they are fewer than six.

    A structured-light depth camera measures the image position of a point far better than its
    depth: about ``pixel_sigma`` pixels across the ray against ``sigma_Z = c Z^2`` along it. An
    isotropic 3D distance weighs both by ``sigma_Z`` and throws away most of the lateral
    information, which lets far-away scenes jitter. Here each 3D-3D pair gives two
    reprojection residuals (landmark projected with the pose vs the measured pixel, in units of
    ``pixel_sigma``) and one depth residual (in units of the combined depth noise of measurement
    and landmark); each 2D-3D pair gives two reprojection residuals; planes as in
    :func:`_refine_pose`. Inliers kept by the depth fallback at ``transform`` (see the module
    docstring) get no depth residual.

    With a ``prior`` pose (the motion model's prediction) and ``prior_sigmas`` =
    ``(rotation radians, translation metres)`` both positive, six more residuals pull the pose
    towards the prediction; this damps the frame-to-frame jitter of scenes whose texture lies
    at one distance, where a small rotation and a lateral translation explain the data alike.
    """
    m3, m2, mp = masks
    p, q = problem.p[m3], problem.q[m3]
    bearings, x2 = problem.bearings[m2], problem.x2[m2]
    pc, pm = problem.planes_c[mp], problem.planes_m[mp]
    if 3 * len(p) + 2 * len(x2) + 4 * len(pc) < 6:
        return None
    r0, t0 = transform[:3, :3], transform[:3, 3]
    angular_sigma = problem.noise.pixel_sigma / focal_length
    measured_uv = p[:, :2] / p[:, 2:3]
    bearing_uv = bearings[:, :2] / bearings[:, 2:3]
    depth_sigma = np.sqrt(2.0) * np.maximum(
        problem.noise.sigma_z_coefficient * p[:, 2] ** 2, problem.noise.min_inlier_threshold / problem.noise.inlier_sigmas
    )
    sa, sd = problem.angle_threshold, problem.distance_threshold
    # Inliers by the depth fallback (depth off by more than the threshold at the start pose)
    # constrain the pose through their reprojection only.
    depth_weight = (np.abs(((q - t0) @ r0)[:, 2] - p[:, 2]) < problem.threshold3[m3]).astype(float)

    use_prior = prior is not None and prior_sigmas[0] > 0 and prior_sigmas[1] > 0
    angular_weight = 1.0 / angular_sigma
    depth_scale = depth_weight / depth_sigma

    def linearised(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals ``(M,)`` at the pose and their Jacobian ``(M, 6)`` with respect to the
        increment ``[w, dt]`` that maps it to ``(Exp(w) rotation, translation + dt)``."""
        parts, jacobians = [], []
        for targets, observed in ((q, measured_uv), (x2, bearing_uv)):
            relative = targets - translation
            landmarks = relative @ rotation  # in the camera frame: R^T (X - t)
            z = np.maximum(landmarks[:, 2], 1e-6)
            # d landmark / d w = R^T [X - t]_x, d landmark / d t = -R^T
            d_landmark = np.concatenate([np.einsum("ji,njk->nik", rotation, cross_matrices(relative)),
                                         np.broadcast_to(-rotation.T, (len(z), 3, 3))], axis=2)
            projected = landmarks[:, :2] / z[:, None]
            d_projected = (d_landmark[:, :2] - projected[:, :, None] * d_landmark[:, 2:3]) / z[:, None, None]
            parts.append(((projected - observed) * angular_weight).ravel())
            jacobians.append((d_projected * angular_weight).reshape(-1, 6))
            if targets is q:
                parts.append(depth_scale * (landmarks[:, 2] - p[:, 2]))
                jacobians.append(depth_scale[:, None] * d_landmark[:, 2])
        normals = pc[:, :3] @ rotation.T
        parts.append(((normals - pm[:, :3]) / sa).ravel())
        d_normals = np.zeros((len(pc), 3, 6))
        d_normals[:, :, :3] = -cross_matrices(normals)  # d (Exp(w) n) / d w = -[n]_x
        jacobians.append(d_normals.reshape(-1, 6) / sa)
        parts.append((pc[:, 3] - normals @ translation - pm[:, 3]) / sd)
        d_offsets = np.concatenate([np.cross(translation, normals), -normals], axis=1)
        jacobians.append(d_offsets / sd)
        if use_prior:
            prior_rotvec = Rotation.from_matrix(prior[:3, :3].T @ rotation).as_rotvec()
            parts.append(prior_rotvec / prior_sigmas[0])
            d_prior = np.zeros((3, 6))
            d_prior[:, :3] = _left_jacobian_inverse(prior_rotvec) @ prior[:3, :3].T
            jacobians.append(d_prior / prior_sigmas[0])
            parts.append((translation - prior[:3, 3]) / prior_sigmas[1])
            jacobians.append(np.hstack([np.zeros((3, 3)), np.eye(3)]) / prior_sigmas[1])
        return np.concatenate(parts), np.concatenate(jacobians, axis=0)

    return linearised


HUBER_SCALE = 2.0  # residuals (in sigmas) beyond this weigh linearly, not quadratically


def _left_jacobian_inverse(rotvec: np.ndarray) -> np.ndarray:
    """``(3, 3)`` inverse left Jacobian of SO(3) at ``rotvec``: ``log(Exp(a) Exp(phi)) = phi +
    J^-1 a`` for small ``a``."""
    angle = float(np.linalg.norm(rotvec))
    cross = cross_matrices(rotvec)
    if angle < 1e-6:
        return np.eye(3) - 0.5 * cross + cross @ cross / 12.0
    factor = 1.0 / angle**2 - (1.0 + math.cos(angle)) / (2.0 * angle * math.sin(angle))
    return np.eye(3) - 0.5 * cross + factor * (cross @ cross)


def _minimise_huber(linearised: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
                    rotation: np.ndarray, translation: np.ndarray, scale: float,
                    max_iterations: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose ``(rotation (3, 3), translation (3,))`` minimising the Huber cost (``scale``) of
    ``linearised(rotation, translation) -> (residuals (M,), jacobian (M, 6))``: Levenberg-
    Marquardt on iteratively reweighted normal equations (the curvature model of
    :func:`~jsr.pipeline.bundle.huber_loss`), each step ``[w, dt]`` applied as
    ``(Exp(w) rotation, translation + dt)``. None if the cost is not finite.

    Written out rather than ``scipy.optimize.least_squares``: with six unknowns and analytic
    derivatives, its finite differences and per-step SVD of the ``(M, 6)`` Jacobian were a
    quarter of the whole pipeline's run time (synth_two, 60 frames)."""
    residuals, jacobian = linearised(rotation, translation)
    cost = huber_cost(residuals, scale)
    if not np.isfinite(cost):
        return None
    damping = 1e-3
    for _ in range(max_iterations):
        magnitude = np.abs(residuals)
        weights = np.where(magnitude <= scale, 1.0, scale / np.maximum(magnitude, 1e-300))
        normal = jacobian.T @ (weights[:, None] * jacobian)
        gradient = jacobian.T @ (weights * residuals)
        if not np.all(np.isfinite(normal)) or not np.all(np.isfinite(gradient)):
            return None
        improved = False
        while damping < 1e10:
            damped = normal + damping * np.diag(np.maximum(np.diag(normal), 1e-12))
            try:
                step = -np.linalg.solve(damped, gradient)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            new_rotation = Rotation.from_rotvec(step[:3]).as_matrix() @ rotation
            new_translation = translation + step[3:]
            new_residuals, new_jacobian = linearised(new_rotation, new_translation)
            new_cost = huber_cost(new_residuals, scale)
            if np.isfinite(new_cost) and new_cost <= cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break
        converged = cost - new_cost <= 1e-10 * max(cost, 1e-12) or np.linalg.norm(step) <= 1e-10
        rotation, translation = new_rotation, new_translation
        residuals, jacobian, cost = new_residuals, new_jacobian, new_cost
        damping = max(damping / 10.0, 1e-9)
        if converged:
            break
    return rotation, translation


# --------------------------------------------------------------------------------------
# Registration
# --------------------------------------------------------------------------------------


def _result(
    problem: _Problem | None,
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
    problem = _Problem(corr, ransac_cfg, noise_cfg)
    _, _, masks = problem.score_one(transform)
    return _result(problem, corr, ransac_cfg, transform, masks, 0, "", started)


def pose_cost(transform: np.ndarray, result: RegistrationResult, ransac_cfg: RansacConfig,
              noise_cfg: NoiseConfig) -> float:
    """How badly ``transform`` (``T_map_cam``, 4x4) explains the inliers of ``result``: the sum
    over them of squared residuals in noise sigmas, each residual capped at its inlier
    threshold (a pair that ``transform`` makes an outlier costs the most a pair can).

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
    transform = np.asarray(transform, dtype=float)
    mask3, mask2, mask_planes = result.inliers_point3d, result.inliers_point2d, result.inliers_plane
    terms = [(point3d_residuals(transform, corr)[mask3] / point3d_thresholds(corr, noise_cfg)[mask3])]
    distance, depth, along = point2d_residuals(transform, corr)
    in_front = (along[mask2] > 0) & (depth[mask2] > 0)
    terms.append(np.where(in_front, distance[mask2] / depth_thresholds(np.abs(depth[mask2]), noise_cfg), 1.0))
    angle, offset = plane_residuals(transform, corr)
    terms.append(angle[mask_planes] / np.deg2rad(ransac_cfg.plane_inlier_angle_degrees))
    terms.append(offset[mask_planes] / ransac_cfg.plane_inlier_distance)
    in_thresholds = np.minimum(np.concatenate(terms), 1.0)
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
        problem = _Problem(corr, ransac_cfg, noise_cfg)
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
    problem = _Problem(corr, ransac_cfg, noise_cfg)

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
    refine = _refine_pose if corr.focal_length is None else functools.partial(
        _refine_pose_image_space,
        focal_length=corr.focal_length,
        prior=initial_guess,
        prior_sigmas=(np.deg2rad(ransac_cfg.prior_rotation_degrees), ransac_cfg.prior_translation),
    )
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
    "Correspondences",
    "RegistrationResult",
    "evaluate_pose",
    "min_inliers",
    "plane_inliers",
    "plane_residuals",
    "point2d_inliers",
    "point2d_residuals",
    "point3d_residuals",
    "point3d_thresholds",
    "point_inliers",
    "register",
]
