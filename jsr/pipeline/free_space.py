"""Free space: where the latest static keyframes saw through (Caccamo et al. 2017 detect moving
regions from registration outliers alone; this is the geometric evidence beside them).

A surface measured now in space that a static keyframe saw empty has moved in; a landmark in
space a keyframe saw through has lost its surface. :class:`DepthView` is one keyframe's
subsampled depth, :func:`free_space_violations` counts the pixels of each segment of a frame
that violate it, and :class:`FreeSpaceViews` keeps the views of the latest static keyframes
and answers the questions detection and region growth ask of them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.stats import norm

from jsr.config import Config
from jsr.geometry import invert_transform, transform_points
from jsr.io.camera import CameraIntrinsics
from jsr.pipeline.correspondences import depth_thresholds
from jsr.pipeline.dense_alignment import DepthSurface, align_depth, carries, depth_target, samples_on_surface
from jsr.pipeline.maps import Keyframe
from jsr.pipeline.object_extent import without_strays

logger = logging.getLogger(__name__)

FREE_SPACE_STRIDE = 4  # free-space tests sample every 4th pixel of every 4th row
FREE_SPACE_VIEWS = 2  # ... against the latest static keyframes


@dataclass
class DepthView:
    """A subsampled depth image of a keyframe for free-space tests: ``depth`` ``(h, w)`` metres
    (0 invalid) at every ``stride``-th pixel, ``T_w_c`` its camera pose. ``near_depth`` is the
    nearest valid depth within ``(2 r + 1)^2`` samples (``r = near_radius``): space counts as
    seen empty only where the whole neighbourhood was seen farther away, so that thin structures,
    depth edges and a colour-to-depth misregistration of a few pixels do not look like violations.
    ``measured_near_depth`` is the same but 0 where a neighbour has no depth: the stricter test
    of :meth:`seen_through` with ``measured_only``, for which a hole next to the sample may hide
    a surface (a translucent or dark object that returned no depth to that view).
    """

    depth: np.ndarray
    T_w_c: np.ndarray
    stride: int
    near_radius: int = 1
    near_depth: np.ndarray | None = None
    measured_near_depth: np.ndarray | None = None

    def __post_init__(self) -> None:
        size = 2 * self.near_radius + 1
        kernel = np.ones((size, size), np.uint8)
        depth = np.asarray(self.depth, dtype=np.float32)
        if self.near_depth is None:
            far = np.where(depth > 0, depth, np.float32(1e6))
            near = cv2.erode(far, kernel)
            self.near_depth = np.where(near < 1e6, near, 0.0).astype(np.float32)
        if self.measured_near_depth is None:
            # 0 where a neighbour has no depth (a hole, a blanked region, beyond the border)
            self.measured_near_depth = cv2.erode(depth, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0.0)

    def blank(self, unknown: np.ndarray) -> None:
        """Forget what the view saw at the samples ``unknown`` ``(h, w)`` bool (as if it had
        measured no depth there), and its neighbourhood minima with them."""
        self.depth = np.where(unknown, np.float32(0.0), self.depth).astype(np.float32)
        self.near_depth = self.measured_near_depth = None
        self.__post_init__()

    def project(self, in_view: np.ndarray, intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 3)`` points in this view's camera frame: their sample column and row (each
        ``(N,)`` int) and whether they fall in the image in front of the camera."""
        z = in_view[:, 2]
        ahead = z > 1e-3
        safe = np.where(ahead, z, 1.0)
        u = np.round((intrinsics.fx * in_view[:, 0] / safe + intrinsics.cx) / self.stride).astype(np.int64)
        v = np.round((intrinsics.fy * in_view[:, 1] / safe + intrinsics.cy) / self.stride).astype(np.int64)
        height, width = self.depth.shape
        return u, v, ahead & (u >= 0) & (u < width) & (v >= 0) & (v < height)

    def sample(self, in_view: np.ndarray, intrinsics, measured_only: bool = False
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 3)`` points in this view's camera frame projected into it: per point whether
        it falls in the image in front of the camera, the depth the view measured there and
        its ``near_depth`` (``measured_near_depth`` with ``measured_only``; each ``(N,)``; 0
        outside)."""
        u, v, inside = self.project(in_view, intrinsics)
        seen, nearest = np.zeros(len(in_view)), np.zeros(len(in_view))
        seen[inside] = self.depth[v[inside], u[inside]]
        near_depth = self.measured_near_depth if measured_only else self.near_depth
        nearest[inside] = near_depth[v[inside], u[inside]]
        return inside, seen, nearest

    def seen_through(self, in_view: np.ndarray, intrinsics, noise, margin: float, sigmas: float,
                     measured_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 3)`` points in this view's camera frame: per point whether the view measured
        depth where it projects, whether the view saw through it (its whole neighbourhood
        farther than the point by more than ``max(margin, sigmas * sigma_Z)``, sigma_Z of the
        measured depth; with ``measured_only`` every neighbour must have depth), and that
        depth (each ``(N,)``)."""
        inside, seen, nearest = self.sample(in_view, intrinsics, measured_only)
        measured = inside & (seen > 0)
        threshold = np.maximum(margin, sigmas * noise.sigma_z_coefficient * seen**2)
        through = measured & (nearest > 0) & (in_view[:, 2] < nearest - threshold)
        return measured, through, seen


def free_space_violations(
    depth: np.ndarray,
    label_image: np.ndarray,
    T_w_c: np.ndarray,
    intrinsics,
    view: DepthView,
    num_segments: int,
    noise,
    margin: float,
    sigmas: float | None = None,
    measured_only: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Per segment ``(S,)`` counts of sampled pixels that lie in space an earlier view saw as
    empty (*violations*; ``measured_only``: see :meth:`DepthView.seen_through`) and of pixels
    that agree with that view (*consistent*).

    Every ``view.stride``-th valid pixel of the frame is moved into the earlier view's camera
    and projected; it violates free space when it is closer to that camera than the surface the
    view measured there, by more than ``max(margin, inlier_sigmas * sigma_Z)``. Only something
    that moved in can do that: static structure seen for the first time stays behind what the
    earlier view saw (or is hidden from it), and a region an object left is farther, not closer.
    """
    stride = view.stride
    z = np.asarray(depth, dtype=np.float64)[::stride, ::stride]
    labels = np.asarray(label_image)[::stride, ::stride]
    rows, cols = np.nonzero((z > 0) & (labels >= 0))
    violations = np.zeros(num_segments, dtype=np.int64)
    consistent = np.zeros(num_segments, dtype=np.int64)
    if not len(rows):
        return violations, consistent
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    zs = z[rows, cols]
    u, v = cols * stride, rows * stride
    camera = np.column_stack([(u - cx) / fx * zs, (v - cy) / fy * zs, zs])
    T_view_cam = np.linalg.inv(view.T_w_c) @ T_w_c
    in_view = camera @ T_view_cam[:3, :3].T + T_view_cam[:3, 3]
    usable, closer, seen = view.seen_through(in_view, intrinsics, noise, margin,
                                             noise.inlier_sigmas if sigmas is None else sigmas, measured_only)
    # agreement uses the registration's tight inlier threshold: between it and the violation
    # margin a pixel is neither (uncertain)
    agrees = usable & (np.abs(in_view[:, 2] - seen) <= np.maximum(
        noise.min_inlier_threshold, noise.inlier_sigmas * noise.sigma_z_coefficient * seen**2))
    segment = labels[rows, cols]
    np.add.at(violations, segment[closer], 1)
    np.add.at(consistent, segment[agrees], 1)
    return violations, consistent


def depth_at_projections(camera_points: np.ndarray, depth: np.ndarray, intrinsics: CameraIntrinsics
                         ) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """``(N, 3)`` camera-frame points projected into ``depth`` ``(H, W)``: their rounded
    pixels ``(u, v)`` (each ``(N,)`` int), whether they fall in the image in front of the
    camera ``(N,)``, and the depth measured there ``(N,)`` (0 outside or invalid)."""
    z = camera_points[:, 2]
    safe = np.where(z > 1e-3, z, 1.0)
    u = np.round(intrinsics.fx * camera_points[:, 0] / safe + intrinsics.cx).astype(np.int64)
    v = np.round(intrinsics.fy * camera_points[:, 1] / safe + intrinsics.cy).astype(np.int64)
    height, width = depth.shape
    inside = (z > 1e-3) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    measured = np.zeros(len(z))
    measured[inside] = depth[v[inside], u[inside]]
    return (u, v), inside, measured


def depth_at_map_points(points: np.ndarray, T_map_cam: np.ndarray, depth: np.ndarray, intrinsics: CameraIntrinsics
                        ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """``(N, 3)`` map-frame points (landmarks) seen from the camera at ``T_map_cam`` (4x4,
    camera to map) in ``depth`` ``(H, W)``: the points in the camera frame ``(N, 3)``, and as
    :func:`depth_at_projections` their pixels, whether they fall in the image and the depth
    measured there."""
    camera_points = transform_points(invert_transform(T_map_cam), points)
    pixels, inside, measured = depth_at_projections(camera_points, depth, intrinsics)
    return camera_points, pixels, inside, measured


class FreeSpaceViews:
    """The subsampled static depth of the latest ``FREE_SPACE_VIEWS`` static keyframes, by
    keyframe id, and the free-space tests against them. The keyframes' poses are read from the
    static map's keyframes when a test runs (after bundle adjustment)."""

    def __init__(self, config: Config, intrinsics: CameraIntrinsics):
        self.config = config
        self.intrinsics = intrinsics
        self.views: list[tuple[int, DepthView]] = []

    @property
    def enabled(self) -> bool:
        """Free-space tests are on (``objects.free_space_detection``) and a view exists."""
        return bool(self.config.objects.free_space_detection and self.views)

    def remember(self, keyframe: Keyframe, depth: np.ndarray, unknown: np.ndarray) -> None:
        """Keep the depth ``(H, W)`` float32 metres of a new static keyframe, subsampled, with
        the pixels ``unknown`` ``(H, W)`` bool (objects, regions that may have moved) blanked:
        nothing is known about free space there."""
        stride = FREE_SPACE_STRIDE
        subsampled = np.array(depth[::stride, ::stride], dtype=np.float32)
        subsampled[unknown[::stride, ::stride]] = 0.0
        self.views.append((keyframe.keyframe_id, DepthView(subsampled, keyframe.T_map_cam, stride)))
        del self.views[:-FREE_SPACE_VIEWS]

    def all_after(self, keyframes: list[Keyframe], after_frame: int) -> bool:
        """Whether every view's keyframe (``keyframes``: the static map's) is of a frame after
        ``after_frame``."""
        return all(keyframes[keyframe_id].frame_index > after_frame for keyframe_id, _ in self.views)

    def counts(self, keyframes: list[Keyframe], depth: np.ndarray, label_image: np.ndarray, num_segments: int,
               T_w_c: np.ndarray, after_frame: int | None = None, measured_only: bool = False,
               static_samples: tuple[np.ndarray, np.ndarray] | None = None,
               surfaces: dict[int, DepthSurface] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per segment ``(S,)``: sampled pixels of a frame (``depth`` and ``label_image`` ``(H, W)``,
        camera pose ``T_w_c``) lying in space the views saw as empty (violations), and pixels
        agreeing with the surface they saw (consistent). ``after_frame``: only the views of
        keyframes of later frames. ``measured_only``: space counts as seen empty only where the
        views measured depth all around (:meth:`DepthView.seen_through`). ``static_samples``:
        the frame's static depth samples (``(N, 3)`` camera frame, ``(N,)`` axial noise) that
        place it first on each view that kept a sampled surface in ``surfaces`` (by keyframe
        id, :meth:`registered_pose`)."""
        config = self.config.objects
        per_view = []
        for keyframe_id, view in self.views:
            if after_frame is not None and keyframes[keyframe_id].frame_index <= after_frame:
                continue
            view.T_w_c = keyframes[keyframe_id].T_map_cam  # after bundle adjustment
            pose = T_w_c
            if static_samples is not None and surfaces is not None and keyframe_id in surfaces:
                pose = self.registered_pose(view, surfaces[keyframe_id], T_w_c, static_samples)
            per_view.append(free_space_violations(depth, label_image, pose, self.intrinsics, view, num_segments,
                                                  self.config.noise, config.free_space_margin,
                                                  config.free_space_sigmas, measured_only))
        if not per_view:
            zeros = np.zeros(num_segments, dtype=np.int64)
            return zeros, zeros.copy()
        violations = np.stack([closer for closer, _ in per_view])
        consistent = np.stack([agrees for _, agrees in per_view])
        # A violation must be seen from every view that sees the segment: one keyframe with a
        # poor pose (or depth) would otherwise put whole surfaces "in front" of themselves.
        sampled = violations + consistent
        covering = sampled > 0
        combined = np.where(covering.any(axis=0),
                            np.min(np.where(covering, violations, np.iinfo(np.int64).max), axis=0), 0)
        # Agreements are summed over the views while violations take the minimum, which leans
        # the share towards "static". Measured (stop 14): taking both counts from one view
        # detects synth_two_sim s4's cylinder 18 frames earlier, but starts 2 false objects on
        # redkitchen300 (a static segment at 0.71 against the cylinder's 0.67-0.73). Kept.
        return combined, consistent.sum(axis=0)

    def registered_pose(self, view: DepthView, surface: DepthSurface, T_w_c: np.ndarray,
                        static_samples: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """The frame's pose ``T_w_c`` placed on ``view`` by its static depth ``static_samples``
        (``(N, 3)`` camera-frame points, ``(N,)`` axial noise): point-to-plane ICP on the view's
        static depth ``surface`` (its keyframe's camera frame) from the feature pose
        (:func:`~jsr.pipeline.dense_alignment.align_depth`), kept when the fit
        :func:`~jsr.pipeline.dense_alignment.carries` and lays significantly more of the
        samples on the view's surface within the noise than the feature pose does (one-sided
        two-proportion z-test at ``detection.confirm_significance``); else ``T_w_c``.

        Free space compares the frame's depth with the view's, and the features' relative pose
        is off where either frame blurred (redkitchen300 seed 2: a keyframe 1.8 cm and 2.1
        degrees off put a table's edge in front of the floor it saw behind; 26-53% of the
        frame's static samples on the view's surface at the feature pose, 53-76% at the
        depth's). Where the feature pose lays the samples as well, the depth's pose differs by
        its own bias, not by a better fit, and it is not taken (the Bonn footage's depth
        distortion: 1.4-5.1 px away, 0.70 against 0.71 on the surface; kitchen_box120 after the
        box's jump: 1.2-1.6 px, 0.95 both; taken, the first moved the frame enough to lose a
        small object's free space, the second to halve the box's in one frame, and the box
        was dissolved and mapped twice)."""
        points, sigma = static_samples
        if not len(points):
            return T_w_c
        target = depth_target([(view.T_w_c, surface)])
        if target is None:
            return T_w_c
        fit = align_depth(points, sigma, target, T_w_c, self.config.dense)
        if not carries(fit, self.config.dense):
            return T_w_c
        count = len(points)
        before = samples_on_surface(points, sigma, target, T_w_c, self.config.dense) / count
        pooled = 0.5 * (before + fit.overlap)
        spread = np.sqrt(max(2.0 * pooled * (1.0 - pooled) / count, 1e-12))
        better = (fit.overlap - before) / spread > norm.isf(self.config.detection.confirm_significance)
        logger.debug("free-space view: on its surface %.3f of the frame's static samples at the feature pose, %.3f at "
                     "the depth's (%s)", before, fit.overlap, "taken" if better else "not taken")
        return fit.pose if better else T_w_c

    def min_samples(self) -> float:
        """Sampled pixels a free-space verdict needs: ``objects.free_space_min_pixels`` (given
        for 640x480) scaled with the image area and the sampling stride."""
        area_scale = (self.intrinsics.width * self.intrinsics.height) / (640 * 480)
        return self.config.objects.free_space_min_pixels * area_scale / FREE_SPACE_STRIDE**2

    def seen_before(self, violations, consistent):
        """Free-space verdict on sampled pixels (per segment as ``(S,)`` arrays, or summed over
        a region): enough of them could be tested and at least half lie where the latest static
        keyframes saw a surface."""
        sampled = violations + consistent
        return (sampled >= self.min_samples()) & (consistent >= 0.5 * sampled)

    def forget_surface(self, keyframes: list[Keyframe], world_points: np.ndarray) -> int:
        """Blank in every view the surface through the ``(N, 3)`` world points, where the view
        measured them: the convex hull of their projections, widened by the neighbourhood
        radius. For an object confirmed to have moved, ``world_points`` are the static
        landmarks that moved with it: the views taken before it was found saw it there as a
        static surface, and that surface is gone. Without this, the object coming back near
        that place is "consistent" with the views and free space cannot find it
        (redkitchen_s4_two_sim, seed 14: a box jumped near where it stood in the first
        keyframe, and was not found for 15 frames). Stray points are left out
        (:func:`~jsr.pipeline.object_extent.without_strays`: a look-alike's match elsewhere).
        Returns the number of samples blanked."""
        points = without_strays(world_points)
        blanked = 0
        for keyframe_id, view in self.views:
            in_view = transform_points(invert_transform(keyframes[keyframe_id].T_map_cam), points)
            inside, seen, _ = view.sample(in_view, self.intrinsics)
            there = inside & (seen > 0) & (np.abs(seen - in_view[:, 2]) <= depth_thresholds(seen, self.config.noise))
            if there.sum() < 3:
                continue
            u, v, _ = view.project(in_view[there], self.intrinsics)
            hull = cv2.convexHull(np.column_stack([u, v]).astype(np.int32))
            unknown = np.zeros(view.depth.shape, np.uint8)
            cv2.fillConvexPoly(unknown, hull, 1)
            size = 2 * view.near_radius + 1
            unknown = cv2.dilate(unknown, np.ones((size, size), np.uint8)).astype(bool) & (view.depth > 0)
            view.blank(unknown)
            blanked += int(unknown.sum())
        return blanked

    def in_free_space(self, keyframes: list[Keyframe], world_points: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: which of the ``(N, 3)`` world points the views saw through, as
        :func:`free_space_violations` judges a pixel: every view that measured depth where the
        point projects saw its whole neighbourhood farther away than the point by more than
        ``max(objects.free_space_margin, objects.free_space_sigmas * sigma_Z)`` (sigma_Z of the
        depth it measured). One keyframe with a poor pose alone does not make a point a phantom."""
        config = self.config.objects
        if not self.enabled or not len(world_points):
            return np.zeros(len(world_points), dtype=bool)
        covered = np.zeros(len(world_points), dtype=bool)
        contradicted = np.zeros(len(world_points), dtype=bool)  # a covering view that did not see through it
        for keyframe_id, view in self.views:
            T_w_view = keyframes[keyframe_id].T_map_cam  # after bundle adjustment
            in_view = transform_points(invert_transform(T_w_view), world_points)
            measured, through, _ = view.seen_through(in_view, self.intrinsics, self.config.noise,
                                                     config.free_space_margin, config.free_space_sigmas)
            covered |= measured
            contradicted |= measured & ~through
        return covered & ~contradicted
