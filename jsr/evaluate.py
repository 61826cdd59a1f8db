"""Evaluation of a results folder against a sequence's ground truth.

Results folder (written by ``jsr reconstruct``)::

    RESULTS/camera.tum                          T_w_c of every tracked frame (world = first camera frame)
    RESULTS/objects/object_<K>/trajectory.tum   T_w_o of estimated object K where it was tracked (same world)
    RESULTS/masks/<colour stem>.png             optional, uint8: 0 static, K pixels given to object K

Sequence folder (TUM layout)::

    SEQ/groundtruth.txt             T_w_c in the ground-truth world
    SEQ/objects/object_<k>.txt      optional, T_w_o of true object k (same world), one per frame
    SEQ/labels/<colour stem>.png    optional, 0 static, k object k
    SEQ/rgb.txt                     colour timestamps and file names (maps stems to timestamps)

Metrics:

* camera: absolute trajectory error (ATE) of the positions after a rigid (SE(3), no scale)
  Umeyama alignment, relative pose error (RPE) over consecutive associated frames, and
  tracking coverage.
* objects: per estimated/true object pair, the pose error of the object *in the camera
  frame* (this removes the unknown alignment of the two worlds) after removing the constant
  offset between the estimated and the true object frames, its translation measured at the
  true object's origin (its centre); estimated objects are matched
  greedily to true ones by lowest median translation error.
* masks: pixel precision and recall of "moving object" against the labels, overall and per
  matched object pair.

Everything :func:`evaluate_run` returns is plain Python (dict, list, int, float, str, None),
so ``json.dumps(metrics, allow_nan=False)`` works; undefined values (e.g. a precision with no
predicted pixel) are ``None``.
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from jsr.errors import InputError
from jsr.geometry import invert_transform, make_transform, transform_points, umeyama_alignment
from jsr.io.dataset import associate_timestamps, read_image_list
from jsr.io.trajectory import read_tum_trajectory
from jsr.io.writers import write_json

logger = logging.getLogger(__name__)

VISIBLE_PIXEL_THRESHOLD = 2000
"""A true object counts as visible in a frame whose label image has more than this many of its pixels."""

MIN_MATCH_FRAMES = 3
"""An estimated object is matched to a true object only over at least this many common frames."""

EXTRA_MAP_MAX_CM = 3.0
EXTRA_MAP_MAX_DEG = 3.0
"""A map left out of the one-to-one matching that follows a matched true object this closely
(median over its frames) is a further map of that object (one object seen as several maps)."""

_TRUE_OBJECT_FILE = re.compile(r"^object_(\d+)\.txt$")
_ESTIMATED_OBJECT_FOLDER = re.compile(r"^object_(\d+)$")


# --------------------------------------------------------------------------------------
# Plain-number helpers


def _number(value: float) -> float | None:
    """A JSON-safe float: NaN and infinities become ``None``."""
    value = float(value)
    return value if math.isfinite(value) else None


def _ratio(numerator: float, denominator: float) -> float | None:
    return float(numerator) / float(denominator) if denominator > 0 else None


def _matrix(transform: np.ndarray) -> list[list[float]]:
    return [[float(value) for value in row] for row in np.asarray(transform, dtype=float)]


def _angle_degrees(rotations: np.ndarray) -> np.ndarray:
    """Rotation angles in degrees of ``(N, 3, 3)`` rotations, accurate also near 0 and 180 degrees.

    ``atan2(sin, cos)`` with ``sin`` from the skew-symmetric part and ``cos`` from the trace;
    ``arccos`` of the trace alone loses half the digits for small angles (~1e-6 degree noise).
    """
    rotations = np.asarray(rotations, dtype=float)
    skew = rotations - np.swapaxes(rotations, -1, -2)
    sine = 0.5 * np.linalg.norm(np.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1), axis=-1)
    cosine = 0.5 * (np.trace(rotations, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sine, cosine))


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else math.nan


# --------------------------------------------------------------------------------------
# Association and camera trajectory metrics


def associate_poses(
    est_timestamps: np.ndarray,
    est_poses: np.ndarray,
    gt_timestamps: np.ndarray,
    gt_poses: np.ndarray,
    max_difference: float = 0.02,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pair estimated and ground-truth poses by nearest timestamp (one-to-one, TUM rule).

    Returns ``(timestamps (M,), est (M, 4, 4), gt (M, 4, 4))`` in the order of the estimate;
    ``timestamps`` are those of the estimate.
    """
    est_timestamps = np.asarray(est_timestamps, dtype=float).reshape(-1)
    gt_timestamps = np.asarray(gt_timestamps, dtype=float).reshape(-1)
    est_poses = np.asarray(est_poses, dtype=float).reshape(-1, 4, 4)
    gt_poses = np.asarray(gt_poses, dtype=float).reshape(-1, 4, 4)
    if len(est_timestamps) != len(est_poses) or len(gt_timestamps) != len(gt_poses):
        raise ValueError("associate_poses needs one timestamp per pose")
    pairs = associate_timestamps(est_timestamps, gt_timestamps, max_difference)
    if not pairs:
        return np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 4, 4))
    est_index = np.array([i for i, _ in pairs])
    gt_index = np.array([j for _, j in pairs])
    return est_timestamps[est_index], est_poses[est_index], gt_poses[gt_index]


@dataclass
class TrajectoryError:
    """Absolute trajectory error, metres. ``alignment`` is ``T_gt_est`` (4x4) applied to the estimate."""

    rmse: float
    mean: float
    median: float
    max: float
    count: int
    alignment: np.ndarray

    def as_dict(self) -> dict:
        return {
            "rmse": _number(self.rmse),
            "mean": _number(self.mean),
            "median": _number(self.median),
            "max": _number(self.max),
            "count": int(self.count),
            "alignment": _matrix(self.alignment),
        }


def absolute_trajectory_error(est_poses: np.ndarray, gt_poses: np.ndarray) -> TrajectoryError:
    """ATE of associated ``(M, 4, 4)`` poses after a rigid Umeyama alignment of the positions.

    The error of a frame is the distance between its aligned estimated position and the true
    one. Needs ``M >= 3``.
    """
    est_positions = np.asarray(est_poses, dtype=float).reshape(-1, 4, 4)[:, :3, 3]
    gt_positions = np.asarray(gt_poses, dtype=float).reshape(-1, 4, 4)[:, :3, 3]
    if len(est_positions) != len(gt_positions):
        raise ValueError(f"{len(est_positions)} estimated but {len(gt_positions)} true poses")
    alignment, _ = umeyama_alignment(est_positions, gt_positions, with_scale=False)
    errors = np.linalg.norm(transform_points(alignment, est_positions) - gt_positions, axis=1)
    return TrajectoryError(
        rmse=_rms(errors),
        mean=float(np.mean(errors)),
        median=float(np.median(errors)),
        max=float(np.max(errors)),
        count=len(errors),
        alignment=alignment,
    )


@dataclass
class RelativePoseError:
    """Relative pose error over frame pairs ``(i, i + delta)``: RMSE in metres and degrees."""

    translation_rmse: float
    rotation_rmse: float
    count: int
    delta: int

    def as_dict(self) -> dict:
        return {
            "translation_rmse": _number(self.translation_rmse),
            "rotation_rmse": _number(self.rotation_rmse),
            "count": int(self.count),
            "delta": int(self.delta),
        }


def relative_pose_error(est_poses: np.ndarray, gt_poses: np.ndarray, delta: int = 1) -> RelativePoseError:
    """RPE of associated ``(M, 4, 4)`` poses over index pairs ``(i, i + delta)``.

    ``E_i = inv(inv(G_i) G_j) inv(P_i) P_j``; translation error ``|t(E_i)|``, rotation error
    the angle of ``E_i``. ``delta`` counts associated frames, not seconds: frames the tracker
    dropped make a pair span more time. With fewer than ``delta + 1`` poses the RMSEs are NaN
    and ``count`` is 0.
    """
    if delta < 1:
        raise ValueError("delta must be >= 1")
    est = np.asarray(est_poses, dtype=float).reshape(-1, 4, 4)
    gt = np.asarray(gt_poses, dtype=float).reshape(-1, 4, 4)
    if len(est) != len(gt):
        raise ValueError(f"{len(est)} estimated but {len(gt)} true poses")
    if len(est) <= delta:
        return RelativePoseError(math.nan, math.nan, 0, delta)
    est_motion = invert_transform(est[:-delta]) @ est[delta:]
    gt_motion = invert_transform(gt[:-delta]) @ gt[delta:]
    errors = invert_transform(gt_motion) @ est_motion
    translation = np.linalg.norm(errors[:, :3, 3], axis=1)
    rotation = _angle_degrees(errors[:, :3, :3])
    return RelativePoseError(_rms(translation), _rms(rotation), len(errors), delta)


# --------------------------------------------------------------------------------------
# Object poses


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

    def as_dict(self) -> dict:
        return {
            "estimated_id": int(self.estimated_id),
            "true_id": int(self.true_id),
            "frames": int(self.frames),
            "translation_rmse_cm": _number(self.translation_rmse_cm),
            "translation_median_cm": _number(self.translation_median_cm),
            "translation_max_cm": _number(self.translation_max_cm),
            "rotation_rmse_deg": _number(self.rotation_rmse_deg),
            "rotation_median_deg": _number(self.rotation_median_deg),
            "rotation_max_deg": _number(self.rotation_max_deg),
            "offset": _matrix(self.offset),
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
    rotation_errors = _angle_degrees(residuals[:, :3, :3])
    return ObjectPoseError(
        estimated_id=int(estimated_id),
        true_id=int(true_id),
        frames=len(translation_errors),
        translation_rmse_cm=_rms(translation_errors),
        translation_median_cm=float(np.median(translation_errors)),
        rotation_rmse_deg=_rms(rotation_errors),
        rotation_median_deg=float(np.median(rotation_errors)),
        offset=offset,
        translation_max_cm=float(np.max(translation_errors)),
        rotation_max_deg=float(np.max(rotation_errors)),
        translation_errors_cm=translation_errors,
        rotation_errors_deg=rotation_errors,
    )


def match_objects(errors: Iterable[ObjectPoseError], min_frames: int = MIN_MATCH_FRAMES) -> list[ObjectPoseError]:
    """Greedy one-to-one matching by lowest median translation error (pairs with >= ``min_frames``)."""
    candidates = sorted(
        (error for error in errors if error.frames >= min_frames),
        key=lambda error: (error.translation_median_cm, error.estimated_id, error.true_id),
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


def _lookup(reference: np.ndarray, other: np.ndarray, max_difference: float) -> np.ndarray:
    """For each reference timestamp, the index of its associated ``other`` timestamp, or -1."""
    index = np.full(len(reference), -1, dtype=int)
    for i, j in associate_timestamps(reference, other, max_difference):
        index[i] = j
    return index


# --------------------------------------------------------------------------------------
# Masks


def _empty_counts() -> dict[str, int]:
    return {"true_positive": 0, "predicted": 0, "actual": 0}


def _counts_to_metrics(counts: dict[str, int]) -> dict:
    true_positive, predicted, actual = counts["true_positive"], counts["predicted"], counts["actual"]
    union = predicted + actual - true_positive
    return {
        "precision": _ratio(true_positive, predicted),
        "recall": _ratio(true_positive, actual),
        "iou": _ratio(true_positive, union),
        "true_positive_pixels": int(true_positive),
        "predicted_pixels": int(predicted),
        "actual_pixels": int(actual),
    }


def _accumulate(counts: dict[str, int], predicted: np.ndarray, actual: np.ndarray) -> None:
    counts["true_positive"] += int(np.count_nonzero(predicted & actual))
    counts["predicted"] += int(np.count_nonzero(predicted))
    counts["actual"] += int(np.count_nonzero(actual))


def mask_precision_recall(
    mask_pairs: Iterable[tuple[np.ndarray, np.ndarray]], matches: Iterable[tuple[int, int]] = ()
) -> dict:
    """Pixel precision/recall of estimated masks against label images.

    ``mask_pairs`` yields ``(mask, label)`` integer images of the same shape (0 static, else an
    object id). Overall: "object" pixels ``mask != 0`` against ``label != 0``. For each
    ``(estimated K, true k)`` in ``matches``: ``mask == K`` against ``label == k``. Counts are
    summed over all frames before dividing (pixel-level, not a mean of per-frame scores).
    Returns ``{"frames", "precision", "recall", "iou", ..._pixels, "pairs": [...]}``; a ratio
    with a zero denominator is ``None``.
    """
    matches = [(int(estimated), int(true)) for estimated, true in matches]
    overall = _empty_counts()
    per_pair = {pair: _empty_counts() for pair in matches}
    frames = 0
    for mask, label in mask_pairs:
        mask, label = np.asarray(mask), np.asarray(label)
        if mask.shape != label.shape:
            raise ValueError(f"mask shape {mask.shape} differs from label shape {label.shape}")
        frames += 1
        _accumulate(overall, mask != 0, label != 0)
        for (estimated, true), counts in per_pair.items():
            _accumulate(counts, mask == estimated, label == true)
    result = {"frames": frames, **_counts_to_metrics(overall), "pairs": []}
    for (estimated, true), counts in per_pair.items():
        result["pairs"].append({"estimated_id": estimated, "true_id": true, **_counts_to_metrics(counts)})
    return result


def _read_index_image(path: Path, what: str) -> np.ndarray:
    """A single-channel integer image (labels or masks)."""
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(f"cannot read {what} {path}: {error.strerror}") from None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is None or image.size == 0:
        raise InputError(f"{what} {path} is unreadable or empty; replace or remove it")
    if image.ndim != 2:
        raise InputError(f"{what} {path} has {image.shape[2]} channels; expected a single-channel id image")
    return image


def _png_stems(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    return {path.stem: path for path in sorted(folder.iterdir()) if path.is_file() and path.suffix.lower() == ".png"}


# --------------------------------------------------------------------------------------
# Whole run


def _read_trajectory(path: Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    timestamps, poses = read_tum_trajectory(path)
    if len(timestamps) == 0:
        raise InputError(f"{what} {path} has no poses")
    return timestamps, poses


def _read_true_objects(sequence_dir: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    folder = sequence_dir / "objects"
    objects = {}
    if folder.is_dir():
        for path in sorted(folder.iterdir()):
            found = _TRUE_OBJECT_FILE.match(path.name)
            if found and path.is_file():
                objects[int(found.group(1))] = _read_trajectory(path, "ground-truth object trajectory")
    return dict(sorted(objects.items()))


def _read_estimated_objects(results_dir: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    folder = results_dir / "objects"
    objects = {}
    if folder.is_dir():
        for path in sorted(folder.iterdir()):
            found = _ESTIMATED_OBJECT_FOLDER.match(path.name)
            trajectory = path / "trajectory.tum"
            if found and trajectory.is_file():
                timestamps, poses = read_tum_trajectory(trajectory)
                objects[int(found.group(1))] = (timestamps, poses)
    return dict(sorted(objects.items()))


def _colour_frames(sequence_dir: Path) -> tuple[np.ndarray, list[str]] | None:
    """Colour timestamps and file stems from ``rgb.txt``, or None when there is none."""
    path = sequence_dir / "rgb.txt"
    if not path.is_file():
        return None
    entries = read_image_list(path)
    return np.array([timestamp for timestamp, _ in entries], dtype=float), [Path(name).stem for _, name in entries]


def _camera_metrics(results_dir: Path, sequence_dir: Path, colour, max_time_difference: float) -> tuple[dict, tuple]:
    est_timestamps, est_poses = _read_trajectory(results_dir / "camera.tum", "camera trajectory")
    gt_timestamps, gt_poses = _read_trajectory(sequence_dir / "groundtruth.txt", "ground truth")
    timestamps, est, gt = associate_poses(est_timestamps, est_poses, gt_timestamps, gt_poses, max_time_difference)
    if len(timestamps) < 3:
        raise InputError(
            f"only {len(timestamps)} of the {len(est_timestamps)} camera poses of {results_dir} have a ground-truth "
            f"pose within {max_time_difference} s; is {sequence_dir} the sequence that was reconstructed?"
        )
    ate = absolute_trajectory_error(est, gt)
    rpe = relative_pose_error(est, gt, delta=1)
    # Coverage is counted over colour frames that have ground truth when rgb.txt is there
    # (groundtruth.txt is often sampled faster than the camera), else over ground-truth poses.
    if colour is not None:
        colour_timestamps = colour[0]
        with_truth = colour_timestamps[_lookup(colour_timestamps, gt_timestamps, max_time_difference) >= 0]
        covered = int(np.count_nonzero(_lookup(with_truth, est_timestamps, max_time_difference) >= 0))
        gt_frames = len(with_truth)
        counted_over = "colour frames with ground truth"
    else:
        gt_frames = len(gt_timestamps)
        covered = len(timestamps)
        counted_over = "ground-truth poses"
    metrics = {
        "frames_estimated": len(est_timestamps),
        "frames_associated": len(timestamps),
        "gt_frames": gt_frames,
        "gt_frames_without_estimate": gt_frames - covered,
        "coverage": _ratio(covered, gt_frames),
        "coverage_counted_over": counted_over,
        "ate": ate.as_dict(),
        "rpe": rpe.as_dict(),
    }
    logger.info(
        "camera: %d poses associated, ATE RMSE %.4f m, RPE %.4f m / %.3f deg",
        len(timestamps), ate.rmse, rpe.translation_rmse, rpe.rotation_rmse,
    )
    return metrics, (est_timestamps, est_poses, gt_timestamps, gt_poses)


def _object_errors(
    estimated: dict, true: dict, cameras: tuple, max_time_difference: float
) -> list[ObjectPoseError]:
    est_camera_timestamps, est_camera_poses, gt_camera_timestamps, gt_camera_poses = cameras
    errors = []
    for estimated_id, (object_timestamps, object_poses) in estimated.items():
        if len(object_timestamps) == 0:
            continue
        est_camera_index = _lookup(object_timestamps, est_camera_timestamps, max_time_difference)
        gt_camera_index = _lookup(object_timestamps, gt_camera_timestamps, max_time_difference)
        for true_id, (true_timestamps, true_poses) in true.items():
            true_index = _lookup(object_timestamps, true_timestamps, max_time_difference)
            common = (est_camera_index >= 0) & (gt_camera_index >= 0) & (true_index >= 0)
            if not np.any(common):
                continue
            errors.append(
                object_pose_error(
                    est_camera_poses[est_camera_index[common]],
                    object_poses[common],
                    gt_camera_poses[gt_camera_index[common]],
                    true_poses[true_index[common]],
                    estimated_id=estimated_id,
                    true_id=true_id,
                )
            )
    return errors


def _visible_frames(
    true: dict, colour, labels: dict[str, Path], max_time_difference: float, min_visible_pixels: int
) -> tuple[dict[int, np.ndarray], str]:
    """Timestamps of the frames where each true object counts as visible, and how that was decided."""
    if colour is None:
        if labels:
            logger.warning(
                "labels found but no rgb.txt to give their timestamps; visibility uses all ground-truth frames"
            )
        return {true_id: timestamps for true_id, (timestamps, _) in true.items()}, "ground-truth object poses"
    colour_timestamps, stems = colour
    # Candidate frames: colour frames with a ground-truth pose of the object.
    candidates = {
        true_id: _lookup(colour_timestamps, timestamps, max_time_difference) >= 0
        for true_id, (timestamps, _) in true.items()
    }
    if not labels:
        visible = {true_id: colour_timestamps[mask] for true_id, mask in candidates.items()}
        return visible, "colour frames with object ground truth"
    # With labels, visibility is only known on labelled frames: the share is measured over those.
    visible = {true_id: [] for true_id in true}
    for position, (timestamp, stem) in enumerate(zip(colour_timestamps, stems)):
        path = labels.get(stem)
        if path is None or not any(mask[position] for mask in candidates.values()):
            continue
        label = _read_index_image(path, "label image")
        counts = np.bincount(label.ravel().astype(np.int64))
        for true_id, mask in candidates.items():
            if mask[position] and true_id < len(counts) and counts[true_id] > min_visible_pixels:
                visible[true_id].append(timestamp)
    how = f"labelled colour frames with more than {min_visible_pixels} pixels of the object"
    return {true_id: np.asarray(times, dtype=float) for true_id, times in visible.items()}, how


def _frames_tracked(visible_timestamps: np.ndarray, map_timestamps: list[np.ndarray],
                    max_time_difference: float) -> int:
    """How many of the ``visible_timestamps`` some map (its trajectory ``map_timestamps``) tracked."""
    tracked = np.zeros(len(visible_timestamps), dtype=bool)
    for timestamps in map_timestamps:
        tracked |= _lookup(visible_timestamps, timestamps, max_time_difference) >= 0
    return int(np.count_nonzero(tracked))


def _objects_section(
    results_dir: Path,
    sequence_dir: Path,
    colour,
    labels: dict[str, Path],
    cameras: tuple,
    max_time_difference: float,
    min_visible_pixels: int,
) -> tuple[dict | None, list[ObjectPoseError]]:
    estimated = _read_estimated_objects(results_dir)
    true = _read_true_objects(sequence_dir)
    if not true:
        return None, []
    errors = _object_errors(estimated, true, cameras, max_time_difference)
    matches = match_objects(errors)
    extra = pool_extra_maps(errors, matches)
    visible, visible_how = _visible_frames(true, colour, labels, max_time_difference, min_visible_pixels)
    matched_rows = []
    for match in matches:
        row = match.as_dict()
        visible_timestamps = visible[match.true_id]
        further = [error.estimated_id for error in extra.get(match.true_id, [])]
        tracked = _frames_tracked(visible_timestamps, [estimated[match.estimated_id][0]], max_time_difference)
        row["visible_frames"] = len(visible_timestamps)
        row["tracked_frames"] = tracked
        row["tracked_share"] = _ratio(tracked, len(visible_timestamps))
        row["further_maps"] = further
        all_maps = [estimated[k][0] for k in (match.estimated_id, *further)]
        row["tracked_share_all_maps"] = _ratio(_frames_tracked(visible_timestamps, all_maps, max_time_difference),
                                               len(visible_timestamps))
        matched_rows.append(row)
        logger.info(
            "object %d -> true object %d: %d frames, %.2f cm / %.2f deg median",
            match.estimated_id, match.true_id, match.frames, match.translation_median_cm, match.rotation_median_deg,
        )
    pooled = [error for errors_of in extra.values() for error in errors_of]
    matched_estimated = {match.estimated_id for match in matches} | {error.estimated_id for error in pooled}
    matched_true = {match.true_id for match in matches}
    section = {
        "estimated": [{"id": key, "frames": len(value[0])} for key, value in estimated.items()],
        "true": [
            {"id": key, "frames": len(value[0]), "visible_frames": len(visible[key])} for key, value in true.items()
        ],
        "visibility": visible_how,
        "matches": matched_rows,
        "further_maps": [error.as_dict() for error in pooled],
        "unmatched_estimated": [key for key in estimated if key not in matched_estimated],
        "unmatched_true": [key for key in true if key not in matched_true],
    }
    return section, matches + pooled


def _merged_ids(results_dir: Path) -> dict[int, int]:
    """``summary.json``'s ``objects_merged``: object id -> the id of the map it became part of
    (masks written before a merge carry the old id)."""
    path = results_dir / "summary.json"
    if not path.is_file():
        return {}
    try:
        merged = json.loads(path.read_text()).get("objects_merged") or {}
        return {int(source): int(target) for source, target in merged.items()}
    except (ValueError, AttributeError, TypeError):
        logger.warning("%s: unreadable objects_merged; masks are taken as written", path)
        return {}


def _masks_section(results_dir: Path, labels: dict[str, Path], matches: list[ObjectPoseError]) -> dict | None:
    masks = _png_stems(results_dir / "masks")
    if not masks or not labels:
        return None
    relabel = np.arange(256, dtype=np.int64)
    for source, target in _merged_ids(results_dir).items():
        if 0 <= source < 256 and 0 <= target < 256:
            relabel[source] = target
    stems = [stem for stem in masks if stem in labels]
    logger.info("masks: %d of %d mask files have a label image", len(stems), len(masks))

    def pairs():
        for stem in stems:
            mask = _read_index_image(masks[stem], "mask")
            if mask.max(initial=0) < 256:
                mask = relabel[mask]
            label = _read_index_image(labels[stem], "label image")
            if mask.shape != label.shape:
                raise InputError(f"mask {masks[stem]} is {mask.shape[1]}x{mask.shape[0]} but its label image is "
                                 f"{label.shape[1]}x{label.shape[0]}")
            yield mask, label

    section = mask_precision_recall(pairs(), [(match.estimated_id, match.true_id) for match in matches])
    section["mask_files"] = len(masks)
    return section


def evaluate_run(
    results_dir: Path,
    sequence_dir: Path,
    max_time_difference: float = 0.02,
    min_visible_pixels: int = VISIBLE_PIXEL_THRESHOLD,
) -> dict:
    """Evaluate a ``jsr reconstruct`` results folder against a sequence's ground truth.

    Returns a JSON-ready dict with ``camera`` (always), ``objects`` (``None`` when the sequence
    has no ``objects/object_<k>.txt``) and ``masks`` (``None`` unless both ``RESULTS/masks`` and
    ``SEQ/labels`` hold PNG files). Raises :class:`InputError` when a folder or a required file
    is missing or unusable.
    """
    results_dir, sequence_dir = Path(results_dir), Path(sequence_dir)
    if not results_dir.is_dir():
        raise InputError(f"results folder {results_dir} does not exist")
    if not sequence_dir.is_dir():
        raise InputError(f"sequence folder {sequence_dir} does not exist")
    if not (results_dir / "camera.tum").is_file():
        raise InputError(f"{results_dir} has no camera.tum; give a folder written by 'jsr reconstruct'")
    if not (sequence_dir / "groundtruth.txt").is_file():
        raise InputError(f"{sequence_dir} has no groundtruth.txt; evaluation needs the ground-truth camera trajectory")
    colour = _colour_frames(sequence_dir)
    labels = _png_stems(sequence_dir / "labels")
    camera, cameras = _camera_metrics(results_dir, sequence_dir, colour, max_time_difference)
    objects, matches = _objects_section(
        results_dir, sequence_dir, colour, labels, cameras, max_time_difference, min_visible_pixels
    )
    masks = _masks_section(results_dir, labels, matches)
    notes = []  # what the figures do not cover, for the reader
    status = _run_status(results_dir)
    if status not in (None, "complete"):
        notes.append(f"the run is {status}: the figures cover only the frames it did")
    if masks is None and labels and not _png_stems(results_dir / "masks"):
        notes.append("masks not evaluated: the results hold no masks/ (run 'jsr reconstruct' with --save-masks)")
    for note in notes:
        logger.warning("%s: %s", results_dir, note)
    return {
        "results_dir": str(results_dir),
        "sequence_dir": str(sequence_dir),
        "max_time_difference": float(max_time_difference),
        "run_status": status,
        "camera": camera,
        "objects": objects,
        "masks": masks,
        "notes": notes,
    }


def _run_status(results_dir: Path) -> str | None:
    """``status`` of ``RESULTS/summary.json`` (complete, interrupted, failed, running), or None
    when there is no readable summary."""
    try:
        return str(json.loads((results_dir / "summary.json").read_text())["status"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def write_metrics(results_dir: Path, metrics: dict) -> Path:
    """Write ``metrics`` to ``RESULTS/metrics.json`` atomically; returns the path."""
    path = Path(results_dir) / "metrics.json"
    write_json(path, metrics)
    return path
