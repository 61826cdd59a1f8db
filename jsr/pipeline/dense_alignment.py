"""The dense geometric term of static tracking: the frame's depth aligned to the depth of the
static map's latest keyframes, beside the feature matches.

Features place the camera from a few hundred keypoints; the depth image holds thousands of
measurements of the same static surfaces, and stays sharp when the colour image blurs. Each
static keyframe keeps a :class:`DepthSurface` (its static pixels sampled on a grid, with
normals). :func:`align_depth` lays the frame's samples on the latest keyframes' surfaces by
point-to-plane ICP (Chen and Medioni 1992; as KinectFusion tracks), each residual divided by its
noise (the axial depth noise ``sigma_Z = c Z^2`` of both ends), minimised under a Huber loss
together with the feature inliers' residuals (those of
:func:`~jsr.pipeline.pose_refinement.refine_pose_image_space`), if any.

With ``dense.enabled``, static tracking (:func:`~jsr.pipeline.static_tracking.with_depth`)
lets the depth carry a frame whose features fail (and, with ``dense.carry_below_inliers``,
one whose features are few) when the fit :func:`carries` it: most samples end on the
keyframes' surfaces and their normals face three ways (not a single wall or a corridor);
``dense.refine`` refines every other frame this way. All are off by default: they carry a
blurred stretch of Kinect footage, but real depth at 2-4 m (the Bonn footage's Xtion)
disagrees with the features by centimetres, systematically, so that thousands of samples do
not average it out, and the camera got worse there (figures in the config).

Frames: a :class:`DepthSurface` is in its keyframe's camera frame, placed in the world by the
keyframe's current pose (so it follows bundle adjustment and loop closure). Poses are
``T_w_c`` ``(4, 4)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from jsr.config import DenseConfig, NoiseConfig
from jsr.geometry import transform_points
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline.correspondences import depth_thresholds
from jsr.pipeline.pose_refinement import HUBER_SCALE, minimise_huber

logger = logging.getLogger(__name__)

NORMAL_NEIGHBOUR_SPACINGS = 6.0  # a grid neighbour farther than this many sample spacings (depth over focal length) is across a depth edge


@dataclass
class DepthSurface:
    """Sampled static depth of one keyframe: ``points`` ``(N, 3)`` and unit ``normals``
    ``(N, 3)`` (facing the camera) in its camera frame, ``sigma`` ``(N,)`` axial noise (m)."""

    points: np.ndarray
    normals: np.ndarray
    sigma: np.ndarray


@dataclass
class DepthTarget:
    """The surfaces of several keyframes in the world frame, with a search tree over them."""

    points: np.ndarray
    normals: np.ndarray
    sigma: np.ndarray
    tree: cKDTree


def sample_stride(config: DenseConfig, intrinsics: CameraIntrinsics) -> int:
    """The sampling stride in pixels: ``dense.stride`` is given at 640 wide."""
    return max(1, int(round(config.stride * intrinsics.width / 640)))


def axial_sigma(z: np.ndarray, noise: NoiseConfig) -> np.ndarray:
    """``(N,)`` axial depth noise at depths ``z``: the inlier threshold over its number of
    sigmas (:func:`~jsr.pipeline.correspondences.depth_thresholds`; at least the floor's share,
    as the feature residuals' ``depth_sigma``)."""
    return depth_thresholds(z, noise) / noise.inlier_sigmas


def depth_samples(depth: np.ndarray, keep: np.ndarray | None, intrinsics: CameraIntrinsics,
                  stride: int) -> tuple[np.ndarray, np.ndarray]:
    """The grid of every ``stride``-th pixel of ``depth`` ``(H, W)`` metres back-projected
    (through the lens distortion, if any): ``(h, w, 3)`` camera-frame points and ``(h, w)``
    bool, valid depth where ``keep`` ``(H, W)``."""
    grid = depth[::stride, ::stride].astype(np.float64)
    rows, cols = np.mgrid[0:grid.shape[0], 0:grid.shape[1]]
    u, v = (cols * stride).astype(np.float64), (rows * stride).astype(np.float64)
    if intrinsics.has_distortion:
        ideal = intrinsics.undistort_pixels(np.stack([u.ravel(), v.ravel()], axis=1))
        u, v = ideal[:, 0].reshape(u.shape), ideal[:, 1].reshape(v.shape)
    points = np.stack([(u - intrinsics.cx) / intrinsics.fx * grid, (v - intrinsics.cy) / intrinsics.fy * grid,
                       grid], axis=-1)
    valid = grid > 0
    if keep is not None:
        valid &= keep[::stride, ::stride]
    return points, valid


def depth_surface(depth: np.ndarray, keep: np.ndarray, intrinsics: CameraIntrinsics, config: DenseConfig,
                  noise: NoiseConfig) -> DepthSurface:
    """The samples of ``depth`` ``(H, W)`` at ``keep`` ``(H, W)`` bool (static pixels) with
    normals from their grid neighbours (central differences; none across a depth edge)."""
    stride = sample_stride(config, intrinsics)
    points, valid = depth_samples(depth, keep, intrinsics, stride)
    z = points[..., 2]
    # neighbours left/right and up/down, each a kept sample near the centre (the rolls wrap
    # around: the border samples get no normal)
    right, left = np.roll(points, -1, axis=1), np.roll(points, 1, axis=1)
    down, up = np.roll(points, -1, axis=0), np.roll(points, 1, axis=0)
    ok = valid & np.roll(valid, -1, 1) & np.roll(valid, 1, 1) & np.roll(valid, -1, 0) & np.roll(valid, 1, 0)
    ok[:, [0, -1]] = False
    ok[[0, -1], :] = False
    limit = NORMAL_NEIGHBOUR_SPACINGS * stride * np.maximum(z, 1e-6) / intrinsics.fx
    for neighbour in (right, left, down, up):
        ok &= np.linalg.norm(neighbour - points, axis=-1) < limit
    normals = np.cross(right - left, down - up)
    length = np.linalg.norm(normals, axis=-1)
    ok &= length > 1e-12
    points, normals, length = points[ok], normals[ok], length[ok]
    normals /= length[:, None]
    normals *= -np.sign(np.einsum("ij,ij->i", normals, points))[:, None]  # facing the camera
    return DepthSurface(points, normals, axial_sigma(points[:, 2], noise))


def depth_target(surfaces: list[tuple[np.ndarray, DepthSurface]]) -> DepthTarget | None:
    """The surfaces ``[(T_w_c, surface), ...]`` in the world frame; None without any point."""
    parts = [(transform_points(T, s.points), s.normals @ T[:3, :3].T, s.sigma) for T, s in surfaces if len(s.points)]
    if not parts:
        return None
    points, normals, sigma = (np.concatenate(p) for p in zip(*parts))
    return DepthTarget(points, normals, sigma, cKDTree(points))


def keyframes_target(keyframes: list, surfaces: dict[int, DepthSurface]) -> DepthTarget | None:
    """:func:`depth_target` of those of ``keyframes`` (static map keyframes) that kept a surface
    (``surfaces`` by keyframe id), placed by their current poses."""
    return depth_target([(k.T_map_cam, surfaces[k.keyframe_id]) for k in keyframes if k.keyframe_id in surfaces])


def frame_samples(depth: np.ndarray, keep: np.ndarray | None, intrinsics: CameraIntrinsics, config: DenseConfig,
                  noise: NoiseConfig) -> tuple[np.ndarray, np.ndarray]:
    """The frame's samples to align: ``(N, 3)`` camera-frame points and ``(N,)`` axial noise."""
    points, valid = depth_samples(depth, keep, intrinsics, sample_stride(config, intrinsics))
    points = points[valid]
    return points, axial_sigma(points[:, 2], noise)


def _pairs(source: np.ndarray, source_sigma: np.ndarray, target: DepthTarget, pose: np.ndarray,
           config: DenseConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest target point of every source point under ``pose``: the source points that found
    one within ``dense.max_distance`` and off its plane by less than the gate, with the
    target's points, normals and the pair's noise (``(K, 3)``, ``(K, 3)``, ``(K, 3)``, ``(K,)``)."""
    in_world = transform_points(pose, source)
    distance, nearest = target.tree.query(in_world, distance_upper_bound=config.max_distance)
    found = np.isfinite(distance)
    nearest = nearest[found]
    q, n = target.points[nearest], target.normals[nearest]
    sigma = np.hypot(source_sigma[found], target.sigma[nearest])
    along = np.einsum("ij,ij->i", in_world[found] - q, n)
    # pairs off the plane by more than the Huber region's reach are other surfaces
    close = np.abs(along) < config.gate_sigmas * sigma
    return source[found][close], q[close], n[close], sigma[close]


def samples_on_surface(source: np.ndarray, source_sigma: np.ndarray, target: DepthTarget, pose: np.ndarray,
                       config: DenseConfig) -> int:
    """How many of the samples ``source`` ``(N, 3)`` (camera frame, noise ``source_sigma``
    ``(N,)``) placed by ``pose`` (``T_w_c``) lie on ``target``'s surfaces within the noise (the
    pairs :func:`align_depth` would use)."""
    return len(_pairs(source, source_sigma, target, pose, config)[0])


def point_to_plane_terms(p: np.ndarray, q: np.ndarray, n: np.ndarray, sigma: np.ndarray):
    """``linearised(rotation, translation) -> (residuals (K,), jacobian (K, 6))`` of the pairs
    ``n . (R p + t - q) / sigma`` with respect to the step ``[w, dt]`` applied as
    ``(Exp(w) R, t + dt)`` (:func:`~jsr.pipeline.pose_refinement.minimise_huber`)."""
    weight = 1.0 / sigma

    def linearised(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rotated = p @ rotation.T
        residuals = np.einsum("ij,ij->i", rotated + translation - q, n) * weight
        # d(Exp(w) R p)/dw = -[R p]_x, so d(n . R p)/dw = (R p) x n
        jacobian = np.concatenate([np.cross(rotated, n), n], axis=1) * weight[:, None]
        return residuals, jacobian

    return linearised


def _stacked(*terms):
    """One ``linearised`` from several (None entries are skipped)."""
    terms = [t for t in terms if t is not None]

    def linearised(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        parts = [t(rotation, translation) for t in terms]
        return np.concatenate([r for r, _ in parts]), np.concatenate([j for _, j in parts], axis=0)

    return linearised


@dataclass
class DenseFit:
    """Result of a dense alignment: ``pose`` ``T_w_c``, the share of the frame's samples that
    lie on the target's surfaces within the noise at the end (``overlap``), how many of them
    (``pairs``) and how their surfaces' normals spread (``normal_spread``, 0 to 1/3,
    :func:`normal_spread`: near 0 when the surfaces leave a direction of translation free, a
    single wall or a corridor)."""

    pose: np.ndarray
    overlap: float
    pairs: int
    normal_spread: float


def align_depth(source: np.ndarray, source_sigma: np.ndarray, target: DepthTarget, start: np.ndarray,
                config: DenseConfig, features=None) -> DenseFit | None:
    """The pose ``T_w_c`` that lays the frame's samples ``source`` ``(N, 3)`` (camera frame,
    noise ``source_sigma`` ``(N,)``) on ``target``'s surfaces, from ``start``: ICP rounds, each
    finding the pairs at the current pose and minimising their point-to-plane residuals
    together with ``features`` (a ``linearised`` of
    :func:`~jsr.pipeline.pose_refinement.image_space_terms` on the feature inliers; None: the
    depth alone). None when the depth alone has fewer than 6 pairs."""
    rotation, translation = start[:3, :3].copy(), start[:3, 3].copy()
    for _ in range(config.iterations):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotation, translation
        p, q, n, sigma = _pairs(source, source_sigma, target, pose, config)
        if len(p) < 6 and features is None:
            return None
        terms = point_to_plane_terms(p, q, n, sigma) if len(p) else None
        solved = minimise_huber(_stacked(features, terms), rotation, translation, HUBER_SCALE, max_iterations=10)
        if solved is None:
            return None
        step = np.linalg.norm(solved[1] - translation) + np.linalg.norm(cv2.Rodrigues(solved[0] @ rotation.T)[0])
        rotation, translation = solved
        if step < 1e-5:
            break
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, translation
    p, q, n, sigma = _pairs(source, source_sigma, target, pose, config)
    return DenseFit(pose, len(p) / max(len(source), 1), len(p), normal_spread(q, target))


def normal_spread(points: np.ndarray, target: DepthTarget) -> float:
    """The smallest eigenvalue of the mean ``n n^T`` of the target's normals at ``points``
    ``(K, 3)`` (world frame), each normal averaged with its 8 nearest samples' first.

    The pose's information from thousands of samples says little about degeneracy: the
    normals' own noise (about 12 degrees on a flat wall at 3 m) makes it look constrained
    along the wall, and so does their spread unless they are averaged (a wall at 4.5 m: 0.06
    raw, below 0.01 averaged)."""
    if len(points) < 9:
        return 0.0
    _, neighbours = target.tree.query(points, k=9)
    averaged = target.normals[neighbours].mean(axis=1)
    averaged /= np.maximum(np.linalg.norm(averaged, axis=1, keepdims=True), 1e-12)
    return float(np.linalg.eigvalsh(averaged.T @ averaged / len(averaged))[0])


def carries(fit: DenseFit | None, config: DenseConfig) -> bool:
    """Whether the depth may place the frame by itself: at least ``dense.min_overlap`` of its
    samples end on the keyframes' surfaces within the noise, and their normals spread by at
    least ``dense.min_normal_spread`` (surfaces facing three ways: not a single wall or a
    corridor)."""
    if fit is None:
        return False
    if fit.overlap < config.min_overlap or fit.normal_spread < config.min_normal_spread:
        logger.debug("depth fit rejected: overlap %.2f, normal spread %.3f", fit.overlap, fit.normal_spread)
        return False
    return True


def disagreement(source: np.ndarray, source_sigma: np.ndarray, target: DepthTarget, feature_pose: np.ndarray,
                 config: DenseConfig) -> float | None:
    """How far the depth alone moves a frame that its features placed at ``feature_pose``
    (``T_w_c``): the median distance (m) between its samples ``source`` ``(N, 3)`` (camera
    frame) placed by the two poses, the depth's fit started at the feature pose. None when the
    depth could not place the frame by itself (:func:`carries`): it says nothing then."""
    fit = align_depth(source, source_sigma, target, feature_pose, config)
    if not carries(fit, config):
        return None
    moved = transform_points(fit.pose, source) - transform_points(feature_pose, source)
    return float(np.median(np.linalg.norm(moved, axis=1)))


def trusted(disagreements: list[float], config: DenseConfig) -> bool:
    """Whether the depth may place frames: the median of the latest ``dense.trust_keyframes``
    keyframes' :func:`disagreement` is at most ``dense.trust_within`` (always with 0; never
    before one is measured).

    The evidence is over frames because the depth's error is systematic: thousands of samples
    weighed by the sensor's noise model do not average it out (the Bonn footage's Xtion at 2-4
    m: its depth alone placed well-registered keyframes a median 6.8 cm from their features;
    7-Scenes' Kinect: 1.8 cm)."""
    if config.trust_within <= 0:
        return True
    latest = disagreements[-config.trust_keyframes:]
    return bool(latest) and float(np.median(latest)) <= config.trust_within


__all__ = ["DenseFit", "DepthSurface", "DepthTarget", "align_depth", "carries", "depth_surface", "depth_target",
           "disagreement", "frame_samples", "keyframes_target", "normal_spread", "samples_on_surface", "trusted"]
