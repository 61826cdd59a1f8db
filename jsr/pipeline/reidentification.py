"""Re-identification: a moving region that is an object seen again, elsewhere (Caccamo et al.
2017 relocalise a lost object by registering against its whole map). The region's features are
registered against every lost object map; when none fits, its surface is tried
(:mod:`jsr.pipeline.shape_reidentification`).
"""

from __future__ import annotations

import logging

import numpy as np

from jsr.pipeline.association import match_frame_to_map
from jsr.pipeline.map_updates import claim_region
from jsr.pipeline.object_registration import ObjectTrackingResult
from jsr.pipeline.registration import register
from jsr.pipeline.shape_reidentification import reidentify_by_shape
from jsr.pipeline.state import FrameContext, SceneState

logger = logging.getLogger(__name__)


def reidentify(state: SceneState, ctx: FrameContext, group: list[int], group_points: np.ndarray,
               outcomes: dict[int, ObjectTrackingResult]) -> bool:
    """Register a moving region against every object map not tracked in this frame, whole
    map and no prediction; on success the region is that object (it is tracked again).
    When features find none, :func:`~jsr.pipeline.shape_reidentification.reidentify_by_shape`
    tries the region's surface (``objects.shape_reidentify``). ``group``: the region's segments;
    ``group_points``: its point measurements no object has; ``outcomes``: this frame's object
    registrations by object id."""
    measurements = ctx.measurements
    lost = [m for m in state.object_maps
            if outcomes.get(m.object_id) is not None and not outcomes[m.object_id].success]
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
