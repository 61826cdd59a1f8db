"""Loop closure of the static map: a revisited place recognised, verified and used to remove the
drift accumulated on the way back to it.

Tracking matches each frame against the landmarks of the latest keyframes only
(``matching.recent_keyframes``), so a camera that comes back to a place it mapped long ago
maps it again, a little off by the drift of the way. A new static keyframe is therefore
compared with the old ones:

1. **Recognition** (:class:`PlaceIndex`): every static keyframe gets a VLAD of its landmarks'
   descriptors, on a vocabulary of its own trained on the static map (the object
   vocabulary is trained when the first object appears, and stays independent of this).
   Candidates are the keyframes at least ``loop_closure.min_keyframe_gap`` older that share
   fewer than ``loop_closure.min_inliers / 2`` landmarks with the new one (not linked yet),
   and look at least as much like it as its own recent neighbours do (ORB-SLAM's relative
   threshold: a scene's appearance varies too much for an absolute one). The
   ``loop_closure.candidates`` most similar are verified.
2. **Verification**: the new keyframe's static point measurements are matched by descriptor
   to the landmarks of the candidate and its old neighbouring keyframes (less those the new
   keyframe observes), and registered by the RANSAC of tracking (on a random stream of its
   own, so that tracking's draws do not depend on it). At least ``loop_closure.min_inliers``
   inliers are needed (as a static keyframe needs ``keyframes.static_min_inliers``).
3. **Correction**, applied at the start of the next frame (after bundle adjustment's result,
   before tracking; as bundle adjustment, at a fixed point so that runs stay reproducible):
   the keyframe pose graph (:mod:`~jsr.pipeline.pose_graph`) spreads the disagreement
   between the loop and the chain of keyframes over the chain; landmarks move with the
   first keyframe that observed them; the new keyframe's point landmarks matched as inliers
   are fused into the old ones they duplicate (planes mapped twice stay two), so that bundle
   adjustment (the next window, which holds the old keyframes observing them fixed, and the
   run over the whole map at the end, ``bundle_adjustment.final_global``) keeps the loop
   closed; the loops closed before stay edges of the pose graph. Frames follow their
   keyframes (``current_pose``), object trajectories follow the camera, and the world poses
   kept from the loop's frame (the previous frame's, the objects' last) move with its
   keyframe.

The same recognition serves relocalisation after a loss (:func:`recognised_landmarks`): the
frame is matched to the landmarks around the keyframes that look most like it, before the
whole map (whose near-duplicate landmarks make the ratio test reject most matches).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from jsr.config import Config
from jsr.geometry import invert_transform, rotation_angle, transform_planes, transform_points
from jsr.pipeline.association import match_frame_to_map
from jsr.pipeline.maps import Map
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.pose_graph import PoseEdge, chain_edges, optimise_pose_graph
from jsr.pipeline.registration import register
from jsr.pipeline.vlad import VladVocabulary

logger = logging.getLogger(__name__)

NEIGHBOURS = 2
"""Keyframes on each side of a candidate whose landmarks are matched with it: one keyframe's
landmarks are a view's worth, its neighbours' cover what the new keyframe sees around it."""

TRAINING_DESCRIPTORS = 4000
"""Descriptors the place vocabulary is trained on, at most: it is trained inside a frame (the
first time a loop is looked for), and k-means of 64 words on 20000 descriptors takes 1.9 s,
on 4000 about 0.2 s; 64 words ranking a few hundred keyframes need no more."""

ODOMETRY_SIGMAS = (0.01, np.radians(1.0))
"""Sigmas (m, rad) of the relative pose of two consecutive keyframes in the pose graph, and of
a loop's. Only their ratio to each other matters: equal sigmas spread a loop's disagreement
evenly over the chain."""


@dataclass(frozen=True)
class LoopClosure:
    """A verified loop: static keyframe ``keyframe`` (taken at ``frame_index``) sees again the
    place of the older keyframe ``matched_keyframe``. ``T_matched_keyframe`` ``(4, 4)`` is the
    new keyframe's pose in the old one's frame, as the old landmarks place it.
    ``fused_landmarks`` ``(M, 2)``: ``[new landmark id, old landmark id]`` inlier pairs.
    ``correction_cm`` / ``correction_degrees``: how far the correction moved the new keyframe
    (filled in when it is applied)."""

    frame_index: int
    keyframe: int
    matched_keyframe: int
    similarity: float
    inliers: int
    T_matched_keyframe: np.ndarray = field(repr=False)
    fused_landmarks: np.ndarray = field(repr=False)
    correction_cm: float = float("nan")
    correction_degrees: float = float("nan")

    def summary(self) -> dict:
        """The loop as plain values (``summary.json``)."""
        return {"frame": self.frame_index, "keyframe": self.keyframe, "matched_keyframe": self.matched_keyframe,
                "similarity": round(self.similarity, 4), "inliers": self.inliers,
                "landmarks_fused": int(len(self.fused_landmarks)),
                "correction_cm": round(self.correction_cm, 3), "correction_degrees": round(self.correction_degrees, 3)}


@dataclass
class PlaceIndex:
    """VLADs of the static keyframes (row ``k``: keyframe ``k``), the vocabulary they use, the
    loop found at the latest keyframe and waiting to be applied, and the loops closed."""

    vocabulary: VladVocabulary | None = None
    vlads: list[np.ndarray] = field(default_factory=list)
    pending: LoopClosure | None = None
    closed: list[LoopClosure] = field(default_factory=list)

    def prepare(self, static_map: Map, config: Config) -> bool:
        """Train the vocabulary if it is not yet (:func:`_train_vocabulary`) and encode the
        keyframes added since the last call; False while the static map has no landmark to
        train it on."""
        if self.vocabulary is None:
            self.vocabulary = _train_vocabulary(static_map, config)
            if self.vocabulary is None:
                return False
        for keyframe in static_map.keyframes[len(self.vlads):]:
            self.vlads.append(self.vocabulary.encode(static_map.points.descriptors[keyframe.point_landmarks]))
        return True


def find_loop(index: PlaceIndex, static_map: Map, measurements: FrameMeasurements, config: Config,
              rng: np.random.Generator) -> LoopClosure | None:
    """Look for an old keyframe that the static map's newest keyframe (taken from
    ``measurements``) sees again; the verified loop, or None. ``rng``: the loops' own stream."""
    settings = config.loop_closure
    keyframes = static_map.keyframes
    newest = len(keyframes) - 1
    last_old = newest - settings.min_keyframe_gap
    if not settings.enabled or last_old < 0 or not index.prepare(static_map, config):
        return None
    vlads = np.stack(index.vlads)
    similarity = vlads @ vlads[newest]  # VLADs are unit vectors: cosine similarity
    neighbours = range(max(0, newest - config.matching.recent_keyframes), newest)
    threshold = float(min(similarity[k] for k in neighbours))
    own = np.unique(keyframes[newest].point_landmarks)
    candidates = []
    for k in np.argsort(-similarity[: last_old + 1], kind="stable"):
        if similarity[k] < threshold or len(candidates) == settings.candidates:
            break
        shared = np.intersect1d(keyframes[k].point_landmarks, own, assume_unique=False)
        if len(shared) < settings.min_inliers // 2:  # not linked yet: a loop to close
            candidates.append(int(k))
    for k in candidates:
        loop = _verify(static_map, newest, k, last_old, float(similarity[k]), measurements, config, rng)
        if loop is not None:
            return loop
    return None


def recognised_landmarks(index: PlaceIndex, static_map: Map, descriptors: np.ndarray, config: Config
                         ) -> np.ndarray | None:
    """Relocalisation by place recognition: the active landmarks of the
    ``loop_closure.candidates`` static keyframes that look most like a frame (its SIFT
    ``descriptors`` ``(N, 128)``; :func:`similar_keyframes`) and of their neighbours. None when
    loop closure is off, or the map holds no more than the ``matching.recent_keyframes`` that
    relocalisation tries first anyway."""
    keyframes = static_map.keyframes
    if not config.loop_closure.enabled or len(keyframes) <= config.matching.recent_keyframes or not len(descriptors):
        return None
    ranked = similar_keyframes(index, static_map, descriptors, config)
    if ranked is None:
        return None
    best = ranked[: config.loop_closure.candidates]
    around = sorted({j for k in best for j in range(max(0, k - NEIGHBOURS), min(len(keyframes), k + NEIGHBOURS + 1))})
    ids = np.unique(np.concatenate([keyframes[j].point_landmarks for j in around]))
    return ids[static_map.points.active[ids]]


def similar_keyframes(index: PlaceIndex, static_map: Map, descriptors: np.ndarray, config: Config
                      ) -> np.ndarray | None:
    """``(K,)`` the static keyframes' indices, the most similar in appearance (VLAD cosine) to
    ``descriptors`` ``(N, 128)`` first. Trains the place vocabulary if needed; None while the
    static map has no landmark to train it on."""
    if not index.prepare(static_map, config):
        return None
    similarity = np.stack(index.vlads) @ index.vocabulary.encode(descriptors)
    return np.argsort(-similarity, kind="stable")


def _train_vocabulary(static_map: Map, config: Config) -> VladVocabulary | None:
    """The place vocabulary, on the static map's landmarks (its own random stream: nothing
    else's draws change); None without any."""
    descriptors = static_map.points.descriptors[static_map.points.active]
    if not len(descriptors):
        return None
    settings = replace(config.vlad, training_descriptors=min(config.vlad.training_descriptors, TRAINING_DESCRIPTORS))
    vocabulary = VladVocabulary.train_on_sample(descriptors, settings, np.random.default_rng([config.seed, 4]))
    logger.debug("loop closure: place vocabulary of %d words trained on %d landmarks' descriptors",
                 vocabulary.size, len(descriptors))
    return vocabulary


def _verify(static_map: Map, newest: int, candidate: int, last_old: int, similarity: float,
            measurements: FrameMeasurements, config: Config, rng: np.random.Generator) -> LoopClosure | None:
    """Register the newest keyframe's measurements against the landmarks around ``candidate``
    (its neighbours up to keyframe ``last_old``, less the landmarks the newest keyframe
    observes: those would only confirm the pose it already has). Points only: planes are
    matched by pose, and under the keyframe's own pose they would find the planes it just
    made."""
    keyframes = static_map.keyframes
    keyframe = keyframes[newest]
    around = keyframes[max(0, candidate - NEIGHBOURS): min(candidate + NEIGHBOURS, last_old) + 1]
    landmark_ids = np.setdiff1d(np.concatenate([kf.point_landmarks for kf in around]), keyframe.point_landmarks)
    landmark_ids = landmark_ids[static_map.points.active[landmark_ids]]
    matched = match_frame_to_map(measurements, static_map, landmark_ids, None, config,
                                 point_measurements=keyframe.point_measurements)
    result = register(matched.correspondences, config.ransac, config.noise, rng)
    if not result.success or result.num_inliers < config.loop_closure.min_inliers:
        logger.debug("loop closure: keyframe %d against %d: %s", newest, candidate,
                     result.reason or f"{result.num_inliers} inliers")
        return None
    inliers = np.concatenate([result.inliers_point3d, result.inliers_point2d]).astype(bool)
    landmark_of = dict(zip(keyframe.point_measurements.tolist(), keyframe.point_landmarks.tolist()))
    pairs = [(landmark_of[m], int(old)) for m, old in zip(matched.point_measurements[inliers],
                                                        matched.point_landmarks[inliers])
             if m in landmark_of and landmark_of[m] != old]
    fused = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    T_matched_keyframe = invert_transform(keyframes[candidate].T_map_cam) @ result.transformation
    return LoopClosure(int(keyframe.frame_index), newest, candidate, similarity, int(result.num_inliers),
                       T_matched_keyframe, fused)


def close_loop(static_map: Map, loop: LoopClosure, earlier: list[LoopClosure] = ()) -> tuple[LoopClosure, np.ndarray]:
    """Apply a verified loop to the static map: the pose graph's correction of the keyframes
    (the first held fixed; the ``earlier`` loops stay edges of the graph, so that this one
    does not open them again), the landmarks moved with the keyframe that first observed
    them, and the duplicated point landmarks fused. Returns the loop with the correction it
    made, and that correction of the new keyframe ``(4, 4)`` (world frame, applied on the
    left): what poses kept in the world from the same frames (the camera's, the objects')
    need too."""
    keyframes = static_map.keyframes
    before = static_map.keyframe_poses
    sigma_translation, sigma_rotation = ODOMETRY_SIGMAS
    edges = chain_edges(before, sigma_translation, sigma_rotation)
    for closed in [*earlier, loop]:
        edges.append(PoseEdge(closed.matched_keyframe, closed.keyframe, closed.T_matched_keyframe, sigma_translation,
                              sigma_rotation))
    after = optimise_pose_graph(before, edges, fixed=0)
    corrections = after @ invert_transform(before)
    for keyframe, pose in zip(keyframes, after):
        keyframe.T_map_cam = pose
    _move_landmarks(static_map, corrections)
    fused = _fuse_landmarks(static_map, loop.fused_landmarks)
    moved = corrections[loop.keyframe]
    closed = LoopClosure(loop.frame_index, loop.keyframe, loop.matched_keyframe, loop.similarity, loop.inliers,
                         loop.T_matched_keyframe, fused,
                         correction_cm=float(np.linalg.norm(after[loop.keyframe][:3, 3] - before[loop.keyframe][:3, 3])) * 100,
                         correction_degrees=float(np.degrees(rotation_angle(moved[:3, :3]))))
    logger.info("frame %d: loop closed, keyframe %d sees the place of keyframe %d (%d inliers): moved %.1f cm / "
                "%.2f deg, %d landmarks fused", loop.frame_index, loop.keyframe, loop.matched_keyframe, loop.inliers,
                closed.correction_cm, closed.correction_degrees, len(fused))
    return closed, moved


def _first_observers(count: int, keyframe_landmarks: list[np.ndarray]) -> np.ndarray:
    """``(count,)`` the index of the first keyframe observing each landmark (-1: none)."""
    first = np.full(count, -1, dtype=np.int64)
    for k, landmarks in enumerate(keyframe_landmarks):
        landmarks = np.asarray(landmarks, dtype=np.int64)
        unseen = landmarks[first[landmarks] < 0]
        first[unseen] = k
    return first


def _move_landmarks(static_map: Map, corrections: np.ndarray) -> None:
    """Move each point and plane landmark by the correction ``(K, 4, 4)`` of the keyframe that
    first observed it (where it was made from)."""
    points, planes = static_map.points, static_map.planes
    point_anchor = _first_observers(len(points), [kf.point_landmarks for kf in static_map.keyframes])
    ids = np.flatnonzero(point_anchor >= 0)
    moved = corrections[point_anchor[ids]]
    points.positions[ids] = np.einsum("nij,nj->ni", moved[:, :3, :3], points.positions[ids]) + moved[:, :3, 3]
    plane_anchor = _first_observers(len(planes), [kf.plane_landmarks for kf in static_map.keyframes])
    for k in np.unique(plane_anchor[plane_anchor >= 0]):  # planes are few
        ids = np.flatnonzero(plane_anchor == k)
        planes.planes[ids] = transform_planes(corrections[k], planes.planes[ids])
        planes.centroids[ids] = transform_points(corrections[k], planes.centroids[ids])


def _fuse_landmarks(static_map: Map, pairs: np.ndarray) -> np.ndarray:
    """Fuse each new landmark into the old one it duplicates (``pairs`` ``(M, 2)``
    ``[new, old]``): the keyframes observing the new one observe the old one instead, and the
    new one is retired. A pair is skipped when a keyframe observes both (it would observe one
    landmark twice), or either is retired. Returns the pairs fused."""
    points = static_map.points
    observers: dict[int, set[int]] = {}
    for k, keyframe in enumerate(static_map.keyframes):
        for landmark in np.unique(keyframe.point_landmarks).tolist():
            observers.setdefault(landmark, set()).add(k)
    fused = []
    for new, old in np.asarray(pairs, dtype=np.int64).reshape(-1, 2).tolist():
        if new == old or not (points.active[new] and points.active[old]):
            continue
        seen_new, seen_old = observers.get(new, set()), observers.get(old, set())
        if seen_new & seen_old:
            continue
        for k in seen_new:
            landmarks = static_map.keyframes[k].point_landmarks
            landmarks[landmarks == new] = old
        observers[old] = seen_old | seen_new
        observers[new] = set()
        points.observations[old] += points.observations[new]
        points.retire(np.array([new]))
        fused.append((new, old))
    return np.array(fused, dtype=np.int64).reshape(-1, 2)
