"""Object maps and their multi-group registration (Caccamo et al. 2017, Sections 2.1-2.2).

An :class:`ObjectMap` is a :class:`~jsr.pipeline.maps.Map` whose frame is the camera frame of
the frame that created it (the object frame). Its keyframes store ``T_map_cam`` = ``T_o_c``,
the camera seen from the object. The object's pose in the world at a tracked frame is
``T_w_o = T_w_c @ inv(T_o_c)``.

Every frame, each object map is registered twice (Section 2.2):

* **frame-based**: all frame measurements against the landmarks of the map's last N
  keyframes (the whole map after the object was lost), exactly as the static map;
* **segment-based**: every frame segment's VLAD is compared with the VLADs of the object
  map's segments; the most similar pairs are registered by RANSAC on the features of the two
  segments, and a success is refined by prediction-based matching of *all* frame
  measurements against the *whole* object map under the predicted pose.

When both succeed the segment-based result wins, as in the paper.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from jsr.config import Config
from jsr.geometry import backproject_pixels, inlier_threshold, transform_points
from jsr.pipeline.association import (
    MatchedFrame,
    match_frame_guided,
    match_frame_to_map,
)
from jsr.pipeline.correspondences import Correspondences, RegistrationResult
from jsr.pipeline.maps import Keyframe, Map
from jsr.pipeline.matching import match_descriptors
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.registration import register
from jsr.pipeline.vlad import SegmentIndex, VladVocabulary

logger = logging.getLogger(__name__)


class ObjectMap(Map):
    """The map of one moving object (landmarks in the object frame).

    ``segment_landmarks[(keyframe_id, segment)]`` holds the point landmark ids of each segment
    the object received in its keyframes: the units of segment-based registration, whose VLADs
    live in the reconstructor's :class:`~jsr.pipeline.vlad.SegmentIndex`.
    ``trajectory`` lists ``(frame_index, timestamp, T_w_o)`` of the frames it was tracked in;
    ``trajectory_anchors[frame_index]`` the map's latest keyframe when that frame was tracked
    and its ``T_map_cam`` then ``(4, 4)``: how far bundle adjustment moved the map since.
    """

    def __init__(self, object_id: int, created_at_frame: int):
        super().__init__(f"object_{object_id}")
        self.object_id = object_id
        self.created_at_frame = created_at_frame
        self.segment_landmarks: dict[tuple[int, int], np.ndarray] = {}
        self.last_T_o_c: np.ndarray | None = None  # camera in the object frame, last tracked frame
        self.last_T_w_o: np.ndarray | None = None  # object in the world, last frame tracked with the camera
        # last_T_w_o came from registered matches, not from a surface alignment alone (a few
        # degrees off): a pose the object may be kept at while it rests
        self.last_pose_registered = True
        self.lost = False  # not tracked in the previous frame: relocalise against the whole map
        self.last_tracked_frame = created_at_frame  # the latest frame it was tracked in (camera tracked or not)
        self.trajectory: list[tuple[int, float, np.ndarray]] = []
        self.trajectory_anchors: dict[int, tuple[Keyframe, np.ndarray]] = {}
        self.frames_tracked = 0

    def record_pose(self, frame_index: int, timestamp: float, T_w_o: np.ndarray) -> None:
        """Append ``T_w_o`` ``(4, 4)`` to the trajectory, anchored to the latest keyframe as it
        is now (what bundle adjustment does to the map from now on applies to this pose)."""
        self.trajectory.append((frame_index, timestamp, T_w_o))
        if self.keyframes:
            latest = self.keyframes[-1]
            self.trajectory_anchors[frame_index] = (latest, latest.T_map_cam.copy())


@dataclass
class ObjectTrackingResult:
    """The registrations of one object map in one frame (inputs of Algorithm 1).

    ``frame_matched``/``frame_result``: frame-based registration. ``segment_matched``/
    ``segment_result``: the prediction-based refinement of the best segment-based
    registration, ``seed_segments`` the frame segments whose RANSAC started it.
    ``T_o_c`` is the pose to use (segment-based when it succeeded), None if both failed.
    """

    object_map: ObjectMap
    frame_matched: MatchedFrame | None = None
    frame_result: RegistrationResult | None = None
    segment_matched: MatchedFrame | None = None
    segment_result: RegistrationResult | None = None
    seed_segments: list[int] = field(default_factory=list)
    segment_pairs_tried: int = 0
    pose_from_surface: bool = False  # re-identified by a surface alignment alone
    moved_from_rest: bool = False  # registered away from its last world pose (Reconstructor._kept_at_rest)

    @property
    def frame_success(self) -> bool:
        return self.frame_result is not None and self.frame_result.success

    @property
    def segment_success(self) -> bool:
        return self.segment_result is not None and self.segment_result.success

    @property
    def success(self) -> bool:
        return self.frame_success or self.segment_success

    @property
    def best(self) -> tuple[MatchedFrame, RegistrationResult] | None:
        """The registration that counts: segment-based when it succeeded, else frame-based."""
        if self.segment_success:
            return self.segment_matched, self.segment_result
        if self.frame_success:
            return self.frame_matched, self.frame_result
        return None

    @property
    def T_o_c(self) -> np.ndarray | None:
        best = self.best
        return None if best is None else best[1].transformation


def inlier_mask(matched: MatchedFrame | None, result: RegistrationResult | None, num_points: int,
                num_planes: int) -> tuple[np.ndarray, np.ndarray]:
    """``(N,)`` and ``(P,)`` bool: frame point and plane measurements that are inliers of a
    successful registration (all False otherwise)."""
    points = np.zeros(num_points, dtype=bool)
    planes = np.zeros(num_planes, dtype=bool)
    if matched is None or result is None or not result.success:
        return points, planes
    point_inliers = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
    points[matched.point_measurements[point_inliers]] = True
    planes[matched.plane_measurements[np.asarray(result.inliers_plane, dtype=bool)]] = True
    return points, planes


def segment_vlads(vocabulary: VladVocabulary, measurements: FrameMeasurements) -> np.ndarray:
    """``(S, K * 128)`` VLAD of every segment of the frame (zero rows for featureless ones)."""
    return vocabulary.encode_groups(measurements.points.descriptors, measurements.segments.point_indices)


class ObjectRegistrar:
    """Frame- and segment-based registration of a frame against one object map."""

    def __init__(self, config: Config, intrinsics, rng: np.random.Generator, focal_length: float | None):
        self.config = config
        self.intrinsics = intrinsics
        self.rng = rng
        self.focal_length = focal_length

    def _register(self, matched: MatchedFrame, initial_guess: np.ndarray | None) -> RegistrationResult:
        return register(matched.correspondences, self.config.ransac, self.config.noise, self.rng,
                        initial_guess=initial_guess)

    def frame_based(self, measurements: FrameMeasurements, object_map: ObjectMap,
                    predicted_T_o_c: np.ndarray | None) -> tuple[MatchedFrame, RegistrationResult]:
        """Registration against the last N keyframes' landmarks (the whole map when lost)."""
        keyframe_count = None if object_map.lost else self.config.matching.recent_keyframes
        landmark_ids = object_map.recent_point_landmarks(keyframe_count)
        prediction = None if object_map.lost else predicted_T_o_c
        matched = match_frame_to_map(measurements, object_map, landmark_ids, prediction, self.config,
                                     self.focal_length)
        return matched, self._register(matched, prediction)

    def segment_based(
        self,
        measurements: FrameMeasurements,
        vlads: np.ndarray,
        object_map: ObjectMap,
        index: SegmentIndex,
        skip_segments: np.ndarray | None = None,
    ) -> tuple[MatchedFrame | None, RegistrationResult | None, list[int], int]:
        """Segment-based registration with prediction-based refinement.

        ``vlads`` ``(S, D)``: VLADs of the frame segments; ``skip_segments`` ``(S,)`` bool marks
        segments not to try (e.g. explained by the static map). Returns the refined matches and
        result (None when no pair succeeded), the seed segment and the number of pairs tried.
        """
        config = self.config
        segments = measurements.segments
        counts = np.array([len(indices) for indices in segments.point_indices], dtype=np.int64)
        usable = counts >= config.vlad.min_segment_points
        if skip_segments is not None:
            usable &= ~skip_segments
        pairs: list[tuple[float, int, tuple[int, int]]] = []
        for segment in np.flatnonzero(usable):
            for key, similarity in index.query(vlads[segment], config.vlad.candidate_segments, object_map.object_id):
                if similarity > 0:
                    pairs.append((-similarity, int(segment), key))
        pairs.sort(key=lambda item: (item[0], item[1], item[2]))
        tried = 0
        best: tuple[MatchedFrame, RegistrationResult, int] | None = None
        all_landmarks = np.flatnonzero(object_map.points.active)
        for _, segment, key in pairs[: config.vlad.max_pairs]:
            landmarks = object_map.segment_landmarks.get(key)
            if landmarks is None:
                continue
            landmarks = landmarks[object_map.points.active[landmarks]]
            if len(landmarks) < config.ransac.min_matches:
                continue
            tried += 1
            seed = match_frame_to_map(measurements, object_map, landmarks, None, config, self.focal_length,
                                      point_measurements=segments.point_indices[segment])
            seed_result = self._register(seed, None)
            if not seed_result.success:
                continue
            # Prediction-based refinement: all measurements against the whole map under the pose.
            refined = match_frame_guided(measurements, object_map, all_landmarks, seed_result.transformation,
                                         self.intrinsics, config, self.focal_length)
            refined_result = self._register(refined, seed_result.transformation)
            if not refined_result.success:
                continue
            if best is None or refined_result.num_inliers > best[1].num_inliers:
                best = (refined, refined_result, segment)
            # The pairs are sorted by similarity: a success explained by a good share of the map
            # ends the search (the paper stops at the first success).
            break
        if best is None:
            return None, None, [], tried
        return best[0], best[1], [best[2]], tried

    def register_object(
        self,
        measurements: FrameMeasurements,
        vlads: np.ndarray | None,
        object_map: ObjectMap,
        index: SegmentIndex | None,
        predicted_T_o_c: np.ndarray | None,
        skip_segments: np.ndarray | None = None,
    ) -> ObjectTrackingResult:
        """Both registrations of one object map, per ``objects.segment_registration``."""
        outcome = ObjectTrackingResult(object_map)
        outcome.frame_matched, outcome.frame_result = self.frame_based(measurements, object_map, predicted_T_o_c)
        mode = self.config.objects.segment_registration
        run_segments = vlads is not None and index is not None and (
            mode == "always" or (mode == "fallback" and not outcome.frame_success))
        if run_segments:
            matched, result, seeds, tried = self.segment_based(measurements, vlads, object_map, index, skip_segments)
            outcome.segment_matched, outcome.segment_result = matched, result
            outcome.seed_segments, outcome.segment_pairs_tried = seeds, tried
        return outcome


def segment_votes(
    point_segment: np.ndarray, num_segments: int, owner: np.ndarray, counted: np.ndarray, num_owners: int
) -> np.ndarray:
    """``(S, num_owners)`` counts of the counted point measurements of each segment per owner.

    ``point_segment`` ``(N,)`` segment of each point (-1: none); ``owner`` ``(N,)`` owner index
    in ``[0, num_owners)``; ``counted`` ``(N,)`` bool.
    """
    keep = counted & (point_segment >= 0)
    votes = np.zeros((num_segments, num_owners), dtype=np.int64)
    np.add.at(votes, (point_segment[keep], owner[keep]), 1)
    return votes


def complete_segments(
    point_segment: np.ndarray,
    num_segments: int,
    point_owner: np.ndarray,
    evidence: np.ndarray,
    object_ids: list[int],
    min_votes: int,
) -> np.ndarray:
    """``(S,)`` owner of every segment: an object id when that object's registration inliers
    outnumber every other map's inliers in the segment (and reach ``min_votes``), else 0.

    ``point_owner`` ``(N,)`` owner after Algorithm 1; ``evidence`` ``(N,)`` bool: points that
    are inliers of the registration of their owner (static or object).
    """
    if not object_ids:
        return np.zeros(num_segments, dtype=np.int64)
    columns = {0: 0} | {object_id: i + 1 for i, object_id in enumerate(object_ids)}
    owner_column = np.array([columns.get(int(o), 0) for o in point_owner], dtype=np.int64)
    votes = segment_votes(point_segment, num_segments, owner_column, evidence, len(columns))
    best_object = 1 + np.argmax(votes[:, 1:], axis=1)
    best_votes = votes[np.arange(num_segments), best_object]
    others = votes.sum(axis=1) - best_votes
    wins = (best_votes >= min_votes) & (best_votes > others)
    ids = np.array([0] + list(object_ids), dtype=np.int64)
    return np.where(wins, ids[best_object], 0)


def depth_adjacent_segments(label_image: np.ndarray, depth: np.ndarray, noise, segments_config,
                            max_gap_pixels: int = 3, min_boundary_pixels: int = 10) -> np.ndarray:
    """``(E, 2)`` pairs ``(a, b)``, ``a < b``, of segments that touch *in 3D*: along at least
    ``min_boundary_pixels`` image neighbours (up to ``max_gap_pixels`` apart, horizontally or
    vertically), their depths differ by less than the segmentation's discontinuity threshold.

    Segments are cut at depth discontinuities, so two segments whose boundary is continuous in
    depth meet at an edge (two faces of a box, a box standing on a table); a box in front of
    a wall is image-adjacent to it but not depth-adjacent.
    """
    labels = np.asarray(label_image)
    z = np.asarray(depth, dtype=np.float64)
    pairs = []
    for gap in range(1, max_gap_pixels + 2):
        for a, b, za, zb in (
            (labels[:, :-gap], labels[:, gap:], z[:, :-gap], z[:, gap:]),
            (labels[:-gap, :], labels[gap:, :], z[:-gap, :], z[gap:, :]),
        ):
            keep = (a >= 0) & (b >= 0) & (a != b) & (za > 0) & (zb > 0)
            if not keep.any():
                continue
            za_k, zb_k = za[keep], zb[keep]
            mean_z = 0.5 * (za_k + zb_k)
            sigma = noise.sigma_z_coefficient * mean_z**2
            threshold = np.maximum(segments_config.min_discontinuity, segments_config.discontinuity_sigmas * sigma)
            continuous = np.abs(za_k - zb_k) < threshold * gap
            if continuous.any():
                pairs.append(np.sort(np.stack([a[keep][continuous], b[keep][continuous]], axis=1), axis=1))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    stacked = np.concatenate(pairs).astype(np.int64)
    # one integer key per pair (a * S + b): counting keys is much faster than unique rows,
    # and sorted keys are the pairs in lexicographic order
    count = int(stacked.max()) + 1
    keys, counts = np.unique(stacked[:, 0] * count + stacked[:, 1], return_counts=True)
    keys = keys[counts >= min_boundary_pixels]
    return np.stack([keys // count, keys % count], axis=1)


def grow_region(seeds: list[int], candidates: np.ndarray, adjacency: np.ndarray) -> list[int]:
    """``seeds`` plus every candidate segment (``candidates`` ``(S,)`` bool) reachable from them
    through ``adjacency`` pairs over candidate segments only; ascending."""
    region = set(int(s) for s in seeds)
    if not len(adjacency):
        return sorted(region)
    neighbours: dict[int, list[int]] = {}
    for a, b in adjacency:
        neighbours.setdefault(int(a), []).append(int(b))
        neighbours.setdefault(int(b), []).append(int(a))
    frontier = list(region)
    while frontier:
        current = frontier.pop()
        for other in neighbours.get(current, []):
            if other not in region and candidates[other]:
                region.add(other)
                frontier.append(other)
    return sorted(region)


def segments_inside_extent(label_image: np.ndarray, depth: np.ndarray, intrinsics, T_o_c: np.ndarray,
                           hull, noise, num_segments: int, margin: float, min_share: float,
                           stride: int = 4, min_samples: int = 10) -> np.ndarray:
    """``(S,)`` bool: segments whose surface lies inside the object's extent, ``hull``
    (:func:`extent_hull` of its landmarks, object frame; None: nothing is inside), widened by
    ``max(margin, inlier_sigmas sigma_Z)`` (the outermost keypoints of a face lie a few
    centimetres inside its edges): at least ``min_share`` of their sampled pixels (every ``stride``-th, with
    depth; at least ``min_samples`` of them) moved into the object frame with ``T_o_c`` fall
    inside. A face of a box seen at a grazing angle, whose keypoints have no reliable depth,
    lies on the hull of the landmarks of the faces next to it; the table the box stands on
    reaches far outside it.
    """
    result = np.zeros(num_segments, dtype=bool)
    if hull is None or num_segments == 0:
        return result
    labels = np.asarray(label_image)[::stride, ::stride]
    z = np.asarray(depth, dtype=np.float64)[::stride, ::stride]
    rows, cols = np.nonzero((labels >= 0) & (z > 0))
    if not len(rows):
        return result
    inside_pixel = pixels_inside_hull(rows * stride, cols * stride, z[rows, cols], intrinsics, T_o_c, hull, noise,
                                      margin)
    segment = labels[rows, cols]
    samples = np.bincount(segment, minlength=num_segments)
    inside = np.bincount(segment, weights=inside_pixel.astype(float), minlength=num_segments)
    return (samples >= min_samples) & (inside >= min_share * np.maximum(samples, 1))


EXTENT_OUTLIER_FACTOR = 3.0  # landmarks farther from the median than this many median distances are left out


def extent_hull(landmarks: np.ndarray):
    """The convex hull (scipy ``ConvexHull``) of ``(L, 3)`` object points (its landmarks, and
    with ``objects.extent_from_surface`` its surface samples), or None when there are fewer
    than 8 of them or they span no volume. Points farther from their median than
    ``EXTENT_OUTLIER_FACTOR`` times the median distance are left out: one stray landmark (a
    scene feature the object map took) must not stretch the extent over the scene."""
    from scipy.spatial import ConvexHull, QhullError

    landmarks = np.asarray(landmarks, dtype=float).reshape(-1, 3)
    if len(landmarks):
        distance = np.linalg.norm(landmarks - np.median(landmarks, axis=0), axis=1)
        landmarks = landmarks[distance <= EXTENT_OUTLIER_FACTOR * max(float(np.median(distance)), 1e-6)]
    if len(landmarks) < 8:
        return None
    try:
        return ConvexHull(landmarks)
    except (QhullError, ValueError):  # flat or degenerate: no volume to be inside of
        return None


def pixels_inside_hull(rows: np.ndarray, cols: np.ndarray, depths: np.ndarray, intrinsics, T_o_c: np.ndarray,
                       hull, noise, margin: float) -> np.ndarray:
    """``(M,)`` bool: pixels ``(rows, cols)`` with depth ``depths`` (metres) whose 3D point,
    moved into the object frame with ``T_o_c``, lies inside ``hull`` widened by
    ``max(margin, inlier_sigmas sigma_Z)``."""
    zs = np.asarray(depths, dtype=np.float64)
    camera = backproject_pixels(cols, rows, zs, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    in_object = transform_points(T_o_c, camera)
    threshold = inlier_threshold(zs, noise.sigma_z_coefficient, noise.inlier_sigmas, margin)
    normals, offsets = hull.equations[:, :3], hull.equations[:, 3]
    # A point's distance outside the hull is the largest over its facets (> 0: outside). Most
    # pixels lie far from the object: a few facets facing every way already put them past
    # the threshold, and only the rest need all facets (the result is the same).
    few = np.unique(np.argmax(normals @ _PREFILTER_DIRECTIONS.T, axis=0))
    candidate = np.max(in_object @ normals[few].T + offsets[few], axis=1) <= threshold
    inside = np.zeros(len(zs), dtype=bool)
    inside[candidate] = np.max(in_object[candidate] @ normals.T + offsets, axis=1) <= threshold[candidate]
    return inside


# the 6 axis and 8 diagonal directions: a hull's facets facing closest to them bound it on all sides
_PREFILTER_DIRECTIONS = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)
                                  if abs(x) + abs(y) + abs(z) in (1, 3)], dtype=float)


UNSUPPORTED_STATIC_SHARE = 0.2  # a segment with a larger share of static-inlier features is supported by the static map


def unsupported_segments(measurements: FrameMeasurements, static_inliers: np.ndarray, min_points: int,
                         max_static_share: float = UNSUPPORTED_STATIC_SHARE) -> np.ndarray:
    """``(S,)`` bool: segments with at least ``min_points`` 3D point features of which at most
    ``max_static_share``, and fewer than ``min_points``, are inliers of the static registration:
    nothing says they are static. Featureless segments are never unsupported (there is no
    evidence either way)."""
    segments, points = measurements.segments, measurements.points
    result = np.zeros(len(segments), dtype=bool)
    for segment, indices in enumerate(segments.point_indices):
        indices = np.asarray(indices, dtype=np.int64)
        three_d = int(points.has_depth[indices].sum())
        if three_d >= min_points:
            static = int(static_inliers[indices].sum())
            result[segment] = static <= max_static_share * three_d and static < min_points
    return result


@dataclass
class DepthView:
    """A subsampled depth image of a keyframe for free-space tests: ``depth`` ``(h, w)`` metres
    (0 invalid) at every ``stride``-th pixel, ``T_w_c`` its camera pose. ``near_depth`` is the
    nearest valid depth within ``(2 r + 1)^2`` samples (``r = near_radius``): space counts as
    seen empty only where the whole neighbourhood was seen farther away, so that thin structures,
    depth edges and a colour-to-depth misregistration of a few pixels do not look like violations.
    """

    depth: np.ndarray
    T_w_c: np.ndarray
    stride: int
    near_radius: int = 1
    near_depth: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.near_depth is None:
            import cv2

            far = np.where(self.depth > 0, self.depth, np.float32(1e6)).astype(np.float32)
            size = 2 * self.near_radius + 1
            near = cv2.erode(far, np.ones((size, size), np.uint8))
            self.near_depth = np.where(near < 1e6, near, 0.0).astype(np.float32)

    def sample(self, in_view: np.ndarray, intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 3)`` points in this view's camera frame projected into it: per point whether
        it falls in the image in front of the camera, the depth the view measured there and
        its ``near_depth`` (each ``(N,)``; 0 outside)."""
        z = in_view[:, 2]
        ahead = z > 1e-3
        safe = np.where(ahead, z, 1.0)
        u = np.round((intrinsics.fx * in_view[:, 0] / safe + intrinsics.cx) / self.stride).astype(np.int64)
        v = np.round((intrinsics.fy * in_view[:, 1] / safe + intrinsics.cy) / self.stride).astype(np.int64)
        height, width = self.depth.shape
        inside = ahead & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        seen, nearest = np.zeros(len(z)), np.zeros(len(z))
        seen[inside] = self.depth[v[inside], u[inside]]
        nearest[inside] = self.near_depth[v[inside], u[inside]]
        return inside, seen, nearest

    def seen_through(self, in_view: np.ndarray, intrinsics, noise, margin: float, sigmas: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 3)`` points in this view's camera frame: per point whether the view measured
        depth where it projects, whether the view saw through it (its whole neighbourhood
        farther than the point by more than ``max(margin, sigmas * sigma_Z)``, sigma_Z of the
        measured depth), and that depth (each ``(N,)``)."""
        inside, seen, nearest = self.sample(in_view, intrinsics)
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
) -> tuple[np.ndarray, np.ndarray]:
    """Per segment ``(S,)`` counts of sampled pixels that lie in space an earlier view saw as
    empty (*violations*) and of pixels that agree with that view (*consistent*).

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
                                             noise.inlier_sigmas if sigmas is None else sigmas)
    # agreement uses the registration's tight inlier threshold: between it and the violation
    # margin a pixel is neither (uncertain)
    agrees = usable & (np.abs(in_view[:, 2] - seen) <= np.maximum(
        noise.min_inlier_threshold, noise.inlier_sigmas * noise.sigma_z_coefficient * seen**2))
    segment = labels[rows, cols]
    np.add.at(violations, segment[closer], 1)
    np.add.at(consistent, segment[agrees], 1)
    return violations, consistent


def register_maps(target: ObjectMap, source: ObjectMap, config: Config, rng: np.random.Generator
                  ) -> RegistrationResult | None:
    """``T_target_source`` between two object maps from their point landmarks alone: the
    active landmarks of ``source`` are matched to those of ``target`` by descriptor (ratio
    test, cross-checked) and registered 3D-3D by RANSAC with the paper's thresholds. Two maps
    of one object (started apart because a jump turned a side the first had never seen to the
    camera) share the landmarks of every side both have seen since, whether or not they were
    ever tracked in the same frame. None when there are too few matches to try.

    A landmark's inlier threshold uses its distance from its map's origin (the camera that
    started the map) as the depth it was measured at.
    """
    source_ids = np.flatnonzero(source.points.active)
    target_ids = np.flatnonzero(target.points.active)
    if min(len(source_ids), len(target_ids)) < config.ransac.min_matches:
        return None
    pairs = match_descriptors(source.points.descriptors[source_ids], target.points.descriptors[target_ids],
                              config.matching.ratio_test, mutual=True,
                              max_distance=config.matching.max_descriptor_distance)
    if len(pairs) < config.ransac.min_matches:
        return None
    source_points = source.points.positions[source_ids[pairs[:, 0]]]
    correspondences = Correspondences(frame_points=source_points,
                                      map_points=target.points.positions[target_ids[pairs[:, 1]]],
                                      point_depths=np.linalg.norm(source_points, axis=1))
    return register(correspondences, config.ransac, config.noise, rng)


def merge_object_maps(target: ObjectMap, source: ObjectMap, T_target_source: np.ndarray) -> np.ndarray:
    """Move everything of ``source`` into ``target`` (two maps found to be one object).

    ``T_target_source`` maps ``source``'s object frame into ``target``'s. Landmarks, planes and
    keyframes are appended (keyframes then renumbered in frame order), the segments' landmark
    lists remapped, and the trajectories joined (``target``'s pose wins in a frame both have).
    Returns ``(L_source,)`` the new landmark id of every ``source`` landmark.
    """
    from jsr.geometry import transform_planes

    points = source.points
    new_ids = target.points.add(
        transform_points(T_target_source, points.positions), points.descriptors,
        1.0 / np.sqrt(np.maximum(points.weights, 1e-12)), points.colors)
    target.points.observations[new_ids] = points.observations
    target.points.retire(new_ids[~points.active])
    new_plane_ids = np.zeros(0, dtype=np.int64)
    if len(source.planes):
        new_plane_ids = target.planes.add(transform_planes(T_target_source, source.planes.planes),
                                          transform_points(T_target_source, source.planes.centroids),
                                          source.planes.point_counts)
    keyframes = list(target.keyframes)
    source_keyframe_position = {}
    for keyframe in source.keyframes:
        source_keyframe_position[keyframe.keyframe_id] = len(keyframes)
        keyframes.append(Keyframe(
            keyframe_id=-1, frame_index=keyframe.frame_index, timestamp=keyframe.timestamp,
            T_map_cam=T_target_source @ keyframe.T_map_cam, point_measurements=keyframe.point_measurements,
            point_landmarks=new_ids[keyframe.point_landmarks], camera_points=keyframe.camera_points,
            pixels=keyframe.pixels, sigma_z=keyframe.sigma_z,
            plane_landmarks=new_plane_ids[keyframe.plane_landmarks] if len(keyframe.plane_landmarks) else
            keyframe.plane_landmarks, camera_planes=keyframe.camera_planes,
            T_map_cam_tracked=T_target_source @ keyframe.T_map_cam_tracked))
    target_keyframe_position = {keyframe.keyframe_id: i for i, keyframe in enumerate(target.keyframes)}
    order = sorted(range(len(keyframes)), key=lambda i: (keyframes[i].frame_index, i))
    new_keyframe_id = {position: rank for rank, position in enumerate(order)}
    target.keyframes = [keyframes[i] for i in order]
    for rank, keyframe in enumerate(target.keyframes):
        keyframe.keyframe_id = rank
    segments = {}
    for (keyframe_id, segment), landmarks in target.segment_landmarks.items():
        segments[(new_keyframe_id[target_keyframe_position[keyframe_id]], segment)] = landmarks
    for (keyframe_id, segment), landmarks in source.segment_landmarks.items():
        segments[(new_keyframe_id[source_keyframe_position[keyframe_id]], segment)] = new_ids[landmarks]
    target.segment_landmarks = segments
    by_frame = {index: (index, timestamp, T_w_o @ np.linalg.inv(T_target_source))
                for index, timestamp, T_w_o in source.trajectory}
    target_frames = {index for index, _, _ in target.trajectory}
    by_frame.update({index: (index, timestamp, T_w_o) for index, timestamp, T_w_o in target.trajectory})
    target.trajectory = [by_frame[index] for index in sorted(by_frame)]
    # the source's anchors follow its keyframes into the target (target's entries win, as above)
    moved_keyframe = {id(keyframe): keyframes[source_keyframe_position[keyframe.keyframe_id]]
                      for keyframe in source.keyframes}
    anchors = {index: (moved_keyframe[id(keyframe)], T_target_source @ T_map_cam)
               for index, (keyframe, T_map_cam) in source.trajectory_anchors.items() if index not in target_frames}
    anchors.update(target.trajectory_anchors)
    target.trajectory_anchors = anchors
    target.frames_tracked = len(target.trajectory)
    target.created_at_frame = min(target.created_at_frame, source.created_at_frame)
    return new_ids
