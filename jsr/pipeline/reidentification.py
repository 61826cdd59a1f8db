"""Re-identification: a moving region that is an object seen again, elsewhere (Caccamo et al.
2017 relocalise a lost object by registering against its whole map). The region's features are
registered against the objects not tracked in this frame (lost a moment ago, or dormant) that
look most like it; when none fits, its surface is tried (:mod:`jsr.pipeline.shape_reidentification`).

Only objects are tried, not candidates, and at most ``objects.reidentify_maps`` of them: the
work a new moving region costs does not grow with the number of maps.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from jsr.pipeline.association import match_frame_to_map
from jsr.pipeline.map_updates import claim_region
from jsr.pipeline.maps import ObjectMap
from jsr.pipeline.object_registration import ObjectTrackingResult
from jsr.pipeline.registration import register
from jsr.pipeline.shape_reidentification import reidentify_by_shape
from jsr.pipeline.object_surfaces import SURFACE_STRIDE
from jsr.pipeline.state import FrameContext, SceneState
from jsr.pipeline.surface_evidence import share_on_surface
from jsr.pipeline.surfaces import sample_surface

logger = logging.getLogger(__name__)


def reidentify(state: SceneState, ctx: FrameContext, group: list[int], group_points: np.ndarray,
               outcomes: dict[int, ObjectTrackingResult], shape_draws: int = 0) -> bool:
    """Register a moving region against the objects not tracked in this frame
    (:func:`lost_objects`), whole map and no prediction; on success the region is that object
    (it is tracked again). With ``shape_draws`` > 0, the region's surface is aligned to theirs
    instead, drawn that many times at most
    (:func:`~jsr.pipeline.shape_reidentification.reidentify_by_shape`, when
    ``objects.shape_reidentify``): the detection tries features on every region of a frame
    first, and surfaces only on the regions left, against the objects still lost. ``group``:
    the region's segments; ``group_points``: its point measurements no object has;
    ``outcomes``: this frame's object registrations by object id (a dormant object found gets
    one, added to ``ctx.outcomes`` too).

    The segments of a re-identified region that lie off its object's surface at the found pose
    (:func:`off_surface`) may be another lost object that moved beside it, in the same frame:
    each is tried as a region of its own, and stays with the first object when no other is
    found there (a face of it that no view has seen yet). redkitchen_s4_two_sim, frame 40: a
    box and a cylinder moved together; the box's surface took the region with the cylinder in
    it, and the two maps were later merged into one."""
    if not _reidentify_region(state, ctx, group, group_points, outcomes, shape_draws):
        return False
    object_id = int(ctx.assignment.segment_owner[group[0]])
    assignment, segments = ctx.assignment, ctx.measurements.segments
    for segment in off_surface(state, ctx, group, outcomes[object_id], outcomes):
        points = segments.point_indices[segment]
        points = points[assignment.point_owner[points] == object_id].astype(np.int64)
        assignment.segment_owner[segment] = 0
        assignment.point_owner[points] = 0
        if any(_reidentify_region(state, ctx, [segment], points, outcomes, draws)
               for draws in (0, state.config.objects.shape_attempts)):
            logger.info("frame %d: segment %d of region %s lies off object %d's surface: it is object %d",
                        ctx.frame.index, segment, group, object_id, int(assignment.segment_owner[segment]))
        else:  # no other object there: back to the first
            assignment.segment_owner[segment] = object_id
            assignment.point_owner[points] = object_id
    return True


def off_surface(state: SceneState, ctx: FrameContext, group: list[int], outcome: ObjectTrackingResult,
                outcomes: dict[int, ObjectTrackingResult]) -> list[int]:
    """The segments of ``group`` (claimed by ``outcome``'s object) with less than half of their
    surface samples on the object's surface model at its pose in this frame (within 1.5
    ``objects.shape_voxel``), least on it first; none unless some other object is lost
    (:func:`is_lost`, ``outcomes`` by object id) and some segment does lie on the surface."""
    object_map = outcome.object_map
    if len(group) < 2 or outcome.T_o_c is None or not any(
            m is not object_map and is_lost(m, outcomes) for m in state.object_maps):
        return []
    model = state.surfaces.model(object_map)
    if model is None:
        return []
    tree = cKDTree(model.points)
    voxel = state.config.objects.shape_voxel
    labels = ctx.measurements.segments.label_image
    off = []
    for segment in group:
        sample = sample_surface(ctx.frame.depth, ctx.frame.color, labels == segment, state.intrinsics,
                                SURFACE_STRIDE, 0.5 * voxel)
        share = share_on_surface(sample.points, tree, outcome.T_o_c, voxel) if len(sample.points) else 1.0
        if share < 0.5:
            off.append((share, int(segment)))
    # least on the surface first: the likeliest other object, found before a new face of this
    # one is tried against it (each try may cost a surface alignment)
    return [segment for _, segment in sorted(off)] if len(off) < len(group) else []


def is_lost(object_map: ObjectMap, outcomes: dict[int, ObjectTrackingResult]) -> bool:
    """Whether ``object_map`` is an object (not a candidate) not tracked in this frame: dormant,
    or its registration (in ``outcomes`` by object id) failed."""
    outcome = outcomes.get(object_map.object_id)
    return object_map.confirmed and (object_map.dormant or (outcome is not None and not outcome.success))


def _reidentify_region(state: SceneState, ctx: FrameContext, group: list[int], group_points: np.ndarray,
                       outcomes: dict[int, ObjectTrackingResult], shape_draws: int) -> bool:
    measurements = ctx.measurements
    lost = lost_objects(state, ctx, group_points, outcomes)
    if shape_draws:
        return state.config.objects.shape_reidentify and bool(lost) and reidentify_by_shape(
            state, ctx, group, group_points, lost, outcomes, shape_draws)
    for object_map in lost:
        matched = match_frame_to_map(measurements, object_map, np.flatnonzero(object_map.points.active), None,
                                     state.config, state.focal_length, point_measurements=group_points)
        result = register(matched.correspondences, state.config.ransac, state.config.noise, state.streams.objects)
        if result.success:
            logger.info("frame %d: moving region %s is object %d again", measurements.frame_index, group,
                        object_map.object_id)
            claim_region(measurements, group, outcomes[object_map.object_id], matched, result, ctx.assignment)
            return True
    return False


def lost_objects(state: SceneState, ctx: FrameContext, group_points: np.ndarray,
                 outcomes: dict[int, ObjectTrackingResult]) -> list[ObjectMap]:
    """The objects (not candidates) not tracked in this frame that a moving region could be,
    most alike first (the best VLAD similarity of the region's point descriptors to the
    segments of each), at most ``objects.reidentify_maps`` of them. A dormant object is given
    an empty registration in ``outcomes`` and ``ctx.outcomes`` (it was not registered)."""
    lost = [m for m in state.object_maps if is_lost(m, outcomes)]
    if len(lost) > state.config.objects.reidentify_maps and state.vocabulary is not None:
        vlad = state.vocabulary.encode(ctx.measurements.points.descriptors[group_points])
        similarity = {}
        for object_map in lost:
            best = state.segment_index.query(vlad, 1, object_map.object_id)
            similarity[object_map.object_id] = best[0][1] if best else 0.0
        lost = sorted(lost, key=lambda m: -similarity[m.object_id])  # stable: ties keep the map order
    lost = lost[:state.config.objects.reidentify_maps]
    for object_map in lost:
        if object_map.object_id not in outcomes:
            outcome = ObjectTrackingResult(object_map)
            outcomes[object_map.object_id] = outcome
            ctx.outcomes.append(outcome)
    return lost
