"""Maps: keyframes, point landmarks and plane landmarks (Sections 2.2 and 2.4 of the paper).

A map has its own frame: the static map's frame is the world (the first camera frame); an
object map's frame is the camera frame of the keyframe that created it. Every keyframe stores
``T_map_cam`` and the measurements it contributed; landmarks live in the map frame.
:class:`ObjectMap` is the map of one moving object, with what tracking it adds (its last
poses, its trajectory in the world, its segments for segment-based registration).

Landmarks are stored as growable structures of arrays (no per-landmark objects), so the
matcher can take ``positions[ids]`` and ``descriptors[ids]`` in one slice.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from jsr.config import KeyframesConfig
from jsr.geometry import invert_transform, rotation_angle, transform_planes, transform_points

logger = logging.getLogger(__name__)


class _GrowableArray:
    """An array that grows along axis 0 with amortised O(1) appends."""

    def __init__(self, row_shape: tuple[int, ...], dtype, capacity: int = 256):
        self._data = np.zeros((capacity,) + row_shape, dtype=dtype)
        self._size = 0

    def __len__(self) -> int:
        return self._size

    @property
    def view(self) -> np.ndarray:
        """The filled rows (a view: writes go to the storage)."""
        return self._data[: self._size]

    def extend(self, rows: np.ndarray) -> np.ndarray:
        """Append rows; returns their indices."""
        rows = np.asarray(rows, dtype=self._data.dtype).reshape((-1,) + self._data.shape[1:])
        needed = self._size + len(rows)
        if needed > len(self._data):
            grown = np.zeros((max(needed, 2 * len(self._data)),) + self._data.shape[1:], dtype=self._data.dtype)
            grown[: self._size] = self._data[: self._size]
            self._data = grown
        self._data[self._size : needed] = rows
        indices = np.arange(self._size, needed)
        self._size = needed
        return indices


class PointLandmarks:
    """3D point landmarks of a map, ``L`` rows.

    ``positions`` ``(L, 3)`` map frame; ``descriptors`` ``(L, 128)`` float32 (the latest
    observation's, which matches the current viewpoint best); ``weights`` ``(L,)`` sum of the
    inverse variances fused so far; ``observations`` ``(L,)`` count; ``colors`` ``(L, 3)``
    uint8; ``active`` ``(L,)`` False once a landmark is retired (it is then never matched).
    """

    def __init__(self):
        self._positions = _GrowableArray((3,), np.float64)
        self._descriptors = _GrowableArray((128,), np.float32)
        self._weights = _GrowableArray((), np.float64)
        self._observations = _GrowableArray((), np.int64)
        self._colors = _GrowableArray((3,), np.uint8)
        self._active = _GrowableArray((), bool)
        self._seen_through = _GrowableArray((), np.int64)

    def __len__(self) -> int:
        return len(self._positions)

    positions = property(lambda self: self._positions.view)
    descriptors = property(lambda self: self._descriptors.view)
    weights = property(lambda self: self._weights.view)
    observations = property(lambda self: self._observations.view)
    colors = property(lambda self: self._colors.view)
    active = property(lambda self: self._active.view)
    seen_through = property(lambda self: self._seen_through.view)  # (L,) frames in a row its surface was seen to be gone

    @property
    def active_count(self) -> int:
        return int(self.active.sum())

    def add(self, positions: np.ndarray, descriptors: np.ndarray, sigmas: np.ndarray, colors: np.ndarray) -> np.ndarray:
        """Create landmarks from ``(K, 3)`` map-frame positions; returns their ids ``(K,)``."""
        ids = self._positions.extend(positions)
        self._descriptors.extend(descriptors)
        self._weights.extend(1.0 / np.maximum(np.asarray(sigmas, dtype=float), 1e-4) ** 2)
        self._observations.extend(np.ones(len(ids), dtype=np.int64))
        self._colors.extend(colors)
        self._active.extend(np.ones(len(ids), dtype=bool))
        self._seen_through.extend(np.zeros(len(ids), dtype=np.int64))
        return ids

    def fuse(self, ids: np.ndarray, positions: np.ndarray, descriptors: np.ndarray, sigmas: np.ndarray) -> None:
        """Fuse new ``(K, 3)`` map-frame observations into landmarks ``ids`` (inverse-variance mean)."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return
        new_weights = 1.0 / np.maximum(np.asarray(sigmas, dtype=float), 1e-4) ** 2
        old_weights = self.weights[ids]
        total = old_weights + new_weights
        self.positions[ids] = (self.positions[ids] * old_weights[:, None] + positions * new_weights[:, None]) / total[:, None]
        self.weights[ids] = total
        self.descriptors[ids] = descriptors
        self.observations[ids] += 1

    def retire(self, ids: np.ndarray) -> None:
        """Stop using landmarks ``ids`` (kept for the record, never matched again)."""
        self.active[np.asarray(ids, dtype=np.int64)] = False


class PlaneLandmarks:
    """Plane landmarks of a map, ``Q`` rows: ``planes`` ``(Q, 4)`` as ``[n, d]`` in the map
    frame (``n . x + d = 0``), ``point_counts`` ``(Q,)`` pixels fused, ``centroids`` ``(Q, 3)``,
    ``observations`` ``(Q,)``.
    """

    def __init__(self):
        self._planes = _GrowableArray((4,), np.float64, capacity=32)
        self._point_counts = _GrowableArray((), np.float64, capacity=32)
        self._centroids = _GrowableArray((3,), np.float64, capacity=32)
        self._observations = _GrowableArray((), np.int64, capacity=32)

    def __len__(self) -> int:
        return len(self._planes)

    planes = property(lambda self: self._planes.view)
    point_counts = property(lambda self: self._point_counts.view)
    centroids = property(lambda self: self._centroids.view)
    observations = property(lambda self: self._observations.view)

    def add(self, planes: np.ndarray, centroids: np.ndarray, point_counts: np.ndarray) -> np.ndarray:
        ids = self._planes.extend(planes)
        self._centroids.extend(centroids)
        self._point_counts.extend(point_counts)
        self._observations.extend(np.ones(len(ids), dtype=np.int64))
        return ids

    def fuse(self, ids: np.ndarray, planes: np.ndarray, centroids: np.ndarray, point_counts: np.ndarray) -> None:
        """Fuse map-frame plane observations, weighted by their pixel counts."""
        for landmark_id, plane, centroid, count in zip(ids, planes, centroids, point_counts):
            old_count = self.point_counts[landmark_id]
            old = self.planes[landmark_id]
            if np.dot(old[:3], plane[:3]) < 0:
                plane = -plane  # same plane, opposite orientation
            normal = old[:3] * old_count + plane[:3] * count
            normal /= np.linalg.norm(normal)
            centroid_sum = self.centroids[landmark_id] * old_count + centroid * count
            self.centroids[landmark_id] = centroid_sum / (old_count + count)
            # the fused plane passes through the fused centroid
            self.planes[landmark_id] = np.append(normal, -normal @ self.centroids[landmark_id])
            self.point_counts[landmark_id] = old_count + count
            self.observations[landmark_id] += 1


@dataclass
class Keyframe:
    """A keyframe of one map.

    ``T_map_cam``: pose of the camera in the map frame when the keyframe was taken.
    ``point_measurements``: ``(K,)`` indices into the frame's point measurements given to this
    map; ``point_landmarks``: ``(K,)`` the landmark each of them was fused into or created.
    ``camera_points``: ``(K, 3)`` their camera-frame positions (NaN for 2D points), and
    ``pixels`` ``(K, 2)``, ``sigma_z`` ``(K,)``: what bundle adjustment needs.
    ``plane_landmarks``/``camera_planes``: the same for planes (``(P,)`` and ``(P, 4)``).
    ``T_map_cam_tracked``: ``T_map_cam`` as tracking measured it, before any bundle adjustment
    (a copy of ``T_map_cam`` unless given): how far bundle adjustment moved the keyframe.
    """

    keyframe_id: int
    frame_index: int
    timestamp: float
    T_map_cam: np.ndarray
    point_measurements: np.ndarray
    point_landmarks: np.ndarray
    camera_points: np.ndarray
    pixels: np.ndarray
    sigma_z: np.ndarray
    plane_landmarks: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    camera_planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    T_map_cam_tracked: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.T_map_cam_tracked is None:
            self.T_map_cam_tracked = np.array(self.T_map_cam, dtype=float)


class Map:
    """A map: keyframes, point landmarks and plane landmarks in one frame."""

    def __init__(self, name: str):
        self.name = name
        self.keyframes: list[Keyframe] = []
        self.points = PointLandmarks()
        self.planes = PlaneLandmarks()

    def __repr__(self) -> str:
        return f"Map({self.name!r}, {len(self.keyframes)} keyframes, {self.points.active_count} points, {len(self.planes)} planes)"

    @property
    def keyframe_poses(self) -> np.ndarray:
        """``(K, 4, 4)`` ``T_map_cam`` of all keyframes."""
        if not self.keyframes:
            return np.zeros((0, 4, 4))
        return np.stack([keyframe.T_map_cam for keyframe in self.keyframes])

    def recent_point_landmarks(self, keyframe_count: int | None) -> np.ndarray:
        """Ids of the active point landmarks seen by the last ``keyframe_count`` keyframes
        (all active landmarks when ``keyframe_count`` is None: relocalisation)."""
        if keyframe_count is None or keyframe_count >= len(self.keyframes):
            ids = np.arange(len(self.points))
        else:
            ids = np.unique(np.concatenate([kf.point_landmarks for kf in self.keyframes[-keyframe_count:]]))
        return ids[self.points.active[ids]] if len(ids) else ids.astype(np.int64)

    def needs_keyframe(self, T_map_cam: np.ndarray, config: KeyframesConfig) -> bool:
        """True if the pose is farther than the thresholds from every keyframe (Section 2.4)."""
        if not self.keyframes:
            return True
        poses = self.keyframe_poses
        relative = invert_transform(poses) @ T_map_cam
        translation = np.linalg.norm(relative[:, :3, 3], axis=1)
        rotation = np.degrees(rotation_angle(relative[:, :3, :3]))
        differs = (translation > config.translation) | (rotation > config.rotation_degrees)
        return bool(np.all(differs))

    def add_keyframe(
        self,
        frame_index: int,
        timestamp: float,
        T_map_cam: np.ndarray,
        points,
        point_indices: np.ndarray,
        matched_landmarks: np.ndarray,
        colors: np.ndarray,
        planes=None,
        plane_indices: np.ndarray | None = None,
        matched_plane_landmarks: np.ndarray | None = None,
    ) -> Keyframe:
        """Add a keyframe made of the given measurements and update the landmarks.

        ``points`` is the frame's :class:`~jsr.pipeline.measurements.PointMeasurements`;
        ``point_indices`` ``(K,)`` the measurements given to this map, ``matched_landmarks``
        ``(K,)`` their matched landmark id or -1. Matched 3D measurements are fused into their
        landmark; unmatched 3D measurements create landmarks; 2D measurements are only kept in
        the keyframe if matched (they constrain bundle adjustment). ``colors`` ``(K, 3)`` uint8.
        ``planes``/``plane_indices``/``matched_plane_landmarks`` do the same for planes.
        """
        point_indices = np.asarray(point_indices, dtype=np.int64)
        matched_landmarks = np.asarray(matched_landmarks, dtype=np.int64)
        has_depth = points.has_depth[point_indices]
        camera_points = points.points[point_indices]
        world_points = transform_points(T_map_cam, np.nan_to_num(camera_points))
        sigmas = np.maximum(points.sigma_z[point_indices], 1e-3)

        fuse = (matched_landmarks >= 0) & has_depth
        self.points.fuse(matched_landmarks[fuse], world_points[fuse], points.descriptors[point_indices[fuse]], sigmas[fuse])
        matched_2d = (matched_landmarks >= 0) & ~has_depth
        self.points.observations[matched_landmarks[matched_2d]] += 1

        create = (matched_landmarks < 0) & has_depth
        landmark_ids = matched_landmarks.copy()
        landmark_ids[create] = self.points.add(
            world_points[create], points.descriptors[point_indices[create]], sigmas[create], colors[create]
        )
        keep = landmark_ids >= 0

        plane_landmark_ids = np.zeros(0, dtype=np.int64)
        camera_planes = np.zeros((0, 4))
        if planes is not None and plane_indices is not None and len(plane_indices):
            plane_indices = np.asarray(plane_indices, dtype=np.int64)
            matched_planes = np.asarray(matched_plane_landmarks, dtype=np.int64)
            camera_planes = np.column_stack([planes.normals[plane_indices], planes.offsets[plane_indices]])
            map_planes = transform_planes(T_map_cam, camera_planes)
            map_centroids = transform_points(T_map_cam, planes.centroids[plane_indices])
            counts = planes.point_counts[plane_indices].astype(float)
            fused = matched_planes >= 0
            self.planes.fuse(matched_planes[fused], map_planes[fused], map_centroids[fused], counts[fused])
            plane_landmark_ids = matched_planes.copy()
            plane_landmark_ids[~fused] = self.planes.add(map_planes[~fused], map_centroids[~fused], counts[~fused])

        keyframe = Keyframe(
            keyframe_id=len(self.keyframes),
            frame_index=frame_index,
            timestamp=timestamp,
            T_map_cam=np.array(T_map_cam, dtype=float),
            point_measurements=point_indices[keep],
            point_landmarks=landmark_ids[keep],
            camera_points=camera_points[keep],
            pixels=points.pixels[point_indices[keep]],
            sigma_z=points.sigma_z[point_indices[keep]],
            plane_landmarks=plane_landmark_ids,
            camera_planes=camera_planes,
        )
        self.keyframes.append(keyframe)
        logger.debug("%s: keyframe %d at frame %d (%d points, %d planes)", self.name, keyframe.keyframe_id,
                     frame_index, int(keep.sum()), len(plane_landmark_ids))
        return keyframe


@dataclass
class Candidacy:
    """An object map on probation: the evidence, over the frames after the one that detected
    it (``born``), that its region moved relative to the static scene as one rigid body
    (:mod:`jsr.pipeline.confirmation`).

    ``evidence_landmarks``: the static landmarks that showed at detection that the region moved
    (matched as its outliers, or displaced where it lies). ``evidence``: summed log-likelihood
    ratios (static map against object map explanation of the measurements both matched) over the
    ``evidence_frames`` that gave any; ``motion_frames``: frames in which some test rejected that
    the static map explains the region (its rigid and non-rigid frames are counted on the map:
    :class:`ObjectMap`). ``free_space_samples``: its sampled pixels found in space the static
    keyframes saw empty, summed over the ``free_space_frames`` in which most of the region lay
    there (:func:`~jsr.pipeline.confirmation.in_free_space`).
    """

    born: int
    evidence_landmarks: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    evidence: float = 0.0
    evidence_frames: int = 0
    motion_frames: int = 0
    free_space_samples: int = 0
    free_space_frames: int = 0


class ObjectMap(Map):
    """The map of one moving object (landmarks in the object frame).

    ``segment_landmarks[(keyframe_id, segment)]`` holds the point landmark ids of each segment
    the object received in its keyframes: the units of segment-based registration, whose VLADs
    live in the scene state's :class:`~jsr.pipeline.vlad.SegmentIndex`.
    ``trajectory`` lists ``(frame_index, timestamp, T_w_o)`` of the frames it was tracked in;
    ``trajectory_anchors[frame_index]`` the map's latest keyframe when that frame was tracked
    and its ``T_map_cam`` then ``(4, 4)``: how far bundle adjustment moved the map since.
    ``candidacy``: while not None, the map is a candidate that must still be confirmed (it
    becomes an object) or is dissolved; ``dormant``: not seen for a while, so it is no longer
    registered every frame, only tried when a new moving region could be it.
    ``rigid_frames``, ``nonrigid_frames``: the frames since its detection in which its
    registration did, or did not, explain it as one rigid body, as a candidate and as an object
    (:func:`~jsr.pipeline.confirmation.weigh_maps`).
    """

    def __init__(self, object_id: int, created_at_frame: int, candidacy: Candidacy | None = None):
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
        self.candidacy = candidacy
        self.dormant = False
        self.rigid_frames = 0
        self.nonrigid_frames = 0

    @property
    def confirmed(self) -> bool:
        """An object: its candidacy, if it had one, ended in confirmation."""
        return self.candidacy is None

    def record_pose(self, frame_index: int, timestamp: float, T_w_o: np.ndarray) -> None:
        """Append ``T_w_o`` ``(4, 4)`` to the trajectory, anchored to the latest keyframe as it
        is now (what bundle adjustment does to the map from now on applies to this pose)."""
        self.trajectory.append((frame_index, timestamp, T_w_o))
        if self.keyframes:
            latest = self.keyframes[-1]
            self.trajectory_anchors[frame_index] = (latest, latest.T_map_cam.copy())


def map_folder(map_: Map) -> str:
    """Folder of a map inside the results: ``static`` or ``objects/object_K``."""
    return f"objects/{map_.name}" if isinstance(map_, ObjectMap) else map_.name
