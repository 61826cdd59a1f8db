"""Shape-based re-identification (beyond the paper): a moving region whose features match no
lost object, because a jump turned the object so that the camera sees sides whose landmarks no
longer match (SIFT does not survive a 50-degree change of view), found by its surface.

The region's surface is aligned to each lost object's surface model; each alignment is a pose
prediction for prediction-based matching of the region's keypoints with the object's landmarks.
Landmarks confirm an alignment; when none does, one alignment alone may decide if the surface
makes it certain (:func:`shape_alone`).
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from jsr.config import Config
from jsr.geometry import transform_points
from jsr.pipeline.association import match_frame_guided
from jsr.pipeline.free_space import DepthView
from jsr.pipeline.map_updates import claim_region
from jsr.pipeline.maps import ObjectMap
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.object_extent import SIZE_FACTOR, largest_spread
from jsr.pipeline.object_registration import ObjectTrackingResult
from jsr.pipeline.object_surfaces import SELF_TEXTURE_MIN, SURFACE_STRIDE
from jsr.pipeline.correspondences import point3d_thresholds
from jsr.pipeline.registration import register, surface_pose_result
from jsr.pipeline.state import FrameContext, SceneState
from jsr.pipeline.surface_alignment import Alignment, align_surfaces, refine_fit
from jsr.pipeline.surface_evidence import (anchors_pin, fitness, geometric_constraint, same_placement, seen_through_share,
                                           texture_agreement, texture_pin)
from jsr.pipeline.surfaces import SurfaceModel, region_model, sample_surface

logger = logging.getLogger(__name__)

SHAPE_CANDIDATES = 4  # surface alignments (best colour agreement first) tried by feature matching
# a surface fit this close to the chosen one in fitness and in texture agreement (of the own
# views') makes the surface ambiguous
SHAPE_RIVAL_FITNESS_GAP, SHAPE_RIVAL_TEXTURE_GAP = 0.1, 0.2
SHAPE_MODE_METRES, SHAPE_MODE_DEGREES = 0.1, 15.0  # fits closer than this (at the region) are one fit, not rivals
SHAPE_CONFIRM_METRES, SHAPE_CONFIRM_DEGREES = 0.2, 30.0  # landmarks confirm a surface fit within this of it
# landmark matches pin a surface fit when the motions its shape leaves free move them at least half as far as the region
ANCHOR_MIN_MOTION_SHARE = 0.5
TEXTURE_LOSS_MARGIN = 0.05  # a refinement that lowers the texture agreement (over the own views') by more is not kept
SHAPE_SEEN_THROUGH_VOXELS, SHAPE_SEEN_THROUGH_SIGMAS = 3.0, 3.0  # a model point is seen through beyond max(3 voxels, 3 sigma_Z)


def reidentify_by_shape(state: SceneState, ctx: FrameContext, group: list[int], group_points: np.ndarray,
                        lost: list[ObjectMap], outcomes: dict[int, ObjectTrackingResult], draws: int) -> bool:
    """:func:`align_to_lost_objects` up to ``draws`` times, while it keeps no alignment: its
    RANSAC draws from FPFH pairs, and once in a while no draw finds the right alignment
    (synth_two_sim s5, frame 18: 1 draw in 40 missed a cylinder that the others found, and
    the cylinder started a second map). Only the
    alignments are drawn again: the region's surface and the lost objects' models are computed
    once (their own views' texture agreement is kept by ``state.surfaces``). An object
    is not tried for a region larger than it can be (:func:`could_hold`): a person walking by
    is no lost box, and aligning a large surface is what costs. A frame runs at most
    ``objects.shape_alignments_per_frame`` (region, object) alignments (``ctx.surface_alignments``
    counts them): once they are spent, a region is not aligned, and starts a map."""
    config, frame, measurements = state.config.objects, ctx.frame, ctx.measurements
    if ctx.surface_alignments >= config.shape_alignments_per_frame:
        logger.debug("frame %d: region %s: no surface alignment left in this frame (%d run)", frame.index, group,
                     ctx.surface_alignments)
        return False
    region_mask = np.isin(measurements.segments.label_image, group)
    sample = sample_surface(frame.depth, frame.color, region_mask, state.intrinsics, SURFACE_STRIDE,
                            0.5 * config.shape_voxel)
    region = region_model(sample, config.shape_voxel)
    if region is None:
        return False
    models = [(object_map, model) for object_map in lost
              if (model := state.surfaces.model(object_map)) is not None and could_hold(model, region)]
    if not models:
        return False
    for attempt in range(draws):
        # a frame runs at most objects.shape_alignments_per_frame alignments, in the order the
        # regions and lost_objects come (most alike first when more are lost than are tried):
        # bonn_crowd_people seed 9, frame 85: two person regions, two lost person maps, two
        # draws: 8 alignments, 13.4 s
        affordable = models[:max(0, config.shape_alignments_per_frame - ctx.surface_alignments)]
        if not affordable:
            return False
        ctx.surface_alignments += len(affordable)
        if align_to_lost_objects(state, ctx, group, group_points, region, affordable, outcomes):
            if attempt:
                logger.debug("frame %d: region %s found by surface alignment at attempt %d", frame.index, group,
                             attempt + 1)
            return True
    return False


def could_hold(model: SurfaceModel, region: SurfaceModel) -> bool:
    """Whether ``region`` (camera frame) is no wider than ``SIZE_FACTOR`` times the object's
    surface ``model`` (its map frame) (:func:`~jsr.pipeline.object_extent.largest_spread`: a
    partial view always fits, a larger thing never)."""
    return largest_spread(region.points) <= SIZE_FACTOR * largest_spread(model.points)


def align_to_lost_objects(state: SceneState, ctx: FrameContext, group: list[int], group_points: np.ndarray,
                          region: SurfaceModel, models: list[tuple[ObjectMap, SurfaceModel]],
                          outcomes: dict[int, ObjectTrackingResult]) -> bool:
    """The region's surface (``region``, camera frame) aligned to each lost object's surface
    model (``models``) (:func:`~jsr.pipeline.surface_alignment.align_surfaces`); each alignment is a pose prediction
    for prediction-based matching of the region's keypoints with the object's landmarks
    (``objects.shape_radius_px``). The registration with most inliers wins if it succeeds
    with at least ``ransac.min_inliers`` inliers and stays near its prediction (20 cm, 30
    degrees): the landmarks confirm the shape, which alone fits a box four ways. Landmarks
    that register away from their fits win when two fits far apart lead them to the same
    pose (:func:`landmarks_agree_elsewhere`), or when the surface agrees with their pose
    (:func:`surface_agrees`); when such a registration's object alone has a surface fit
    at the same pose that :func:`shape_alone` accepts, that fit's pose is taken instead.

    A jump that turns the object far shows it from sides whose landmarks no longer match
    (SIFT does not survive a 50-degree change of view), so when no landmarks confirm any
    alignment, one alignment alone may still decide (:func:`shape_alone`)."""
    config, frame, measurements = state.config.objects, ctx.frame, ctx.measurements
    region_centre = region.points.mean(axis=0)  # where alignments are compared (same_placement)
    best = None
    fits = []  # (object map, its surface model, the alignments): for the surface-alone decision
    away = []  # (object map, surface fit, matches, registration) of landmarks that registered away from their fit
    for object_map, model in models:
        landmarks = np.flatnonzero(object_map.points.active)
        alignments = align_surfaces(region, model, config.shape_voxel, state.streams.objects)
        fits.append((object_map, model, alignments))
        logger.debug("frame %d: region %s (%d surface points) vs object %d (%d): %d alignments",
                     measurements.frame_index, group, len(region.points), object_map.object_id,
                     len(model.points), len(alignments))
        for alignment in alignments[:SHAPE_CANDIDATES]:
            T_o_c = alignment.T_model_region
            matched = match_frame_guided(measurements, object_map, landmarks, T_o_c, state.intrinsics, state.config,
                                         state.focal_length, point_measurements=group_points,
                                         radius_px=config.shape_radius_px)
            logger.debug("frame %d: object %d, surface alignment with fitness %.2f, colour residual %.3f: "
                         "%d landmark matches", measurements.frame_index, object_map.object_id, alignment.fitness,
                         alignment.color_residual, len(matched.point_measurements))
            if len(matched.point_measurements) < state.config.ransac.min_matches:
                continue
            result = register(matched.correspondences, state.config.ransac, state.config.noise, state.streams.objects)
            logger.debug("frame %d: object %d under that alignment: %d of %d inliers", measurements.frame_index,
                         object_map.object_id, result.num_inliers, result.num_matches)
            if not result.success or result.num_inliers < state.config.ransac.min_inliers:
                continue
            if not same_placement(T_o_c, result.transformation, region_centre, SHAPE_CONFIRM_METRES,
                                  SHAPE_CONFIRM_DEGREES):
                away.append((object_map, T_o_c, matched, result))
                continue
            if best is None or result.num_inliers > best[3].num_inliers:
                best = (object_map, T_o_c, matched, result)
    surface_only = []

    own_texture = state.surfaces.self_texture  # (kept while the object's views stay the same)

    # this frame's depth, camera frame: would a model placed by an alignment be seen through?
    view = DepthView(np.asarray(frame.depth[::SURFACE_STRIDE, ::SURFACE_STRIDE], dtype=np.float32),
                     np.eye(4), SURFACE_STRIDE)
    if best is None:
        best = landmarks_agree_elsewhere(away, region_centre)
    if best is None and away:
        model_of = {object_map.object_id: model for object_map, model, _ in fits}
        best = next((item for item in sorted(away, key=lambda item: -item[3].num_inliers)
                     if surface_agrees(state, item[0], region, model_of[item[0].object_id],
                                             item[3].transformation, view, own_texture(item[0]))), None)

    def alone(object_map: ObjectMap, model: SurfaceModel, alignments: list[Alignment]) -> Alignment | None:
        return shape_alone(state, object_map, region, model, alignments, view, own_texture(object_map),
                           landmark_anchors(state, measurements, object_map, group_points))

    if best is None and not away:
        surface_only = [(object_map, fit) for object_map, model, alignments in fits
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
            surface_only = [(object_map, fit)]
    if len(surface_only) == 1:  # two lost objects fitting as well: neither is trusted
        object_map, alignment = surface_only[0]
        T_o_c = alignment.T_model_region
        matched = match_frame_guided(measurements, object_map, np.flatnonzero(object_map.points.active), T_o_c,
                                     state.intrinsics, state.config, state.focal_length,
                                     point_measurements=group_points, radius_px=config.shape_radius_px)
        # The pose is the surface's. The landmark matches that agree with it (too few to
        # register) link the view to the old landmarks, so that bundle adjustment refines the
        # surface's pose, but only from detection.min_segment_features of them on: a match
        # or two may agree by chance. The region's other features become new landmarks.
        result = surface_pose_result(T_o_c, matched.correspondences, state.config.ransac, state.config.noise,
                                     state.config.detection.min_segment_features)
        logger.info("frame %d: moving region %s is object %d again (its surface alone: fitness %.2f, colour "
                    "residual %.3f)", measurements.frame_index, group, object_map.object_id, alignment.fitness,
                    alignment.color_residual)
        claim_region(measurements, group, outcomes[object_map.object_id], matched, result, ctx.assignment)
        outcomes[object_map.object_id].pose_from_surface = True
        return True
    if best is None:
        return False
    object_map, _, matched, result = best
    logger.info("frame %d: moving region %s is object %d again (surface alignment, %d of %d landmark matches "
                "agree)", measurements.frame_index, group, object_map.object_id, result.num_inliers,
                result.num_matches)
    claim_region(measurements, group, outcomes[object_map.object_id], matched, result, ctx.assignment)
    return True


def landmark_anchors(state: SceneState, measurements: FrameMeasurements, object_map: ObjectMap,
                     group_points: np.ndarray) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """For :func:`shape_alone`: a function of a surface fit ``T_o_c`` (object <- camera)
    giving the region's keypoints ``(K, 3)`` (camera frame) and the landmarks ``(K, 3)``
    (object frame) that prediction-based matching (``objects.shape_radius_px``) under it
    pairs within the 3D inlier threshold of that fit."""
    landmarks = np.flatnonzero(object_map.points.active)

    def anchors(T_o_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        matched = match_frame_guided(measurements, object_map, landmarks, T_o_c, state.intrinsics, state.config,
                                     state.focal_length, point_measurements=group_points,
                                     radius_px=state.config.objects.shape_radius_px)
        corr = matched.correspondences
        residuals = np.linalg.norm(transform_points(T_o_c, corr.frame_points) - corr.map_points, axis=1)
        agree = residuals <= point3d_thresholds(corr, state.config.noise)
        return corr.frame_points[agree], corr.map_points[agree]

    return anchors


def landmarks_agree_elsewhere(away: list[tuple], region_centre: np.ndarray) -> tuple | None:
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


def surface_agrees(state: SceneState, object_map: ObjectMap, region: SurfaceModel, model: SurfaceModel,
                   T_o_c: np.ndarray, view: DepthView, own_texture: float | None) -> bool:
    """Whether the object's surface agrees with a pose that its landmarks found (``T_o_c``,
    object <- camera) away from the surface fit that guided their matching: the region
    on the model (``objects.shape_min_fitness``), the model not seen through
    (``objects.shape_max_seen_through``) and its texture lining up as in
    :func:`shape_alone`. The landmarks pin the pose; the surface rules out chance
    matches (synth_two_sim seed 2: one registration 0.9 degrees off the truth, under a
    fit 83 degrees off). ``own_texture``: ``ObjectSurfaces.self_texture`` of the object."""
    config = state.config.objects
    if config.shape_min_texture_ratio <= 0 or own_texture is None or own_texture < SELF_TEXTURE_MIN:
        return False
    tree = cKDTree(model.points)
    if fitness(region, tree, T_o_c, config.shape_voxel) < config.shape_min_fitness:
        return False
    share = seen_through(state, model, T_o_c, view)
    if share is None or share > config.shape_max_seen_through:
        return False
    texture = texture_agreement(region, model, tree, T_o_c, config.shape_voxel) / own_texture
    logger.debug("object %d: landmark pose away from the surface fits: texture agreement %.2f, %.3f seen "
                 "through", object_map.object_id, texture, share)
    return texture >= config.shape_min_texture_ratio


def shape_alone(state: SceneState, object_map: ObjectMap, region: SurfaceModel, model: SurfaceModel,
                alignments: list[Alignment], view: DepthView, own_texture: float | None,
                anchors_of: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None) -> Alignment | None:
    """The alignment that the region's surface alone makes certain, or None
    (``own_texture``: ``ObjectSurfaces.self_texture`` of the object). It must
    - lie on the model: at least ``objects.shape_min_fitness`` of the region on its surface
      (the rest may show sides the map never saw: the jump turned the object);
    - leave the model where this view (``view``, the frame's depth) saw it or something in
      front of it: of the model's points that face the camera and fall where the frame
      measured depth, at most ``objects.shape_max_seen_through`` seen through
      (:func:`~jsr.pipeline.surface_evidence.seen_through_share`, which leaves out faces seen
      nearly edge-on). Measured: right fits 0-0.7%;
      wrong fits on kitchen_box120 10-90%. A fit that the view sees
      through is no rival either: the object cannot be there;
    - line up the object's texture (:func:`~jsr.pipeline.surface_evidence.texture_agreement`) at
      least ``objects.shape_min_texture_ratio`` times as well as the object's own views
      line up with each other (``ObjectSurfaces.self_texture``, which must be at least
      SELF_TEXTURE_MIN: an object of one colour has no texture to tell its fits apart).
      Texture, not the colour residual: a jump that turns the object changes its shading
      (right fits 2.2-2.4 times the own views' colour residual on kitchen_box120 and
      synth_jump, as much as a box turned over), not how its texture lines up (right fits
      0.57-0.94 of the own views' agreement, wrong ones that the view allows at most 0.32);
    - be pinned by shape (:func:`~jsr.pipeline.surface_evidence.geometric_constraint` at least
      ``objects.shape_min_constraint``): along a free motion (a box seen on one face or
      two, a cylinder turned about its axis) that the texture lines up well does not pin
      the fit (synth_two seed 5: a fit 14 degrees off along it, texture agreement 0.87 of
      the own views'), so the fit must be pinned otherwise:
      - by landmarks: ``anchors_of(T_o_c)`` gives the region's 3D keypoints (camera
        frame) and the landmarks (object frame) they match under a fit, within the inlier
        threshold; at least ``detection.min_segment_features`` of them, placed so that the
        free motions move them (:func:`pin_by_anchors`), pin the fit, refined on surface and
        landmarks together, if the matches under the refined fit still pin it and its
        texture still passes (unrefined if the refinement loses texture agreement,
        TEXTURE_LOSS_MARGIN) (synth_jump seeds 2 and 4: a box jumped and showed two faces,
        5 of 6 and 5 of 9 guided matches within 1.1 cm of the right fit, too few to
        register on their own);
      - or else by the texture's peak along the free motions
        (:func:`~jsr.pipeline.surface_evidence.texture_pin`, which moves the fit to the peak);
    - have no rival: no other fit that the view allows, as complete (fitness within 0.1)
      and elsewhere, whose texture passes the same test and lines up nearly as well (within
      0.2 of the own views' agreement). A fit that lines up clearly worse is told apart by
      the texture (redkitchen_s3_two_jump, seed 3, frame 56: a box's fits lined up 0.92
      and, 0.1 more complete and elsewhere, 0.60; refused, the box started a second map).
    The fit chosen is the one whose texture lines up best; one pinned by shape is returned
    refined by geometry alone (:func:`~jsr.pipeline.surface_alignment.refine_fit`), one pinned by
    landmarks refined on both, one pinned by texture at its texture's peak.
    """
    config = state.config.objects
    if not alignments or config.shape_min_texture_ratio <= 0:  # 0: only fits that landmarks confirm
        return None
    if own_texture is None or own_texture < SELF_TEXTURE_MIN:
        logger.debug("object %d: its own views' texture agreement %s: the surface alone is not trusted",
                     object_map.object_id, own_texture)
        return None
    tree = cKDTree(model.points)
    through = [seen_through(state, model, a.T_model_region, view) for a in alignments]
    texture = [texture_agreement(region, model, tree, a.T_model_region, config.shape_voxel) / own_texture
               for a in alignments]
    allowed = [share is None or share <= config.shape_max_seen_through for share in through]
    on_model = [k for k, a in enumerate(alignments) if a.fitness >= config.shape_min_fitness
                and through[k] is not None and allowed[k]]
    logger.debug("object %d: surface fits %s, seen through %s, texture agreement %s of its own views' %.2f",
                 object_map.object_id, [round(a.fitness, 2) for a in alignments],
                 [None if share is None else round(share, 3) for share in through],
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
              and texture[k] >= max(config.shape_min_texture_ratio, texture[chosen_index] - SHAPE_RIVAL_TEXTURE_GAP)
              and not same_placement(a.T_model_region, chosen.T_model_region, centre, SHAPE_MODE_METRES,
                                     SHAPE_MODE_DEGREES)]
    if rivals:
        return None
    constraint = geometric_constraint(region, model, tree, chosen.T_model_region, config.shape_voxel)
    logger.debug("object %d: surface fit %.2f, texture agreement %.2f of its own views', %.3f seen through, "
                 "constraint %.3f", object_map.object_id, chosen.fitness, texture[chosen_index],
                 through[chosen_index], constraint)
    if constraint >= config.shape_min_constraint:
        # Pinned by shape: point-to-plane ICP polishes the coloured ICP's fit, whose colour
        # term the turned object's shading pulls off (kitchen_box120, synth_jump: 2-6 degrees
        # before, 1-3.5 after)
        refined = refine_fit(region, model, tree, chosen.T_model_region, config.shape_voxel)
        return dataclasses.replace(chosen, T_model_region=refined)
    no_anchors = (np.zeros((0, 3)), np.zeros((0, 3)))
    anchors = no_anchors if anchors_of is None else anchors_of(chosen.T_model_region)
    if not pin_by_anchors(state.config, region, model, tree, chosen.T_model_region, anchors[0]):
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
    still = anchors_of(refined)
    if texture_refined < config.shape_min_texture_ratio or not pin_by_anchors(state.config, region, model, tree,
                                                                               refined, still[0]):
        return None
    return dataclasses.replace(chosen, T_model_region=refined)


def seen_through(state: SceneState, model: SurfaceModel, T_o_c: np.ndarray, view: DepthView) -> float | None:
    """:func:`~jsr.pipeline.surface_evidence.seen_through_share` of the object's surface model at
    ``T_o_c`` in this frame's ``view`` (beyond SHAPE_SEEN_THROUGH voxels and sigmas)."""
    return seen_through_share(model, T_o_c, view, state.intrinsics, state.config.noise,
                              SHAPE_SEEN_THROUGH_VOXELS * state.config.objects.shape_voxel,
                              SHAPE_SEEN_THROUGH_SIGMAS)


def pin_by_anchors(config: Config, region: SurfaceModel, model: SurfaceModel, tree: cKDTree, T_o_c: np.ndarray,
                   points: np.ndarray) -> bool:
    """Whether landmark matches at ``points`` ``(K, 3)`` (camera frame) pin the surface fit
    ``T_o_c``: at least ``detection.min_segment_features`` of them (fewer may agree by
    chance), and placed so that every motion the shape leaves free moves them
    (:func:`~jsr.pipeline.surface_evidence.anchors_pin`, ANCHOR_MIN_MOTION_SHARE)."""
    if len(points) < max(3, config.detection.min_segment_features):
        return False
    objects = config.objects
    return anchors_pin(region, model, tree, T_o_c, objects.shape_voxel, objects.shape_min_constraint, points,
                       ANCHOR_MIN_MOTION_SHARE)
