"""The surfaces of the object maps: depth samples of their keyframes' pixels.

Beyond the paper's sparse maps, every object keyframe keeps a surface sample of the pixels given
to the object (camera frame). Placed with the keyframes' bundle-adjusted poses they make the
object's surface model (shape-based re-identification after a jump that turned the object so far
that its landmarks no longer match) and span its extent together with its landmarks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from jsr.config import Config
from jsr.geometry import transform_points
from jsr.io.camera import CameraIntrinsics
from jsr.io.dataset import Frame
from jsr.pipeline.maps import ObjectMap
from jsr.pipeline.surface_evidence import fitness, texture_agreement
from jsr.pipeline.surfaces import SurfaceModel, SurfaceSample, build_model, region_model, sample_surface

SURFACE_STRIDE = 2  # object surface samples (shape-based re-identification) use every 2nd pixel and row
EXTENT_SURFACE_STEP = 8  # an object's extent takes every 8th of its surface samples (objects.extent_from_surface) ...
# ... from its last 10 keyframes: older ones carry the pose errors of earlier re-identifications,
# and a hull only grows (synth_jump s1 at 320x240, a 14470 cm3 box: the hull over all keyframes
# reached 16400 cm3 by frame 36 and 31240 by frame 57, mask precision 0.919; over the last 10,
# precision 0.981, recall the same)
EXTENT_SURFACE_KEYFRAMES = 10
SELF_TEXTURE_MIN_OVERLAP = 0.5  # own views compared only where this share of one lies on the others
SELF_TEXTURE_VIEWS = 6  # an object's latest keyframe samples that measure how its own views agree
SELF_TEXTURE_MIN = 0.2  # own views agreeing less (an object of one colour): no texture to tell fits apart (measured: kitchen_box120 0.38-0.51, synthetic 0.87-0.9)


@dataclass
class _BuiltModel:
    """An object's surface model, the views ``[(T_map_cam copy, sample), ...]`` it was built
    from, and its own views' texture agreement once computed (``textured``)."""

    views: list
    model: SurfaceModel | None
    own_texture: float | None = None
    textured: bool = False


class ObjectSurfaces:
    """Surface samples of the object keyframes: ``samples[frame index][object id]`` (camera
    frame of that frame)."""

    def __init__(self, config: Config, intrinsics: CameraIntrinsics):
        self.config = config
        self.intrinsics = intrinsics
        self.samples: dict[int, dict[int, SurfaceSample]] = {}
        # a lost object's model is asked for in every frame with a moving region, and building
        # it (normals) and its own texture take 0.1-0.3 s each: kept while its views stay the same
        self._built: dict[int, _BuiltModel] = {}

    def of(self, frame_index: int, object_id: int) -> SurfaceSample | None:
        """The sample object ``object_id`` got in frame ``frame_index``, if any."""
        return self.samples.get(frame_index, {}).get(object_id)

    def remember(self, frame: Frame, ownership: np.ndarray, object_maps: list[ObjectMap]) -> None:
        """Keep a surface sample of every object that got a keyframe (or started) in this frame
        (``ownership`` ``(H, W)`` uint8: the frame's pixels per map)."""
        if not (self.config.objects.enabled and self.config.objects.shape_reidentify):
            return
        samples = {}
        for object_map in object_maps:
            if object_map.keyframes and object_map.keyframes[-1].frame_index == frame.index:
                samples[object_map.object_id] = sample_surface(
                    frame.depth, frame.color, ownership == object_map.object_id, self.intrinsics, SURFACE_STRIDE,
                    0.5 * self.config.objects.shape_voxel)
        if samples:
            self.samples[frame.index] = samples

    def move(self, frame_indices: list[int], source_id: int, target_id: int) -> None:
        """The samples of object ``source_id`` in ``frame_indices`` become ``target_id``'s (its
        map was merged into the target's); a sample the target has in a frame wins."""
        for index in frame_indices:
            surfaces = self.samples.get(index, {})
            if source_id in surfaces:
                sample = surfaces.pop(source_id)
                surfaces.setdefault(target_id, sample)

    def _views(self, object_map: ObjectMap) -> list[tuple[np.ndarray, SurfaceSample]]:
        """``[(T_map_cam, sample), ...]`` of the object's keyframes that have a sample."""
        views = [(keyframe.T_map_cam, self.of(keyframe.frame_index, object_map.object_id))
                 for keyframe in object_map.keyframes]
        return [(T, sample) for T, sample in views if sample is not None]

    def _built_model(self, object_map: ObjectMap) -> _BuiltModel:
        """The object's model as last built, built anew when its views changed (a keyframe
        added, moved by bundle adjustment, or a sample moved by a merge)."""
        views = self._views(object_map)
        built = self._built.get(object_map.object_id)
        if built is None or len(built.views) != len(views) or not all(
                a[1] is b[1] and np.array_equal(a[0], b[0]) for a, b in zip(built.views, views)):
            model = build_model(views, self.config.objects.shape_voxel) if views else None
            built = _BuiltModel([(T.copy(), sample) for T, sample in views], model)
            self._built[object_map.object_id] = built
        return built

    def model(self, object_map: ObjectMap) -> SurfaceModel | None:
        """The object's surface in its map frame, from the samples of its keyframes (at their
        current, bundle-adjusted poses); None without enough points."""
        return self._built_model(object_map).model

    def extent_points(self, object_map: ObjectMap) -> np.ndarray:
        """``(N, 3)`` points (object map frame) whose convex hull is the object's extent: its
        active landmarks and, with ``objects.extent_from_surface``, every EXTENT_SURFACE_STEP-th
        surface sample of its last EXTENT_SURFACE_KEYFRAMES keyframes (at their current poses).

        Why the samples: a face whose keypoints have no depth (seen at a grazing angle, at
        320x240 a whole side of a box) adds no landmark, so the hull of the landmarks leaves it
        out, and once the keyframes that saw it move in have left the free-space views nothing
        gives it to the object any more."""
        landmarks = object_map.points.positions[object_map.points.active]
        if not self.config.objects.extent_from_surface:
            return landmarks
        parts = [landmarks]
        for keyframe in object_map.keyframes[-EXTENT_SURFACE_KEYFRAMES:]:
            sample = self.of(keyframe.frame_index, object_map.object_id)
            if sample is not None and len(sample.points):
                parts.append(transform_points(keyframe.T_map_cam,
                                              sample.points[::EXTENT_SURFACE_STEP].astype(np.float64)))
        return np.vstack(parts)

    def self_texture(self, object_map: ObjectMap) -> float | None:
        """:meth:`own_texture`, computed once while the object's views stay the same."""
        built = self._built_model(object_map)
        if not built.textured:
            built.own_texture, built.textured = self.own_texture(object_map), True
        return built.own_texture

    def own_texture(self, object_map: ObjectMap) -> float | None:
        """Median texture agreement (:func:`~jsr.pipeline.surface_evidence.texture_agreement`) of
        each of the object's last keyframe surface samples with the model of its other
        keyframes, at their bundle-adjusted poses: how well the object's own views line up
        (noise, shading, pose error). Only samples that mostly overlap the others count
        (SELF_TEXTURE_MIN_OVERLAP: two views that share an edge only compare little); None
        without two such views."""
        voxel = self.config.objects.shape_voxel
        views = [view for view in self._views(object_map) if len(view[1].points)][-SELF_TEXTURE_VIEWS:]
        agreements = []
        for k, (T_model_camera, sample) in enumerate(views):
            others = build_model([view for j, view in enumerate(views) if j != k], voxel)
            own = region_model(sample, voxel)
            if others is None or own is None:
                continue
            tree = cKDTree(others.points)
            if fitness(own, tree, T_model_camera, voxel) >= SELF_TEXTURE_MIN_OVERLAP:  # else: other faces
                agreements.append(texture_agreement(own, others, tree, T_model_camera, voxel))
        return float(np.median(agreements)) if agreements else None
