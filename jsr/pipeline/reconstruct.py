"""The Reconstructor: one frame in, one :class:`FrameReport` out.

``process(frame)`` reads like the paper's system overview (Figure 2):

1. extract measurements (points, planes, segments);
2. register the frame against the static map (frame-based registration, Section 2.2.1),
   against the landmarks of the last N keyframes, or against the whole map after a loss;
3. update the map when registration succeeded and the pose is new (Section 2.4);
4. let bundle adjustment refine the map (asynchronously, applied at deterministic points).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from jsr.config import Config
from jsr.io.camera import CameraIntrinsics
from jsr.io.dataset import Frame
from jsr.pipeline.bundle import BundleScheduler
from jsr.pipeline.frontend import FrontEnd
from jsr.pipeline.maps import Map
from jsr.pipeline.matching import match_descriptors, match_planes
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.registration import Correspondences, RegistrationResult, register

logger = logging.getLogger(__name__)

STATIC_MAP = "static"


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
    maps: dict[str, MapCounts] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class MatchedFrame:
    """Correspondences of a frame's measurements with a map's landmarks."""

    correspondences: Correspondences
    point_measurements: np.ndarray  # (K,) measurement index of each point correspondence, 3D ones first
    point_landmarks: np.ndarray  # (K,) landmark id of each
    is_3d: np.ndarray  # (K,) True for 3D-3D, False for 2D-3D
    plane_measurements: np.ndarray  # (P,)
    plane_landmarks: np.ndarray  # (P,)


def match_frame_to_map(
    measurements: FrameMeasurements,
    target: Map,
    landmark_ids: np.ndarray,
    T_map_cam_predicted: np.ndarray | None,
    config: Config,
    focal_length: float | None = None,
) -> MatchedFrame:
    """Match all measurements of a frame with the landmarks ``landmark_ids`` of ``target``.

    Points by SIFT descriptor (ratio test); planes by geometry under the predicted pose
    (no planes are matched without a prediction). ``focal_length`` (pixels) turns on the
    image-space pose refinement of :func:`~jsr.pipeline.registration.register`.
    """
    points = measurements.points
    pairs = np.zeros((0, 2), dtype=np.int64)
    if len(points) and len(landmark_ids):
        pairs = match_descriptors(points.descriptors, target.points.descriptors[landmark_ids], config.matching.ratio_test)
    measurement_ids = pairs[:, 0].astype(np.int64)
    matched_landmarks = landmark_ids[pairs[:, 1]].astype(np.int64) if len(pairs) else np.zeros(0, dtype=np.int64)
    is_3d = points.has_depth[measurement_ids]
    order = np.argsort(~is_3d, kind="stable")  # 3D correspondences first
    measurement_ids, matched_landmarks, is_3d = measurement_ids[order], matched_landmarks[order], is_3d[order]

    plane_pairs = np.zeros((0, 2), dtype=np.int64)
    planes = measurements.planes
    if T_map_cam_predicted is not None and len(planes) and len(target.planes):
        frame_planes = np.column_stack([planes.normals, planes.offsets])
        plane_pairs = match_planes(
            frame_planes,
            target.planes.planes,
            T_map_cam_predicted,
            config.matching.plane_angle_degrees,
            config.matching.plane_distance,
        )
    plane_measurements = plane_pairs[:, 0].astype(np.int64)
    plane_landmarks = plane_pairs[:, 1].astype(np.int64)

    three_d, two_d = measurement_ids[is_3d], measurement_ids[~is_3d]
    correspondences = Correspondences(
        frame_points=points.points[three_d],
        map_points=target.points.positions[matched_landmarks[is_3d]],
        frame_bearings=points.bearings[two_d],
        map_points_2d=target.points.positions[matched_landmarks[~is_3d]],
        frame_planes=np.column_stack([planes.normals, planes.offsets])[plane_measurements]
        if len(plane_measurements)
        else np.zeros((0, 4)),
        map_planes=target.planes.planes[plane_landmarks] if len(plane_landmarks) else np.zeros((0, 4)),
        point_depths=points.points[three_d, 2],
        focal_length=focal_length,
    )
    return MatchedFrame(correspondences, measurement_ids, matched_landmarks, is_3d, plane_measurements, plane_landmarks)


def inlier_landmarks(matched: MatchedFrame, result: RegistrationResult, num_points: int) -> np.ndarray:
    """``(num_points,)`` landmark id of each point measurement that is a registration inlier, else -1."""
    landmark_of = np.full(num_points, -1, dtype=np.int64)
    inliers = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
    landmark_of[matched.point_measurements[inliers]] = matched.point_landmarks[inliers]
    return landmark_of


def inlier_plane_landmarks(matched: MatchedFrame, result: RegistrationResult, num_planes: int) -> np.ndarray:
    """``(num_planes,)`` landmark id of each plane measurement that is an inlier, else -1."""
    landmark_of = np.full(num_planes, -1, dtype=np.int64)
    inliers = np.asarray(result.inliers_plane, dtype=bool)
    landmark_of[matched.plane_measurements[inliers]] = matched.plane_landmarks[inliers]
    return landmark_of


def sample_colors(frame: Frame, pixels: np.ndarray) -> np.ndarray:
    """``(N, 3)`` uint8 colours of the frame at ``(N, 2)`` pixel positions (nearest pixel)."""
    height, width = frame.color.shape[:2]
    u = np.clip(np.round(pixels[:, 0]).astype(int), 0, width - 1)
    v = np.clip(np.round(pixels[:, 1]).astype(int), 0, height - 1)
    return frame.color[v, u]


class Reconstructor:
    """Tracks the camera against a static map and grows the map, one frame at a time.

    Usage::

        reconstructor = Reconstructor(config, sequence.intrinsics)
        for frame in sequence:
            report = reconstructor.process(frame)
        reconstructor.finish()
    """

    def __init__(self, config: Config, intrinsics: CameraIntrinsics):
        self.config = config
        self.intrinsics = intrinsics
        self.rng = np.random.default_rng(config.seed)
        self.frontend = FrontEnd(config, intrinsics)
        self.static_map = Map(STATIC_MAP)
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

    @property
    def maps(self) -> list[Map]:
        return [self.static_map]

    def process(self, frame: Frame) -> FrameReport:
        """Process one frame; never raises for a frame that simply cannot be registered."""
        started = time.perf_counter()
        measurements = self.frontend.process(frame)
        # A bundle adjustment started after the previous keyframe ran while the front-end
        # worked; it is applied here, always at this point, so runs stay reproducible.
        self.bundle.apply_finished(self.static_map, wait=True)
        if self.reports and self._last_pose is not None and self.reports[-1].tracked:
            # bundle adjustment may have moved the keyframe the last pose hangs from
            self._last_pose = self.current_pose(self.reports[-1])
        timings = dict(measurements.timings_ms)
        report = FrameReport(frame.index, frame.timestamp, frame.name, tracked=False, T_w_c=None)

        if not self.static_map.keyframes:
            self._initialise(frame, measurements, report)
        else:
            self._track(frame, measurements, report, timings)

        if report.tracked and self.static_map.keyframes:
            reference = self.static_map.keyframes[-1]
            report.reference_keyframe = reference.keyframe_id
            report.T_keyframe_cam = np.linalg.inv(reference.T_map_cam) @ report.T_w_c
        report.maps = {m.name: MapCounts(len(m.keyframes), m.points.active_count, len(m.planes), report.tracked)
                       for m in self.maps}
        timings["frame_total"] = (time.perf_counter() - started) * 1000.0
        report.timings_ms = timings
        self.reports.append(report)
        return report

    def _initialise(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport) -> None:
        """The first frame with enough 3D points defines the world frame and the static map."""
        points = measurements.points
        if int(points.has_depth.sum()) < self.config.ransac.min_matches:
            report.reason = "too few 3D points to start the map"
            return
        pose = np.eye(4)
        indices = np.arange(len(points))
        self.static_map.add_keyframe(
            frame.index, frame.timestamp, pose, points, indices, np.full(len(points), -1),
            sample_colors(frame, points.pixels), measurements.planes, np.arange(len(measurements.planes)),
            np.full(len(measurements.planes), -1),
        )
        report.tracked, report.T_w_c, report.new_keyframe = True, pose, True
        self._last_pose = pose
        self._previous = (measurements, pose)

    def _predicted_pose(self) -> np.ndarray | None:
        if self._last_pose is None:
            return None
        return self._last_pose @ self._velocity  # constant velocity in the camera frame

    def _track(self, frame: Frame, measurements: FrameMeasurements, report: FrameReport, timings: dict) -> None:
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
                result, bridged = bridge_result, True
                self.frames_bridged += 1
        timings["matching"], timings["registration"] = matching_ms, registration_ms
        report.matches, report.inliers = result.num_matches, result.num_inliers

        if not result.success:
            report.reason = result.reason
            self.frames_lost += 1
            self._lost = True
            self._previous = None
            logger.info("frame %d: static registration failed (%s)", frame.index, result.reason)
            return

        pose = result.transformation
        report.tracked, report.T_w_c, report.relocalised = True, pose, relocalise
        if self._last_pose is not None and not relocalise:
            self._velocity = np.linalg.inv(self._last_pose) @ pose
        else:
            self._velocity = np.eye(4)
        self._last_pose = pose
        self._lost = False
        self._previous = (measurements, pose)
        report.bridged = bridged

        tic = time.perf_counter()
        if bridged or self.static_map.needs_keyframe(pose, config.keyframes):
            points = measurements.points
            if bridged:  # matched to the previous frame, not to the map: all measurements are new
                landmark_of = np.full(len(points), -1, dtype=np.int64)
                plane_landmark_of = np.full(len(measurements.planes), -1, dtype=np.int64)
            else:
                landmark_of = inlier_landmarks(matched, result, len(points))
                plane_landmark_of = inlier_plane_landmarks(matched, result, len(measurements.planes))
            self.static_map.add_keyframe(
                frame.index, frame.timestamp, pose, points, np.arange(len(points)), landmark_of,
                sample_colors(frame, points.pixels), measurements.planes, np.arange(len(measurements.planes)),
                plane_landmark_of,
            )
            report.new_keyframe = True
            self.bundle.maybe_start(self.static_map)
        timings["map_update"] = (time.perf_counter() - tic) * 1000.0

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
        """Wait for and apply the last bundle adjustment."""
        self.bundle.finish(self.static_map)

    def close(self) -> None:
        """Stop the worker threads (front-end and bundle adjustment); the maps stay usable."""
        self.frontend.close()
        self.bundle.shutdown()
