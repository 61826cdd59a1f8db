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

from jsr.pipeline.association import match_frame_to_map
from jsr.pipeline.map_updates import claim_region
from jsr.pipeline.maps import ObjectMap
from jsr.pipeline.object_registration import ObjectTrackingResult
from jsr.pipeline.registration import register
from jsr.pipeline.shape_reidentification import reidentify_by_shape
from jsr.pipeline.state import FrameContext, SceneState

logger = logging.getLogger(__name__)


def reidentify(state: SceneState, ctx: FrameContext, group: list[int], group_points: np.ndarray,
               outcomes: dict[int, ObjectTrackingResult]) -> bool:
    """Register a moving region against the objects not tracked in this frame
    (:func:`lost_objects`), whole map and no prediction; on success the region is that object
    (it is tracked again). When features find none,
    :func:`~jsr.pipeline.shape_reidentification.reidentify_by_shape` tries the region's surface
    (``objects.shape_reidentify``). ``group``: the region's segments; ``group_points``: its
    point measurements no object has; ``outcomes``: this frame's object registrations by
    object id (a dormant object found gets one, added to ``ctx.outcomes`` too)."""
    measurements = ctx.measurements
    lost = lost_objects(state, ctx, group_points, outcomes)
    for object_map in lost:
        matched = match_frame_to_map(measurements, object_map, np.flatnonzero(object_map.points.active), None,
                                     state.config, state.focal_length, point_measurements=group_points)
        result = register(matched.correspondences, state.config.ransac, state.config.noise, state.streams.objects)
        if result.success:
            logger.info("frame %d: moving region %s is object %d again", measurements.frame_index, group,
                        object_map.object_id)
            claim_region(measurements, group, outcomes[object_map.object_id], matched, result, ctx.assignment)
            return True
    if state.config.objects.shape_reidentify and lost:
        return reidentify_by_shape(state, ctx, group, group_points, lost, outcomes)
    return False


def lost_objects(state: SceneState, ctx: FrameContext, group_points: np.ndarray,
                 outcomes: dict[int, ObjectTrackingResult]) -> list[ObjectMap]:
    """The objects (not candidates) not tracked in this frame that a moving region could be,
    most alike first (the best VLAD similarity of the region's point descriptors to the
    segments of each), at most ``objects.reidentify_maps`` of them. A dormant object is given
    an empty registration in ``outcomes`` and ``ctx.outcomes`` (it was not registered)."""
    lost = [m for m in state.object_maps if m.confirmed and (
        m.dormant or (outcomes.get(m.object_id) is not None and not outcomes[m.object_id].success))]
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
