"""The Reconstructor: one frame in, one :class:`~jsr.pipeline.state.FrameReport` out.

:meth:`Reconstructor.process` reads like the paper's system overview (Figure 2) and Algorithm 1;
each stage is a module of its own, handed the state that lasts across frames
(:class:`~jsr.pipeline.state.SceneState`) and what this frame computed so far
(:class:`~jsr.pipeline.state.FrameContext`):

1. extract measurements: points, planes, segments (:mod:`~jsr.pipeline.frontend`);
2. register the frame against the static map, frame-based, Section 2.2.1
   (:mod:`~jsr.pipeline.static_tracking`);
3. register it against every object map, frame- and segment-based, Section 2.2
   (:mod:`~jsr.pipeline.object_tracking`), and merge maps that turn out to be one object
   (:mod:`~jsr.pipeline.map_merging`);
4. give every measurement to one map, Algorithm 1, Section 2.3 (:mod:`~jsr.pipeline.classify`);
5. detect moving regions among the static map's outliers and start candidate object maps or
   re-identify objects, Section 2.1 (:mod:`~jsr.pipeline.moving_regions`), and confirm, dissolve
   or declare non-rigid the candidates by their evidence over frames
   (:mod:`~jsr.pipeline.confirmation`);
6. keep what may have moved out of the static map and retire static landmarks that belonged to
   an object (:mod:`~jsr.pipeline.static_hygiene`);
7. update each map whose registration succeeded, when its view is new, Section 2.4
   (:mod:`~jsr.pipeline.map_updates`);
8. let bundle adjustment refine the maps (asynchronously, applied at deterministic points).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager

import numpy as np

from jsr.config import Config
from jsr.io.camera import CameraIntrinsics
from jsr.io.dataset import Frame
from jsr.pipeline.bundle_noise import GROUPS
from jsr.pipeline.bundle_scheduler import BundleScheduler
from jsr.pipeline.loop_closure import LoopClosure, close_loop
from jsr.pipeline.classify import classify_frame
from jsr.pipeline.confirmation import drop_undecided, weigh_maps
from jsr.pipeline.free_space import FreeSpaceViews
from jsr.pipeline.frontend import FrontEnd
from jsr.pipeline.map_merging import merge_duplicates
from jsr.pipeline.map_updates import initialise, update_object, update_static
from jsr.pipeline.maps import Map, ObjectMap
from jsr.pipeline.moving_regions import detect_moving_regions
from jsr.pipeline.object_registration import ObjectRegistrar
from jsr.pipeline.object_surfaces import ObjectSurfaces
from jsr.pipeline.object_tracking import register_objects
from jsr.pipeline.object_trajectory import object_trajectory
from jsr.pipeline.ownership import detail_boxes, ownership_image, published_mask
from jsr.pipeline.state import DYNAMIC, STATIC_MAP, FrameContext, FrameReport, MapCounts, RandomStreams, SceneState
from jsr.pipeline.static_hygiene import beside_moved_objects, retire_static_landmarks, retire_vacated_landmarks
from jsr.pipeline.static_tracking import current_pose, register_static, static_inlier_landmarks

logger = logging.getLogger(__name__)


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
    Everything that lasts across frames is in :attr:`state`.
    """

    def __init__(self, config: Config, intrinsics: CameraIntrinsics, init_object_mask: np.ndarray | None = None):
        self.config = config
        self.intrinsics = intrinsics
        self.frontend = FrontEnd(config, intrinsics)
        streams = RandomStreams.from_seed(config.seed)
        # Image-space refinement needs the focal length; None keeps the 3D-distance refinement.
        focal_length = 0.5 * (intrinsics.fx + intrinsics.fy) if config.ransac.refinement == "image" else None
        self.state = SceneState(
            config=config,
            intrinsics=intrinsics,
            streams=streams,
            bundle=BundleScheduler(config.bundle_adjustment, config.noise, intrinsics.matrix),
            registrar=ObjectRegistrar(config, intrinsics, streams.objects, focal_length),
            free_space=FreeSpaceViews(config, intrinsics),
            surfaces=ObjectSurfaces(config, intrinsics),
            focal_length=focal_length,
        )
        self._init_object_mask = None if init_object_mask is None else np.asarray(init_object_mask, dtype=bool)
        if config.objects.enabled and config.objects.shape_reidentify:
            # Open3D (surface models, their alignment) takes seconds to load: here, not in the
            # first frame that re-identifies an object by its shape
            import open3d  # noqa: F401

    # what users of the results read
    @property
    def static_map(self) -> Map:
        return self.state.static_map

    @property
    def object_maps(self) -> list[ObjectMap]:
        """The objects: confirmed object maps (candidates on probation are not listed)."""
        return [m for m in self.state.object_maps if m.confirmed]

    @property
    def maps(self) -> list[Map]:
        """The static map and the objects."""
        return [self.state.static_map, *self.object_maps]

    @property
    def reports(self) -> list[FrameReport]:
        return self.state.reports

    @property
    def merged_into(self) -> dict[int, int]:
        """Object id -> the id of the map it was merged into."""
        return self.state.merged_into

    @property
    def objects_dissolved(self) -> list[int]:
        """Ids of the candidates that never moved beyond the noise (given to the static map)."""
        return self.state.dissolved

    @property
    def sensor_noise(self) -> dict[str, float] | None:
        """The sensor's noise as bundle adjustment estimated it from the static map's residuals
        (:mod:`~jsr.pipeline.bundle_noise`): per kind of residual, its sigma as a multiple of the
        configured one; None before the static map's first bundle adjustment was applied, or
        with ``bundle_adjustment.estimate_noise`` off."""
        components = self.state.bundle.noise_components
        return None if components is None else {name: float(v) for name, v in zip(GROUPS, components)}

    @property
    def loops_closed(self) -> list[LoopClosure]:
        """The static map's loops closed so far (:mod:`~jsr.pipeline.loop_closure`)."""
        return list(self.state.places.closed)

    @property
    def objects_non_rigid(self) -> list[int]:
        """Ids of the candidates no rigid motion explained (their regions are dynamic)."""
        return self.state.non_rigid

    @property
    def keyframe_masks(self) -> dict[int, np.ndarray]:
        """Frame index -> ``(H, W)`` uint8 ownership image, for the frames that gave some map a keyframe."""
        return self.state.keyframe_masks

    # ----------------------------------------------------------------------------------
    # One frame

    def process(self, frame: Frame) -> FrameReport:
        """Process one frame; never raises for a frame that simply cannot be registered."""
        state = self.state
        started = time.perf_counter()
        if not np.any(frame.depth > 0):
            # 2D matches may still place the camera, but nothing of the frame enters a map in 3D
            logger.warning("frame %d: depth image %s has no valid depth; check it (the frame can only be placed "
                           "from 2D matches)", frame.index, frame.depth_path.name)
        measurements = self.frontend.process(frame, detail_boxes(state, frame.index))
        report = FrameReport(frame.index, frame.timestamp, frame.name, tracked=False, T_w_c=None)
        ctx = FrameContext(frame, measurements, report, timings=dict(measurements.timings_ms))
        with _timed(ctx, "bundle_wait"):
            self._apply_bundle_adjustments()
        with _timed(ctx, "loop_closure"):
            self._close_pending_loop()
        if state.reports and state.camera.last_pose is not None and state.reports[-1].tracked:
            # bundle adjustment or a loop may have moved the keyframe the last pose hangs from
            state.camera.last_pose = self.current_pose(state.reports[-1])
        if not state.static_map.keyframes:
            initialise(state, ctx, self._init_object_mask)  # the world frame, the static map (and object 1)
        else:
            self._track(ctx)
        self._finish_report(ctx, started)
        return report

    def _track(self, ctx: FrameContext) -> None:
        """The stages of a frame once the static map exists (Algorithm 1 and Section 2)."""
        state, objects_on = self.state, self.config.objects.enabled
        register_static(state, ctx)
        with _timed(ctx, "objects"):
            if objects_on:
                register_objects(state, ctx)
            merge_duplicates(state, ctx)
        classify_frame(state, ctx)
        if objects_on and ctx.static is not None:
            with _timed(ctx, "detection"):
                detect_moving_regions(state, ctx)
        if objects_on:
            with _timed(ctx, "confirmation"):
                weigh_maps(state, ctx)
        state.memory.previous_static_inliers = static_inlier_landmarks(ctx.static) if ctx.registered else None
        state.memory.previous_depth = ctx.frame.depth if ctx.registered else None
        with _timed(ctx, "map_update"):
            if ctx.static is not None:
                if objects_on and self.config.objects.hold_back_beside_moved and \
                        self.config.objects.hold_back_suspects and not ctx.static.bridged:
                    ctx.suspects.extend(beside_moved_objects(state, ctx))
                update_static(state, ctx)
                retire_static_landmarks(state, ctx)
                if objects_on:
                    retire_vacated_landmarks(state, ctx.frame, ctx.report.T_w_c, ctx.static)
            for outcome in ctx.outcomes:
                update_object(state, ctx, outcome)

    def _apply_bundle_adjustments(self) -> None:
        """Bundle adjustments started after earlier keyframes ran while the front-end worked;
        they are applied here, always at this point, so runs stay reproducible."""
        state = self.state
        for map_ in state.maps:
            state.bundle.apply_finished(map_, wait=True)

    def _close_pending_loop(self) -> None:
        """Apply the loop found at the last static keyframe, if any
        (:func:`~jsr.pipeline.loop_closure.close_loop`): after bundle adjustment's result, so
        that no run is in flight on the poses it moves."""
        state, places = self.state, self.state.places
        if places.pending is None:
            return
        closed, correction = close_loop(state.static_map, places.pending, places.closed)
        places.closed.append(closed)
        places.pending = None
        # world poses kept from the loop's frame (the last one) move with its keyframe: the
        # previous frame's pose (bridging) and the objects' last poses (their prediction)
        if state.camera.previous is not None:
            measurements, pose = state.camera.previous
            state.camera.previous = (measurements, correction @ pose)
        for object_map in state.object_maps:
            if object_map.last_T_w_o is not None:
                object_map.last_T_w_o = correction @ object_map.last_T_w_o

    def _finish_report(self, ctx: FrameContext, started: float) -> None:
        """The frame's pose anchor, ownership mask and map sizes into its report; the report
        and what the next frames need of this one into the state."""
        state, frame, report = self.state, ctx.frame, ctx.report
        if report.tracked and state.static_map.keyframes:
            reference = state.static_map.keyframes[-1]
            report.reference_keyframe = reference.keyframe_id
            report.T_keyframe_cam = np.linalg.inv(reference.T_map_cam) @ report.T_w_c
        ownership = ownership_image(ctx.measurements, ctx.assignment, ctx.dynamic)
        report.mask = published_mask(ownership, state.object_maps)  # may be dropped by the caller once written
        report.dynamic_pixels = int(np.count_nonzero(report.mask == DYNAMIC))
        state.memory.previous_mask = ownership
        if report.new_keyframe or report.objects_created or any(
                m.keyframes and m.keyframes[-1].frame_index == frame.index for m in state.object_maps):
            state.keyframe_masks[frame.index] = ownership
            state.surfaces.remember(frame, ownership, state.object_maps)
        report.maps = {STATIC_MAP: MapCounts(len(state.static_map.keyframes), state.static_map.points.active_count,
                                             len(state.static_map.planes), report.tracked)}
        for object_map in self.object_maps:
            report.maps[object_map.name] = MapCounts(
                len(object_map.keyframes), object_map.points.active_count, len(object_map.planes),
                object_map.object_id in report.objects_tracked)
        ctx.timings["frame_total"] = (time.perf_counter() - started) * 1000.0
        report.timings_ms = ctx.timings
        state.reports.append(report)

    # ----------------------------------------------------------------------------------
    # Outputs

    def keyframe_pixel_mask(self, map_: Map, keyframe_id: int) -> np.ndarray | None:
        """``(H, W)`` bool: the pixels of a keyframe that were given to ``map_`` (for TSDF fusion)."""
        frame_index = map_.keyframes[keyframe_id].frame_index
        ownership = self.state.keyframe_masks.get(frame_index)
        if ownership is None:
            return None
        owner = map_.object_id if isinstance(map_, ObjectMap) else 0
        return ownership == owner

    def object_trajectory(self, object_map: ObjectMap) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps ``(F,)`` and ``T_w_o`` ``(F, 4, 4)`` of an object in the frames it was
        tracked, after bundle adjustment of both maps
        (:func:`~jsr.pipeline.object_trajectory.object_trajectory`)."""
        return object_trajectory(self.state.static_map, self.state.reports, object_map)

    def current_pose(self, report: FrameReport) -> np.ndarray | None:
        """``T_w_c`` of a tracked frame with the latest keyframe poses (after bundle adjustment)."""
        return current_pose(self.state.static_map, report)

    def finish(self) -> None:
        """Drop the candidates still undecided (dissolved), wait for and apply the last
        bundle adjustments, close the loop found at the last keyframe, then
        (``bundle_adjustment.final_global``) adjust the whole static map once."""
        drop_undecided(self.state)
        for map_ in self.state.maps:
            self.state.bundle.finish(map_)
        self._close_pending_loop()
        if self.config.bundle_adjustment.final_global:
            self.state.bundle.run_global(self.state.static_map)

    def close(self) -> None:
        """Stop the worker threads (front-end and bundle adjustment); the maps stay usable."""
        self.frontend.close()
        self.state.bundle.shutdown()


@contextmanager
def _timed(ctx: FrameContext, stage: str):
    """``with _timed(ctx, stage):`` puts the block's milliseconds into ``ctx.timings[stage]``."""
    started = time.perf_counter()
    yield
    ctx.timings[stage] = (time.perf_counter() - started) * 1000.0
