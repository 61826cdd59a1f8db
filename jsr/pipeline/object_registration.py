"""Registration of a frame against one object map (Caccamo et al. 2017, Section 2.2).

Every frame, each object map is registered twice:

* **frame-based**: all frame measurements against the landmarks of the map's last N
  keyframes (the whole map after the object was lost), exactly as the static map;
* **segment-based**: every frame segment's VLAD is compared with the VLADs of the object
  map's segments; the most similar pairs are registered by RANSAC on the features of the two
  segments, and a success is refined by prediction-based matching of *all* frame
  measurements against the *whole* object map under the predicted pose.

When both succeed the segment-based result wins, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jsr.config import Config
from jsr.pipeline.association import MatchedFrame, match_frame_guided, match_frame_to_map
from jsr.pipeline.maps import ObjectMap
from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.correspondences import RegistrationResult
from jsr.pipeline.registration import register
from jsr.pipeline.vlad import SegmentIndex, VladVocabulary


@dataclass
class ObjectTrackingResult:
    """The registrations of one object map in one frame (inputs of Algorithm 1).

    ``frame_matched``/``frame_result``: frame-based registration. ``segment_matched``/
    ``segment_result``: the prediction-based refinement of the best segment-based
    registration, ``seed_segments`` the frame segments whose RANSAC started it.
    ``T_o_c`` is the pose to use (segment-based when it succeeded), None if both failed.
    """

    object_map: ObjectMap
    frame_matched: MatchedFrame | None = None
    frame_result: RegistrationResult | None = None
    segment_matched: MatchedFrame | None = None
    segment_result: RegistrationResult | None = None
    seed_segments: list[int] = field(default_factory=list)
    segment_pairs_tried: int = 0
    pose_from_surface: bool = False  # re-identified by a surface alignment alone
    moved_from_rest: bool = False  # registered away from its last world pose (:func:`jsr.pipeline.object_tracking.kept_at_rest`)
    at_rest: bool = False  # kept at its last world pose, which explains its registration (the same function)

    @property
    def frame_success(self) -> bool:
        return self.frame_result is not None and self.frame_result.success

    @property
    def segment_success(self) -> bool:
        return self.segment_result is not None and self.segment_result.success

    @property
    def success(self) -> bool:
        return self.frame_success or self.segment_success

    @property
    def best(self) -> tuple[MatchedFrame, RegistrationResult] | None:
        """The registration that counts: segment-based when it succeeded, else frame-based."""
        if self.segment_success:
            return self.segment_matched, self.segment_result
        if self.frame_success:
            return self.frame_matched, self.frame_result
        return None

    @property
    def T_o_c(self) -> np.ndarray | None:
        best = self.best
        return None if best is None else best[1].transformation


def segment_vlads(vocabulary: VladVocabulary, measurements: FrameMeasurements) -> np.ndarray:
    """``(S, K * 128)`` VLAD of every segment of the frame (zero rows for featureless ones)."""
    return vocabulary.encode_groups(measurements.points.descriptors, measurements.segments.point_indices)


class ObjectRegistrar:
    """Frame- and segment-based registration of a frame against one object map."""

    def __init__(self, config: Config, intrinsics, rng: np.random.Generator, focal_length: float | None):
        self.config = config
        self.intrinsics = intrinsics
        self.rng = rng
        self.focal_length = focal_length

    def _register(self, matched: MatchedFrame, initial_guess: np.ndarray | None) -> RegistrationResult:
        return register(matched.correspondences, self.config.ransac, self.config.noise, self.rng,
                        initial_guess=initial_guess)

    def frame_based(self, measurements: FrameMeasurements, object_map: ObjectMap,
                    predicted_T_o_c: np.ndarray | None) -> tuple[MatchedFrame, RegistrationResult]:
        """Registration against the last N keyframes' landmarks (the whole map when lost)."""
        keyframe_count = None if object_map.lost else self.config.matching.recent_keyframes
        landmark_ids = object_map.recent_point_landmarks(keyframe_count)
        prediction = None if object_map.lost else predicted_T_o_c
        matched = match_frame_to_map(measurements, object_map, landmark_ids, prediction, self.config,
                                     self.focal_length)
        return matched, self._register(matched, prediction)

    def segment_based(
        self,
        measurements: FrameMeasurements,
        vlads: np.ndarray,
        object_map: ObjectMap,
        index: SegmentIndex,
        skip_segments: np.ndarray | None = None,
    ) -> tuple[MatchedFrame | None, RegistrationResult | None, list[int], int]:
        """Segment-based registration with prediction-based refinement.

        ``vlads`` ``(S, D)``: VLADs of the frame segments; ``skip_segments`` ``(S,)`` bool marks
        segments not to try (e.g. explained by the static map). Returns the refined matches and
        result (None when no pair succeeded), the seed segment and the number of pairs tried.
        """
        config = self.config
        segments = measurements.segments
        counts = np.array([len(indices) for indices in segments.point_indices], dtype=np.int64)
        usable = counts >= config.vlad.min_segment_points
        if skip_segments is not None:
            usable &= ~skip_segments
        pairs: list[tuple[float, int, tuple[int, int]]] = []
        for segment in np.flatnonzero(usable):
            for key, similarity in index.query(vlads[segment], config.vlad.candidate_segments, object_map.object_id):
                if similarity > 0:
                    pairs.append((-similarity, int(segment), key))
        pairs.sort(key=lambda item: (item[0], item[1], item[2]))
        tried = 0
        best: tuple[MatchedFrame, RegistrationResult, int] | None = None
        all_landmarks = np.flatnonzero(object_map.points.active)
        for _, segment, key in pairs[: config.vlad.max_pairs]:
            landmarks = object_map.segment_landmarks.get(key)
            if landmarks is None:
                continue
            landmarks = landmarks[object_map.points.active[landmarks]]
            if len(landmarks) < config.ransac.min_matches:
                continue
            tried += 1
            seed = match_frame_to_map(measurements, object_map, landmarks, None, config, self.focal_length,
                                      point_measurements=segments.point_indices[segment])
            seed_result = self._register(seed, None)
            if not seed_result.success:
                continue
            # Prediction-based refinement: all measurements against the whole map under the pose.
            refined = match_frame_guided(measurements, object_map, all_landmarks, seed_result.transformation,
                                         self.intrinsics, config, self.focal_length)
            refined_result = self._register(refined, seed_result.transformation)
            if not refined_result.success:
                continue
            if best is None or refined_result.num_inliers > best[1].num_inliers:
                best = (refined, refined_result, segment)
            # The pairs are sorted by similarity: a success explained by a good share of the map
            # ends the search (the paper stops at the first success).
            break
        if best is None:
            return None, None, [], tried
        return best[0], best[1], [best[2]], tried

    def register_object(
        self,
        measurements: FrameMeasurements,
        vlads: np.ndarray | None,
        object_map: ObjectMap,
        index: SegmentIndex | None,
        predicted_T_o_c: np.ndarray | None,
        skip_segments: np.ndarray | None = None,
    ) -> ObjectTrackingResult:
        """Both registrations of one object map, per ``objects.segment_registration``."""
        outcome = ObjectTrackingResult(object_map)
        outcome.frame_matched, outcome.frame_result = self.frame_based(measurements, object_map, predicted_T_o_c)
        mode = self.config.objects.segment_registration
        run_segments = vlads is not None and index is not None and (
            mode == "always" or (mode == "fallback" and not outcome.frame_success))
        if run_segments:
            matched, result, seeds, tried = self.segment_based(measurements, vlads, object_map, index, skip_segments)
            outcome.segment_matched, outcome.segment_result = matched, result
            outcome.seed_segments, outcome.segment_pairs_tried = seeds, tried
        return outcome
