"""A results folder read against a sequence's ground truth into metrics (:func:`evaluate_run`)
and written as ``RESULTS/metrics.json`` (:func:`write_metrics`).

Results folder (written by ``jsr reconstruct``)::

    RESULTS/camera.tum                          T_w_c of every tracked frame (world = first camera frame)
    RESULTS/objects/object_<K>/trajectory.tum   T_w_o of estimated object K where it was tracked (same world)
    RESULTS/masks/<colour stem>.png             optional, uint8: 0 static, K pixels given to object K

Sequence folder (TUM layout)::

    SEQ/groundtruth.txt             T_w_c in the ground-truth world
    SEQ/objects/object_<k>.txt      optional, T_w_o of true object k (same world), one per frame
    SEQ/labels/<colour stem>.png    optional, 0 static, k object k
    SEQ/rgb.txt                     colour timestamps and file names (maps stems to timestamps)

Everything :func:`evaluate_run` returns is plain Python (dict, list, int, float, str, None),
so ``json.dumps(metrics, allow_nan=False)`` works; undefined values (e.g. a precision with no
predicted pixel) are ``None``.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import cv2
import numpy as np

from jsr.errors import InputError
from jsr.evaluate.masks import mask_precision_recall
from jsr.evaluate.objects import ObjectPoseError, match_objects, object_pose_error, pool_extra_maps
from jsr.evaluate.stats import ratio
from jsr.evaluate.trajectory import absolute_trajectory_error, associate_poses, relative_pose_error
from jsr.io.dataset import associate_timestamps, read_image_list
from jsr.io.trajectory import read_tum_trajectory
from jsr.io.writers import write_json

logger = logging.getLogger(__name__)

VISIBLE_PIXEL_THRESHOLD = 2000
"""A true object counts as visible in a frame whose label image has more than this many of its pixels."""

_TRUE_OBJECT_FILE = re.compile(r"^object_(\d+)\.txt$")
_ESTIMATED_OBJECT_FOLDER = re.compile(r"^object_(\d+)$")


def _lookup(reference: np.ndarray, other: np.ndarray, max_difference: float) -> np.ndarray:
    """For each reference timestamp, the index of its associated ``other`` timestamp, or -1."""
    index = np.full(len(reference), -1, dtype=int)
    for i, j in associate_timestamps(reference, other, max_difference):
        index[i] = j
    return index


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
        "coverage": ratio(covered, gt_frames),
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
        row["tracked_share"] = ratio(tracked, len(visible_timestamps))
        row["further_maps"] = further
        all_maps = [estimated[k][0] for k in (match.estimated_id, *further)]
        row["tracked_share_all_maps"] = ratio(_frames_tracked(visible_timestamps, all_maps, max_time_difference),
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
