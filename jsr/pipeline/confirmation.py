"""Confirmation of candidate objects by evidence over frames.

Caccamo et al. 2017 start an object map from one frame's outliers, and close with the cure for
what that gets wrong: use a sequence of frames for detection. A moving region found by detection
starts a *candidate* object map (:class:`~jsr.pipeline.maps.Candidacy`); its measurements stay
out of the static map, and its pixels are written as moving but unmodelled (255) until it is
decided. In each frame after its birth the candidate is registered like every object map, and
weighed:

* **Rigid or not.** Its registration must explain what it matched as one rigid body: it
  succeeds, and its outliers are no more than the frame's mismatch rate (the static
  registration's outlier ratio) makes likely (binomial tail below ``detection.significance``);
  in a frame that moved it, its landmarks also lie on the measured depth (:func:`_rigid`).
  A frame in which part of its region was found moving again without its registration
  following it (``FrameContext.unexplained``: a person's limbs move against the torso RANSAC
  locked onto; or it was not found at all) is not rigid either.
* **Moved or not.** For the measurements matched both by the candidate (its inliers) and by the
  static map, the log-likelihood ratio of the two explanations with the paper's noise model:
  ``sum(cost under the camera pose against the static landmarks - cost under the candidate's
  pose against its own landmarks)``, costs in squared noise sigmas, each residual capped at its
  inlier threshold (:func:`~jsr.pipeline.registration.scaled_residuals`). Were the region
  static, the candidate would fit the same measurements only by its own 6 pose parameters: the
  ratio is then a chi-square with 6 degrees of freedom, and the frame shows motion when it
  exceeds the quantile at ``detection.confirm_significance``. A frame shows motion too when
  the static landmarks that showed, at detection, that the region moved
  (``Candidacy.evidence_landmarks``) still disagree with the measured depth beyond the
  chi-square bound (:func:`evidence_misfit`), or when the region lies in space the static
  keyframes measured empty all around, over enough of its pixels in its probation's frames
  (:func:`in_free_space`).

Decisions, in the frame they become certain: **confirmed** (an object from now on; the report
lists it as created) when at least ``detection.confirm_frames`` rigid frames showed motion and
the rigid frames outnumber the non-rigid ones; **non-rigid** (people, cloth: dynamic and
unmodelled) when its non-rigid frames reach ``detection.confirm_frames`` and outnumber the
rigid ones: the map is dropped and its region labelled dynamic; **dissolved** when
``detection.confirm_window`` frames passed undecided: it never moved beyond the noise; when it
was seen resting (rigid in ``confirm_frames`` frames, none showing motion), its landmarks join
the static map at their world positions.

Confirmed objects are weighed for rigidity over their whole life (:func:`_weigh_object`): a
walking person's torso can look rigid for the few frames of probation, and its limbs, then its
whole body, stop fitting one rigid motion afterwards. Left as an object, every later moving
region was aligned to its person-sized surface (seconds per frame on bonn_crowd_people).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.stats import binom, chi2

from jsr.geometry import transform_points
from jsr.pipeline.correspondences import depth_thresholds
from jsr.pipeline.free_space import depth_at_map_points
from jsr.pipeline.map_updates import not_static_pixels
from jsr.pipeline.maps import ObjectMap
from jsr.pipeline.object_registration import ObjectTrackingResult
from jsr.pipeline.registration import scaled_residuals, squared_cost
from jsr.pipeline.state import DYNAMIC, FrameContext, SceneState

logger = logging.getLogger(__name__)

POSE_PARAMETERS = 6  # what the candidate fits per frame on top of the static explanation


def weigh_maps(state: SceneState, ctx: FrameContext) -> None:
    """Weigh every object map once in this frame: each candidate registered (or missed), and
    decide those that are certain (confirm, declare non-rigid or dissolve; see the module
    docstring); each confirmed object registered, for rigidity over its life
    (:func:`_weigh_object`)."""
    outcomes = {outcome.object_map.object_id: outcome for outcome in ctx.outcomes}
    for object_map in list(state.object_maps):
        outcome = outcomes.get(object_map.object_id)
        if object_map.confirmed:
            _weigh_object(state, ctx, object_map, outcome)
        else:
            _weigh_candidate(state, ctx, object_map, outcome)


def _weigh_candidate(state: SceneState, ctx: FrameContext, object_map: ObjectMap,
                     outcome: ObjectTrackingResult | None) -> None:
    """Count this frame's evidence for a candidate (rigid or not; if rigid, moved or not) and
    :func:`_decide` it."""
    candidacy = object_map.candidacy
    if candidacy.born == ctx.frame.index:
        return  # the frame that detected it is the hypothesis, not its confirmation
    if object_map.object_id in ctx.unexplained:
        object_map.nonrigid_frames += 1
        logger.debug("frame %d: candidate %d: part of its region moved without its registration following it",
                     ctx.frame.index, object_map.object_id)
    elif outcome is not None and outcome.success and ctx.registered:
        if _rigid(state, ctx, outcome):
            object_map.rigid_frames += 1
            ratio, counted = motion_evidence(state, ctx, outcome)
            if counted:
                candidacy.evidence += ratio
                candidacy.evidence_frames += 1
            significance = state.config.detection.confirm_significance
            by_matches = counted > 0 and ratio > chi2.isf(significance, POSE_PARAMETERS)
            fit, seen = evidence_misfit(state, ctx, candidacy.evidence_landmarks)
            by_landmarks = seen > 0 and fit > chi2.isf(significance, seen)
            by_free_space = in_free_space(state, ctx, object_map)
            candidacy.motion_frames += by_matches or by_landmarks or by_free_space
            logger.debug("frame %d: candidate %d rigid; its matches' log-likelihood ratio %+.1f (%d measurements), "
                         "its evidence landmarks' misfit %.1f (%d seen), in space seen empty: %s", ctx.frame.index,
                         object_map.object_id, ratio, counted, fit, seen, by_free_space)
        else:
            object_map.nonrigid_frames += 1
            logger.debug("frame %d: candidate %d: its registration does not explain it as one rigid body",
                         ctx.frame.index, object_map.object_id)
    _decide(state, ctx, object_map, outcome)


def _weigh_object(state: SceneState, ctx: FrameContext, object_map: ObjectMap,
                  outcome: ObjectTrackingResult | None) -> None:
    """Keep weighing a confirmed object registered in this frame as one rigid body (as
    candidates are, :func:`_rigid`), over its life since its detection. One that turns out
    :func:`_non_rigid` was a non-rigid mover that looked rigid while on probation (a person's
    torso, walking on): it is dropped and its region labelled dynamic, as a non-rigid candidate
    is. Frames in which it was an object keep its id in ``masks/``."""
    if outcome is None or not outcome.success or not ctx.registered:
        return
    if _rigid(state, ctx, outcome):
        object_map.rigid_frames += 1
        return
    object_map.nonrigid_frames += 1
    if _non_rigid(state, object_map):
        _drop(state, ctx, object_map, outcome, non_rigid=True)


def _non_rigid(state: SceneState, object_map: ObjectMap) -> bool:
    """Whether the map's non-rigid frames reach ``detection.confirm_frames`` and outnumber its
    rigid ones: no single rigid motion explains it."""
    return (object_map.nonrigid_frames >= state.config.detection.confirm_frames
            and object_map.nonrigid_frames > object_map.rigid_frames)


def motion_evidence(state: SceneState, ctx: FrameContext, outcome: ObjectTrackingResult) -> tuple[float, int]:
    """The log-likelihood ratio that the measurements matched both by ``outcome``'s map (as
    inliers) and by the static map are where the object map has them, not where the static map
    has them; and how many measurements (points and planes) it counts. Costs are squared
    residuals in noise sigmas, capped at the inlier threshold; the static side at the camera
    pose of ``ctx.static``, the object side at the object's registered pose."""
    config = state.config
    object_matched, object_result = outcome.best
    static_matched, static_result = ctx.static.matched, ctx.static.result
    measurements = ctx.measurements

    def costs(matched, result, transform):
        """Per point and plane measurement ``(N,)``, ``(P,)``: its cost (NaN where unmatched)."""
        points3d, points2d, angles, offsets = scaled_residuals(transform, result.correspondences, config.ransac,
                                                               config.noise)
        point_cost = np.full(len(measurements.points), np.nan)
        point_cost[matched.point_measurements] = squared_cost(np.concatenate([points3d, points2d]), config.noise)
        plane_cost = np.full(len(measurements.planes), np.nan)
        plane_cost[matched.plane_measurements] = (squared_cost(angles, config.noise)
                                                  + squared_cost(offsets, config.noise))
        return point_cost, plane_cost

    static_points, static_planes = costs(static_matched, static_result, static_result.transformation)
    object_points, object_planes = costs(object_matched, object_result, object_result.transformation)
    inlier_points = np.zeros(len(measurements.points), dtype=bool)
    point_rows = np.concatenate([object_result.inliers_point3d, object_result.inliers_point2d]).astype(bool)
    inlier_points[object_matched.point_measurements[point_rows]] = True
    inlier_planes = np.zeros(len(measurements.planes), dtype=bool)
    inlier_planes[object_matched.plane_measurements[np.asarray(object_result.inliers_plane, dtype=bool)]] = True
    both_points = inlier_points & ~np.isnan(static_points)
    both_planes = inlier_planes & ~np.isnan(static_planes)
    ratio = float((static_points[both_points] - object_points[both_points]).sum()
                  + (static_planes[both_planes] - object_planes[both_planes]).sum())
    return ratio, int(both_points.sum() + both_planes.sum())


def evidence_misfit(state: SceneState, ctx: FrameContext, landmarks: np.ndarray) -> tuple[float, int]:
    """How badly the static map explains this frame's depth where the static landmarks
    ``landmarks`` (those that showed, at detection, that a region moved) project
    (:func:`depth_misfit` at the camera pose). A surface nearer than one of them counts too:
    they were in view a moment before the detection, from about here, so what hides them now
    came there since (the object itself, moved in front of its old place)."""
    if not len(landmarks) or ctx.T_w_c is None:
        return 0.0, 0
    return depth_misfit(state, ctx, ctx.T_w_c, state.static_map.points.positions[landmarks], hidden_count=True)


def depth_misfit(state: SceneState, ctx: FrameContext, T_map_cam: np.ndarray, points: np.ndarray,
                 hidden_count: bool = False) -> tuple[float, int]:
    """How badly the frame's depth agrees with ``(L, 3)`` map points seen from ``T_map_cam``:
    the summed squared depth residuals at their projections in noise sigmas, each capped at the
    inlier threshold, and how many points it counts. Unless ``hidden_count``, only points whose
    measured depth is not nearer than theirs by more than the threshold count (one hidden
    behind something proves nothing). Were the points where the depth says, the sum would be a
    chi-square with one degree per point."""
    camera, _, inside, measured = depth_at_map_points(points, T_map_cam, ctx.frame.depth, state.intrinsics)
    z = camera[:, 2]
    threshold = depth_thresholds(z, state.config.noise)
    counted = inside & (measured > 0) & (hidden_count | (measured >= z - threshold))
    scaled = np.minimum(np.abs(measured[counted] - z[counted]) / threshold[counted], 1.0)
    return float(squared_cost(scaled, state.config.noise).sum()), int(counted.sum())


def in_free_space(state: SceneState, ctx: FrameContext, candidate: ObjectMap) -> bool:
    """Whether the candidate's region in this frame (its segments) lies in space the latest
    static keyframes saw empty, by the free-space test of detection made strict: a share of at
    least ``objects.free_space_share`` of its sampled pixels closer than the surface they saw
    by the noise margin, where they measured depth all around (``measured_only``), and, over
    the frames of its probation in which that share held, at least
    ``objects.free_space_min_pixels`` (scaled) such pixels a frame on average. Detection may
    act on a region beside a depth hole; confirmation may not: the hole may hide the surface,
    and a region's edge next to it is where a pose error moves a thin object onto the
    background behind it (redkitchen300, seed 1: a red plastic stand by the sink, seen by one
    keyframe view at the edge of a hole of 65 samples; 26-37 of its samples "seen through" in
    each frame, 13-20 of them with depth all around, fewer than the test asks for: it is
    dissolved instead of confirmed).

    The count is weighed over frames, not in each: what one view covers of a region changes
    from frame to frame, and a region wholly in free space in every frame is no less so for
    dipping below the count in one (kitchen_box120, frames 23-27 after the box's jump: 31, 27,
    23, 20 and 31 samples seen through, none agreeing, against 25 asked for: confirmed at frame
    27 when each frame had to pass alone, at frame 25 now). A frame whose share held is recorded
    in ``candidate.candidacy`` (``free_space_samples``, ``free_space_frames``), so this is asked
    once per weighed frame (:func:`_weigh_candidate`)."""
    if not state.free_space.enabled:
        return False
    segments = np.flatnonzero(ctx.assignment.segment_owner == candidate.object_id)
    if not len(segments):
        return False
    # the frame is placed on each view by the depth of its static pixels: those that keyframe
    # surfaces are built from (map_updates.not_static_pixels; made only when first counted)
    static = (lambda: ~not_static_pixels(state, ctx)) if state.config.objects.free_space_registered else None
    violations, consistent = ctx.measured_free_space_counts(state, static)
    moved, seen = int(violations[segments].sum()), int((violations[segments] + consistent[segments]).sum())
    if not (moved > 0 and moved >= state.config.objects.free_space_share * seen):
        return False
    candidacy = candidate.candidacy
    candidacy.free_space_samples += moved
    candidacy.free_space_frames += 1
    return candidacy.free_space_samples >= state.free_space.min_samples() * candidacy.free_space_frames


def _rigid(state: SceneState, ctx: FrameContext, outcome: ObjectTrackingResult) -> bool:
    """Whether the candidate's registration has no more outliers than the frame's mismatch rate
    makes likely (binomial tail at ``detection.significance``). The mismatch rate is the static
    registration's outlier ratio over the point measurements given to the static map (those of
    objects, candidates and people left out: they are outliers for another reason).

    In a frame that moved it (registered away from its last world pose, or with no such pose),
    its landmarks at the registered pose must also lie on the measured depth (chi-square at
    ``detection.confirm_significance``): a limb that moved against the torso leaves its
    landmarks over the background. Not in a frame that left it where it was
    (``outcome.at_rest``, :func:`~jsr.pipeline.object_tracking.kept_at_rest`): nothing of it
    moved, so nothing could bend, and the misfit is the landmarks' and the sensor's own error.
    Set 3 bonn_s4_two_sim's box, resting 2.4 m away after its jump, had been declared not rigid
    by that error (misfit 94-111 against bounds of 89-91 in 3 of 5 frames, while its landmarks
    fit the depth better than the static map's did: 1.7-1.9 squared sigmas each, against
    2.3-3.0)."""
    _, result = outcome.best
    static_matched, static_result = ctx.static.matched, ctx.static.result
    rows = ctx.assignment.point_owner[static_matched.point_measurements] == 0
    inliers = np.concatenate([static_result.inliers_point3d, static_result.inliers_point2d]).astype(bool)
    mismatch_rate = 1.0 - inliers[rows].sum() / max(int(rows.sum()), 1)
    rate = float(np.clip(mismatch_rate, 0.05, 0.95))
    outliers = result.num_matches - result.num_inliers
    chance = float(binom.sf(outliers - 1, result.num_matches, rate))
    few_outliers = chance >= state.config.detection.significance
    object_map = outcome.object_map
    if outcome.at_rest:
        logger.debug("frame %d: candidate %d at rest: %d of %d matches outliers (mismatch rate %.2f: chance %.3g)",
                     ctx.frame.index, object_map.object_id, outliers, result.num_matches, rate, chance)
        return few_outliers
    misfit, seen = depth_misfit(state, ctx, result.transformation,
                                object_map.points.positions[object_map.points.active])
    bound = chi2.isf(state.config.detection.confirm_significance, max(seen, 1))
    logger.debug("frame %d: candidate %d: %d of %d matches outliers (mismatch rate %.2f: chance %.3g); its landmarks' "
                 "depth misfit %.1f over %d (bound %.1f)", ctx.frame.index, object_map.object_id, outliers,
                 result.num_matches, rate, chance, misfit, seen, bound)
    return few_outliers and misfit <= bound


def _decide(state: SceneState, ctx: FrameContext, object_map: ObjectMap, outcome: ObjectTrackingResult | None) -> None:
    """Confirm, declare non-rigid or dissolve ``object_map`` (registered by ``outcome`` in this
    frame, if at all) when its evidence is certain."""
    detection = state.config.detection
    candidacy = object_map.candidacy
    age = ctx.frame.index - candidacy.born
    if candidacy.motion_frames >= detection.confirm_frames and object_map.rigid_frames > object_map.nonrigid_frames:
        object_map.candidacy = None
        # the static keyframes taken before it moved saw it where it stood as static surface
        evidence = candidacy.evidence_landmarks
        blanked = state.free_space.forget_surface(state.static_map.keyframes,
                                                  state.static_map.points.positions[evidence])
        logger.debug("frame %d: object %d's old place (%d static landmarks) blanked in %d free-space samples",
                     ctx.frame.index, object_map.object_id, len(evidence), blanked)
        ctx.report.objects_created.append(object_map.object_id)
        if object_map.last_tracked_frame == ctx.frame.index:
            ctx.report.objects_tracked.append(object_map.object_id)
        logger.info("frame %d: object %d confirmed (moved in %d of %d rigid frames; its matches' log-likelihood "
                    "ratio %.1f over %d frames)", ctx.frame.index, object_map.object_id, candidacy.motion_frames,
                    object_map.rigid_frames, candidacy.evidence, candidacy.evidence_frames)
    elif _non_rigid(state, object_map):
        _drop(state, ctx, object_map, outcome, non_rigid=True)
    elif age >= detection.confirm_window:
        # it never showed motion: static if it was seen to rest, else nothing is known of it
        _drop(state, ctx, object_map, outcome, non_rigid=False,
              static=object_map.rigid_frames >= detection.confirm_frames and not candidacy.motion_frames)


def _drop(state: SceneState, ctx: FrameContext, object_map: ObjectMap, outcome: ObjectTrackingResult | None,
          non_rigid: bool, static: bool = False) -> None:
    """Remove a candidate that was not confirmed. Non-rigid: its pixels in this frame are
    dynamic (``ctx.dynamic``) and nothing of it enters the static map. Dissolved (``static``:
    it was seen resting): its active point landmarks join the static map at their world
    positions (its last world pose), this frame's measurements given to it are static again,
    and this frame becomes a static keyframe in which those that matched its landmarks observe
    them (``ctx.given_to_static``): the landmarks are matched from the next frame on like every
    static landmark. Otherwise (hardly seen since it was detected) it is only forgotten."""
    object_id = object_map.object_id
    _forget(state, object_map, DYNAMIC if non_rigid else 0)
    assignment = ctx.assignment
    own_segments = np.flatnonzero(assignment.segment_owner == object_id).tolist()
    for owner in (assignment.point_owner, assignment.plane_owner, assignment.segment_owner):
        owner[owner == object_id] = 0
    if non_rigid:
        state.non_rigid.append(object_id)
        ctx.dynamic.extend(own_segments)
        logger.info("frame %d: %s %d is not rigid (%d of %d frames not explained as one rigid body): dynamic, "
                    "unmodelled", ctx.frame.index, "candidate" if object_map.candidacy else "object", object_id,
                    object_map.nonrigid_frames, object_map.nonrigid_frames + object_map.rigid_frames)
        return
    state.dissolved.append(object_id)
    if not static:
        logger.info("frame %d: candidate %d dropped (seen in %d of the %d frames since its detection, never moving)",
                    ctx.frame.index, object_id, object_map.rigid_frames,
                    ctx.frame.index - object_map.candidacy.born)
        return
    static_ids = _give_landmarks(state, object_map)
    if static_ids is not None:
        if outcome is not None and outcome.success and ctx.registered:
            matched, result = outcome.best
            rows = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
            given = np.full(len(ctx.measurements.points), -1, dtype=np.int64)
            given[matched.point_measurements[rows]] = static_ids[matched.point_landmarks[rows]]
            ctx.given_to_static = given if ctx.given_to_static is None else np.maximum(ctx.given_to_static, given)
            ctx.force_static_keyframe = True
    logger.info("frame %d: candidate %d dissolved (never moved beyond the noise: log-likelihood ratio %.1f over %d "
                "frames); its landmarks given to the static map", ctx.frame.index, object_id,
                object_map.candidacy.evidence, object_map.candidacy.evidence_frames)


def drop_undecided(state: SceneState) -> None:
    """At the end of a run: the candidates still on probation had too few frames to show that
    they moved; they are dissolved (listed, their landmarks given to the static map)."""
    for object_map in [m for m in state.object_maps if not m.confirmed]:
        _forget(state, object_map, 0)
        state.dissolved.append(object_map.object_id)
        _give_landmarks(state, object_map)
        logger.info("candidate %d dissolved at the end of the run (undecided)", object_map.object_id)


def _forget(state: SceneState, object_map: ObjectMap, mask_value: int) -> None:
    """Remove a candidate map from the scene: its bundle adjustment, its segments' index, and
    its pixels in the keyframes' ownership images, which become ``mask_value`` (0 static,
    DYNAMIC non-rigid)."""
    state.bundle.finish(object_map)
    state.object_maps.remove(object_map)
    state.segment_index.remove_map(object_map.object_id)
    for masks in state.keyframe_masks.values():
        masks[masks == object_map.object_id] = mask_value


def _give_landmarks(state: SceneState, object_map: ObjectMap) -> np.ndarray | None:
    """Add the active point landmarks of a dissolved candidate to the static map at their world
    positions (its last world pose): ``(L,)`` the static id of each of its landmarks (-1 for
    inactive ones), or None when it had none or no world pose."""
    points = object_map.points
    active = np.flatnonzero(points.active)
    if not len(active) or object_map.last_T_w_o is None:
        return None
    world = transform_points(object_map.last_T_w_o, points.positions[active])
    sigmas = 1.0 / np.sqrt(np.maximum(points.weights[active], 1e-12))
    static_ids = np.full(len(points), -1, dtype=np.int64)
    static_ids[active] = state.static_map.points.add(world, points.descriptors[active], sigmas, points.colors[active])
    return static_ids
