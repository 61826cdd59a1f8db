"""The Reconstructor: one frame in, one :class:`FrameReport` out.

``process(frame)`` reads like the paper's system overview (Figure 2):

1. extract measurements (points, planes, segments);
2. register the frame against the static map (frame-based registration, Section 2.2.1),
   against the landmarks of the last N keyframes, or against the whole map after a loss;
3. register it against every object map, frame-based and segment-based (Section 2.2);
4. give every measurement to one map (Algorithm 1, Section 2.3);
5. detect moving segments among the static map's outliers and start object maps (Section 2.1);
6. update each map whose registration succeeded, when its pose is new (Section 2.4), and
   retire static landmarks that turned out to belong to an object;
7. let bundle adjustment refine the maps (asynchronously, applied at deterministic points).
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from jsr.config import Config
from jsr.geometry import backproject_pixels, invert_transform, rotation_angle, transform_points
from jsr.io.camera import CameraIntrinsics
from jsr.io.dataset import Frame
from jsr.pipeline.bundle_scheduler import BundleScheduler
from jsr.pipeline.frontend import FrontEnd
from jsr.pipeline.maps import Map
from jsr.pipeline.matching import guided_match
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.association import (
    MatchedFrame,
    inlier_landmarks,
    inlier_plane_landmarks,
    match_frame_guided,
    match_frame_to_map,
    sample_colors,
)
from jsr.pipeline.classify import ObjectRegistration, classify_measurements, segment_of_planes
from jsr.pipeline.detection import (detect_moving_segments, displaced_landmark_groups, merge_adjacent_moving_segments,
                                    partially_moving_segments, segment_outlier_stats)
from jsr.pipeline.objects import (
    ObjectMap,
    ObjectRegistrar,
    ObjectTrackingResult,
    complete_segments,
    DepthView,
    depth_adjacent_segments,
    free_space_violations,
    grow_region,
    inlier_mask,
    merge_object_maps,
    register_maps,
    segment_vlads,
    segments_inside_extent,
    extent_hull,
    pixels_inside_hull,
    unsupported_segments,
    UNSUPPORTED_STATIC_SHARE,
)
from jsr.pipeline.registration import (RegistrationResult, depth_thresholds, evaluate_pose, point3d_thresholds,
                                      pose_cost, register, surface_pose_result)
from jsr.pipeline.surface_alignment import Alignment, align_surfaces, refine_fit
from jsr.pipeline.surface_evidence import (
    anchors_pin,
    fitness,
    geometric_constraint,
    same_placement,
    seen_through_share,
    texture_agreement,
    texture_pin,
)
from jsr.pipeline.surfaces import SurfaceModel, SurfaceSample, build_model, region_model, sample_surface
from jsr.pipeline.vlad import SegmentIndex, VladVocabulary

logger = logging.getLogger(__name__)

STATIC_MAP = "static"
FREE_SPACE_STRIDE = 4  # free-space tests sample every 4th pixel of every 4th row
FREE_SPACE_VIEWS = 2  # ... against the latest static keyframes
MAX_OBJECT_ID = 255  # ownership masks are uint8 images
SHAPE_CANDIDATES = 4  # surface alignments (best colour agreement first) tried by feature matching
SURFACE_STRIDE = 2  # object surface samples (shape-based re-identification) use every 2nd pixel and row
EXTENT_SURFACE_STEP = 8  # an object's extent takes every 8th of its surface samples (objects.extent_from_surface) ...
# ... from its last 10 keyframes: older ones carry the pose errors of earlier re-identifications,
# and a hull only grows (synth_jump s1 at 320x240, a 14470 cm3 box: the hull over all keyframes
# reached 16400 cm3 by frame 36 and 31240 by frame 57, mask precision 0.919; over the last 10,
# precision 0.981, recall the same)
EXTENT_SURFACE_KEYFRAMES = 10
SHAPE_RIVAL_FITNESS_GAP = 0.1  # a surface fit this close in fitness to the chosen one, whose texture passes too, makes the surface ambiguous
SHAPE_MODE_METRES, SHAPE_MODE_DEGREES = 0.1, 15.0  # fits closer than this (at the region) are one fit, not rivals
SHAPE_CONFIRM_METRES, SHAPE_CONFIRM_DEGREES = 0.2, 30.0  # landmarks confirm a surface fit within this of it
# landmark matches pin a surface fit when the motions its shape leaves free move them at least half as far as the region
ANCHOR_MIN_MOTION_SHARE = 0.5
TEXTURE_LOSS_MARGIN = 0.05  # a refinement that lowers the texture agreement (over the own views') by more is not kept
SHAPE_SEEN_THROUGH_VOXELS, SHAPE_SEEN_THROUGH_SIGMAS = 3.0, 3.0  # a model point is seen through beyond max(3 voxels, 3 sigma_Z)
SELF_TEXTURE_MIN_OVERLAP = 0.5  # own views compared only where this share of one lies on the others
SELF_TEXTURE_VIEWS = 6  # an object's latest keyframe samples that measure how its own views agree
UNMATCHED_FEATURE_FACTOR = 2  # a face whose 3D features hardly match the static map grows into an object from twice min_segment_features of them
SELF_TEXTURE_MIN = 0.2  # own views agreeing less (an object of one colour): no texture to tell fits apart (measured: kitchen_box120 0.38-0.51, synthetic 0.87-0.9)
# two frames' rotations fitted to 5-15 points each differ by a few degrees (synth_two seed 3: 3.2)
TURN_MEMORY_DEGREES_FACTOR = 2
# objects.extent_unseen_only: the static keyframes must have seen at least this share of a
# segment's sampled pixels (a moving object's face a keyframe saw in part, 8 of 50 samples on
# synth_smooth seed 1 at 320x240, is not the background that took over a map)
SEEN_SINCE_MIN_COVER = 0.5
IN_PLACE_TURN_INLIER_FACTOR = 2  # overruling the in-place veto by one frame's rigid turn takes this many times the usual agreeing outliers (two frames: see detection.in_place_turn_memory_frames)
# A segment that turned as a whole has nearly all its matches agree on the turn; a static one
# on real data has RANSAC fit a spurious turn to 5-9 of its 7-15 matches (kitchen_box120)
WHOLE_TURN_MIN_SHARE = 0.8
CANDIDATE_DETAIL_FRAMES = 3  # a moving region too poor in 3D points to start a map gets detail keypoints this many frames
OWNERSHIP_FILL_RADIUS = 3  # px at 640 wide: pixels in no segment (no depth) take the owner of most labelled neighbours


def _pixel_box(pixels: np.ndarray) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (end exclusive) bounding the True pixels of ``(H, W)`` bool."""
    rows, cols = np.nonzero(pixels)
    return int(cols.min()), int(rows.min()), int(cols.max()) + 1, int(rows.max()) + 1


def fill_unlabelled(ownership: np.ndarray, unlabelled: np.ndarray, radius: int) -> np.ndarray:
    """``ownership`` ``(H, W)`` uint8 with every ``unlabelled`` pixel (no segment: no depth,
    mostly) given to the object owning more than half of the labelled pixels within ``radius``
    (0 otherwise): depth dropouts inside an object's faces belong to it."""
    if not unlabelled.any() or not ownership.any():
        return ownership
    size = (2 * radius + 1, 2 * radius + 1)
    labelled = (~unlabelled).astype(np.float32)
    labelled_count = cv2.boxFilter(labelled, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    filled = ownership.copy()
    for object_id in np.unique(ownership[~unlabelled & (ownership > 0)]):
        mine = ((ownership == object_id) & ~unlabelled).astype(np.float32)
        count = cv2.boxFilter(mine, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
        filled[unlabelled & (count > 0.5 * labelled_count)] = object_id
    return filled


def features_in_segments(measurements: FrameMeasurements, segment_ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """``(N,)`` bool over the frame's points and ``(P,)`` bool over its planes: those lying in
    one of the segments ``segment_ids``."""
    segments = measurements.segments
    members = np.zeros(len(segments), dtype=bool)
    members[segment_ids] = True
    point_segment = segments.segment_of_points(len(measurements.points))
    plane_segment = segment_of_planes(segments, len(measurements.planes))
    return ((point_segment >= 0) & members[np.maximum(point_segment, 0)],
            (plane_segment >= 0) & members[np.maximum(plane_segment, 0)])


@dataclass
class MapCounts:
    """Size of one map after a frame (a row of ``landmarks.csv``)."""

    keyframes: int
    point_landmarks: int
    plane_landmarks: int
    tracked: bool


@dataclass
class FrameReport:
    """What happened to one frame.

    ``T_w_c`` is the pose when the frame was tracked. ``reference_keyframe`` (the static map's
    newest keyframe then) and ``T_keyframe_cam`` tie the frame to that keyframe, so that the
    pose can follow the keyframe when bundle adjustment moves it (see
    :meth:`Reconstructor.current_pose`).
    """

    frame_index: int
    timestamp: float
    name: str
    tracked: bool
    T_w_c: np.ndarray | None
    relocalised: bool = False
    bridged: bool = False
    reference_keyframe: int = -1
    T_keyframe_cam: np.ndarray | None = None
    new_keyframe: bool = False
    matches: int = 0
    inliers: int = 0
    reason: str = ""
    objects_tracked: list[int] = field(default_factory=list)
    objects_created: list[int] = field(default_factory=list)
    mask: np.ndarray | None = field(default=None, repr=False)  # (H, W) uint8: 0 static, K object K
    maps: dict[str, MapCounts] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class StaticRegistration:
    """The static map's registration of one frame (``matched`` is against the map, or against
    the previous frame when ``bridged``)."""

    matched: MatchedFrame
    result: RegistrationResult
    bridged: bool = False


def _little_static_support(measurements: FrameMeasurements, static_inliers: np.ndarray) -> np.ndarray:
    """``(S,)`` bool: segments at most UNSUPPORTED_STATIC_SHARE of whose 3D point features are
    static inliers (``static_inliers`` ``(N,)`` bool), so that the static map does not show
    them in place (featureless segments included)."""
    points, segments = measurements.points, measurements.segments
    point_segment = segments.segment_of_points(len(points))
    in_segment = point_segment >= 0
    static_support = np.bincount(point_segment[in_segment & static_inliers], minlength=len(segments))
    three_d = np.bincount(point_segment[in_segment & points.has_depth], minlength=len(segments))
    return static_support <= UNSUPPORTED_STATIC_SHARE * np.maximum(three_d, 1)


def static_inlier_landmarks(static: StaticRegistration) -> np.ndarray:
    """Sorted ids of the static landmarks matched as inliers by ``static`` (none if it failed)."""
    if not static.result.success:
        return np.zeros(0, dtype=np.int64)
    inlier_rows = np.concatenate([static.result.inliers_point3d, static.result.inliers_point2d]).astype(bool)
    return np.unique(static.matched.point_landmarks[inlier_rows])


@dataclass
class FrameAssignment:
    """Which map every measurement of a frame was given to (0: static, K: object K).

    ``point_owner`` ``(N,)``, ``plane_owner`` ``(P,)``, ``segment_owner`` ``(S,)``.
    """

    point_owner: np.ndarray
    plane_owner: np.ndarray
    segment_owner: np.ndarray
    not_object_pixels: np.ndarray | None = None  # (H, W) bool: pixels of object segments left out (mixed segments)


def _keyframe_correction(keyframe, since: np.ndarray | None = None) -> np.ndarray:
    """``(4, 4)`` what bundle adjustment did to a keyframe, in its map's frame, since it was
    at ``since`` (its ``T_map_cam`` then; default: as tracked, ``T_map_cam_tracked``):
    ``T_map_cam @ inv(since)``, to left-multiply a pose measured against the map as it was then."""
    return keyframe.T_map_cam @ np.linalg.inv(keyframe.T_map_cam_tracked if since is None else since)


def _region_centroid(measurements: FrameMeasurements, segment_ids: list[int], T_w_c: np.ndarray) -> np.ndarray | None:
    """``(3,)`` world-frame centroid of the 3D point measurements in the segments
    ``segment_ids`` (camera pose ``T_w_c``), or None when none of them has depth."""
    points = measurements.points
    indices = np.concatenate([measurements.segments.point_indices[s] for s in segment_ids]).astype(np.int64)
    indices = indices[points.has_depth[indices]]
    return transform_points(T_w_c, points.points[indices]).mean(axis=0) if len(indices) else None


def _mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """``(4, 4)`` the mean of rigid transforms: chordal L2 mean rotation, mean translation."""
    stack = np.asarray(transforms, dtype=float).reshape(-1, 4, 4)
    mean = np.eye(4)
    mean[:3, :3] = Rotation.from_matrix(stack[:, :3, :3]).mean().as_matrix()
    mean[:3, 3] = stack[:, :3, 3].mean(axis=0)
    return mean


class Reconstructor:
    """Tracks the camera against a static map, detects and tracks moving objects in their
    own maps, and grows every map, one frame at a time.

    Usage::

        reconstructor = Reconstructor(config, sequence.intrinsics)
        for frame in sequence:
            report = reconstructor.process(frame)
        reconstructor.finish()

    ``init_object_mask`` ``(H, W)`` bool (optional) starts object map 1 on the first frame from
    the segments inside the mask (the paper's manual start, for an object that has not moved).
    """

    def __init__(self, config: Config, intrinsics: CameraIntrinsics, init_object_mask: np.ndarray | None = None):
        self.config = config
        self.intrinsics = intrinsics
        self.rng = np.random.default_rng(config.seed)  # the static map's registrations
        # Object registration and detection draw from a stream of their own: turning them on
        # (or an object appearing) does not change the RANSAC samples of camera tracking.
        self.objects_rng = np.random.default_rng([config.seed, 1])
        # The whole-segment turn test (detection.partial_outlier_ratio) runs on many static
        # segments of real data and finds nothing; its draws go to a third stream so that it
        # leaves the object registrations' samples as they were (on kitchen_box120 those
        # alone moved the box's rotation error between 0.8 and 1.25 degrees)
        self.turn_test_rng = np.random.default_rng([config.seed, 2])
        self.frontend = FrontEnd(config, intrinsics)
        self.static_map = Map(STATIC_MAP)
        self.object_maps: list[ObjectMap] = []
        self.bundle = BundleScheduler(config.bundle_adjustment, config.noise, intrinsics.matrix)
        self.reports: list[FrameReport] = []
        self._last_pose: np.ndarray | None = None
        self._velocity = np.eye(4)
        self._lost = False
        self.frames_lost = 0
        self.frames_bridged = 0
        self._previous: tuple[FrameMeasurements, np.ndarray] | None = None  # last tracked frame
        # Image-space refinement needs the focal length; None keeps the 3D-distance refinement.
        self._focal_length = (
            0.5 * (intrinsics.fx + intrinsics.fy) if config.ransac.refinement == "image" else None
        )
        self._init_object_mask = None if init_object_mask is None else np.asarray(init_object_mask, dtype=bool)
        self.registrar = ObjectRegistrar(config, intrinsics, self.objects_rng, self._focal_length)
        self.vocabulary: VladVocabulary | None = None
        self.segment_index = SegmentIndex()
        # Per-frame ownership images of the frames that gave a keyframe to some map: the dense
        # models fuse only the pixels each map received.
        self.keyframe_masks: dict[int, np.ndarray] = {}
        self.merged_into: dict[int, int] = {}  # object id -> the id of the map it was merged into
        # Surface samples (camera frame) of the object keyframes: frame index -> object id ->
        # sample; an object's surface model for shape-based re-identification.
        self.object_surfaces: dict[int, dict[int, SurfaceSample]] = {}
        self._next_object_id = 1
        self._adjacency_cache: np.ndarray | None = None
        self._free_space_cache: tuple[np.ndarray, np.ndarray] | None = None
        self._frame_pose: np.ndarray | None = None  # T_w_c of the frame being processed, if tracked
        self._previous_mask: np.ndarray | None = None  # (H, W) uint8 ownership image of the last frame
        self._candidate_boxes: list[tuple[tuple[int, int, int, int], int]] = []  # (box, last frame to use it)
        self._static_matched: np.ndarray | None = None  # (N,) bool: its points matched to the static map
        # This frame's segments that may have moved, but not surely enough to start a map:
        # an unconfirmed in-place turn, a moving region too poor in 3D points.
        self._suspect_segments: list[int] = []
        # In-place turns of recent frames that had too few agreeing outliers alone:
        # (frame index, (4, 4) world motion of the region, new place -> old place)
        self._recent_turns: list[tuple[int, np.ndarray]] = []
        # this frame's rigid motions of moving regions: (segments, world motion new place -> old place)
        self._frame_motions: list[tuple[list[int], np.ndarray]] = []
        # Subsampled depth of the latest static keyframes, for free-space tests (detection).
        self.depth_views: list[tuple[int, DepthView]] = []
        # Ids of the static landmarks that were inliers of the previous frame's static
        # registration (None after a bridged or lost frame): detection by displaced landmarks.
        self._previous_static_inliers: np.ndarray | None = None

    @property
    def maps(self) -> list[Map]:
        return [self.static_map, *self.object_maps]

    # ----------------------------------------------------------------------------------
    # One frame

    def process(self, frame: Frame) -> FrameReport:
        """Process one frame; never raises for a frame that simply cannot be registered."""
        started = time.perf_counter()
        if not np.any(frame.depth > 0):
            # 2D matches may still place the camera, but nothing of the frame enters a map in 3D
            logger.warning("frame %d: depth image %s has no valid depth; check it (the frame can only be placed "
                           "from 2D matches)", frame.index, frame.depth_path.name)
        measurements = self.frontend.process(frame, self._detail_boxes(frame.index))
        # Bundle adjustments started after earlier keyframes ran while the front-end worked;
        # they are applied here, always at this point, so runs stay reproducible.
        for map_ in self.maps:
            self.bundle.apply_finished(map_, wait=True)
        if self.reports and self._last_pose is not None and self.reports[-1].tracked:
            # bundle adjustment may have moved the keyframe the last pose hangs from
            self._last_pose = self.current_pose(self.reports[-1])
        timings = dict(measurements.timings_ms)
        report = FrameReport(frame.index, frame.timestamp, frame.name, tracked=False, T_w_c=None)

        if not self.static_map.keyframes:
            assignment = self._initialise(frame, measurements, report)
        else:
            assignment = self._process_tracking(frame, measurements, report, timings)

        if report.tracked and self.static_map.keyframes:
            reference = self.static_map.keyframes[-1]
            report.reference_keyframe = reference.keyframe_id
            report.T_keyframe_cam = np.linalg.inv(reference.T_map_cam) @ report.T_w_c
        report.mask = self._ownership_image(measurements, assignment)
        self._previous_mask = report.mask  # report.mask may be dropped by the caller once written
        if report.new_keyframe or report.objects_created or any(
                m.keyframes and m.keyframes[-1].frame_index == frame.index for m in self.object_maps):
            self.keyframe_masks[frame.index] = report.mask
            self._remember_surfaces(frame, report.mask)
        report.maps = {STATIC_MAP: MapCounts(len(self.static_map.keyframes), self.static_map.points.active_count,
                                             len(self.static_map.planes), report.tracked)}
        for object_map in self.object_maps:
            report.maps[object_map.name] = MapCounts(
                len(object_map.keyframes), object_map.points.active_count, len(object_map.planes),
                object_map.object_id in report.objects_tracked)
        timings["frame_total"] = (time.perf_counter() - started) * 1000.0
        report.timings_ms = timings
        self.reports.append(report)
        return report

    def _detail_boxes(self, frame_index: int) -> list[tuple[int, int, int, int]]:
        """Pixel boxes ``(x0, y0, x1, y1)`` of the objects in the previous frame's ownership
        image, and of the moving regions of the last ``CANDIDATE_DETAIL_FRAMES`` frames that
        had too few 3D points to start a map, grown by ``features.object_detail_margin`` of
        their size on every side: where the front-end adds the finest-scale keypoints (small
        objects carry few otherwise)."""
        # expired candidates go even with the detail pass off, so the list cannot grow
        self._candidate_boxes = [(box, until) for box, until in self._candidate_boxes if until >= frame_index]
        features = self.config.features
        if not (self.config.objects.enabled and features.object_detail):
            return []
        regions = [box for box, _ in self._candidate_boxes]
        mask = self._previous_mask
        if mask is not None and mask.any():
            for object_id in np.unique(mask[mask > 0]):
                regions.append(_pixel_box(mask == object_id))
        if not regions:
            return []
        width, height = self.intrinsics.width, self.intrinsics.height
        boxes = []
        for x0, y0, x1, y1 in regions:
            grow_x = int(round(features.object_detail_margin * (x1 - x0)))
            grow_y = int(round(features.object_detail_margin * (y1 - y0)))
            boxes.append((max(0, x0 - grow_x), max(0, y0 - grow_y), min(width, x1 + grow_x), min(height, y1 + grow_y)))
        return boxes

    def _process_tracking(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport,
                          timings: dict) -> FrameAssignment:
        static = self._register_static(frame, measurements, report, timings)
        objects_on = self.config.objects.enabled
        tic = time.perf_counter()
        tracked_objects = self._register_objects(measurements, report, static) if objects_on else []
        tracked_objects = self._merge_duplicates(measurements, tracked_objects)
        timings["objects"] = (time.perf_counter() - tic) * 1000.0
        self._adjacency_cache = None
        self._free_space_cache = None
        self._frame_pose = report.T_w_c if static is not None else None
        self._suspect_segments = []
        self._static_matched = np.zeros(len(measurements.points), dtype=bool)
        if static is not None and not static.bridged:
            self._static_matched[static.matched.point_measurements] = True
        assignment = self._classify(frame, measurements, static, tracked_objects)
        if objects_on and static is not None:
            tic = time.perf_counter()
            self._detect(frame, measurements, report, static, tracked_objects, assignment)
            timings["detection"] = (time.perf_counter() - tic) * 1000.0
        self._previous_static_inliers = None if static is None or static.bridged else static_inlier_landmarks(static)
        tic = time.perf_counter()
        if static is not None:
            if (objects_on and self.config.objects.hold_back_beside_moved and self.config.objects.hold_back_suspects
                    and not static.bridged):
                self._suspect_segments.extend(self._beside_moved_objects(frame, measurements, report, static,
                                                                         tracked_objects, assignment))
            self._update_static(frame, measurements, report, static, assignment)
            self._retire_static_landmarks(static, assignment)
            if objects_on:
                self._retire_vacated_landmarks(frame, report.T_w_c, static)
        for outcome in tracked_objects:
            if self._update_object(frame, measurements, report, outcome, assignment):
                self._merge_registered_maps(outcome.object_map, frame.index, assignment, report)
        timings["map_update"] = (time.perf_counter() - tic) * 1000.0
        return assignment

    # ----------------------------------------------------------------------------------
    # Start

    def _initialise(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport) -> FrameAssignment:
        """The first frame with enough 3D points defines the world frame and the static map
        (and object map 1 when an initial object mask was given)."""
        points, planes, segments = measurements.points, measurements.planes, measurements.segments
        assignment = FrameAssignment(np.zeros(len(points), dtype=np.int64), np.zeros(len(planes), dtype=np.int64),
                                     np.zeros(len(segments), dtype=np.int64))
        if int(points.has_depth.sum()) < self.config.ransac.min_matches:
            report.reason = "too few 3D points to start the map"
            return assignment
        pose = np.eye(4)
        if self._init_object_mask is not None:
            object_segments = self._segments_in_mask(measurements, self._init_object_mask)
            if object_segments:
                object_map = self._start_object(frame, measurements, object_segments, pose, assignment)
                if object_map is not None:
                    report.objects_created.append(object_map.object_id)
                    report.objects_tracked.append(object_map.object_id)
                else:
                    logger.warning("the initial object mask covers too few 3D features on frame %d (an object map "
                                   "needs %d); no object map started: give a larger mask or box", frame.index,
                                   min(self.config.detection.min_object_points, self.config.ransac.min_matches))
            else:
                logger.warning("the initial object mask covers no segment of frame %d; no object map started",
                               frame.index)
        static_points = np.flatnonzero(assignment.point_owner == 0)
        static_planes = np.flatnonzero(assignment.plane_owner == 0)
        self.static_map.add_keyframe(
            frame.index, frame.timestamp, pose, points, static_points, np.full(len(static_points), -1),
            sample_colors(frame, points.pixels[static_points]), planes, static_planes,
            np.full(len(static_planes), -1),
        )
        report.tracked, report.T_w_c, report.new_keyframe = True, pose, True
        self._last_pose = pose
        self._previous = (measurements, pose)
        self._remember_depth(frame, measurements, assignment)
        return assignment

    def _segments_in_mask(self, measurements: FrameMeasurements, mask: np.ndarray) -> list[int]:
        """Segments with at least half of their pixels inside ``mask`` ``(H, W)`` bool."""
        labels = measurements.segments.label_image
        if mask.shape != labels.shape:
            raise ValueError(f"initial object mask is {mask.shape[1]}x{mask.shape[0]} but frames are "
                             f"{labels.shape[1]}x{labels.shape[0]}")
        inside = np.bincount(labels[mask & (labels >= 0)], minlength=len(measurements.segments))
        total = np.maximum(np.asarray(measurements.segments.pixel_counts), 1)
        return np.flatnonzero(inside >= 0.5 * total).tolist()

    # ----------------------------------------------------------------------------------
    # Static map registration

    def _predicted_pose(self) -> np.ndarray | None:
        if self._last_pose is None:
            return None
        return self._last_pose @ self._velocity  # constant velocity in the camera frame

    def _register_static(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport,
                         timings: dict) -> StaticRegistration | None:
        """Frame-based registration against the static map; sets the report's pose."""
        config = self.config
        relocalise = self._lost
        predicted = None if relocalise else self._predicted_pose()
        # Tracking matches the landmarks of the last N keyframes. After a loss the frame is
        # relocalised: first against those same keyframes without a pose prior (the camera is
        # usually still near where it was lost), then against the whole map. The whole map alone
        # is not enough: its many near-duplicate landmarks make Lowe's ratio test reject most
        # matches.
        attempts = [config.matching.recent_keyframes]
        if relocalise and len(self.static_map.keyframes) > config.matching.recent_keyframes:
            attempts.append(None)
        matching_ms = registration_ms = 0.0
        for keyframe_count in attempts:
            landmark_ids = self.static_map.recent_point_landmarks(keyframe_count)
            tic = time.perf_counter()
            matched = match_frame_to_map(measurements, self.static_map, landmark_ids, predicted, config,
                                         self._focal_length)
            matching_ms += (time.perf_counter() - tic) * 1000.0
            tic = time.perf_counter()
            result = register(matched.correspondences, config.ransac, config.noise, self.rng, initial_guess=predicted)
            registration_ms += (time.perf_counter() - tic) * 1000.0
            if result.success:
                break
        bridged = False
        if not result.success and self._previous is not None and config.matching.bridge_with_previous_frame:
            # The map has no good view of this frame (fast motion into unmapped space): register
            # against the previous tracked frame instead, and make this frame a keyframe so that
            # the map grows into the new view rather than being lost for good.
            tic = time.perf_counter()
            previous_map = self._previous_frame_map()
            bridge = match_frame_to_map(measurements, previous_map, np.arange(len(previous_map.points)),
                                        predicted, config, self._focal_length)
            bridge_result = register(bridge.correspondences, config.ransac, config.noise, self.rng,
                                     initial_guess=predicted)
            registration_ms += (time.perf_counter() - tic) * 1000.0
            if bridge_result.success:
                matched, result, bridged = bridge, bridge_result, True
                self.frames_bridged += 1
        timings["matching"], timings["registration"] = matching_ms, registration_ms
        report.matches, report.inliers = result.num_matches, result.num_inliers

        if not result.success:
            report.reason = result.reason
            self.frames_lost += 1
            self._lost = True
            self._previous = None
            logger.info("frame %d: static registration failed (%s)", frame.index, result.reason)
            return None

        pose = result.transformation
        report.tracked, report.T_w_c, report.relocalised, report.bridged = True, pose, relocalise, bridged
        if self._last_pose is not None and not relocalise:
            self._velocity = np.linalg.inv(self._last_pose) @ pose
        else:
            self._velocity = np.eye(4)
        self._last_pose = pose
        self._lost = False
        self._previous = (measurements, pose)
        return StaticRegistration(matched, result, bridged)

    # ----------------------------------------------------------------------------------
    # Object maps: registration, classification, detection

    def _register_objects(self, measurements: FrameMeasurements, report: FrameReport,
                          static: StaticRegistration | None) -> list[ObjectTrackingResult]:
        """Frame- and segment-based registration of the frame against every object map."""
        if not self.object_maps:
            return []
        vlads = None
        if self.config.objects.segment_registration != "off" and self.vocabulary is not None:
            vlads = segment_vlads(self.vocabulary, measurements)
        skip = self._static_segments(measurements, static)
        outcomes = []
        for object_map in self.object_maps:
            predicted = object_map.last_T_o_c
            where_it_was = None  # T_o_c: its last world pose seen from this camera
            if report.tracked and object_map.last_T_w_o is not None:
                # The object most often stays where it was: predict it there.
                predicted = where_it_was = np.linalg.inv(object_map.last_T_w_o) @ report.T_w_c
            outcome = self.registrar.register_object(measurements, vlads, object_map, self.segment_index, predicted,
                                                     skip)
            if where_it_was is not None and object_map.last_pose_registered and outcome.success:
                outcome = self._kept_at_rest(outcome, where_it_was, measurements.frame_index)
            outcomes.append(outcome)
            logger.debug(
                "frame %d: object %d frame-based %s (%d matches, %d inliers), segment-based %s (%d pairs)",
                measurements.frame_index, object_map.object_id, outcome.frame_success,
                outcome.frame_result.num_matches, outcome.frame_result.num_inliers, outcome.segment_success,
                outcome.segment_pairs_tried)
            if not outcome.success:
                if not object_map.lost:
                    logger.info("frame %d: object %d not found", measurements.frame_index, object_map.object_id)
                object_map.lost = True
        return outcomes

    def _kept_at_rest(self, outcome: ObjectTrackingResult, resting_T_o_c: np.ndarray,
                      frame_index: int) -> ObjectTrackingResult:
        """``outcome`` with its registration replaced by one at ``resting_T_o_c`` (4x4, camera to
        object map frame: the object's last world pose seen from this camera) when that pose
        explains the registration's inliers nearly as well as the registered pose: its
        :func:`pose_cost` is at most ``objects.resting_max_extra_cost`` higher. Else ``outcome``.

        Why: a resting object registered anew each frame wanders within the noise (a cylinder
        about its axis by degrees over a sequence), and every keyframe taken at a wandered pose
        makes its map agree with the wandering.
        """
        bound = self.config.objects.resting_max_extra_cost
        if bound <= 0:
            return outcome
        _, registered = outcome.best
        ransac, noise = self.config.ransac, self.config.noise
        extra = (pose_cost(resting_T_o_c, registered, ransac, noise)
                 - pose_cost(registered.transformation, registered, ransac, noise))
        object_id = outcome.object_map.object_id
        if extra > bound:
            logger.debug("frame %d: object %d moved (its last world pose costs %.1f more)", frame_index, object_id,
                         extra)
            return dataclasses.replace(outcome, moved_from_rest=True)
        resting = evaluate_pose(resting_T_o_c, registered.correspondences, ransac, noise)
        if not resting.success:
            logger.debug("frame %d: object %d moved (its last world pose: %s)", frame_index, object_id,
                         resting.reason)
            return dataclasses.replace(outcome, moved_from_rest=True)
        logger.debug("frame %d: object %d at rest (its last world pose costs %.1f more)", frame_index, object_id,
                     extra)
        if outcome.segment_success:
            return dataclasses.replace(outcome, segment_result=resting)
        return dataclasses.replace(outcome, frame_result=resting)

    def _merge_duplicates(self, measurements: FrameMeasurements,
                          outcomes: list[ObjectTrackingResult]) -> list[ObjectTrackingResult]:
        """Two object maps that explain the same measurements in one frame are one object (its
        first map saw a side the second never did, e.g. before a jump that turned it): the
        newer map is merged into the older one (``objects.merge_maps``)."""
        config = self.config.objects
        successful = [o for o in outcomes if o.success]
        if not config.merge_maps or len(successful) < 2:
            return outcomes
        num_points, num_planes = len(measurements.points), len(measurements.planes)
        inliers = {o.object_map.object_id: inlier_mask(*o.best, num_points, num_planes)[0] for o in successful}
        merged: set[int] = set()
        for i, target in enumerate(successful):
            for source in successful[i + 1:]:
                target_id, source_id = target.object_map.object_id, source.object_map.object_id
                if target_id in merged or source_id in merged:
                    continue
                shared = int((inliers[target_id] & inliers[source_id]).sum())
                if shared < config.merge_min_shared_inliers:
                    continue
                self._merge_maps(target.object_map, source.object_map, target.T_o_c @ np.linalg.inv(source.T_o_c),
                                 measurements.frame_index, f"{shared} shared inliers")
                inliers[target_id] |= inliers[source_id]
                merged.add(source_id)
        return [o for o in outcomes if o.object_map.object_id not in merged]

    def _merge_registered_maps(self, object_map: ObjectMap, frame_index: int, assignment: FrameAssignment,
                               report: FrameReport) -> None:
        """Merge ``object_map`` (which just got a keyframe) with every other object map its
        landmarks register with (:func:`register_maps`, at least ``objects.map_merge_min_inliers``
        inliers): one object seen as two maps, though never in the same frame. The older map
        keeps its id; this frame's assignment and report follow the merge."""
        config = self.config.objects
        if not config.merge_maps or config.map_merge_min_inliers <= 0:
            return
        for other in [m for m in self.object_maps if m is not object_map]:
            if other not in self.object_maps or object_map not in self.object_maps:
                continue
            if other.last_tracked_frame == frame_index:
                continue  # both seen in this frame: _merge_duplicates compared their inliers
            target, source = (other, object_map) if other.object_id < object_map.object_id else (object_map, other)
            result = register_maps(target, source, self.config, self.objects_rng)
            if result is None or not result.success or result.num_inliers < config.map_merge_min_inliers:
                continue
            self._merge_maps(target, source, result.transformation, frame_index,
                             f"{result.num_inliers} of {result.num_matches} landmark matches agree")
            for owner in (assignment.point_owner, assignment.plane_owner, assignment.segment_owner):
                owner[owner == source.object_id] = target.object_id
            for ids in (report.objects_tracked, report.objects_created):
                if source.object_id in ids:
                    ids.remove(source.object_id)
                    if ids is report.objects_tracked and target.object_id not in ids:
                        ids.append(target.object_id)
            object_map = target

    def _merge_maps(self, target: ObjectMap, source: ObjectMap, T_target_source: np.ndarray, frame_index: int,
                    evidence: str) -> None:
        """Move ``source`` into ``target`` (:func:`merge_object_maps`) and keep every index of
        the reconstructor consistent: segment VLADs, the merged-id table, the keyframe
        ownership masks, and the tracking state (``source``'s when it was tracked later)."""
        self.bundle.finish(target)
        self.bundle.finish(source)
        source_frames = [keyframe.frame_index for keyframe in source.keyframes]
        source_last, target_last = source.last_tracked_frame, target.last_tracked_frame
        merge_object_maps(target, source, T_target_source)
        target.last_tracked_frame = max(source_last, target_last)
        if source_last > target_last and source.last_T_o_c is not None:
            # the source saw the object last: the merged map continues from there
            target.last_T_o_c = T_target_source @ source.last_T_o_c
            target.last_T_w_o = None if source.last_T_w_o is None else source.last_T_w_o @ np.linalg.inv(T_target_source)
            target.last_pose_registered = source.last_pose_registered
            target.lost = source.lost
        self.object_maps.remove(source)
        self._reindex_segments(target)
        self.segment_index.remove_map(source.object_id)
        self.merged_into[source.object_id] = target.object_id
        for earlier, into in self.merged_into.items():
            if into == source.object_id:
                self.merged_into[earlier] = target.object_id
        for index in source_frames:
            mask = self.keyframe_masks.get(index)
            if mask is not None:
                mask[mask == source.object_id] = target.object_id
            surfaces = self.object_surfaces.get(index, {})
            if source.object_id in surfaces:
                sample = surfaces.pop(source.object_id)
                surfaces.setdefault(target.object_id, sample)
        logger.info("frame %d: object %d is object %d (%s); maps merged", frame_index, source.object_id,
                    target.object_id, evidence)

    def _reindex_segments(self, object_map: ObjectMap) -> None:
        """Rebuild the VLADs of an object map's segments (after its keyframes were renumbered)."""
        self.segment_index.remove_map(object_map.object_id)
        if self.vocabulary is None:
            return
        for key, landmarks in object_map.segment_landmarks.items():
            self.segment_index.add(object_map.object_id, key,
                                   self.vocabulary.encode(object_map.points.descriptors[landmarks]))

    def _static_segments(self, measurements: FrameMeasurements, static: StaticRegistration | None) -> np.ndarray:
        """``(S,)`` bool: segments whose matched features clearly follow the static map (they
        are not tried in segment-based registration, which saves most of its RANSAC runs)."""
        segments = measurements.segments
        if static is None or static.bridged:
            return np.zeros(len(segments), dtype=bool)
        num_points = len(measurements.points)
        matched = np.zeros(num_points, dtype=bool)
        matched[static.matched.point_measurements] = True
        inliers, _ = inlier_mask(static.matched, static.result, num_points, len(measurements.planes))
        stats = segment_outlier_stats(segments, matched, inliers)
        detection = self.config.detection
        return (stats.matched >= detection.min_segment_features) & (
            stats.outlier_ratio <= 0.5 * detection.segment_outlier_ratio)

    def _adjacency(self, frame: Frame, measurements: FrameMeasurements) -> np.ndarray:
        """Depth-adjacent segment pairs of this frame (computed once, when first needed)."""
        if self._adjacency_cache is None:
            self._adjacency_cache = depth_adjacent_segments(
                measurements.segments.label_image, frame.depth, self.config.noise, self.config.segments)
        return self._adjacency_cache

    def _grow(self, frame: Frame, measurements: FrameMeasurements, seeds: list[int], static_inliers: np.ndarray,
              segment_owner: np.ndarray, inside: np.ndarray | None = None, known_since: int = -1) -> list[int]:
        """``seeds`` grown into depth-adjacent segments that nothing shows to be static
        (``objects.grow_segments``): the faces of an object whose features are not matched yet.
        ``inside`` ``(S,)`` bool: segments inside the extent of the object, a map since frame
        ``known_since``."""
        if not self.config.objects.grow_segments or not seeds:
            return sorted(int(s) for s in seeds)
        if self._frame_pose is None:
            return sorted(int(s) for s in seeds)  # without a camera pose nothing can be checked
        candidates = unsupported_segments(measurements, static_inliers, self.config.detection.min_segment_features)
        candidates &= segment_owner == 0
        # A segment whose surface lies where the static keyframes saw one has not moved, even if
        # the static map holds few landmarks on it (a table top the object stands on) ...
        violations, consistent = self._free_space(frame, measurements)
        seen_static = self._seen_before(violations, consistent)
        # ... unless the static landmarks matched in it are (nearly) all outliers: they moved
        # with it, and the surface the keyframes saw there was the object itself before it moved.
        min_features = self.config.detection.min_segment_features
        stats = segment_outlier_stats(measurements.segments, self._static_matched, static_inliers)
        point_segment = measurements.segments.segment_of_points(len(measurements.points))
        in_segment = static_inliers & (point_segment >= 0)
        static_count = np.bincount(point_segment[in_segment], minlength=len(measurements.segments))
        moved = (stats.matched >= min_features) & (stats.outlier_ratio >= 1.0 - UNSUPPORTED_STATIC_SHARE) & (
            static_count < min_features)
        candidates &= ~seen_static | moved
        # A face with keypoints none of which is a static inlier (seen at a grazing angle, with
        # few of them with depth, or a side the camera had not seen before the object moved),
        # a good share of which lies in space the static keyframes saw empty: it moved in. This
        # overrides seen_static: the rest of such a face may agree with a surface the keyframes
        # saw, the object's own face in the same place before a jump.
        sampled = violations + consistent
        features = np.array([len(i) for i in measurements.segments.point_indices])
        share = self.config.objects.grow_violation_share
        if share > 0:
            candidates |= (features >= min_features) & (segment_owner == 0) & (static_count == 0) & (
                sampled >= self._free_space_min_samples()) & (violations >= share * sampled)
        if self.config.objects.grow_unmatched:
            # A textured face where the static keyframes saw a surface, whose 3D features hardly
            # match the static map at all: had the keyframes seen this texture there, its
            # features would match their landmarks. They saw another surface within the
            # free-space margin, the object's own face before it jumped (synth_two seed 4,
            # frames 11-27: the box's second face, 43 3D features, 2 matched, 51 of its 243
            # sampled pixels in free space; the box kept 65-76% of its pixels without this
            # rule, 99% with it). Part of the face must lie in space they saw empty (as many
            # sampled pixels as free-space detection needs): a static surface the registration
            # matched little in has none (synth_jump seed 3 at 320x240, frame 39: a grazing
            # table top, 66 keypoints, 10 with depth, none matched, 255 sampled pixels in
            # agreement and none in free space).
            three_d = np.bincount(point_segment[measurements.points.has_depth & (point_segment >= 0)],
                                  minlength=len(measurements.segments))
            candidates |= seen_static & (segment_owner == 0) & (static_count == 0) & (
                three_d >= UNMATCHED_FEATURE_FACTOR * min_features) & (
                stats.matched <= UNSUPPORTED_STATIC_SHARE * three_d) & (
                violations >= self._free_space_min_samples())
        if inside is not None:
            # Inside the object's extent and not shown static by its features: the object's own
            # faces, even without reliable 3D features (seen at a grazing angle). Not where the
            # static keyframes saw a surface (objects.extent_unseen_only): once the extent took in
            # some background (the place a jumped object left), it would otherwise take the scene
            # around it segment by segment (synth_two_sim seed 1 at 320x240: 70% of the box's
            # mask static by the end).
            taken = inside & (segment_owner == 0) & (static_count < min_features) & (
                static_count <= UNSUPPORTED_STATIC_SHARE * np.maximum(features, 1))
            if self.config.objects.extent_unseen_only and taken.any():
                # only keyframes taken once the object had its map (its pixels left out of them)
                # count: before, they saw the object's own faces as static surfaces
                later = self._free_space_since(frame, measurements, known_since)
                samples = np.asarray(measurements.segments.pixel_counts) / FREE_SPACE_STRIDE**2
                seen_since = self._seen_before(*later) & ~moved & (
                    later[0] + later[1] >= SEEN_SINCE_MIN_COVER * samples)
                if (taken & seen_since).any():
                    logger.debug("frame %d: segments %s inside the extent of the object of seeds %s stay static: "
                                 "static keyframes since frame %d saw a surface there (%s of %s tested, of %s)",
                                 measurements.frame_index, np.flatnonzero(taken & seen_since).tolist(), seeds,
                                 known_since, later[1][taken & seen_since].tolist(),
                                 (later[0] + later[1])[taken & seen_since].tolist(),
                                 samples[taken & seen_since].astype(int).tolist())
                taken &= ~seen_since
            candidates |= taken
        return grow_region(seeds, candidates, self._adjacency(frame, measurements))

    def _free_space(self, frame: Frame, measurements: FrameMeasurements) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_free_space_counts` of this frame at its camera pose (computed once)."""
        if self._free_space_cache is None:
            self._free_space_cache = self._free_space_counts(frame, measurements, self._frame_pose)
        return self._free_space_cache

    def _classify(self, frame: Frame, measurements: FrameMeasurements, static: StaticRegistration | None,
                  outcomes: list[ObjectTrackingResult]) -> FrameAssignment:
        """Algorithm 1 (lines 14-24), then segment completion (``objects.segment_completion``)
        and growth into depth-adjacent unsupported segments (``objects.grow_segments``)."""
        points, planes, segments = measurements.points, measurements.planes, measurements.segments
        num_points, num_planes = len(points), len(planes)
        point_segment = segments.segment_of_points(num_points)
        plane_segment = segment_of_planes(segments, num_planes)
        registrations = []
        for outcome in outcomes:
            frame_points, frame_planes = inlier_mask(outcome.frame_matched, outcome.frame_result, num_points,
                                                     num_planes)
            segment_points, segment_planes = inlier_mask(outcome.segment_matched, outcome.segment_result,
                                                         num_points, num_planes)
            registrations.append(ObjectRegistration(
                object_id=outcome.object_map.object_id,
                frame_success=outcome.frame_success,
                frame_inliers_points=frame_points,
                frame_inliers_planes=frame_planes,
                segment_success=outcome.segment_success,
                matching_segments=list(outcome.seed_segments),
                segment_inliers_points=segment_points,
                segment_inliers_planes=segment_planes,
            ))
        point_owner, plane_owner = classify_measurements(num_points, num_planes, point_segment, plane_segment,
                                                         registrations)
        segment_owner = np.zeros(len(segments), dtype=np.int64)
        tracked = [r for r in registrations if r.frame_success or r.segment_success]
        static_inliers = np.zeros(num_points, dtype=bool)
        if static is not None:
            static_inliers, _ = inlier_mask(static.matched, static.result, num_points, num_planes)
        by_id = {o.object_map.object_id: o for o in outcomes if o.success}
        hulls = {object_id: extent_hull(self._extent_points(o.object_map))
                 for object_id, o in by_id.items()}  # each object's extent, once per frame
        if tracked and self.config.objects.segment_completion:
            # Evidence: points that are inliers of the registration of the map they were given to.
            evidence = static_inliers & (point_owner == 0)
            for r in tracked:
                evidence |= (point_owner == r.object_id) & (r.frame_inliers_points | r.segment_inliers_points)
            segment_owner = complete_segments(point_segment, len(segments), point_owner, evidence,
                                              [r.object_id for r in tracked], self.config.detection.min_segment_features)
            for r in tracked:
                own = np.flatnonzero(segment_owner == r.object_id).tolist()
                inside = None if not self.config.objects.grow_inside_extent else segments_inside_extent(
                    segments.label_image, frame.depth, self.intrinsics, by_id[r.object_id].T_o_c, hulls[r.object_id],
                    self.config.noise, len(segments), self.config.objects.extent_margin,
                    self.config.objects.extent_share)
                grown = self._grow(frame, measurements, own, static_inliers, segment_owner, inside,
                                   by_id[r.object_id].object_map.created_at_frame)
                segment_owner[[s for s in grown if segment_owner[s] == 0]] = r.object_id
            # Features and planes inside an object's segment go to that object, matched or not:
            # new views of the object grow its map instead of leaking into the static map.
            in_object_segment = (point_segment >= 0) & (segment_owner[np.maximum(point_segment, 0)] > 0)
            point_owner = np.where(in_object_segment, segment_owner[np.maximum(point_segment, 0)], point_owner)
            plane_in_object = (plane_segment >= 0) & (segment_owner[np.maximum(plane_segment, 0)] > 0)
            plane_owner = np.where(plane_in_object, segment_owner[np.maximum(plane_segment, 0)], plane_owner)
        for r in tracked:  # the seed segments of segment-based registration belong to their object
            for segment in r.matching_segments if r.segment_success else []:
                segment_owner[segment] = r.object_id
        assignment = FrameAssignment(point_owner.astype(np.int64), plane_owner.astype(np.int64), segment_owner)
        if tracked and self.config.objects.split_mixed_segments:
            object_inliers = np.zeros(num_points, dtype=bool)
            for r in tracked:
                object_inliers |= r.frame_inliers_points | r.segment_inliers_points
            self._split_mixed_segments(frame, measurements, assignment, static_inliers & ~object_inliers, by_id, hulls)
        return assignment

    def _split_mixed_segments(self, frame: Frame, measurements: FrameMeasurements, assignment: FrameAssignment,
                              static_evidence: np.ndarray, outcomes: dict[int, ObjectTrackingResult],
                              hulls: dict) -> None:
        """Beyond the paper, which takes segments to be parts of one surface: a segment given
        to an object that also holds ``detection.min_segment_features`` static-registration
        inliers (``static_evidence`` ``(N,)``: not inliers of any object) spans the object and
        the static scene (a box standing on a table, in one depth segment). Its static inliers,
        and its features outside the object's extent (:func:`pixels_inside_hull`), stay static;
        only its pixels inside that extent go into the object's mask; a plane that is such a
        segment stays static (``objects.split_mixed_segments``)."""
        segments = measurements.segments
        point_segment = segments.segment_of_points(len(measurements.points))
        owner_of_point = np.where(point_segment >= 0, assignment.segment_owner[np.maximum(point_segment, 0)], 0)
        evidence = static_evidence & (owner_of_point > 0)
        counts = np.bincount(point_segment[evidence], minlength=len(segments)) if evidence.any() else \
            np.zeros(len(segments), dtype=np.int64)
        mixed = np.flatnonzero((counts >= self.config.detection.min_segment_features) & (assignment.segment_owner > 0))
        if not len(mixed):
            return
        in_mixed = np.isin(point_segment, mixed)
        assignment.point_owner[evidence & in_mixed] = 0
        plane_segment = segment_of_planes(segments, len(measurements.planes))
        assignment.plane_owner[np.isin(plane_segment, mixed)] = 0
        labels = segments.label_image
        not_object = np.zeros(labels.shape, dtype=bool)
        points = measurements.points
        for segment in mixed:
            object_id = int(assignment.segment_owner[segment])
            outcome, hull = outcomes.get(object_id), hulls.get(object_id)
            if outcome is None or hull is None:
                continue
            rows, cols = np.nonzero(labels == segment)
            depth = frame.depth[rows, cols]
            inside = (depth > 0) & pixels_inside_hull(rows, cols, depth, self.intrinsics, outcome.T_o_c, hull,
                                                      self.config.noise, self.config.objects.extent_margin)
            not_object[rows[~inside], cols[~inside]] = True
            members = np.flatnonzero((point_segment == segment) & (assignment.point_owner == object_id))
            if len(members):
                member_inside = points.has_depth[members] & pixels_inside_hull(
                    points.pixels[members, 1], points.pixels[members, 0], np.nan_to_num(points.points[members, 2]),
                    self.intrinsics, outcome.T_o_c, hull, self.config.noise, self.config.objects.extent_margin)
                assignment.point_owner[members[~member_inside]] = 0
            logger.debug("frame %d: segment %d is mixed (%d static inliers); %d of %d pixels are object %d",
                         measurements.frame_index, segment, counts[segment], int(inside.sum()), len(rows), object_id)
        assignment.not_object_pixels = not_object

    def _detect(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport,
                static: StaticRegistration, outcomes: list[ObjectTrackingResult], assignment: FrameAssignment) -> None:
        """Section 2.1: segments mostly made of static-map outliers are moving regions. Each
        group of touching moving segments is first registered against the existing object maps
        (an object seen again, elsewhere); if none fits, it starts a new object map."""
        if static.bridged:
            return  # matched against the previous frame only: outliers say nothing about motion
        self._frame_motions = []
        points, segments = measurements.points, measurements.segments
        num_points = len(points)
        matched = np.zeros(num_points, dtype=bool)
        matched[static.matched.point_measurements] = True
        inliers, _ = inlier_mask(static.matched, static.result, num_points, len(measurements.planes))
        owned = assignment.point_owner > 0  # measurements already given to an object
        by_outliers = detect_moving_segments(segments, matched, inliers, self.config.detection, exclude=owned)
        in_place = by_outliers
        by_outliers = self._not_in_place(measurements, static, by_outliers, inliers, report.T_w_c, keep_unknown=False)
        in_place = [s for s in in_place if s not in by_outliers]
        # where an object this frame lost was a frame ago: that object, moved, whatever its outliers say
        where_lost = self._where_just_lost(measurements, sorted(set(by_outliers) | set(in_place)), outcomes)
        if where_lost:
            logger.debug("frame %d: segments %s lie where a just-lost object was", measurements.frame_index,
                         where_lost)
        violations, consistent = self._free_space(frame, measurements)
        by_outliers = self._rigidly_moved(frame, measurements, static, by_outliers, inliers)
        turn_degrees = self.config.detection.in_place_turn_degrees
        if turn_degrees > 0:
            # An object turning about itself: one rigid turn of its region decides.
            # Segments with an outlier ratio between detection.partial_outlier_ratio and
            # detection.segment_outlier_ratio, when their matched features, inliers too, agree on
            # it: the features near the axis stay within the inlier threshold, and the others
            # moved too little for the in-place test to tell (synth_jump seed 9: a box turned 29
            # degrees, 9 of its 17 matches inliers, 8 of 8 outliers "in place"; not detected for
            # 10 frames).
            partial = partially_moving_segments(segments, matched, inliers, self.config.detection, exclude=owned)
            turned_whole = self._rigidly_moved(frame, measurements, static, partial, inliers, with_inliers=True,
                                               min_turn_degrees=turn_degrees, exclude=owned)
            # Segments of outliers that the in-place test found near where they were: it cannot
            # tell the object's own features from a look-alike's, the turn of their outliers can.
            turned_in_place = self._rigidly_moved(frame, measurements, static, in_place, inliers,
                                                  min_turn_degrees=turn_degrees)
            by_outliers = sorted(set(by_outliers) | set(turned_whole) | set(turned_in_place))
        by_free_space = self._free_space_segments(measurements, violations, consistent, inliers)
        by_free_space = self._not_in_place(measurements, static, by_free_space, inliers, report.T_w_c,
                                           keep_unknown=True)
        # The in-place veto, over each group of touching segments and over its outlier and its
        # displaced landmarks together, but only from as many landmarks as detection by
        # outliers needs: a turned object's one or two outliers are often found "in place" on
        # its own new texture (synth_two_sim seed 3), while a static surface whose depth
        # disagrees at its landmarks (a depth edge, redkitchen300 seed 1: 7 of 10 in place) has
        # many. Its displaced landmarks count too: a cylinder that moved 8 cm and turned 35
        # degrees had all 7 outlier landmarks found on look-alikes of its own texture, but 45
        # displaced ones (synth_two seed 3, frame 19; detected 3 frames later without them).
        by_displacement = []
        for group, displaced in self._displaced_landmark_groups(frame, measurements, static, inliers, report.T_w_c):
            if not self._mostly_in_place(measurements, static, group, inliers, report.T_w_c,
                                         self.config.detection.min_segment_features, also=displaced):
                by_displacement.extend(group)
        moving = sorted(set(by_outliers) | set(by_free_space) | set(by_displacement) | set(where_lost))
        moving = [s for s in moving if assignment.segment_owner[s] == 0]
        if not moving:
            return
        groups = merge_adjacent_moving_segments(segments, moving, self.config.detection.merge_gap_pixels)
        groups = [part for group in groups for part in self._split_by_motion(measurements, group, report.T_w_c)]
        by_id = {outcome.object_map.object_id: outcome for outcome in outcomes}
        for index, group in enumerate(groups):
            # a group does not grow into another group of this frame (an object beside it that moved too)
            others = [s for k, other in enumerate(groups) if k != index for s in other]
            owner = assignment.segment_owner.copy()
            owner[others] = np.where(owner[others] == 0, -1, owner[others])
            group = self._grow(frame, measurements, group, inliers, owner)
            group_points = np.concatenate([segments.point_indices[s] for s in group]).astype(np.int64)
            group_points = group_points[assignment.point_owner[group_points] == 0]
            if int(points.has_depth[group_points].sum()) < self.config.detection.min_object_points:
                # a small object carries few half-resolution keypoints: look closer at it in
                # the next frames (features.object_detail) and start it once it has enough
                self._candidate_boxes.append((_pixel_box(np.isin(segments.label_image, group)),
                                              frame.index + CANDIDATE_DETAIL_FRAMES))
                self._suspect_segments.extend(group)  # nor does its new place enter the static map
                continue
            if self.config.objects.reidentify and self._reidentify(frame, measurements, group, group_points, by_id,
                                                                   assignment):
                continue
            object_map = self._start_object(frame, measurements, group, report.T_w_c, assignment)
            if object_map is not None:
                report.objects_created.append(object_map.object_id)
                report.objects_tracked.append(object_map.object_id)

    def _split_by_motion(self, measurements: FrameMeasurements, group: list[int], T_w_c: np.ndarray) -> list[list[int]]:
        """A group of touching moving segments, split when the rigid motions found for its parts
        this frame (:meth:`_rigidly_moved`) disagree: two objects side by side that moved in the
        same frame (the paper's method makes them one map). Two motions disagree when they put
        the old place of either part's centroid (world frame) more than
        ``detection.split_motion_distance`` apart. Parts whose motions agree stay together;
        a segment of the group without a motion of its own (found by free space or displaced
        landmarks) joins the part nearest to it in the image. Returns the groups, each
        ascending (the group itself when there is nothing to split)."""
        limit = self.config.detection.split_motion_distance
        parts = [(sorted(set(g) & set(group)), motion) for g, motion in self._frame_motions if set(g) & set(group)]
        if limit <= 0 or len(parts) < 2:
            return [group]
        clusters: list[tuple[list[int], list[np.ndarray], list[np.ndarray]]] = []  # segments, motions, centroids
        for segment_ids, motion in parts:
            centre = _region_centroid(measurements, segment_ids, T_w_c)
            if centre is None:
                continue
            for members, motions, centres in clusters:
                checks = np.array(centres + [centre])
                if all(np.linalg.norm(transform_points(motion, checks) - transform_points(other, checks), axis=1).max()
                       <= limit for other in motions):
                    members.extend(segment_ids)
                    motions.append(motion)
                    centres.append(centre)
                    break
            else:
                clusters.append((list(segment_ids), [motion], [centre]))
        if len(clusters) < 2:
            return [group]
        labels = measurements.segments.label_image
        pixel_centres = {}
        for segment in group:
            rows, cols = np.nonzero(labels == segment)
            pixel_centres[segment] = np.array([cols.mean(), rows.mean()]) if len(rows) else np.zeros(2)
        split = [list(cluster[0]) for cluster in clusters]
        for segment in group:
            if any(segment in part for part in split):
                continue
            nearest = min(range(len(split)), key=lambda k: min(
                np.linalg.norm(pixel_centres[segment] - pixel_centres[s]) for s in split[k]))
            split[nearest].append(segment)
        logger.debug("frame %d: segments %s moved apart: split into %s", measurements.frame_index, group, split)
        return [sorted(part) for part in split]

    def _where_just_lost(self, measurements: FrameMeasurements, candidates: list[int],
                         outcomes: list[ObjectTrackingResult]) -> list[int]:
        """The candidate segments at least half of whose pixels were, in the previous frame,
        given to an object that this frame's registration lost: most likely that object,
        moved (a jump that turned it so that most of its landmarks no longer match)."""
        previous = self._previous_mask
        if not self.config.detection.where_lost or previous is None or not self.reports:
            return []
        tracked_before = set(self.reports[-1].objects_tracked)
        lost_ids = [outcome.object_map.object_id for outcome in outcomes
                    if not outcome.success and outcome.object_map.object_id in tracked_before]
        if not lost_ids:
            return []
        where = np.isin(previous, lost_ids)
        labels = measurements.segments.label_image
        total = np.maximum(np.asarray(measurements.segments.pixel_counts), 1)
        inside = np.bincount(labels[where & (labels >= 0)], minlength=len(total))
        return [segment for segment in candidates if inside[segment] >= 0.5 * total[segment]]

    def _outliers_in_place(self, measurements: FrameMeasurements, static: StaticRegistration,
                           segment: int | list[int], static_inliers: np.ndarray, T_w_c: np.ndarray,
                           also: np.ndarray | None = None) -> tuple[int, int]:
        """``(found, total)``: of the static landmarks matched as outliers in ``segment`` (one
        segment or a list of them), together with the static landmark ids ``also``, how many
        are still where the static map has them. Each is projected with the camera pose and
        looked for among the frame's keypoints near its projection (guided matching). A
        landmark found there has not moved (its outlier match went to a look-alike, such as the
        next cabinet door); one on an object that moved, even one that turned in place, is not
        found: its spot looks different now."""
        matched = static.matched
        point_segment = measurements.segments.segment_of_points(len(measurements.points))
        outlier = ~static_inliers[matched.point_measurements]
        rows = np.flatnonzero(outlier & np.isin(point_segment[matched.point_measurements], segment))
        landmarks = np.unique(matched.point_landmarks[rows])
        if also is not None:
            landmarks = np.union1d(landmarks, np.asarray(also, dtype=np.int64))
        if not len(landmarks):
            return 0, 0
        points = measurements.points
        found = guided_match(points.pixels, points.descriptors, self.static_map.points.positions[landmarks],
                             self.static_map.points.descriptors[landmarks], T_w_c, self.intrinsics,
                             self.config.matching.guided_radius_px, self.config.matching.ratio_test,
                             self.config.matching.max_descriptor_distance)
        if len(found):
            # a landmark lying where the latest static keyframes saw empty space is a phantom
            # (what it was on moved away), not evidence of a surface still in place
            phantom = self._in_free_space(self.static_map.points.positions[landmarks[found[:, 1]]])
            if phantom.any():
                logger.debug("frame %d: segment %s: %d of the outlier landmarks found in place lie in free space",
                             measurements.frame_index, segment, int(phantom.sum()))
            found = found[~phantom]
        return len(found), len(landmarks)

    def _in_free_space(self, world_points: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: which of the ``(N, 3)`` world points the latest static keyframes saw
        through, as :func:`~jsr.pipeline.objects.free_space_violations` judges a pixel: every
        keyframe that measured depth where the point projects saw its whole neighbourhood
        farther away than the point by more than ``max(objects.free_space_margin,
        objects.free_space_sigmas * sigma_Z)`` (sigma_Z of the depth it measured). One keyframe
        with a poor pose alone does not make a point a phantom."""
        config = self.config.objects
        if not (config.free_space_detection and self.depth_views) or not len(world_points):
            return np.zeros(len(world_points), dtype=bool)
        covered = np.zeros(len(world_points), dtype=bool)
        contradicted = np.zeros(len(world_points), dtype=bool)  # a covering view that did not see through it
        for keyframe_id, view in self.depth_views:
            T_w_view = self.static_map.keyframes[keyframe_id].T_map_cam  # after bundle adjustment
            in_view = transform_points(invert_transform(T_w_view), world_points)
            measured, through, _ = view.seen_through(in_view, self.intrinsics, self.config.noise,
                                                     config.free_space_margin, config.free_space_sigmas)
            covered |= measured
            contradicted |= measured & ~through
        return covered & ~contradicted

    def _not_in_place(self, measurements: FrameMeasurements, static: StaticRegistration, candidates: list[int],
                      static_inliers: np.ndarray, T_w_c: np.ndarray, keep_unknown: bool) -> list[int]:
        """The candidate segments fewer than half of whose outlier landmarks are still in place
        (:meth:`_outliers_in_place`); ``keep_unknown`` keeps segments without outlier landmarks."""
        return [segment for segment in candidates if not self._mostly_in_place(
            measurements, static, segment, static_inliers, T_w_c, 1, unknown=not keep_unknown)]

    def _mostly_in_place(self, measurements: FrameMeasurements, static: StaticRegistration, segment: int | list[int],
                         static_inliers: np.ndarray, T_w_c: np.ndarray, min_landmarks: int,
                         unknown: bool = False, also: np.ndarray | None = None) -> bool:
        """Whether at least half of the segment's outlier landmarks (and of the landmarks
        ``also``) are still in place, judged from at least ``min_landmarks`` of them (fewer:
        ``unknown``)."""
        found, total = self._outliers_in_place(measurements, static, segment, static_inliers, T_w_c, also)
        if total < min_landmarks:
            return unknown
        if found >= 0.5 * total:
            logger.debug("frame %d: segment %s: %d of %d outlier landmarks are still in place",
                         measurements.frame_index, segment, found, total)
            return True
        return False

    def _rigidly_moved(self, frame: Frame, measurements: FrameMeasurements, static: StaticRegistration,
                       candidates: list[int], static_inliers: np.ndarray,
                       min_turn_degrees: float | None = None, with_inliers: bool = False,
                       exclude: np.ndarray | None = None) -> list[int]:
        """The candidate segments whose static-map outliers agree on one rigid motion
        (``detection.require_rigid_motion``), grouped as touching regions. With
        ``min_turn_degrees``, only motions turning the region by at least that much count. With
        ``with_inliers``, the motion must explain ``WHOLE_TURN_MIN_SHARE`` of all their matched
        3D features, static inliers too. ``exclude`` ``(N,)`` bool: point measurements left out
        (those already given to an object).

        An object that moved carries its old landmarks along: their matches are outliers of the
        camera pose but inliers of one other rigid transformation. Outliers from view-dependent
        appearance (specular highlights) or repeated texture agree on nothing.
        """
        if not candidates:
            return candidates
        if not self.config.detection.require_rigid_motion:
            return candidates if min_turn_degrees is None else []
        segments = measurements.segments
        matched = static.matched
        three_d = matched.is_3d
        point_segment = segments.segment_of_points(len(measurements.points))
        # the pairs the motion is fitted to: the outliers (with_inliers: every matched 3D pair)
        fitted_pairs = three_d & (with_inliers | ~static_inliers[matched.point_measurements])
        if exclude is not None:
            fitted_pairs &= ~exclude[matched.point_measurements]
        confirmed: list[int] = []
        for group in merge_adjacent_moving_segments(segments, candidates, self.config.detection.merge_gap_pixels):
            in_group = fitted_pairs & np.isin(point_segment[matched.point_measurements], group)
            rows = np.flatnonzero(in_group[three_d])  # 3D pairs come first in the correspondences
            if len(rows) < self.config.detection.min_segment_features:
                continue
            subset = matched.correspondences.subset(point3d=rows, point2d=np.zeros(0, dtype=np.int64),
                                                    plane=np.zeros(0, dtype=np.int64))
            usual_inliers = max(self.config.detection.min_segment_features, self.config.ransac.min_inliers)
            # a motion is remembered (and held back) from min_segment_features agreeing outliers; one
            # frame alone decides it with the usual (an in-place turn: twice the usual), two frames
            # with the same motion with min_segment_features each
            memory = self.config.detection.in_place_turn_memory_frames > 0
            ransac = dataclasses.replace(self.config.ransac, min_matches=self.config.detection.min_segment_features,
                                         min_inliers=self.config.detection.min_segment_features
                                         if memory or min_turn_degrees is not None else usual_inliers,
                                         min_inlier_ratio=WHOLE_TURN_MIN_SHARE if with_inliers else 0.5)
            rng = self.turn_test_rng if with_inliers else self.objects_rng
            motion = register(subset, ransac, self.config.noise, rng)
            if not motion.success:
                continue
            # The region's motion relative to the static scene, seen from the camera: a small one
            # is the camera pose's own error over part of the image, not an object that moved.
            relative = np.linalg.inv(static.result.transformation) @ motion.transformation
            moved = np.linalg.norm(relative[:3, 3])
            turned = np.degrees(rotation_angle(relative[:3, :3]))
            logger.debug("frame %d: segments %s moved %.3f m, %.1f deg (%d of %d %s agree)",
                         measurements.frame_index, group, moved, turned, motion.num_inliers, len(rows),
                         "matches" if with_inliers else "outliers")
            detection = self.config.detection
            if not (moved >= detection.min_motion or turned >= detection.min_motion_degrees):
                continue
            if min_turn_degrees is not None and turned < min_turn_degrees:
                continue
            if moved < detection.free_space_veto_motion and self._seen_static(frame, measurements, group):
                # A small motion of a region whose surface is where the static keyframes saw
                # one: on real data, a camera pose that is off over part of the image.
                logger.debug("frame %d: segments %s: surface seen there before", measurements.frame_index, group)
                continue
            if detection.vacancy_veto and self._old_place_still_there(frame.depth, segments, group,
                                                                      static.result.transformation,
                                                                      motion.transformation):
                logger.debug("frame %d: segments %s: where they came from is not vacated", measurements.frame_index,
                             group)
                continue
            if motion.num_inliers >= usual_inliers:
                # evidence of how this region moved, for telling apart two objects that moved side by
                # side (_split_by_motion), even where an in-place turn still awaits confirmation
                self._frame_motions.append((list(group), motion.transformation @ invert_transform(
                    static.result.transformation)))
            needed = usual_inliers if min_turn_degrees is None else IN_PLACE_TURN_INLIER_FACTOR * usual_inliers
            if motion.num_inliers < needed:
                # too few agreeing outliers to decide alone (an object turned so that few of its
                # features match): the same motion in a recent frame confirms it
                seen = memory and self._turn_seen_before(measurements, group, static.result.transformation,
                                                         motion.transformation)
                if not seen:
                    # not confirmed (yet): its new place stays out of the static map meanwhile
                    self._suspect_segments.extend(group)
                    continue
            confirmed.extend(group)
        return sorted(confirmed)

    def _turn_seen_before(self, measurements: FrameMeasurements, group: list[int], T_w_c: np.ndarray,
                          T_w_old: np.ndarray) -> bool:
        """Whether a motion of the region ``group`` (its camera-frame points go to their old
        place by ``T_w_old``; ``T_w_c`` is the camera pose) with too few agreeing outliers to
        decide alone -- an in-place turn, or a jump that turned the object so that few of its
        features still match -- was also found in one of the last
        ``detection.in_place_turn_memory_frames`` frames. Same motion: it takes the region's
        centroid to within ``detection.min_motion`` of the same old place, and the rotations
        differ by at most ``TURN_MEMORY_DEGREES_FACTOR`` times ``detection.min_motion_degrees``
        (each is fitted to as few as ``detection.min_segment_features`` points, and two such
        frames together hold the usual agreeing outliers). An object that moved and came to
        rest gives the same motion in every frame; look-alikes and a person walking give a
        different one each time. The motion is remembered either way (in the world frame of this
        frame: a later bundle adjustment moves it by millimetres). Memory counts frame indices."""
        centroid = _region_centroid(measurements, group, T_w_c)
        if centroid is None:
            return False
        motion = T_w_old @ invert_transform(T_w_c)  # world, new place -> old place
        detection = self.config.detection
        frame_index = measurements.frame_index
        memory = detection.in_place_turn_memory_frames
        self._recent_turns = [turn for turn in self._recent_turns if frame_index - turn[0] <= memory]
        old_place = transform_points(motion, centroid[None])[0]
        seen = False
        for earlier_frame, earlier_motion in self._recent_turns:
            if earlier_frame == frame_index:
                continue
            earlier_old_place = transform_points(earlier_motion, centroid[None])[0]
            difference = np.degrees(rotation_angle(earlier_motion[:3, :3].T @ motion[:3, :3]))
            if np.linalg.norm(old_place - earlier_old_place) <= detection.min_motion \
                    and difference <= TURN_MEMORY_DEGREES_FACTOR * detection.min_motion_degrees:
                seen = True
                break
        self._recent_turns.append((frame_index, motion))
        logger.debug("frame %d: segments %s: in-place turn %s in an earlier frame", frame_index, group,
                     "also seen" if seen else "not seen")
        return seen

    def _seen_static(self, frame: Frame, measurements: FrameMeasurements, group: list[int]) -> bool:
        """Whether most sampled pixels of the segments ``group`` lie where the latest static
        keyframes saw a surface (free-space test; False when too few pixels could be tested)."""
        if not (self.config.objects.free_space_detection and self.depth_views):
            return False
        violations, consistent = self._free_space(frame, measurements)
        return bool(self._seen_before(violations[group].sum(), consistent[group].sum()))

    def _seen_before(self, violations, consistent):
        """Free-space verdict on sampled pixels (per segment as ``(S,)`` arrays, or summed over
        a region): enough of them could be tested and at least half lie where the latest static
        keyframes saw a surface."""
        sampled = violations + consistent
        return (sampled >= self._free_space_min_samples()) & (consistent >= 0.5 * sampled)

    def _depth_at_projections(self, camera_points: np.ndarray, depth: np.ndarray
                              ) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
        """``(N, 3)`` camera-frame points projected into ``depth`` ``(H, W)``: their rounded
        pixels ``(u, v)`` (each ``(N,)`` int), whether they fall in the image in front of the
        camera ``(N,)``, and the depth measured there ``(N,)`` (0 outside or invalid)."""
        intr = self.intrinsics
        z = camera_points[:, 2]
        safe = np.where(z > 1e-3, z, 1.0)
        u = np.round(intr.fx * camera_points[:, 0] / safe + intr.cx).astype(np.int64)
        v = np.round(intr.fy * camera_points[:, 1] / safe + intr.cy).astype(np.int64)
        height, width = depth.shape
        inside = (z > 1e-3) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        measured = np.zeros(len(z))
        measured[inside] = depth[v[inside], u[inside]]
        return (u, v), inside, measured

    def _old_place_still_there(self, depth: np.ndarray, segments, group: list[int], T_w_c: np.ndarray,
                               T_w_old: np.ndarray) -> bool:
        """Whether the surface a region would have come from is still where it was.

        ``T_w_old`` maps the region's camera-frame points to where the static map had them
        (its outliers' rigid motion), ``T_w_c`` is the camera pose. A region that moved has
        left its old place: seen from this camera, the depth there is now *behind* the old
        surface (vacated). A false motion (repeated texture: the next cabinet door over; a pose
        error over part of the image) points at a place whose surface is still there. Samples
        whose old place projects onto the region itself (a move within the object's own
        extent) or is hidden by something nearer say nothing. Still there: at least half of
        at least ``objects.free_space_min_pixels`` (scaled) samples.
        """
        labels = segments.label_image
        stride = FREE_SPACE_STRIDE
        sub_labels = labels[::stride, ::stride]
        sub_depth = depth[::stride, ::stride].astype(np.float64)
        rows, cols = np.nonzero(np.isin(sub_labels, group) & (sub_depth > 0))
        if not len(rows):
            return False
        intr = self.intrinsics
        camera = backproject_pixels(cols * stride, rows * stride, sub_depth[rows, cols], intr.fx, intr.fy, intr.cx,
                                    intr.cy)
        old_world = transform_points(T_w_old, camera)
        old_camera = transform_points(invert_transform(T_w_c), old_world)  # the old place seen from this camera
        zo = old_camera[:, 2]
        (uo, vo), inside, seen = self._depth_at_projections(old_camera, depth)
        on_region = np.zeros(len(zo), dtype=bool)
        on_region[inside] = np.isin(labels[vo[inside], uo[inside]], group)
        known = ~on_region & (seen > 0)
        margin = depth_thresholds(zo, self.config.noise)
        there = known & (np.abs(seen - zo) <= margin)
        vacated = known & (seen > zo + margin)
        evidence = int(there.sum() + vacated.sum())
        return evidence >= self._free_space_min_samples() and there.sum() >= 0.5 * evidence

    def _reidentify(self, frame: Frame, measurements: FrameMeasurements, group: list[int], group_points: np.ndarray,
                    outcomes: dict[int, ObjectTrackingResult], assignment: FrameAssignment) -> bool:
        """Register a moving region against every object map not tracked in this frame, whole
        map and no prediction; on success the region is that object (it is tracked again).
        When features find none, :meth:`_reidentify_by_shape` tries the region's surface
        (``objects.shape_reidentify``)."""
        lost = [m for m in self.object_maps
                if outcomes.get(m.object_id) is not None and not outcomes[m.object_id].success]
        for object_map in lost:
            matched = match_frame_to_map(measurements, object_map, np.flatnonzero(object_map.points.active), None,
                                         self.config, self._focal_length, point_measurements=group_points)
            result = register(matched.correspondences, self.config.ransac, self.config.noise, self.objects_rng)
            if result.success:
                logger.info("frame %d: moving region %s is object %d again", measurements.frame_index, group,
                            object_map.object_id)
                self._claim_region(measurements, group, outcomes[object_map.object_id], matched, result, assignment)
                return True
        if self.config.objects.shape_reidentify and lost:
            return self._reidentify_by_shape(frame, measurements, group, group_points, lost, outcomes, assignment)
        return False

    def _reidentify_by_shape(self, frame: Frame, measurements: FrameMeasurements, group: list[int],
                             group_points: np.ndarray, lost: list[ObjectMap],
                             outcomes: dict[int, ObjectTrackingResult], assignment: FrameAssignment) -> bool:
        """:meth:`_align_to_lost_objects` up to ``objects.shape_attempts`` times, while it keeps
        no alignment: its RANSAC draws from FPFH pairs, and once in a while no draw finds the
        right alignment (synth_two_sim s5, frame 18: 1 draw in 40 missed a cylinder that the
        others found, and the cylinder started a second map). Only the alignments are drawn
        again: the region's surface, the lost objects' models and their own views' texture
        agreement are computed once."""
        config = self.config.objects
        region_mask = np.isin(measurements.segments.label_image, group)
        sample = sample_surface(frame.depth, frame.color, region_mask, self.intrinsics, SURFACE_STRIDE,
                                0.5 * config.shape_voxel)
        region = region_model(sample, config.shape_voxel)
        if region is None:
            return False
        models = [(object_map, model) for object_map in lost if (model := self._surface_model(object_map)) is not None]
        own_textures: dict[int, float | None] = {}  # :meth:`_surface_self_texture` per map, once (~0.3 s each)
        for attempt in range(config.shape_attempts):
            if self._align_to_lost_objects(frame, measurements, group, group_points, region, models, own_textures,
                                           outcomes, assignment):
                if attempt:
                    logger.debug("frame %d: region %s found by surface alignment at attempt %d", frame.index, group,
                                 attempt + 1)
                return True
        return False

    def _align_to_lost_objects(self, frame: Frame, measurements: FrameMeasurements, group: list[int],
                               group_points: np.ndarray, region: SurfaceModel,
                               models: list[tuple[ObjectMap, SurfaceModel]], own_textures: dict[int, float | None],
                               outcomes: dict[int, ObjectTrackingResult], assignment: FrameAssignment) -> bool:
        """The region's surface (``region``, camera frame) aligned to each lost object's surface
        model (``models``; ``own_textures`` caches :meth:`_surface_self_texture` per map)
        (:func:`~jsr.pipeline.surfaces.align_surfaces`); each alignment is a pose prediction
        for prediction-based matching of the region's keypoints with the object's landmarks
        (``objects.shape_radius_px``). The registration with most inliers wins if it succeeds
        with at least ``ransac.min_inliers`` inliers and stays near its prediction (20 cm, 30
        degrees): the landmarks confirm the shape, which alone fits a box four ways. Landmarks
        that register away from their fits win when two fits far apart lead them to the same
        pose (:meth:`_landmarks_agree_elsewhere`), or when the surface agrees with their pose
        (:meth:`_surface_agrees`); when such a registration's object alone has a surface fit
        at the same pose that :meth:`_shape_alone` accepts, that fit's pose is taken instead.

        A jump that turns the object far shows it from sides whose landmarks no longer match
        (SIFT does not survive a 50-degree change of view), so when no landmarks confirm any
        alignment, one alignment alone may still decide (:meth:`_shape_alone`)."""
        config = self.config.objects
        region_centre = region.points.mean(axis=0)  # where alignments are compared (same_placement)
        best = None
        fits = []  # (object map, its surface model, the alignments): for the surface-alone decision
        away = []  # (object map, surface fit, matches, registration) of landmarks that registered away from their fit
        for object_map, model in models:
            landmarks = np.flatnonzero(object_map.points.active)
            alignments = align_surfaces(region, model, config.shape_voxel, self.objects_rng)
            fits.append((object_map, model, alignments))
            logger.debug("frame %d: region %s (%d surface points) vs object %d (%d): %d alignments",
                         measurements.frame_index, group, len(region.points), object_map.object_id,
                         len(model.points), len(alignments))
            for alignment in alignments[:SHAPE_CANDIDATES]:
                T_o_c = alignment.T_model_region
                matched = match_frame_guided(measurements, object_map, landmarks, T_o_c, self.intrinsics, self.config,
                                             self._focal_length, point_measurements=group_points,
                                             radius_px=config.shape_radius_px)
                logger.debug("frame %d: object %d, surface alignment with fitness %.2f, colour residual %.3f: "
                             "%d landmark matches", measurements.frame_index, object_map.object_id, alignment.fitness,
                             alignment.color_residual, len(matched.point_measurements))
                if len(matched.point_measurements) < self.config.ransac.min_matches:
                    continue
                result = register(matched.correspondences, self.config.ransac, self.config.noise, self.objects_rng)
                logger.debug("frame %d: object %d under that alignment: %d of %d inliers", measurements.frame_index,
                             object_map.object_id, result.num_inliers, result.num_matches)
                if not result.success or result.num_inliers < self.config.ransac.min_inliers:
                    continue
                if not same_placement(T_o_c, result.transformation, region_centre, SHAPE_CONFIRM_METRES,
                                      SHAPE_CONFIRM_DEGREES):
                    away.append((object_map, T_o_c, matched, result))
                    continue
                if best is None or result.num_inliers > best[3].num_inliers:
                    best = (object_map, T_o_c, matched, result)
        shape_alone = []

        def own_texture(object_map: ObjectMap) -> float | None:
            """:meth:`_surface_self_texture`, computed once per map here (model builds, ~0.3 s)."""
            if object_map.object_id not in own_textures:
                own_textures[object_map.object_id] = self._surface_self_texture(object_map)
            return own_textures[object_map.object_id]

        # this frame's depth, camera frame: would a model placed by an alignment be seen through?
        view = DepthView(np.asarray(frame.depth[::SURFACE_STRIDE, ::SURFACE_STRIDE], dtype=np.float32),
                         np.eye(4), SURFACE_STRIDE)
        if best is None:
            best = self._landmarks_agree_elsewhere(away, region_centre)
        if best is None and away:
            model_of = {object_map.object_id: model for object_map, model, _ in fits}
            best = next((item for item in sorted(away, key=lambda item: -item[3].num_inliers)
                         if self._surface_agrees(item[0], region, model_of[item[0].object_id],
                                                 item[3].transformation, view, own_texture(item[0]))), None)

        def alone(object_map: ObjectMap, model: SurfaceModel, alignments: list[Alignment]) -> Alignment | None:
            return self._shape_alone(object_map, region, model, alignments, view, own_texture(object_map),
                                     self._landmark_anchors(measurements, object_map, group_points))

        if best is None and not away:
            shape_alone = [(object_map, fit) for object_map, model, alignments in fits
                           if (fit := alone(object_map, model, alignments)) is not None]
        elif best is not None and any(best is item for item in away):
            # A registration away from its fit, of few landmarks: when the object's surface
            # alone, pinned, finds the same pose, the surface's pose is taken (synth_two_sim
            # seed 2 frame 56: the registration 8 of 13 inliers, 6.8 degrees off; the surface
            # fit, pinned by 7 matches, 2.3 degrees)
            object_map, model, alignments = next(item for item in fits if item[0] is best[0])
            fit = alone(object_map, model, alignments)
            if fit is not None and same_placement(fit.T_model_region, best[3].transformation, region_centre,
                                                  SHAPE_MODE_METRES, SHAPE_MODE_DEGREES):
                shape_alone = [(object_map, fit)]
        if len(shape_alone) == 1:  # two lost objects fitting as well: neither is trusted
            object_map, alignment = shape_alone[0]
            T_o_c = alignment.T_model_region
            matched = match_frame_guided(measurements, object_map, np.flatnonzero(object_map.points.active), T_o_c,
                                         self.intrinsics, self.config, self._focal_length,
                                         point_measurements=group_points, radius_px=config.shape_radius_px)
            # The pose is the surface's. The landmark matches that agree with it (too few to
            # register) link the view to the old landmarks, so that bundle adjustment refines the
            # surface's pose, but only from detection.min_segment_features of them on: a match
            # or two may agree by chance. The region's other features become new landmarks.
            result = surface_pose_result(T_o_c, matched.correspondences, self.config.ransac, self.config.noise,
                                         self.config.detection.min_segment_features)
            logger.info("frame %d: moving region %s is object %d again (its surface alone: fitness %.2f, colour "
                        "residual %.3f)", measurements.frame_index, group, object_map.object_id, alignment.fitness,
                        alignment.color_residual)
            self._claim_region(measurements, group, outcomes[object_map.object_id], matched, result, assignment)
            outcomes[object_map.object_id].pose_from_surface = True
            return True
        if best is None:
            return False
        object_map, _, matched, result = best
        logger.info("frame %d: moving region %s is object %d again (surface alignment, %d of %d landmark matches "
                    "agree)", measurements.frame_index, group, object_map.object_id, result.num_inliers,
                    result.num_matches)
        self._claim_region(measurements, group, outcomes[object_map.object_id], matched, result, assignment)
        return True

    def _landmark_anchors(self, measurements: FrameMeasurements, object_map: ObjectMap, group_points: np.ndarray
                          ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """For :meth:`_shape_alone`: a function of a surface fit ``T_o_c`` (object <- camera)
        giving the region's keypoints ``(K, 3)`` (camera frame) and the landmarks ``(K, 3)``
        (object frame) that prediction-based matching (``objects.shape_radius_px``) under it
        pairs within the 3D inlier threshold of that fit."""
        landmarks = np.flatnonzero(object_map.points.active)

        def anchors(T_o_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            matched = match_frame_guided(measurements, object_map, landmarks, T_o_c, self.intrinsics, self.config,
                                         self._focal_length, point_measurements=group_points,
                                         radius_px=self.config.objects.shape_radius_px)
            corr = matched.correspondences
            residuals = np.linalg.norm(transform_points(T_o_c, corr.frame_points) - corr.map_points, axis=1)
            agree = residuals <= point3d_thresholds(corr, self.config.noise)
            return corr.frame_points[agree], corr.map_points[agree]

        return anchors

    @staticmethod
    def _landmarks_agree_elsewhere(away: list[tuple], region_centre: np.ndarray) -> tuple | None:
        """Of the registrations that the landmarks found away from the surface fit that
        predicted them (``away``: ``(object map, T_o_c prediction, matches, registration)``),
        the one with most inliers when another one of the same object, predicted by a fit
        elsewhere (beyond SHAPE_CONFIRM of it), found the same pose (within SHAPE_MODE): the
        surface fits were wrong, the landmarks found the object from two starting guesses
        (synth_two_sim seed 2: three fits 58-171 degrees off, their landmark registrations all
        within 6 degrees of the truth). None otherwise: one registration away from its fit
        may be chance matches."""
        agreeing = []
        for a, b in itertools.combinations(away, 2):
            if a[0] is b[0] and same_placement(a[3].transformation, b[3].transformation, region_centre,
                                               SHAPE_MODE_METRES, SHAPE_MODE_DEGREES) \
                    and not same_placement(a[1], b[1], region_centre, SHAPE_CONFIRM_METRES, SHAPE_CONFIRM_DEGREES):
                agreeing += [a, b]
        return max(agreeing, key=lambda item: item[3].num_inliers) if agreeing else None

    def _surface_agrees(self, object_map: ObjectMap, region: SurfaceModel, model: SurfaceModel,
                        T_o_c: np.ndarray, view: DepthView, own_texture: float | None) -> bool:
        """Whether the object's surface agrees with a pose that its landmarks found (``T_o_c``,
        object <- camera) away from the surface fit that guided their matching: the region
        on the model (``objects.shape_min_fitness``), the model not seen through
        (``objects.shape_max_seen_through``) and its texture lining up as in
        :meth:`_shape_alone`. The landmarks pin the pose; the surface rules out chance
        matches (synth_two_sim seed 2: one registration 0.9 degrees off the truth, under a
        fit 83 degrees off). ``own_texture``: :meth:`_surface_self_texture` of the object."""
        config = self.config.objects
        if config.shape_min_texture_ratio <= 0 or own_texture is None or own_texture < SELF_TEXTURE_MIN:
            return False
        tree = cKDTree(model.points)
        if fitness(region, tree, T_o_c, config.shape_voxel) < config.shape_min_fitness:
            return False
        share = self._seen_through(model, T_o_c, view)
        if share is None or share > config.shape_max_seen_through:
            return False
        texture = texture_agreement(region, model, tree, T_o_c, config.shape_voxel) / own_texture
        logger.debug("object %d: landmark pose away from the surface fits: texture agreement %.2f, %.3f seen "
                     "through", object_map.object_id, texture, share)
        return texture >= config.shape_min_texture_ratio

    def _shape_alone(self, object_map: ObjectMap, region: SurfaceModel, model: SurfaceModel,
                     alignments: list[Alignment], view: DepthView, own_texture: float | None,
                     landmark_anchors: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
                     ) -> Alignment | None:
        """The alignment that the region's surface alone makes certain, or None
        (``own_texture``: :meth:`_surface_self_texture` of the object). It must
        - lie on the model: at least ``objects.shape_min_fitness`` of the region on its surface
          (the rest may show sides the map never saw: the jump turned the object);
        - leave the model where this view (``view``, the frame's depth) saw it or something in
          front of it: of the model's points that face the camera and fall where the frame
          measured depth, at most ``objects.shape_max_seen_through`` seen through
          (:func:`~jsr.pipeline.surfaces.seen_through_share`). Measured: right fits 0-0.4%;
          wrong fits on kitchen_box120 10-90%. A fit that the view sees
          through is no rival either: the object cannot be there;
        - line up the object's texture (:func:`~jsr.pipeline.surfaces.texture_agreement`) at
          least ``objects.shape_min_texture_ratio`` times as well as the object's own views
          line up with each other (:meth:`_surface_self_texture`, which must be at least
          SELF_TEXTURE_MIN: an object of one colour has no texture to tell its fits apart).
          Texture, not the colour residual: a jump that turns the object changes its shading
          (right fits 2.2-2.4 times the own views' colour residual on kitchen_box120 and
          synth_jump, as much as a box turned over), not how its texture lines up (right fits
          0.57-0.94 of the own views' agreement, wrong ones that the view allows at most 0.32);
        - be pinned by shape (:func:`~jsr.pipeline.surfaces.geometric_constraint` at least
          ``objects.shape_min_constraint``): along a free motion (a box seen on one face or
          two, a cylinder turned about its axis) that the texture lines up well does not pin
          the fit (synth_two seed 5: a fit 14 degrees off along it, texture agreement 0.87 of
          the own views'), so the fit must be pinned otherwise:
          - by landmarks: ``landmark_anchors(T_o_c)`` gives the region's 3D keypoints (camera
            frame) and the landmarks (object frame) they match under a fit, within the inlier
            threshold; at least ``detection.min_segment_features`` of them, placed so that the
            free motions move them (:meth:`_anchors_pin`), pin the fit, refined on surface and
            landmarks together, if the matches under the refined fit still pin it and its
            texture still passes (unrefined if the refinement loses texture agreement,
            TEXTURE_LOSS_MARGIN) (synth_jump seeds 2 and 4: a box jumped and showed two faces,
            5 of 6 and 5 of 9 guided matches within 1.1 cm of the right fit, too few to
            register on their own);
          - or else by the texture's peak along the free motions
            (:func:`~jsr.pipeline.surfaces.texture_pin`, which moves the fit to the peak);
        - have no rival: no other fit that the view allows, as complete (fitness within 0.1)
          and elsewhere, whose texture passes the same test.
        The fit chosen is the one whose texture lines up best; one pinned by shape is returned
        refined by geometry alone (:func:`~jsr.pipeline.surfaces.refine_fit`), one pinned by
        landmarks refined on both, one pinned by texture at its texture's peak.
        """
        config = self.config.objects
        if not alignments or config.shape_min_texture_ratio <= 0:  # 0: only fits that landmarks confirm
            return None
        if own_texture is None or own_texture < SELF_TEXTURE_MIN:
            logger.debug("object %d: its own views' texture agreement %s: the surface alone is not trusted",
                         object_map.object_id, own_texture)
            return None
        tree = cKDTree(model.points)
        seen_through = [self._seen_through(model, a.T_model_region, view) for a in alignments]
        texture = [texture_agreement(region, model, tree, a.T_model_region, config.shape_voxel) / own_texture
                   for a in alignments]
        allowed = [share is None or share <= config.shape_max_seen_through for share in seen_through]
        on_model = [k for k, a in enumerate(alignments) if a.fitness >= config.shape_min_fitness
                    and seen_through[k] is not None and allowed[k]]
        logger.debug("object %d: surface fits %s, seen through %s, texture agreement %s of its own views' %.2f",
                     object_map.object_id, [round(a.fitness, 2) for a in alignments],
                     [None if share is None else round(share, 3) for share in seen_through],
                     [round(t, 2) for t in texture], own_texture)
        if not on_model:
            return None
        chosen_index = max(on_model, key=lambda k: texture[k])
        chosen = alignments[chosen_index]
        if texture[chosen_index] < config.shape_min_texture_ratio:
            return None
        centre = region.points.mean(axis=0)
        rivals = [k for k, a in enumerate(alignments) if k != chosen_index and allowed[k]
                  and a.fitness >= chosen.fitness - SHAPE_RIVAL_FITNESS_GAP
                  and texture[k] >= config.shape_min_texture_ratio
                  and not same_placement(a.T_model_region, chosen.T_model_region, centre, SHAPE_MODE_METRES,
                                         SHAPE_MODE_DEGREES)]
        if rivals:
            return None
        constraint = geometric_constraint(region, model, tree, chosen.T_model_region, config.shape_voxel)
        logger.debug("object %d: surface fit %.2f, texture agreement %.2f of its own views', %.3f seen through, "
                     "constraint %.3f", object_map.object_id, chosen.fitness, texture[chosen_index],
                     seen_through[chosen_index], constraint)
        if constraint >= config.shape_min_constraint:
            # Pinned by shape: point-to-plane ICP polishes the coloured ICP's fit, whose colour
            # term the turned object's shading pulls off (kitchen_box120, synth_jump: 2-6 degrees
            # before, 1-3.5 after)
            refined = refine_fit(region, model, tree, chosen.T_model_region, config.shape_voxel)
            return dataclasses.replace(chosen, T_model_region=refined)
        no_anchors = (np.zeros((0, 3)), np.zeros((0, 3)))
        anchors = no_anchors if landmark_anchors is None else landmark_anchors(chosen.T_model_region)
        if not self._anchors_pin(region, model, tree, chosen.T_model_region, anchors[0]):
            pinned = texture_pin(region, model, tree, chosen.T_model_region, config.shape_voxel,
                                 config.shape_min_constraint, config.shape_min_fitness)
            logger.debug("object %d: surface fit not pinned by shape, %d landmark matches agree with it, %s by "
                         "texture", object_map.object_id, len(anchors[0]), "pinned" if pinned is not None else "not")
            return None if pinned is None else dataclasses.replace(chosen, T_model_region=pinned)
        refined = refine_fit(region, model, tree, chosen.T_model_region, config.shape_voxel, anchors=anchors)
        texture_refined = texture_agreement(region, model, tree, refined, config.shape_voxel) / own_texture
        logger.debug("object %d: surface fit pinned by %d landmark matches, texture agreement %.2f after "
                     "refinement", object_map.object_id, len(anchors[0]), texture_refined)
        if texture_refined < texture[chosen_index] - TEXTURE_LOSS_MARGIN:
            # the refinement lost texture agreement: the surface model pulled it off (a
            # cylinder's; synth_two_sim s2 frame 56: 0.84 -> 0.73, 2.3 -> 7.8 degrees off); the
            # fit itself, which the matches pin, is kept
            return chosen
        still = landmark_anchors(refined)
        if texture_refined < config.shape_min_texture_ratio or not self._anchors_pin(region, model, tree, refined,
                                                                                      still[0]):
            return None
        return dataclasses.replace(chosen, T_model_region=refined)

    def _seen_through(self, model: SurfaceModel, T_o_c: np.ndarray, view: DepthView) -> float | None:
        """:func:`~jsr.pipeline.surfaces.seen_through_share` of the object's surface model at
        ``T_o_c`` in this frame's ``view`` (beyond SHAPE_SEEN_THROUGH voxels and sigmas)."""
        return seen_through_share(model, T_o_c, view, self.intrinsics, self.config.noise,
                                  SHAPE_SEEN_THROUGH_VOXELS * self.config.objects.shape_voxel,
                                  SHAPE_SEEN_THROUGH_SIGMAS)

    def _anchors_pin(self, region: SurfaceModel, model: SurfaceModel, tree: cKDTree, T_o_c: np.ndarray,
                     points: np.ndarray) -> bool:
        """Whether landmark matches at ``points`` ``(K, 3)`` (camera frame) pin the surface fit
        ``T_o_c``: at least ``detection.min_segment_features`` of them (fewer may agree by
        chance), and placed so that every motion the shape leaves free moves them
        (:func:`~jsr.pipeline.surfaces.anchors_pin`, ANCHOR_MIN_MOTION_SHARE)."""
        if len(points) < max(3, self.config.detection.min_segment_features):
            return False
        config = self.config.objects
        return anchors_pin(region, model, tree, T_o_c, config.shape_voxel, config.shape_min_constraint, points,
                           ANCHOR_MIN_MOTION_SHARE)

    def _surface_self_texture(self, object_map: ObjectMap) -> float | None:
        """Median texture agreement (:func:`~jsr.pipeline.surfaces.texture_agreement`) of
        each of the object's last keyframe surface samples with the model of its other
        keyframes, at their bundle-adjusted poses: how well the object's own views line up
        (noise, shading, pose error). Only samples that mostly overlap the others count
        (SELF_TEXTURE_MIN_OVERLAP: two views that share an edge only compare little); None
        without two such views."""
        voxel = self.config.objects.shape_voxel
        views = [(keyframe.T_map_cam, self.object_surfaces.get(keyframe.frame_index, {}).get(object_map.object_id))
                 for keyframe in object_map.keyframes]
        views = [view for view in views if view[1] is not None and len(view[1].points)][-SELF_TEXTURE_VIEWS:]
        agreements = []
        for k, (T_model_camera, sample) in enumerate(views):
            others = build_model([view for j, view in enumerate(views) if j != k], voxel)
            own = region_model(sample, voxel)
            if others is None or own is None:
                continue
            tree = cKDTree(others.points)
            if fitness(own, tree, T_model_camera, voxel) >= SELF_TEXTURE_MIN_OVERLAP:  # else: other faces
                agreements.append(texture_agreement(own, others, tree, T_model_camera, voxel))
        return float(np.median(agreements)) if agreements else None

    def _claim_region(self, measurements: FrameMeasurements, group: list[int], outcome: ObjectTrackingResult,
                      matched: MatchedFrame, result: RegistrationResult, assignment: FrameAssignment) -> None:
        """The segments ``group`` and their unowned features go to ``outcome``'s object, which
        is tracked in this frame by ``result``."""
        object_id = outcome.object_map.object_id
        outcome.frame_matched, outcome.frame_result = matched, result
        assignment.segment_owner[group] = object_id
        points_in, planes_in = features_in_segments(measurements, group)
        assignment.point_owner[points_in & (assignment.point_owner == 0)] = object_id
        assignment.plane_owner[planes_in & (assignment.plane_owner == 0)] = object_id

    def _remember_surfaces(self, frame: Frame, ownership: np.ndarray) -> None:
        """Keep a surface sample of every object that got a keyframe (or started) in this frame."""
        if not (self.config.objects.enabled and self.config.objects.shape_reidentify):
            return
        samples = {}
        for object_map in self.object_maps:
            if object_map.keyframes and object_map.keyframes[-1].frame_index == frame.index:
                samples[object_map.object_id] = sample_surface(
                    frame.depth, frame.color, ownership == object_map.object_id, self.intrinsics, SURFACE_STRIDE,
                    0.5 * self.config.objects.shape_voxel)
        if samples:
            self.object_surfaces[frame.index] = samples

    def _extent_points(self, object_map: ObjectMap) -> np.ndarray:
        """``(N, 3)`` points (object map frame) whose convex hull is the object's extent: its
        active landmarks and, with ``objects.extent_from_surface``, every EXTENT_SURFACE_STEP-th
        surface sample of its last EXTENT_SURFACE_KEYFRAMES keyframes (at their current poses).

        Why the samples: a face whose keypoints have no depth (seen at a grazing angle, at
        320x240 a whole side of a box) adds no landmark, so the hull of the landmarks leaves it
        out, and once the keyframes that saw it move in have left the free-space views nothing
        gives it to the object any more."""
        landmarks = object_map.points.positions[object_map.points.active]
        if not self.config.objects.extent_from_surface:
            return landmarks
        parts = [landmarks]
        for keyframe in object_map.keyframes[-EXTENT_SURFACE_KEYFRAMES:]:
            sample = self.object_surfaces.get(keyframe.frame_index, {}).get(object_map.object_id)
            if sample is not None and len(sample.points):
                parts.append(transform_points(keyframe.T_map_cam,
                                              sample.points[::EXTENT_SURFACE_STEP].astype(np.float64)))
        return np.vstack(parts)

    def _surface_model(self, object_map: ObjectMap) -> SurfaceModel | None:
        """The object's surface in its map frame, from the samples of its keyframes (at their
        current, bundle-adjusted poses); None without enough points."""
        views = []
        for keyframe in object_map.keyframes:
            sample = self.object_surfaces.get(keyframe.frame_index, {}).get(object_map.object_id)
            if sample is not None:
                views.append((keyframe.T_map_cam, sample))
        return build_model(views, self.config.objects.shape_voxel) if views else None

    def _ensure_vocabulary(self, measurements: FrameMeasurements) -> None:
        """Train the VLAD vocabulary once, on the static map's descriptors (and this frame's)."""
        if self.vocabulary is not None:
            return
        config = self.config.vlad
        descriptors = np.concatenate([self.static_map.points.descriptors, measurements.points.descriptors])
        rng = np.random.default_rng(self.config.seed)  # its own stream: RANSAC draws stay unchanged
        if len(descriptors) > config.training_descriptors:
            descriptors = descriptors[np.sort(rng.choice(len(descriptors), config.training_descriptors, replace=False))]
        self.vocabulary = VladVocabulary.train(descriptors, config.vocabulary_size, rng, config.kmeans_iterations,
                                               config.normalization)
        logger.info("VLAD vocabulary of %d words trained on %d descriptors", self.vocabulary.size, len(descriptors))

    def _start_object(self, frame: Frame, measurements: FrameMeasurements, segment_ids: list[int],
                      T_w_c: np.ndarray, assignment: FrameAssignment) -> ObjectMap | None:
        """A new object map from the given segments; its frame is this camera frame."""
        points, planes = measurements.points, measurements.planes
        points_in, planes_in = features_in_segments(measurements, segment_ids)
        point_ids = np.flatnonzero(points_in & (assignment.point_owner == 0) & points.has_depth)
        plane_ids = np.flatnonzero(planes_in & (assignment.plane_owner == 0))
        if len(point_ids) < min(self.config.detection.min_object_points, self.config.ransac.min_matches):
            return None
        if self._next_object_id > MAX_OBJECT_ID:
            logger.warning("frame %d: %d object maps already; no more are started (masks hold ids up to %d)",
                           frame.index, MAX_OBJECT_ID, MAX_OBJECT_ID)
            return None
        object_id = self._next_object_id  # ids are never reused, also after merges
        self._next_object_id += 1
        object_map = ObjectMap(object_id, frame.index)
        keyframe = object_map.add_keyframe(
            frame.index, frame.timestamp, np.eye(4), points, point_ids, np.full(len(point_ids), -1),
            sample_colors(frame, points.pixels[point_ids]), planes, plane_ids, np.full(len(plane_ids), -1))
        assignment.point_owner[point_ids] = object_id
        assignment.plane_owner[plane_ids] = object_id
        assignment.segment_owner[segment_ids] = object_id
        self.object_maps.append(object_map)
        self._ensure_vocabulary(measurements)
        self._index_segments(object_map, keyframe, measurements, segment_ids)
        object_map.last_T_o_c = np.eye(4)
        object_map.last_T_w_o = np.array(T_w_c, dtype=float)
        object_map.record_pose(frame.index, frame.timestamp, object_map.last_T_w_o)
        object_map.frames_tracked = 1
        logger.info("frame %d: object %d detected (%d segments, %d points, %d planes)", frame.index, object_id,
                    len(segment_ids), len(point_ids), len(plane_ids))
        return object_map

    def _index_segments(self, object_map: ObjectMap, keyframe, measurements: FrameMeasurements,
                        segment_ids) -> None:
        """Store the VLAD and landmark ids of every segment an object keyframe received."""
        if self.vocabulary is None:
            return
        landmark_of = np.full(len(measurements.points), -1, dtype=np.int64)
        landmark_of[keyframe.point_measurements] = keyframe.point_landmarks
        for segment in segment_ids:
            indices = np.asarray(measurements.segments.point_indices[segment], dtype=np.int64)
            landmarks = landmark_of[indices]
            landmarks = np.unique(landmarks[landmarks >= 0])
            if len(landmarks) < self.config.vlad.min_segment_points:
                continue
            key = (keyframe.keyframe_id, int(segment))
            object_map.segment_landmarks[key] = landmarks
            self.segment_index.add(object_map.object_id, key,
                                   self.vocabulary.encode(object_map.points.descriptors[landmarks]))

    # ----------------------------------------------------------------------------------
    # Map updates

    def _update_static(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport,
                       static: StaticRegistration, assignment: FrameAssignment) -> None:
        """Add a keyframe to the static map (its own measurements only) when the pose is new."""
        pose = report.T_w_c
        if not (static.bridged or self.static_map.needs_keyframe(pose, self.config.keyframes)):
            return
        points, planes = measurements.points, measurements.planes
        static_points = np.flatnonzero(assignment.point_owner == 0)
        static_planes = np.flatnonzero(assignment.plane_owner == 0)
        if self._holding_back() and not static.bridged:
            static_points, static_planes = self._without_suspects(measurements, static, static_points, static_planes)
        if static.bridged:  # matched to the previous frame, not to the map: all measurements are new
            landmark_of = np.full(len(points), -1, dtype=np.int64)
            plane_landmark_of = np.full(len(planes), -1, dtype=np.int64)
        else:
            landmark_of = inlier_landmarks(static.matched, static.result, len(points))
            plane_landmark_of = inlier_plane_landmarks(static.matched, static.result, len(planes))
        self.static_map.add_keyframe(
            frame.index, frame.timestamp, pose, points, static_points, landmark_of[static_points],
            sample_colors(frame, points.pixels[static_points]), planes, static_planes,
            plane_landmark_of[static_planes],
        )
        report.new_keyframe = True
        self._remember_depth(frame, measurements, assignment)
        self.bundle.maybe_start(self.static_map)

    def _beside_moved_objects(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport,
                              static: StaticRegistration, outcomes: list[ObjectTrackingResult],
                              assignment: FrameAssignment) -> list[int]:
        """Segments to hold back from the static keyframe (``objects.hold_back_beside_moved``):
        unowned, with no static inlier (point or plane), and depth-adjacent to a segment of an
        object that moved in this frame: started, found again after it was lost, or registered
        away from its last world pose (the resting test, ``objects.resting_max_extra_cost``;
        with that test off, a tracked object never counts as moved).

        Why: where an object has just moved to, the static map knows nothing, and a face of it
        that its map has not taken (a side seen at a grazing angle, whose keypoints have little
        depth) would give the static keyframe its landmarks and its depth. From then on the face
        is static: its features are static inliers and its surface is where a keyframe saw one.
        Held back, it stays unexplained, and the growth rules can give it to the object in the
        next frames (synth_jump s1 at 320x240: the box's side face, frames 29-37)."""
        moved = set(report.objects_created)
        for outcome in outcomes:
            object_map = outcome.object_map
            if outcome.best is not None and (object_map.lost or outcome.moved_from_rest):
                moved.add(object_map.object_id)  # found again in this frame, or away from its last world pose
        owner = assignment.segment_owner
        of_moved = np.isin(owner, sorted(moved))
        if not of_moved.any():
            return []
        adjacency = self._adjacency(frame, measurements)
        if not len(adjacency):
            return []
        point_inliers, plane_inliers = inlier_mask(static.matched, static.result, len(measurements.points),
                                                   len(measurements.planes))
        point_segment = measurements.segments.segment_of_points(len(measurements.points))
        plane_segment = segment_of_planes(measurements.segments, len(measurements.planes))
        static_count = np.bincount(point_segment[point_inliers & (point_segment >= 0)],
                                   minlength=len(measurements.segments))
        static_count += np.bincount(plane_segment[plane_inliers & (plane_segment >= 0)],
                                    minlength=len(measurements.segments))  # a featureless table top's plane
        beside = np.zeros(len(owner), dtype=bool)
        first, second = adjacency[:, 0], adjacency[:, 1]
        beside[first[of_moved[second]]] = True
        beside[second[of_moved[first]]] = True
        held = np.flatnonzero(beside & (owner == 0) & (static_count == 0)).tolist()
        if held:
            logger.debug("frame %d: objects %s moved; segments %s beside them, with no static inlier, are held back",
                         frame.index, sorted(moved), held)
        return held

    def _holding_back(self) -> bool:
        """Whether this frame has suspect segments to keep out of a static keyframe
        (``objects.hold_back_suspects``)."""
        return bool(self.config.objects.hold_back_suspects and self._suspect_segments)

    def _without_suspects(self, measurements: FrameMeasurements, static: StaticRegistration,
                          point_ids: np.ndarray, plane_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``point_ids`` ``(K,)`` and ``plane_ids`` ``(L,)`` without the measurements of this
        frame's suspect segments that are no static inliers: segments whose outliers agree on
        an in-place turn not yet confirmed (:meth:`_rigidly_moved`), and moving regions too
        poor in 3D points to start a map (:meth:`_detect`). :meth:`_remember_depth` leaves
        their pixels out of the free-space views too.

        Why: a small object that turned and moved a few centimetres keeps only 6-9 matched
        outliers. A static keyframe taking its new surface as landmarks would make it static
        in every later frame, so the turn would never be confirmed. Held back, its old
        landmarks stay outliers and nothing of its new place enters the static map."""
        point_inliers, plane_inliers = inlier_mask(static.matched, static.result, len(measurements.points),
                                                   len(measurements.planes))
        point_segment = measurements.segments.segment_of_points(len(measurements.points))
        held = np.isin(point_segment[point_ids], self._suspect_segments) & ~point_inliers[point_ids]
        plane_segment = segment_of_planes(measurements.segments, len(measurements.planes))
        held_planes = np.isin(plane_segment[plane_ids], self._suspect_segments) & ~plane_inliers[plane_ids]
        if held.any() or held_planes.any():
            logger.debug("frame %d: %d points and %d planes of suspect segments %s held back from the static keyframe",
                         measurements.frame_index, int(held.sum()), int(held_planes.sum()), self._suspect_segments)
        return point_ids[~held], plane_ids[~held_planes]

    def _remember_depth(self, frame: Frame, measurements: FrameMeasurements, assignment: FrameAssignment) -> None:
        """Keep the static pixels' depth of the new static keyframe (subsampled) for free-space tests."""
        if not (self.config.objects.enabled and self.config.objects.free_space_detection):
            return
        stride = FREE_SPACE_STRIDE
        depth = np.array(frame.depth[::stride, ::stride], dtype=np.float32)
        ownership = self._ownership_image(measurements, assignment)[::stride, ::stride]
        depth[ownership > 0] = 0.0  # where objects were, nothing is known about free space
        if self._holding_back():  # nor where something may have moved to (see _without_suspects)
            depth[np.isin(measurements.segments.label_image[::stride, ::stride], self._suspect_segments)] = 0.0
        keyframe_id = self.static_map.keyframes[-1].keyframe_id
        self.depth_views.append((keyframe_id, DepthView(depth, self.static_map.keyframes[-1].T_map_cam, stride)))
        del self.depth_views[:-FREE_SPACE_VIEWS]

    def _free_space_since(self, frame: Frame, measurements: FrameMeasurements,
                          after_frame: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_free_space` counted over the static keyframes of frames after ``after_frame``
        only (the frame's own counts, computed once, when all of them are)."""
        keyframes = self.static_map.keyframes
        if all(keyframes[keyframe_id].frame_index > after_frame for keyframe_id, _ in self.depth_views):
            return self._free_space(frame, measurements)
        return self._free_space_counts(frame, measurements, self._frame_pose, after_frame=after_frame)

    def _free_space_counts(self, frame: Frame, measurements: FrameMeasurements, T_w_c: np.ndarray,
                           after_frame: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per segment ``(S,)``: sampled pixels lying in space the latest static keyframes saw
        as empty (violations), and pixels agreeing with the surface they saw (consistent).
        ``after_frame``: only the keyframes of later frames."""
        segments = measurements.segments
        per_view = []
        for keyframe_id, view in self.depth_views:
            if after_frame is not None and self.static_map.keyframes[keyframe_id].frame_index <= after_frame:
                continue
            view.T_w_c = self.static_map.keyframes[keyframe_id].T_map_cam  # after bundle adjustment
            per_view.append(free_space_violations(frame.depth, segments.label_image, T_w_c, self.intrinsics, view,
                                                  len(segments), self.config.noise,
                                                  self.config.objects.free_space_margin,
                                                  self.config.objects.free_space_sigmas))
        if not per_view:
            zeros = np.zeros(len(segments), dtype=np.int64)
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

    @property
    def _area_scale(self) -> float:
        """Image area relative to 640x480 (pixel-count thresholds are given for 640x480)."""
        return (self.intrinsics.width * self.intrinsics.height) / (640 * 480)

    def _free_space_min_samples(self) -> float:
        return self.config.objects.free_space_min_pixels * self._area_scale / FREE_SPACE_STRIDE**2

    def _free_space_segments(self, measurements: FrameMeasurements, violations: np.ndarray, consistent: np.ndarray,
                             static_inliers: np.ndarray) -> list[int]:
        """Segments that lie in space the latest static keyframes saw as empty: something moved
        in (an object that jumped to where the static map has no landmarks of it)."""
        config = self.config.objects
        if not config.free_space_detection or not self.depth_views:
            return []
        segments = measurements.segments
        moving = (violations >= self._free_space_min_samples()) & (
            violations >= config.free_space_share * (violations + consistent))
        # tiny segments (thin structures, depth edges) are where depth noise looks like motion
        moving &= np.asarray(segments.pixel_counts) >= config.free_space_min_segment_pixels * self._area_scale
        moving &= _little_static_support(measurements, static_inliers)
        return np.flatnonzero(moving).tolist()

    def _displaced_landmark_groups(self, frame: Frame, measurements: FrameMeasurements, static: StaticRegistration,
                                   static_inliers: np.ndarray, T_w_c: np.ndarray) -> list[tuple[list[int], np.ndarray]]:
        """Groups of touching segments whose static landmarks all went missing at once: an
        object that turned or jumped so that its features match nothing (no outliers to detect
        it by), over about where it stood (so that free space says nothing either;
        synth_two_sim seed 3: a cylinder turned 35 degrees, 2 of its 30 features matched).

        The static landmarks that were inliers in the previous frame are projected with the
        camera pose ``T_w_c`` (``static_inliers``: ``(N,)`` bool, this frame's point
        measurements that are inliers of ``static``); one is *displaced* when it is no inlier
        now and the depth measured at its projection is off its predicted depth by more than
        the inlier threshold (its surface is not there). Segments, alone or with touching
        ones, with enough of them move (:func:`~jsr.pipeline.detection.displaced_landmark_groups`).
        A static surface that lost its matches to blur keeps its depth; one that a nearer
        static surface hides keeps most of its landmarks elsewhere.
        Measured (share 0.8): no segment on redkitchen300 or bonn_crowd200, one static
        segment of kitchen_box120 with 6 displaced landmarks, objects with 10-37 (one segment
        each). Stop 20: synth_two seed 4's cylinder, jumped, lay in two segments with 6 and 7
        displaced landmarks; synth_two_sim seed 4's, in one segment with 5 of 5 displaced and
        56% of its pixels in free space (where free-space detection wants 60%).

        Returns ``(group, landmark ids)`` pairs: each group's segments and the static landmarks
        displaced in it."""
        config = self.config.detection
        previous = self._previous_static_inliers
        if config.displaced_share <= 0 or previous is None or not len(previous):
            return []
        landmarks = previous[self.static_map.points.active[previous]]
        camera_points = transform_points(invert_transform(T_w_c), self.static_map.points.positions[landmarks])
        (u, v), inside, measured = self._depth_at_projections(camera_points, frame.depth)
        with_depth = inside & (measured > 0)
        if not with_depth.any():
            return []
        segments = measurements.segments
        segment = np.full(len(landmarks), -1, dtype=np.int64)
        segment[with_depth] = segments.label_image[v[with_depth], u[with_depth]]
        with_depth &= segment >= 0
        z = camera_points[:, 2]
        threshold = depth_thresholds(z, self.config.noise)
        kept = np.isin(landmarks, static_inlier_landmarks(static))
        displaced = with_depth & ~kept & (np.abs(measured - z) > threshold)
        projecting = np.bincount(segment[with_depth], minlength=len(segments))
        displaced_count = np.bincount(segment[displaced], minlength=len(segments))
        violations, consistent = self._free_space(frame, measurements)
        groups = displaced_landmark_groups(segments, displaced_count, projecting,
                                           _little_static_support(measurements, static_inliers), violations,
                                           consistent, self._free_space_min_samples(), config)
        # seen through: the surface measured behind them (the background an object left, or
        # an object that turned away over its old place)
        seen_through = np.bincount(segment[displaced & (measured > z)], minlength=len(segments))
        for group in groups:
            logger.debug("frame %d: segments %s: %s of %s previous static inliers displaced (%s seen through)",
                         measurements.frame_index, group, displaced_count[group].tolist(),
                         projecting[group].tolist(), seen_through[group].tolist())
        return [(group, landmarks[displaced & np.isin(segment, group)]) for group in groups]

    def _retire_static_landmarks(self, static: StaticRegistration, assignment: FrameAssignment) -> None:
        """Static-map hygiene: landmarks the static map took from an object (before it moved)
        would keep pulling the camera. A landmark matched to a measurement that went to an
        object, or matched as an outlier in several frames in a row, is retired."""
        if static.bridged:
            return
        config = self.config.objects
        matched = static.matched
        landmarks = matched.point_landmarks
        if not len(landmarks):
            return
        result = static.result
        inlier = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
        streak = self.static_map.points.outlier_streak
        streak[landmarks[inlier]] = 0
        streak[landmarks[~inlier]] += 1
        retire = np.zeros(len(landmarks), dtype=bool)
        if config.enabled and config.retire_object_matches:
            retire |= assignment.point_owner[matched.point_measurements] > 0
        if config.retire_after_outliers > 0:
            retire |= streak[landmarks] >= config.retire_after_outliers
        retired = landmarks[retire & self.static_map.points.active[landmarks]]
        if len(retired):
            self.static_map.points.retire(retired)
            logger.debug("static map: %d landmarks retired", len(retired))

    def _retire_vacated_landmarks(self, frame: Frame, T_w_c: np.ndarray, static: StaticRegistration) -> None:
        """Static-map hygiene, geometric: a landmark of the static map that projects into
        this frame where the measured surface lies clearly *behind* it has lost its surface (an
        object it was on moved away). Seen through in ``objects.retire_after_vacated`` frames in
        a row, and not a registration inlier meanwhile, it is retired ("in a row" counts the
        frames that measure depth where it projects: its count survives frames out of view).
        Only once some object has been detected: before that nothing moved, and a landmark seen
        through is a depth edge or a colour/depth misregistration (measured: retiring those
        costs redkitchen300 ATE). Even then, only when no pixel within
        ``objects.vacated_window_px`` of its projection is near it (its surface is not just
        beside) and at least ``objects.vacated_cluster_size`` other landmarks within
        ``objects.vacated_cluster_radius`` are seen through too (an object's old place is an
        area)."""
        config = self.config.objects
        if config.retire_after_vacated <= 0 or not self.static_map.keyframes:
            return
        if self._next_object_id == 1:
            return  # nothing was seen to move yet: a surface seen through is a depth artefact
        points = self.static_map.points
        # every active landmark, not only the recent keyframes': what an object carried before
        # it moved was taken by the keyframes of before the motion, often no longer recent
        # when its old place comes back into view (synth_two seed 4: the static landmarks on
        # objects 2.1% -> 1.0%: 85 fewer landmarks, all of object origin)
        ids = self.static_map.recent_point_landmarks(None)
        if not len(ids):
            return
        camera = (points.positions[ids] - T_w_c[:3, 3]) @ T_w_c[:3, :3]
        z = camera[:, 2]
        (u, v), inside, measured = self._depth_at_projections(camera, frame.depth)
        seen = measured > 0
        noise = self.config.noise
        # the free-space test's margins: only a surface clearly gone counts, not a depth edge
        margin = np.maximum(config.free_space_margin, config.free_space_sigmas * noise.sigma_z_coefficient * z**2)
        through = seen & (measured > z + margin)
        if config.vacated_window_px > 0 and through.any():
            # gone means gone around it too: a landmark on a depth edge, projected a few pixels
            # off, has its own surface next to the pixel behind it
            radius = max(1, int(round(config.vacated_window_px * frame.depth.shape[1] / 640)))
            nearest = cv2.erode(np.where(frame.depth > 0, frame.depth, np.inf).astype(np.float32),
                                np.ones((2 * radius + 1, 2 * radius + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)
            near_surface = np.zeros(len(z))
            near_surface[inside] = nearest[v[inside], u[inside]]
            through &= near_surface > z + margin
        if not static.bridged:
            # a landmark registered as an inlier in this frame is where its feature is: a
            # "seen through" reading there is a depth edge or colour/depth misregistration
            result = static.result
            inliers = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
            through &= ~np.isin(ids, static.matched.point_landmarks[inliers])
        counts = points.seen_through
        counts[ids[seen & ~through]] = 0
        counts[ids[through]] += 1
        retire = through & (counts[ids] >= config.retire_after_vacated)
        if config.vacated_cluster_size > 0 and retire.any():
            # the place an object left is an area of landmarks seen through together; a depth
            # edge or misregistered pixel gives them one by one (measured on kitchen_box120:
            # the box's old place, 45 landmarks with a median of 32 seen-through neighbours
            # within 15 cm; elsewhere mostly single ones)
            through_positions = points.positions[ids[through]]
            neighbours = cKDTree(through_positions).query_ball_point(
                points.positions[ids[retire]], config.vacated_cluster_radius, return_length=True)
            retire[retire] = neighbours - 1 >= config.vacated_cluster_size  # itself is one of them
        retire = ids[retire]
        if len(retire):
            points.retire(retire)
            logger.debug("static map: %d landmarks retired, their surface is gone", len(retire))

    def _update_object(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport,
                       outcome: ObjectTrackingResult, assignment: FrameAssignment) -> bool:
        """Record the object's pose and add a keyframe when the object-relative view is new
        (then True)."""
        object_map = outcome.object_map
        if object_map not in self.object_maps:
            return False  # merged into another map earlier in this frame
        best = outcome.best
        if best is None:
            return False
        matched, result = best
        T_o_c = result.transformation
        object_map.lost = False
        object_map.last_T_o_c = T_o_c
        object_map.last_tracked_frame = frame.index
        object_map.frames_tracked += 1
        report.objects_tracked.append(object_map.object_id)
        if report.tracked:
            T_w_o = report.T_w_c @ np.linalg.inv(T_o_c)
            object_map.last_T_w_o = T_w_o
            object_map.last_pose_registered = not outcome.pose_from_surface
            object_map.record_pose(frame.index, frame.timestamp, T_w_o)
        points, planes = measurements.points, measurements.planes
        own_points = np.flatnonzero(assignment.point_owner == object_map.object_id)
        landmark_of = inlier_landmarks(matched, result, len(points))
        if not (object_map.needs_keyframe(T_o_c, self.config.keyframes)
                or self._map_would_grow(object_map, points, own_points, landmark_of)):
            return False
        own_planes = np.flatnonzero(assignment.plane_owner == object_map.object_id)
        plane_landmark_of = inlier_plane_landmarks(matched, result, len(planes))
        keyframe = object_map.add_keyframe(
            frame.index, frame.timestamp, T_o_c, points, own_points, landmark_of[own_points],
            sample_colors(frame, points.pixels[own_points]), planes, own_planes, plane_landmark_of[own_planes])
        own_segments = np.flatnonzero(assignment.segment_owner == object_map.object_id)
        self._index_segments(object_map, keyframe, measurements, own_segments)
        self.bundle.maybe_start(object_map)
        return True

    def _map_would_grow(self, object_map: ObjectMap, points, own_points: np.ndarray,
                        landmark_of: np.ndarray) -> bool:
        """Whether this frame's 3D measurements given to the object and matching none of its
        landmarks are at least ``objects.grow_keyframe_ratio`` times its active landmarks (and
        at least ``detection.min_object_points``): a map starts from the few features of the
        segments that gave it away, and should take the rest of the object in as soon as it
        is seen, not only once the object-relative view has changed (measured on
        kitchen_box120: a map started from 26 points was tracked by 9-15 inliers for 12 frames,
        until a view change gave it a keyframe of 188 points)."""
        ratio = self.config.objects.grow_keyframe_ratio
        if ratio <= 0 or not len(own_points):
            return False
        new = int(np.count_nonzero(points.has_depth[own_points] & (landmark_of[own_points] < 0)))
        return new >= max(self.config.detection.min_object_points, ratio * object_map.points.active_count)

    # ----------------------------------------------------------------------------------
    # Outputs

    def _ownership_image(self, measurements: FrameMeasurements, assignment: FrameAssignment) -> np.ndarray:
        """``(H, W)`` uint8: 0 static, K for the pixels of the segments and features of object K."""
        labels = measurements.segments.label_image
        image = np.zeros(labels.shape, dtype=np.uint8)
        if not np.any(assignment.segment_owner > 0) and not np.any(assignment.point_owner > 0):
            return image
        owner_of_label = np.append(assignment.segment_owner, 0).astype(np.uint8)  # label -1 -> static
        image = owner_of_label[np.where(labels >= 0, labels, len(assignment.segment_owner))]
        if assignment.not_object_pixels is not None:
            image[assignment.not_object_pixels] = 0
        image = fill_unlabelled(image, labels < 0, max(1, round(OWNERSHIP_FILL_RADIUS * labels.shape[1] / 640)))
        object_points = np.flatnonzero(assignment.point_owner > 0)
        if len(object_points):
            height, width = labels.shape
            pixels = np.round(measurements.points.pixels[object_points]).astype(int)
            u, v = np.clip(pixels[:, 0], 0, width - 1), np.clip(pixels[:, 1], 0, height - 1)
            image[v, u] = assignment.point_owner[object_points].astype(np.uint8)
        return image

    def keyframe_pixel_mask(self, map_: Map, keyframe_id: int) -> np.ndarray | None:
        """``(H, W)`` bool: the pixels of a keyframe that were given to ``map_`` (for TSDF fusion)."""
        frame_index = map_.keyframes[keyframe_id].frame_index
        ownership = self.keyframe_masks.get(frame_index)
        if ownership is None:
            return None
        owner = map_.object_id if isinstance(map_, ObjectMap) else 0
        return ownership == owner

    def object_trajectory(self, object_map: ObjectMap) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps ``(F,)`` and ``T_w_o`` ``(F, 4, 4)`` of an object in the frames it was
        tracked, after bundle adjustment of both maps. The camera pose is the static map's
        latest (as in ``camera.tum``). The object's pose relative to the camera, ``T_o_c`` as
        tracking measured it, is corrected by what bundle adjustment changed in the object's
        keyframes (:func:`_keyframe_correction`): the mean correction of the keyframes taken
        while the object rested where it is (tracking kept one world pose), so that it stays
        at one place there; else what bundle adjustment did, since the first frame of the rest
        (or the frame itself, when the object moved), to the map's latest keyframe of that time
        (``trajectory_anchors``: the pose was registered against the map as it was then,
        already refined by earlier runs; a keyframe's whole correction would count those runs
        twice).

        Why: a registration right after a jump sees few of the map's landmarks and lands a
        degree or two off, and the object at rest keeps that pose; the keyframes taken there
        are refined with every later view of the same landmarks (synth_jump seed 7 without
        depth noise: 2.4 degrees as tracked, 0.6 at the keyframes). One keyframe alone can be
        off about a symmetry axis that its few landmarks hardly fix (a cylinder's)."""
        reports = {report.frame_index: report for report in self.reports}
        keyframe_frames = [keyframe.frame_index for keyframe in object_map.keyframes]
        corrections = [_keyframe_correction(keyframe) for keyframe in object_map.keyframes]
        entries = object_map.trajectory
        # runs of consecutive entries at one world pose: the object at rest, as tracking kept it
        run_starts = [i for i in range(len(entries))
                      if i == 0 or not np.allclose(entries[i][2], entries[i - 1][2], rtol=0.0, atol=1e-9)]
        run_bounds = list(zip(run_starts, run_starts[1:] + [len(entries)]))
        timestamps, poses = [], []
        for start, stop in run_bounds:
            frames = {entries[i][0] for i in range(start, stop)}
            in_run = [k for k, frame_index in enumerate(keyframe_frames) if frame_index in frames]
            anchor = object_map.trajectory_anchors.get(entries[start][0])  # when the kept pose was registered
            if in_run:
                correction = _mean_transform([corrections[k] for k in in_run])
            elif anchor is not None:
                correction = _keyframe_correction(*anchor)
            else:  # (a map built by hand) the pose as tracked
                correction = np.eye(4)
            for frame_index, timestamp, T_w_o in entries[start:stop]:
                report = reports.get(frame_index)
                if report is not None and report.tracked:
                    T_o_c = correction @ (np.linalg.inv(T_w_o) @ report.T_w_c)
                    T_w_o = self.current_pose(report) @ np.linalg.inv(T_o_c)
                timestamps.append(timestamp)
                poses.append(T_w_o)
        return np.array(timestamps), np.array(poses).reshape(-1, 4, 4)

    def current_pose(self, report: FrameReport) -> np.ndarray | None:
        """``T_w_c`` of a tracked frame with the latest keyframe poses (after bundle adjustment)."""
        if not report.tracked:
            return None
        if report.reference_keyframe < 0:
            return report.T_w_c
        return self.static_map.keyframes[report.reference_keyframe].T_map_cam @ report.T_keyframe_cam

    def _previous_frame_map(self) -> Map:
        """A one-keyframe map made of the previous tracked frame's 3D points (world frame)."""
        measurements, pose = self._previous
        points = measurements.points
        previous = Map("previous_frame")
        previous.add_keyframe(-1, 0.0, pose, points, np.arange(len(points)), np.full(len(points), -1),
                              np.zeros((len(points), 3), np.uint8))
        return previous

    def finish(self) -> None:
        """Wait for and apply the last bundle adjustments."""
        for map_ in self.maps:
            self.bundle.finish(map_)

    def close(self) -> None:
        """Stop the worker threads (front-end and bundle adjustment); the maps stay usable."""
        self.frontend.close()
        self.bundle.shutdown()
