"""Region growth: a moving region or an object's segments grown into the depth-adjacent
segments that nothing shows to be static (beyond the paper, whose segments are taken as they are
matched): the faces of an object whose features are not matched yet.
"""

from __future__ import annotations

import logging

import numpy as np

from jsr.pipeline.detection import segment_outlier_stats
from jsr.pipeline.free_space import FREE_SPACE_STRIDE
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.object_extent import wider_than
from jsr.pipeline.region_motion import mostly_in_place
from jsr.pipeline.state import FrameContext, SceneState

logger = logging.getLogger(__name__)

UNSUPPORTED_STATIC_SHARE = 0.2  # a segment with a larger share of static-inlier features is supported by the static map
UNMATCHED_FEATURE_FACTOR = 2  # a face whose 3D features hardly match the static map grows into an object from twice min_segment_features of them
# objects.extent_unseen_only: the static keyframes must have seen at least this share of a
# segment's sampled pixels (a moving object's face a keyframe saw in part, 8 of 50 samples on
# synth_smooth seed 1 at 320x240, is not the background that took over a map)
SEEN_SINCE_MIN_COVER = 0.5


def grow(state: SceneState, ctx: FrameContext, seeds: list[int], static_inliers: np.ndarray,
         segment_owner: np.ndarray, inside: np.ndarray | None = None, known_since: int = -1,
         object_width: float | None = None) -> list[int]:
    """``seeds`` grown into depth-adjacent segments that nothing shows to be static
    (``objects.grow_segments``): the faces of an object whose features are not matched yet.
    ``static_inliers`` ``(N,)`` bool: the frame's static inliers; ``segment_owner`` ``(S,)``
    (0: nobody's yet; others are not taken).
    ``inside`` ``(S,)`` bool: segments inside the extent of the object, a map since frame
    ``known_since``. ``object_width``: the width of everything known of the object (its
    extent, :func:`~jsr.pipeline.object_extent.largest_spread`); a segment more than
    ``SIZE_FACTOR`` times wider is not taken for lacking static support alone (a composite box
    resting on a real carpet took a 1.1 m piece of it, which the static map held few
    features on, and its map followed the carpet from then on: 26 cm, 66 degrees off)."""
    config = state.config
    measurements = ctx.measurements
    if not config.objects.grow_segments or not seeds:
        return sorted(int(s) for s in seeds)
    if ctx.T_w_c is None:
        return sorted(int(s) for s in seeds)  # without a camera pose nothing can be checked
    candidates = unsupported_segments(measurements, static_inliers, config.detection.min_segment_features)
    candidates &= segment_owner == 0
    # A segment whose surface lies where the static keyframes saw one has not moved, even if
    # the static map holds few landmarks on it (a table top the object stands on) ...
    violations, consistent = ctx.free_space_counts(state)
    seen_static = state.free_space.seen_before(violations, consistent)
    # ... unless the static landmarks matched in it are (nearly) all outliers: they moved
    # with it, and the surface the keyframes saw there was the object itself before it moved.
    min_features = config.detection.min_segment_features
    stats = segment_outlier_stats(measurements.segments, ctx.static_matched(), static_inliers)
    point_segment = measurements.segments.segment_of_points(len(measurements.points))
    in_segment = static_inliers & (point_segment >= 0)
    static_count = np.bincount(point_segment[in_segment], minlength=len(measurements.segments))
    moved = (stats.matched >= min_features) & (stats.outlier_ratio >= 1.0 - UNSUPPORTED_STATIC_SHARE) & (
        static_count < min_features)
    # Outlier matches alone do not show that: on a repetitive texture (a carpet) most matches
    # go to look-alikes. Its landmarks are then still found in place, and it has not moved
    # (redkitchen_s4_two_sim, seed 14, frame 26: the floor, 13 of 25 outlier landmarks in
    # place, joined a cylinder that jumped above it and the map followed the floor).
    for segment in np.flatnonzero(moved & seen_static & candidates):
        moved[segment] = not mostly_in_place(state, ctx, int(segment), static_inliers, 1)
    candidates &= ~seen_static | moved
    if object_width is not None and candidates.any():
        wide = np.flatnonzero(candidates)
        candidates[wide[wider_than(measurements.segments.label_image, ctx.frame.depth, state.intrinsics, wide,
                                   object_width)]] = False
    why = {"unsupported": candidates.copy()}  # which rule let each segment in (debug log)
    # A face with keypoints none of which is a static inlier (seen at a grazing angle, with
    # few of them with depth, or a side the camera had not seen before the object moved),
    # a good share of which lies in space the static keyframes saw empty: it moved in. This
    # overrides seen_static: the rest of such a face may agree with a surface the keyframes
    # saw, the object's own face in the same place before a jump.
    sampled = violations + consistent
    features = np.array([len(i) for i in measurements.segments.point_indices])
    share = config.objects.grow_violation_share
    if share > 0:
        why["moved in"] = (features >= min_features) & (segment_owner == 0) & (static_count == 0) & (
            sampled >= state.free_space.min_samples()) & (violations >= share * sampled)
        candidates |= why["moved in"]
    if config.objects.grow_unmatched:
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
        why["unmatched"] = seen_static & (segment_owner == 0) & (static_count == 0) & (
            three_d >= UNMATCHED_FEATURE_FACTOR * min_features) & (
            stats.matched <= UNSUPPORTED_STATIC_SHARE * three_d) & (
            violations >= state.free_space.min_samples())
        candidates |= why["unmatched"]
    if inside is not None:
        # Inside the object's extent and not shown static by its features: the object's own
        # faces, even without reliable 3D features (seen at a grazing angle). Not where the
        # static keyframes saw a surface (objects.extent_unseen_only): once the extent took in
        # some background (the place a jumped object left), it would otherwise take the scene
        # around it segment by segment (synth_two_sim seed 1 at 320x240: 70% of the box's
        # mask static by the end).
        taken = inside & (segment_owner == 0) & (static_count < min_features) & (
            static_count <= UNSUPPORTED_STATIC_SHARE * np.maximum(features, 1))
        if config.objects.extent_unseen_only and taken.any():
            # only keyframes taken once the object had its map (its pixels left out of them)
            # count: before, they saw the object's own faces as static surfaces
            later = ctx.free_space_since(state, known_since)
            samples = np.asarray(measurements.segments.pixel_counts) / FREE_SPACE_STRIDE**2
            seen_since = state.free_space.seen_before(*later) & ~moved & (
                later[0] + later[1] >= SEEN_SINCE_MIN_COVER * samples)
            if (taken & seen_since).any():
                logger.debug("frame %d: segments %s inside the extent of the object of seeds %s stay static: "
                             "static keyframes since frame %d saw a surface there (%s of %s tested, of %s)",
                             measurements.frame_index, np.flatnonzero(taken & seen_since).tolist(), seeds,
                             known_since, later[1][taken & seen_since].tolist(),
                             (later[0] + later[1])[taken & seen_since].tolist(),
                             samples[taken & seen_since].astype(int).tolist())
            taken &= ~seen_since
        why["inside extent"] = taken
        candidates |= taken
    grown = grow_region(seeds, candidates, ctx.segment_adjacency(config))
    added = [s for s in grown if s not in seeds]
    if added:
        logger.debug("frame %d: seeds %s grown by %s", measurements.frame_index, sorted(int(s) for s in seeds),
                     {int(s): [rule for rule, mask in why.items() if mask[s]] for s in added})
    return grown


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
