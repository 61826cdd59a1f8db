"""Object pose errors (in the camera frame, up to a constant object-frame offset) and the
matching of estimated object maps to true objects."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
from scipy.spatial.transform import Rotation

from jsr.evaluate.stats import angle_degrees, matrix, number, rms
from jsr.geometry import invert_transform, make_transform

MIN_MATCH_FRAMES = 3
"""An estimated object is matched to a true object only when it follows it in at least this many frames."""

FOLLOW_MAX_CM = 5.0
FOLLOW_MAX_DEG = 10.0
"""An estimated map follows a true object in a frame where its pose error there (after the
constant offset) is at most this; those are the frames of the object it covers. Well above the
errors of a map that tracks the object (its targets are 2 cm and 2 degrees), well below those
of a map of something else (a jump moves an object by tens of centimetres)."""

EXTRA_MAP_MAX_CM = 3.0
EXTRA_MAP_MAX_DEG = 3.0
"""A map left out of the one-to-one matching that follows a matched true object this closely
(median over its frames) is a further map of that object (one object seen as several maps)."""


@dataclass
class ObjectPoseError:
    """Pose error of estimated object ``estimated_id`` against true object ``true_id``.

    Errors are those of the object pose in the camera frame, after removing the constant
    ``offset`` ``X`` between the estimated and the true object frames
    (``C_est_i ~= C_gt_i X``); translation errors are those of the true object's origin (its
    centre). ``offset`` is ``X`` (4x4).
    """

    estimated_id: int
    true_id: int
    frames: int
    translation_rmse_cm: float
    translation_median_cm: float
    rotation_rmse_deg: float
    rotation_median_deg: float
    offset: np.ndarray
    translation_max_cm: float = math.nan
    rotation_max_deg: float = math.nan
    translation_errors_cm: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    rotation_errors_deg: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    frames_followed: int = 0
    """Common frames whose error is within ``FOLLOW_MAX_CM`` and ``FOLLOW_MAX_DEG``."""

    def as_dict(self) -> dict:
        return {
            "estimated_id": int(self.estimated_id),
            "true_id": int(self.true_id),
            "frames": int(self.frames),
            "frames_followed": int(self.frames_followed),
            "translation_rmse_cm": number(self.translation_rmse_cm),
            "translation_median_cm": number(self.translation_median_cm),
            "translation_max_cm": number(self.translation_max_cm),
            "rotation_rmse_deg": number(self.rotation_rmse_deg),
            "rotation_median_deg": number(self.rotation_median_deg),
            "rotation_max_deg": number(self.rotation_max_deg),
            "offset": matrix(self.offset),
        }


def object_pose_error(
    est_camera: np.ndarray,
    est_object: np.ndarray,
    gt_camera: np.ndarray,
    gt_object: np.ndarray,
    estimated_id: int = 0,
    true_id: int = 0,
) -> ObjectPoseError:
    """Object pose error from associated ``(M, 4, 4)`` stacks (one row per common frame).

    ``est_camera``/``est_object`` are ``T_w_c``/``T_w_o`` in the estimate's world,
    ``gt_camera``/``gt_object`` in the ground-truth world. The object pose in the camera frame,
    ``C_i = inv(T_w_c_i) T_w_o_i``, does not depend on the world, and the estimated object frame
    is only defined up to a constant offset ``X``: ``C_est_i ~= C_gt_i X``. The translation
    error is measured where the object is, at the true object's origin (its centre, for the
    synthetic sequences and kitchen_box120), not at the estimated frame's origin: jsr puts that
    origin at the camera of the detecting frame, a metre or more away, where a 1-degree
    rotation error alone would move it by 2-3 cm. With ``B_i = inv(C_est_i) C_gt_i``, the true
    object frame in the estimated one (``= inv(X)`` for a perfect estimate):

    * ``R(inv(X))`` is the chordal L2 mean of the rotations of ``B_i``;
    * the estimated centre is ``t(C_est_i inv(X))``; its distance to the true centre
      ``t(C_gt_i)`` is ``|t(B_i) - t(inv(X))|`` whatever ``R(inv(X))``, so ``t(inv(X))`` is
      the per-axis median of the ``t(B_i)`` (robust to a few lost frames).

    A perfect estimate (``B_i = inv(X)`` for all ``i``) thus gives ``X`` back and zero error.
    Per frame, the translation error is that centre distance, and the rotation error the
    angle of ``D_i = inv(C_gt_i X) C_est_i``.
    """
    stacks = [
        np.asarray(poses, dtype=float).reshape(-1, 4, 4) for poses in (est_camera, est_object, gt_camera, gt_object)
    ]
    if len({len(poses) for poses in stacks}) != 1:
        raise ValueError("object_pose_error needs the same number of poses in every stack")
    if len(stacks[0]) == 0:
        raise ValueError("object_pose_error needs at least one common frame")
    est_camera, est_object, gt_camera, gt_object = stacks
    in_camera_est = invert_transform(est_camera) @ est_object
    in_camera_gt = invert_transform(gt_camera) @ gt_object
    true_in_estimated = invert_transform(in_camera_est) @ in_camera_gt  # B_i
    rotation = Rotation.from_matrix(true_in_estimated[:, :3, :3]).mean().as_matrix()
    centre = np.median(true_in_estimated[:, :3, 3], axis=0)  # the true centre in the estimated frame
    offset = invert_transform(make_transform(rotation, centre))
    predicted = in_camera_gt @ offset
    translation_errors = np.linalg.norm(true_in_estimated[:, :3, 3] - centre, axis=1) * 100.0
    residuals = invert_transform(predicted) @ in_camera_est
    rotation_errors = angle_degrees(residuals[:, :3, :3])
    return ObjectPoseError(
        estimated_id=int(estimated_id),
        true_id=int(true_id),
        frames=len(translation_errors),
        translation_rmse_cm=rms(translation_errors),
        translation_median_cm=float(np.median(translation_errors)),
        rotation_rmse_deg=rms(rotation_errors),
        rotation_median_deg=float(np.median(rotation_errors)),
        offset=offset,
        translation_max_cm=float(np.max(translation_errors)),
        rotation_max_deg=float(np.max(rotation_errors)),
        translation_errors_cm=translation_errors,
        rotation_errors_deg=rotation_errors,
        frames_followed=int(np.count_nonzero((translation_errors <= FOLLOW_MAX_CM)
                                             & (rotation_errors <= FOLLOW_MAX_DEG))),
    )


def match_objects(errors: Iterable[ObjectPoseError], min_frames: int = MIN_MATCH_FRAMES) -> list[ObjectPoseError]:
    """Greedy one-to-one matching: a true object goes to the map that follows it in the most
    frames (:attr:`ObjectPoseError.frames_followed`, at least ``min_frames``), ties to the lower
    median translation error. An object split into a long map and a short one is so measured
    on the long one (the short one can still be pooled by :func:`pool_extra_maps`)."""
    candidates = sorted(
        (error for error in errors if error.frames_followed >= min_frames),
        key=lambda error: (-error.frames_followed, error.translation_median_cm, error.estimated_id, error.true_id),
    )
    used_estimated, used_true, matches = set(), set(), []
    for error in candidates:
        if error.estimated_id in used_estimated or error.true_id in used_true:
            continue
        used_estimated.add(error.estimated_id)
        used_true.add(error.true_id)
        matches.append(error)
    return matches


def pool_extra_maps(errors: Iterable[ObjectPoseError], matches: list[ObjectPoseError],
                    min_frames: int = MIN_MATCH_FRAMES) -> dict[int, list[ObjectPoseError]]:
    """``true id -> [errors of its further maps]``: estimated maps not in ``matches`` whose
    median error against a matched true object is at most ``EXTRA_MAP_MAX_CM`` and
    ``EXTRA_MAP_MAX_DEG`` over at least ``min_frames`` frames (the closest such object). A
    tool that splits one object into several maps then gets the tracked frames of all of
    them, and their masks, counted for that object."""
    matched_estimated = {match.estimated_id for match in matches}
    matched_true = {match.true_id for match in matches}
    best: dict[int, ObjectPoseError] = {}
    for error in errors:
        if (error.estimated_id in matched_estimated or error.true_id not in matched_true
                or error.frames < min_frames or error.translation_median_cm > EXTRA_MAP_MAX_CM
                or error.rotation_median_deg > EXTRA_MAP_MAX_DEG):
            continue
        current = best.get(error.estimated_id)
        if current is None or (error.translation_median_cm, error.true_id) < (current.translation_median_cm,
                                                                             current.true_id):
            best[error.estimated_id] = error
    pooled: dict[int, list[ObjectPoseError]] = {}
    for estimated_id in sorted(best):
        pooled.setdefault(best[estimated_id].true_id, []).append(best[estimated_id])
    return pooled
