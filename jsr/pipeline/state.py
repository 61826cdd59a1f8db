"""The two kinds of state the Reconstructor's stages share, kept apart on purpose.

* :class:`SceneState`: what lasts across frames, named in one place: the maps, the camera's
  motion model, what detection remembers of recent frames, the free-space views, the object
  surface samples, the random streams and the worker for bundle adjustment.
* :class:`FrameContext`: what one frame computes (its measurements, the static registration,
  the object registrations, the assignment of measurements to maps, the regions found moving
  or held back, adjacency and free-space counts), created per frame and handed to every stage.
  Nothing of it outlives the frame except what a stage writes into the :class:`SceneState`.

Also the values a frame's processing returns: :class:`FrameReport`, :class:`MapCounts`,
:class:`FrameAssignment` and :class:`StaticRegistration`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from jsr.config import Config
from jsr.io.camera import CameraIntrinsics
from jsr.io.dataset import Frame
from jsr.pipeline.association import MatchedFrame, inlier_mask
from jsr.pipeline.bundle_scheduler import BundleScheduler
from jsr.pipeline.dense_alignment import DepthSurface, frame_samples
from jsr.pipeline.free_space import FreeSpaceViews
from jsr.pipeline.loop_closure import PlaceIndex
from jsr.pipeline.maps import Map, ObjectMap
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.object_registration import ObjectRegistrar, ObjectTrackingResult
from jsr.pipeline.object_surfaces import ObjectSurfaces
from jsr.pipeline.correspondences import RegistrationResult
from jsr.pipeline.segments import depth_adjacent_segments
from jsr.pipeline.vlad import SegmentIndex, VladVocabulary

STATIC_MAP = "static"
DYNAMIC = 255  # ownership masks: moving, but no rigid object map explains it (people; candidates not yet confirmed)
MAX_OBJECT_ID = DYNAMIC - 1  # ownership masks are uint8 images


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
    :meth:`~jsr.pipeline.reconstruct.Reconstructor.current_pose`).
    """

    frame_index: int
    timestamp: float
    name: str
    tracked: bool
    T_w_c: np.ndarray | None
    relocalised: bool = False
    bridged: bool = False
    by_depth: bool = False  # placed by its depth: the features failed (or had fewer inliers than dense.carry_below_inliers)
    reference_keyframe: int = -1
    T_keyframe_cam: np.ndarray | None = None
    new_keyframe: bool = False
    matches: int = 0
    inliers: int = 0
    reason: str = ""
    objects_tracked: list[int] = field(default_factory=list)
    objects_created: list[int] = field(default_factory=list)  # confirmed in this frame (or found by an initial mask)
    # (H, W) uint8: 0 static, K object K, DYNAMIC moving but unmodelled (non-rigid, or a candidate not yet confirmed)
    mask: np.ndarray | None = field(default=None, repr=False)
    dynamic_pixels: int = 0  # pixels of this frame labelled DYNAMIC
    maps: dict[str, MapCounts] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class StaticRegistration:
    """The static map's registration of one frame (``matched`` is against the map, or against
    the previous frame when ``bridged``; ``by_depth``: the frame's depth placed it, its
    features failed or were few)."""

    matched: MatchedFrame
    result: RegistrationResult
    bridged: bool = False
    by_depth: bool = False


@dataclass
class FrameAssignment:
    """Which map every measurement of a frame was given to (0: static, K: object K).

    ``point_owner`` ``(N,)``, ``plane_owner`` ``(P,)``, ``segment_owner`` ``(S,)``.
    """

    point_owner: np.ndarray
    plane_owner: np.ndarray
    segment_owner: np.ndarray
    not_object_pixels: np.ndarray | None = None  # (H, W) bool: pixels of object segments left out (mixed segments)

    @classmethod
    def all_static(cls, measurements: FrameMeasurements) -> "FrameAssignment":
        """Every measurement of the frame given to the static map."""
        return cls(np.zeros(len(measurements.points), dtype=np.int64),
                   np.zeros(len(measurements.planes), dtype=np.int64),
                   np.zeros(len(measurements.segments), dtype=np.int64))


@dataclass
class CameraTrack:
    """The camera's motion model and tracking status, carried from frame to frame.

    ``last_pose`` ``T_w_c`` of the last tracked frame; ``velocity`` ``(4, 4)`` the last
    frame-to-frame motion in the camera frame (constant-velocity prediction); ``previous``
    the last tracked frame's measurements and pose (bridging after a failed registration);
    ``best_matches`` the most matches to the static map of a frame since the last static
    keyframe (how well the map saw the view at best; ``keyframes.tracked_share``).
    """

    last_pose: np.ndarray | None = None
    velocity: np.ndarray = field(default_factory=lambda: np.eye(4))
    lost: bool = False
    previous: tuple[FrameMeasurements, np.ndarray] | None = None
    frames_lost: int = 0
    frames_bridged: int = 0
    best_matches: int = 0


@dataclass
class DetectionMemory:
    """What moving-object detection remembers of recent frames.

    ``recent_turns``: motions of regions with too few agreeing outliers to decide alone,
    ``(frame index, (4, 4) world motion new place -> old place)``; ``candidate_boxes``:
    pixel boxes ``(x0, y0, x1, y1)`` of moving regions too poor in 3D points to start a map,
    with the last frame to look closer at them; ``pending_displaced``: the static landmarks
    displaced in such a region, ``(L,)`` ids with the same last frame, still tested for
    displacement in the next frames (they are no static inliers any more, so the region's
    evidence would otherwise last one frame); ``previous_mask``: the last frame's ``(H, W)``
    uint8 ownership image (0 static, K object or candidate K, DYNAMIC non-rigid);
    ``previous_static_inliers``: ids of the static landmarks that were inliers of the last
    frame's static registration (None after a bridged or lost frame), and ``previous_depth``
    that frame's ``(H, W)`` depth image (m), to tell which of them the depth shows displaced
    since.
    """

    recent_turns: list[tuple[int, np.ndarray]] = field(default_factory=list)
    candidate_boxes: list[tuple[tuple[int, int, int, int], int]] = field(default_factory=list)
    pending_displaced: list[tuple[np.ndarray, int]] = field(default_factory=list)
    previous_mask: np.ndarray | None = None
    previous_static_inliers: np.ndarray | None = None
    previous_depth: np.ndarray | None = None


@dataclass
class RandomStreams:
    """The run's random streams, one per purpose, all derived from ``config.seed``.

    ``static``: the static map's registrations. ``objects``: object registration and
    detection, so that turning objects on (or an object appearing) does not change the RANSAC
    samples of camera tracking. ``loops``: the verification of loop closures
    (:mod:`~jsr.pipeline.loop_closure`).
    """

    static: np.random.Generator
    objects: np.random.Generator
    loops: np.random.Generator

    @classmethod
    def from_seed(cls, seed: int) -> "RandomStreams":
        # [seed, 2] was the stream of a detection test since removed: loops keep their samples
        return cls(np.random.default_rng(seed), np.random.default_rng([seed, 1]), np.random.default_rng([seed, 3]))


@dataclass
class SceneState:
    """Everything the reconstruction keeps from one frame to the next.

    ``keyframe_masks``: the ownership images of the frames that gave a keyframe to some map
    (the dense models fuse only the pixels each map received). ``surfaces``: surface samples
    of the object keyframes (an object's surface model for shape-based re-identification, and
    its extent). ``free_space``: subsampled depth of the latest static keyframes (free-space
    tests). ``merged_into``: object id -> the id of the map it was merged into. ``places``: the
    static keyframes' appearance, for loop closure. ``depth_surfaces``: the latest static
    keyframes' sampled static depth, for the dense term of tracking and for placing a frame on
    the free-space views, and ``depth_disagreements``
    how far their depth alone moved them from their features' pose (whether the depth is trusted).
    ``focal_length``: for image-space refinement (``ransac.refinement: image``), else None.
    """

    config: Config
    intrinsics: CameraIntrinsics
    streams: RandomStreams
    bundle: BundleScheduler
    registrar: ObjectRegistrar
    free_space: FreeSpaceViews
    surfaces: ObjectSurfaces
    focal_length: float | None
    static_map: Map = field(default_factory=lambda: Map(STATIC_MAP))
    object_maps: list[ObjectMap] = field(default_factory=list)
    camera: CameraTrack = field(default_factory=CameraTrack)
    memory: DetectionMemory = field(default_factory=DetectionMemory)
    reports: list[FrameReport] = field(default_factory=list)
    keyframe_masks: dict[int, np.ndarray] = field(default_factory=dict)
    merged_into: dict[int, int] = field(default_factory=dict)
    dissolved: list[int] = field(default_factory=list)  # candidates that never moved: given to the static map
    non_rigid: list[int] = field(default_factory=list)  # candidates no rigid motion explained: dynamic
    next_object_id: int = 1  # ids are never reused, also after merges
    vocabulary: VladVocabulary | None = None
    segment_index: SegmentIndex = field(default_factory=SegmentIndex)
    places: PlaceIndex = field(default_factory=PlaceIndex)
    depth_surfaces: dict[int, DepthSurface] = field(default_factory=dict)  # static keyframe id -> its sampled depth (the latest dense.keyframes)
    depth_disagreements: list[float] = field(default_factory=list)  # m, per static keyframe placed by its features (dense_alignment.disagreement)

    @property
    def maps(self) -> list[Map]:
        return [self.static_map, *self.object_maps]

    @property
    def area_scale(self) -> float:
        """Image area relative to 640x480 (pixel-count thresholds are given for 640x480)."""
        return (self.intrinsics.width * self.intrinsics.height) / (640 * 480)

    @property
    def objects_seen(self) -> bool:
        """Whether some object map was ever started (merged maps count)."""
        return self.next_object_id > 1


@dataclass
class FrameContext:
    """What one frame computes, handed from stage to stage (created per frame).

    ``static``: the static registration (None when it failed, or on the first frame);
    ``outcomes``: the registrations of every object map; ``assignment``: the map every
    measurement goes to (Algorithm 1 and what follows). ``suspects``: segments that may have
    moved, but not surely enough to start a map (an unconfirmed in-place turn, a moving region
    too poor in 3D points, a face beside an object that just moved): kept out of the static
    keyframe. ``dynamic``: segments moving with no rigid object map to explain them (people):
    kept out of the static map, written as DYNAMIC; ``unexplained``: candidates part of whose
    region moved without their registration following it (:mod:`~jsr.pipeline.confirmation`).
    ``given_to_static``: ``(N,)`` static landmark id for point measurements whose landmark a
    dissolved candidate just gave to the static map (-1 elsewhere; None: no such), and
    ``force_static_keyframe`` makes this frame a static keyframe so that they are linked to it.
    ``adjacency`` and ``free_space`` are computed when first needed (:meth:`segment_adjacency`,
    :meth:`free_space_counts`).
    """

    frame: Frame
    measurements: FrameMeasurements
    report: FrameReport
    timings: dict[str, float]
    static: StaticRegistration | None = None
    outcomes: list[ObjectTrackingResult] = field(default_factory=list)
    assignment: FrameAssignment | None = None
    suspects: list[int] = field(default_factory=list)
    dynamic: list[int] = field(default_factory=list)
    unexplained: set[int] = field(default_factory=set)
    given_to_static: np.ndarray | None = None
    force_static_keyframe: bool = False
    adjacency: np.ndarray | None = None  # (E, 2) depth-adjacent segment pairs
    free_space: tuple[np.ndarray, np.ndarray] | None = None  # (S,) violations, (S,) consistent
    measured_free_space: tuple[np.ndarray, np.ndarray] | None = None  # the same, measured_only
    surface_alignments: int = 0  # (region, lost object) surface alignments run (objects.shape_alignments_per_frame)

    @property
    def T_w_c(self) -> np.ndarray | None:
        """The camera pose of this frame when the static registration placed it."""
        return self.report.T_w_c if self.static is not None else None

    @property
    def registered(self) -> bool:
        """Whether the static registration's features placed this frame against the map itself
        (not bridged to the previous frame, not carried by its depth): only then do its
        outliers say anything about motion."""
        return self.static is not None and not self.static.bridged and not self.static.by_depth

    def static_inliers(self) -> tuple[np.ndarray, np.ndarray]:
        """``(N,)`` and ``(P,)`` bool: point and plane measurements that are inliers of the
        static registration (all False without one)."""
        num_points, num_planes = len(self.measurements.points), len(self.measurements.planes)
        if self.static is None:
            return np.zeros(num_points, dtype=bool), np.zeros(num_planes, dtype=bool)
        return inlier_mask(self.static.matched, self.static.result, num_points, num_planes)

    def static_matched(self) -> np.ndarray:
        """``(N,)`` bool: point measurements matched to the static map (none when bridged)."""
        matched = np.zeros(len(self.measurements.points), dtype=bool)
        if self.registered:
            matched[self.static.matched.point_measurements] = True
        return matched

    def segment_adjacency(self, config: Config) -> np.ndarray:
        """``(E, 2)`` depth-adjacent segment pairs of this frame
        (:func:`~jsr.pipeline.segments.depth_adjacent_segments`), computed once."""
        if self.adjacency is None:
            self.adjacency = depth_adjacent_segments(self.measurements.segments.label_image, self.frame.depth,
                                                     config.noise, config.segments)
        return self.adjacency

    def free_space_counts(self, state: SceneState) -> tuple[np.ndarray, np.ndarray]:
        """Per segment ``(S,)``: sampled pixels in space the latest static keyframes saw empty,
        and pixels agreeing with what they saw (:meth:`FreeSpaceViews.counts` at this frame's
        pose), computed once."""
        if self.free_space is None:
            self.free_space = self._counts(state, None)
        return self.free_space

    def measured_free_space_counts(self, state: SceneState,
                                   static_pixels: Callable[[], np.ndarray] | None = None
                                   ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`free_space_counts` where space counts as seen empty only if the views measured
        depth all around it (``measured_only``), computed once: the evidence that confirms a
        candidate (:mod:`~jsr.pipeline.confirmation`). ``static_pixels`` gives the frame's
        ``(H, W)`` bool static pixels, whose depth places the frame on each view first (with
        ``objects.free_space_registered``; None: at the feature pose); called only when the
        counts are first computed."""
        if self.measured_free_space is None:
            static_samples = None
            if static_pixels is not None:
                static_samples = frame_samples(self.frame.depth, static_pixels(), state.intrinsics,
                                               state.config.dense, state.config.noise)
            self.measured_free_space = self._counts(state, None, measured_only=True, static_samples=static_samples,
                                                    surfaces=state.depth_surfaces)
        return self.measured_free_space

    def free_space_since(self, state: SceneState, after_frame: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`free_space_counts` over the static keyframes of frames after ``after_frame``
        only (the frame's own counts when all of them are)."""
        if state.free_space.all_after(state.static_map.keyframes, after_frame):
            return self.free_space_counts(state)
        return self._counts(state, after_frame)

    def _counts(self, state: SceneState, after_frame: int | None, measured_only: bool = False,
                static_samples: tuple[np.ndarray, np.ndarray] | None = None,
                surfaces: dict[int, DepthSurface] | None = None) -> tuple[np.ndarray, np.ndarray]:
        segments = self.measurements.segments
        return state.free_space.counts(state.static_map.keyframes, self.frame.depth, segments.label_image,
                                       len(segments), self.T_w_c, after_frame=after_frame,
                                       measured_only=measured_only, static_samples=static_samples,
                                       surfaces=surfaces)
