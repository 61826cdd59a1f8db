"""Moving-object benchmark: detection, object maps, object tracking, masks and map hygiene.

    python bench/objects.py [--frames N] [--sequences synth_jump,synth_smooth,...] [--set section.key=value]
                            [--seed S[,S...]] [--size WxH] [--pipeline-seeds P[,P...]] [--json FILE] [--keep-synthetic DIR]

Runs :class:`jsr.pipeline.reconstruct.Reconstructor` in-process over every frame of each
sequence and compares what it did with the ground truth (``groundtruth.txt``,
``objects/object_<k>.txt``, ``labels/<colour stem>.png``). Sequences (``--sequences``):

* ``synth_jump``      synthetic, one object moved by abrupt jumps (``jsr synth --objects 1 --motion jump``);
* ``synth_smooth``    synthetic, one object moved continuously (``--motion smooth``);
* ``synth_two``       synthetic, two objects jumping at different times (``--objects 2 --motion jump``);
* ``synth_two_sim``   stretch: two objects jumping in the same frames (``--simultaneous``);
* ``kitchen_box120``  ``../shared/data/kitchen_box120`` (real kitchen, composited box jumping
                      every 20 frames); skipped when ``../shared/data`` is absent.

Synthetic sequences are 640x480 (``--size``), ``--frames`` frames (default 60), generated with the same seed
(``--seed``) into a temporary folder; ``--seed 1,2,3`` runs each synthetic sequence once per
seed, one column each (seed 1 alone hid misses that seeds 2 and 3 show; the rules were tuned
on seeds 1-5, so check a change on unseen ones too, e.g. ``--seed 6,7,8,9``: in December 2026
they missed a target in 6 of 16 sequences against 1 of 20 for seeds 1-5). The seed fixes the camera path and the static room
independently of the objects, so the ``--objects 0`` sequence with the same seed is exactly the
same video without the objects (checked: identical camera poses, identical static pixels); it
is the "without objects" twin for the ATE ratio. For kitchen_box120 the twin is
``../shared/data/redkitchen300`` restricted to the same number of first frames (the kitchen
frames the box was composited into). ``--pipeline-seeds 0,1,2,3,4`` runs each real sequence
and its twin once per pipeline (RANSAC) seed, one column each, and prints the ratio of the
mean ATEs: on kitchen_box120 the seed alone moves the ATE by 25% (0.99-1.29 cm).

Figures, per sequence ("true moving object": a true object that moves at least once in the
frames used; "moves" = its true T_w_o changes by > 1 mm or > 0.5 deg from the previous frame):

1. detection delay: per true moving object, frames from its first motion to the creation of
   the first object map whose mask in its creation frame overlaps that object's labels most
   (among true objects); "-" if no such map was created. Negative: created before it moved.
2. object maps: maps created / true moving objects. Every estimated map is matched to the true
   object its masks overlap most over the whole run (pixels with mask == K and label == k,
   summed over frames); a map overlapping no object is spurious. Target: exactly one map per
   moving object and no other.
3. pose error: for each true moving object, the trajectory T_w_o of each map matched to it
   against the true T_w_o on common frames, as ``jsr.evaluate.objects.object_pose_error`` does: poses
   compared in the camera frame (C = inv(T_w_c) T_w_o, which needs no world alignment) after removing the constant offset between the estimated and true object frames
   (one offset per map), the translation error taken at the true object's centre; translation RMSE (cm) and rotation RMSE (deg) pooled over the tracked
   frames of all its maps (per map in the JSON). The poses scored are those the run writes:
   T_w_c of ``camera.tum`` and T_w_o of ``objects/object_K/trajectory.tum``
   (``Reconstructor.object_trajectory``), both after bundle adjustment of their maps.
4. tracked: share of the frames from the object's first motion on in which it is visible
   (> 2000 labelled pixels) and some map matched to it is in ``FrameReport.objects_tracked``.
5. mask precision / recall: pixels with mask > 0 against label > 0, summed over all frames
   (also per true object: pixels of its matched maps against its labels, in the JSON and the
   "per object" rows). "Recall once moved" counts an object's labelled pixels only from its
   first motion on: before an object moves nothing tells it from the static scene (the
   paper's method included), so those frames bound the plain recall (1/6 of the frames of the
   60-frame synthetic sequences); the target applies to this one. Maps merged into another
   map later (summary ``objects_merged``) count as that map in every frame.
6. contamination: "object lm on static" = share of the active landmarks of all object maps
   whose origin is labelled static; "static lm on objects" = share of the static map's active
   landmarks whose origin is labelled as an object. A landmark's origin is the pixel of its
   first observation: in the earliest keyframe (by frame index) of its map listing it in
   ``point_landmarks``, the pixel ``keyframe.pixels`` (rounded, clipped), looked up in the
   label image of that keyframe's frame.
7. camera ATE (cm, rigid SE(3) Umeyama alignment of positions, ``jsr.evaluate``), of the
   bundle-adjusted poses of tracked frames; the same on the twin without objects; their ratio.
   For a real sequence with labels, also a control: the ATE of the same sequence with the
   labelled object pixels (dilated by ``BLANK_MARGIN_PX``) blanked (no depth, grey colour).
   kitchen_box120's background is redkitchen re-encoded as JPEG after compositing, so its
   features differ from the twin's also away from the box; the control shows how much of the
   ratio that alone makes ("ATE, objects blanked" and "ATE ratio to blanked", no target).
8. fps: frames / seconds spent loading and processing frames plus ``finish()`` (as
   ``jsr reconstruct`` counts it; the benchmark's own label bookkeeping is not included).

Values that miss their target are marked with ``*``. ``--json FILE`` writes every figure
(and per-object and per-map details). A default run (4 synthetic sequences + twin, generated
at ~1 s a frame, and kitchen_box120 + twin) takes a few minutes on 2 cores; ``--seed 1,2,3`` took 8 minutes.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from jsr.config import load_config  # noqa: E402
from jsr.evaluate.objects import object_pose_error  # noqa: E402
from jsr.evaluate.run import VISIBLE_PIXEL_THRESHOLD  # noqa: E402
from jsr.evaluate.trajectory import absolute_trajectory_error, associate_poses  # noqa: E402
from jsr.geometry import invert_transform, rotation_angle  # noqa: E402
from jsr.io.dataset import associate_timestamps, open_sequence  # noqa: E402
from jsr.io.trajectory import read_tum_trajectory  # noqa: E402
from jsr.pipeline.reconstruct import Reconstructor  # noqa: E402

SHARED = REPO.parent / "shared" / "data"

# name: (objects, motion, simultaneous); the twin is the same seed with objects=0.
SYNTHETIC = {
    "synth_jump": (1, "jump", False),
    "synth_smooth": (1, "smooth", False),
    "synth_two": (2, "jump", False),
    "synth_two_sim": (2, "jump", True),
}
REAL = {"kitchen_box120": "redkitchen300"}  # sequence with an object: its static twin
DEFAULT_SEQUENCES = ",".join([*SYNTHETIC, *REAL])
SYNTH_SIZE = (640, 480)
DEFAULT_SYNTH_FRAMES = 60

MOTION_TRANSLATION = 0.001  # m: a true object "moves" between frames beyond 1 mm ...
MOTION_ROTATION_DEG = 0.5  # ... or 0.5 degree
LABEL_BINS = 256  # masks are uint8; labels are clipped to 255 for the confusion matrix
ID_BINS = 32  # per-frame confusion matrices keep object ids below this
BLANK_MARGIN_PX = 2  # the control run blanks the labelled object pixels and this margin (JPEG bleed)

TARGETS = {
    "detection_delay": 3,  # frames, at most
    "tracked_share": 0.90,  # at least
    "pose_cm": 2.0,  # at most
    "pose_deg": 2.0,
    "mask_precision": 0.90,  # at least
    "mask_recall": 0.90,
    "contamination": 0.02,  # at most, each way
    "ate_ratio": 1.2,  # at most
}


# --------------------------------------------------------------------------------------
# Sequences


def synthetic_sequence(root: Path, name: str, frames: int, seed: int, size: tuple[int, int] = SYNTH_SIZE) -> Path:
    """Generate (or reuse, when its synth.yaml has the same options) a synthetic sequence of
    ``size`` ``(width, height)`` pixels."""
    import yaml

    from jsr.synth.options import SynthOptions
    from jsr.synth.write import generate_sequence

    objects, motion, simultaneous = SYNTHETIC[name] if name in SYNTHETIC else (0, "static", False)
    options = SynthOptions(frames=frames, objects=objects, motion=motion, simultaneous=simultaneous,
                           width=size[0], height=size[1], seed=seed)
    out = root / (f"{name}_f{frames}_s{seed}" + ("" if size == SYNTH_SIZE else f"_{size[0]}x{size[1]}"))
    metadata = out / "synth.yaml"
    if metadata.is_file() and (out / "rgb.txt").is_file():
        from dataclasses import asdict

        if yaml.safe_load(metadata.read_text()).get("options") == asdict(options):
            print(f"  {name}: reusing {out}", flush=True)
            return out
    print(f"  {name}: generating {frames} frames ({objects} objects, {motion}"
          f"{', simultaneous' if simultaneous else ''}, seed {seed}) ...", end="", flush=True)
    started = time.perf_counter()
    generate_sequence(out, options, overwrite=True)
    print(f" {time.perf_counter() - started:.0f} s", flush=True)
    return out


def read_label(path: Path) -> np.ndarray | None:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if image is None or image.ndim != 2:
        return None
    return image


class BlankedSequence:
    """``sequence`` with every frame's labelled object pixels (``labels_dir/<colour stem>.png``
    above 0, dilated by ``BLANK_MARGIN_PX``) blanked: depth 0 and grey colour. The control run:
    the same background with no object in it."""

    def __init__(self, sequence, labels_dir: Path):
        self.sequence, self.labels_dir = sequence, labels_dir
        self.intrinsics, self.groundtruth = sequence.intrinsics, sequence.groundtruth
        self.kernel = np.ones((2 * BLANK_MARGIN_PX + 1,) * 2, np.uint8)

    def __len__(self) -> int:
        return len(self.sequence)

    def __getitem__(self, index: int):
        frame = self.sequence[index]
        label = read_label(self.labels_dir / f"{frame.name}.png")
        if label is not None and label.shape == frame.depth.shape:
            blank = cv2.dilate((label > 0).astype(np.uint8), self.kernel) > 0
            frame.depth = np.where(blank, 0, frame.depth).astype(frame.depth.dtype)
            frame.color = np.where(blank[..., None], 128, frame.color).astype(frame.color.dtype)
        return frame


def per_frame_poses(frame_timestamps: np.ndarray, timestamps: np.ndarray, poses: np.ndarray,
                    max_difference: float) -> list[np.ndarray | None]:
    """The pose associated with every frame (by timestamp), or None."""
    result: list[np.ndarray | None] = [None] * len(frame_timestamps)
    for i, j in associate_timestamps(frame_timestamps, timestamps, max_difference):
        result[i] = poses[j]
    return result


def first_motion(poses: list[np.ndarray | None]) -> int | None:
    """First frame whose true pose differs from the previous frame's by > 1 mm or > 0.5 deg."""
    for index in range(1, len(poses)):
        previous, current = poses[index - 1], poses[index]
        if previous is None or current is None:
            continue
        relative = invert_transform(previous) @ current
        if (np.linalg.norm(relative[:3, 3]) > MOTION_TRANSLATION
                or math.degrees(float(rotation_angle(relative[:3, :3]))) > MOTION_ROTATION_DEG):
            return index
    return None


# --------------------------------------------------------------------------------------
# One run


@dataclass
class RunRecord:
    """What a run leaves for scoring (masks are reduced to counts as the frames go)."""

    reports: list = field(default_factory=list)
    confusion: np.ndarray = field(default_factory=lambda: np.zeros((LABEL_BINS, LABEL_BINS), np.int64))
    label_counts: dict[int, np.ndarray] = field(default_factory=dict)  # frame index -> pixels per label
    # map K -> (frame it was created at, label row of its first mask: the frame that confirms a
    # candidate writes its pixels as 255, so its id first shows in the next frame's mask)
    creation_overlap: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)
    labelled_frames: int = 0
    frame_confusion: dict[int, np.ndarray] = field(default_factory=dict)  # frame -> (ID_BINS, ID_BINS) mask x label
    merged_into: dict[int, int] = field(default_factory=dict)  # object id -> the map it was merged into
    seconds: float = 0.0
    poses: dict[int, np.ndarray] = field(default_factory=dict)  # frame index -> bundle-adjusted T_w_c
    object_poses: dict[int, dict[int, np.ndarray]] = field(default_factory=dict)  # map K -> frame -> written T_w_o
    static_map: object = None
    object_maps: list = field(default_factory=list)
    loops_closed: int = 0  # loops the static map closed (jsr.pipeline.loop_closure)


def run_pipeline(sequence, config, labels_dir: Path | None) -> RunRecord:
    """Every frame through a Reconstructor; mask/label counts gathered per frame."""
    record = RunRecord()
    reconstructor = Reconstructor(config, sequence.intrinsics)
    unshown: dict[int, int] = {}  # map K created at frame f, its id not yet in a labelled frame's mask
    try:
        for index in range(len(sequence)):
            started = time.perf_counter()
            frame = sequence[index]
            report = reconstructor.process(frame)
            record.seconds += time.perf_counter() - started
            label = read_label(labels_dir / f"{frame.name}.png") if labels_dir is not None else None
            unshown.update({object_id: report.frame_index for object_id in report.objects_created})
            if label is not None and report.mask is not None and report.mask.shape == label.shape:
                clipped = np.minimum(label, LABEL_BINS - 1).astype(np.int64).ravel()
                frame_confusion = np.bincount(report.mask.astype(np.int64).ravel() * LABEL_BINS + clipped,
                                              minlength=LABEL_BINS * LABEL_BINS).reshape(LABEL_BINS, LABEL_BINS)
                record.confusion += frame_confusion
                record.label_counts[report.frame_index] = frame_confusion.sum(axis=0)
                record.frame_confusion[report.frame_index] = frame_confusion[:ID_BINS, :ID_BINS].copy()
                record.labelled_frames += 1
                for object_id, created in list(unshown.items()):
                    if object_id < LABEL_BINS and frame_confusion[object_id].any():
                        record.creation_overlap[object_id] = (created, frame_confusion[object_id].copy())
                        del unshown[object_id]
            report.mask = None  # counted; the reconstructor keeps the keyframes' own copies
            record.reports.append(report)
        for object_id, created in unshown.items():  # never shown in a labelled mask: overlaps nothing
            record.creation_overlap[object_id] = (created, np.zeros(LABEL_BINS, np.int64))
        started = time.perf_counter()
        reconstructor.finish()
        record.seconds += time.perf_counter() - started
        record.poses = {r.frame_index: reconstructor.current_pose(r) for r in record.reports if r.tracked}
        record.static_map = reconstructor.static_map
        record.loops_closed = len(reconstructor.loops_closed)
        record.object_maps = list(reconstructor.object_maps)
        for object_map in record.object_maps:
            _, written = reconstructor.object_trajectory(object_map)
            record.object_poses[object_map.object_id] = {
                index: T_w_o for (index, _, _), T_w_o in zip(object_map.trajectory, written)}
        record.merged_into = dict(reconstructor.merged_into)
        resolve_merged_ids(record)
    finally:
        reconstructor.close()
    return record


def resolve_merged_ids(record: RunRecord) -> None:
    """Score what the run ended with: an object map merged into another one later counts as that
    map in every frame (mask pixels, tracked objects; creations keep their own id), as the summary's
    ``objects_merged`` table says."""
    if not record.merged_into:
        return
    final = lambda k: record.merged_into.get(k, k)  # noqa: E731 (merged_into is already transitive)
    for report in record.reports:
        report.objects_tracked = sorted({final(k) for k in report.objects_tracked})
    for source, target in record.merged_into.items():
        if source < LABEL_BINS and target < LABEL_BINS:
            record.confusion[target] += record.confusion[source]
            record.confusion[source] = 0
        if source < ID_BINS and target < ID_BINS:
            for confusion in record.frame_confusion.values():
                confusion[target] += confusion[source]
                confusion[source] = 0


def camera_ate(record: RunRecord, sequence, max_difference: float) -> float | None:
    """ATE RMSE (m) of the tracked frames' bundle-adjusted poses; None without ground truth."""
    if sequence.groundtruth is None or len(record.poses) < 3:
        return None
    timestamps = {r.frame_index: r.timestamp for r in record.reports}
    indices = sorted(record.poses)
    _, est, gt = associate_poses(np.array([timestamps[i] for i in indices]),
                                 np.array([record.poses[i] for i in indices]), *sequence.groundtruth, max_difference)
    return absolute_trajectory_error(est, gt).rmse if len(est) >= 3 else None


# --------------------------------------------------------------------------------------
# Scoring


def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    """``numerator / denominator``; None when either is missing (None) or the denominator is not positive."""
    if numerator is None or denominator is None or not denominator > 0:
        return None
    return float(numerator) / float(denominator)


def landmark_origins(map_, names: dict[int, str], labels_dir: Path, cache: dict) -> tuple[int, int, int]:
    """``(active landmarks with a known origin, of which labelled static, of which labelled object)``."""
    count = len(map_.points)
    origin_frame = np.full(count, -1, dtype=np.int64)
    origin_pixel = np.zeros((count, 2))
    for keyframe in sorted(map_.keyframes, key=lambda kf: kf.frame_index):
        ids = np.asarray(keyframe.point_landmarks, dtype=np.int64)
        if not len(ids):
            continue
        ids, first = np.unique(ids, return_index=True)
        new = (ids >= 0) & (ids < count)
        new[new] &= origin_frame[ids[new]] < 0
        origin_frame[ids[new]] = keyframe.frame_index
        origin_pixel[ids[new]] = np.asarray(keyframe.pixels)[first[new]]
    known = np.asarray(map_.points.active, dtype=bool) & (origin_frame >= 0)
    on_static = on_object = counted = 0
    for frame_index in np.unique(origin_frame[known]):
        if frame_index not in cache:
            name = names.get(int(frame_index))
            cache[frame_index] = read_label(labels_dir / f"{name}.png") if name is not None else None
        label = cache[frame_index]
        if label is None:
            continue
        ids = np.flatnonzero(known & (origin_frame == frame_index))
        height, width = label.shape
        u = np.clip(np.round(origin_pixel[ids, 0]).astype(int), 0, width - 1)
        v = np.clip(np.round(origin_pixel[ids, 1]).astype(int), 0, height - 1)
        values = label[v, u]
        counted += len(ids)
        on_static += int(np.count_nonzero(values == 0))
        on_object += int(np.count_nonzero(values > 0))
    return counted, on_static, on_object


def score(record: RunRecord, sequence, seq_dir: Path, max_difference: float) -> dict:
    """Every figure of one run against the sequence's ground truth (plain JSON-ready values)."""
    reports = {r.frame_index: r for r in record.reports}
    frame_indices = sorted(reports)
    position = {index: p for p, index in enumerate(frame_indices)}
    frame_timestamps = np.array([reports[i].timestamp for i in frame_indices])
    names = {i: reports[i].name for i in frame_indices}
    labels_dir = seq_dir / "labels"

    gt_camera = per_frame_poses(frame_timestamps, *sequence.groundtruth, max_difference) \
        if sequence.groundtruth is not None else [None] * len(frame_indices)
    true_objects: dict[int, list] = {}
    objects_dir = seq_dir / "objects"
    for path in sorted(objects_dir.glob("object_*.txt")) if objects_dir.is_dir() else []:
        suffix = path.stem.split("_", 1)[1]
        if suffix.isdigit():
            true_objects[int(suffix)] = per_frame_poses(frame_timestamps, *read_tum_trajectory(path), max_difference)
    first_motions = {k: first_motion(poses) for k, poses in true_objects.items()}
    moving = [k for k, frame in first_motions.items() if frame is not None]

    # Match every estimated map to the true object its masks overlap most over the run.
    confusion = record.confusion
    true_ids = [k for k in true_objects if k < LABEL_BINS]
    maps = []
    for object_map in record.object_maps:
        K = object_map.object_id
        overlap = {k: int(confusion[K, k]) for k in true_ids} if K < LABEL_BINS else {}
        best = max(overlap, key=overlap.get) if overlap and max(overlap.values()) > 0 else None
        maps.append({"id": K, "created_at_frame": object_map.created_at_frame, "matched_true": best,
                     "overlap_pixels": overlap, "mask_pixels": int(confusion[K].sum()) if K < LABEL_BINS else 0,
                     "frames_tracked": len(object_map.trajectory), "keyframes": len(object_map.keyframes),
                     "active_landmarks": int(object_map.points.active_count)})

    objects = []
    for k in true_ids:
        start = first_motions[k]
        matched = [m for m in maps if m["matched_true"] == k]
        row = {"true_id": k, "first_motion_frame": start, "maps": [m["id"] for m in matched]}
        # 1. detection delay
        detecting = sorted((frame, K) for K, (frame, overlap) in record.creation_overlap.items()
                           if K < LABEL_BINS and true_ids and overlap[k] > 0
                           and overlap[k] == max(overlap[j] for j in true_ids))
        row["detected_at_frame"] = detecting[0][0] if detecting else None
        row["detected_by_map"] = detecting[0][1] if detecting else None
        row["detection_delay"] = detecting[0][0] - start if detecting and start is not None else None
        after = sorted(frame for frame, _ in record.creation_overlap.values() if start is not None and frame >= start)
        row["first_creation_after_motion"] = after[0] if after else None
        # 3. pose error, per matched map (each has its own object frame, so its own offset),
        #    pooled over the frames of all maps matched to the object
        row["pose"], row["pose_per_map"] = None, []
        translation_errors, rotation_errors = [], []
        for K in row["maps"]:
            rows = [(record.poses[i], T_w_o, gt_camera[position[i]], true_objects[k][position[i]])
                    for i, T_w_o in record.object_poses[K].items() if i in record.poses]
            rows = [r for r in rows if r[2] is not None and r[3] is not None]
            if not rows:
                continue
            error = object_pose_error(*(np.array(column) for column in zip(*rows)), estimated_id=K, true_id=k)
            translation_errors.append(error.translation_errors_cm)
            rotation_errors.append(error.rotation_errors_deg)
            row["pose_per_map"].append({"map": K, "frames": error.frames,
                                        "translation_rmse_cm": error.translation_rmse_cm,
                                        "rotation_rmse_deg": error.rotation_rmse_deg})
        if translation_errors:
            translation, rotation = np.concatenate(translation_errors), np.concatenate(rotation_errors)
            row["pose"] = {"frames": len(translation),
                           "translation_rmse_cm": float(np.sqrt(np.mean(translation ** 2))),
                           "rotation_rmse_deg": float(np.sqrt(np.mean(rotation ** 2))),
                           "translation_median_cm": float(np.median(translation)),
                           "rotation_median_deg": float(np.median(rotation))}
        # 4. tracked share over visible frames from the first motion on
        visible = [i for i in frame_indices if start is not None and i >= start and i in record.label_counts
                   and record.label_counts[i][k] > VISIBLE_PIXEL_THRESHOLD]
        tracked = [i for i in visible if set(reports[i].objects_tracked) & set(row["maps"])]
        row["visible_frames"] = len(visible)
        row["tracked_frames"] = len(tracked)
        row["tracked_share"] = _ratio(len(tracked), len(visible))
        # 5. per-object mask precision / recall
        predicted = sum(int(confusion[K].sum()) for K in row["maps"])
        true_positive = sum(int(confusion[K, k]) for K in row["maps"])
        row["mask_precision"] = _ratio(true_positive, predicted)
        row["mask_recall"] = _ratio(true_positive, int(confusion[:, k].sum()))
        # ... and over the frames from its first motion on (before it, no motion can show it)
        moved = sum((c for i, c in record.frame_confusion.items() if start is not None and i >= start),
                    np.zeros((ID_BINS, ID_BINS), np.int64))
        if k < ID_BINS:
            hits = sum(int(moved[K, k]) for K in row["maps"] if K < ID_BINS)
            row["mask_recall_moved"] = _ratio(hits, int(moved[:, k].sum()))
            row["mask_precision_moved"] = _ratio(hits, sum(int(moved[K].sum()) for K in row["maps"] if K < ID_BINS))
            row["moved_labelled_pixels"] = int(moved[:, k].sum())
            row["moved_hits_any_map"] = int(moved[1:, k].sum())
        objects.append(row)

    # 6. contamination
    cache: dict = {}
    counted = on_static = 0
    for object_map in record.object_maps:
        c, s, _ = landmark_origins(object_map, names, labels_dir, cache)
        counted, on_static = counted + c, on_static + s
    static_counted, _, static_on_object = landmark_origins(record.static_map, names, labels_dir, cache)

    tp = int(confusion[1:, 1:].sum())
    moved_labelled = sum(o.get("moved_labelled_pixels", 0) for o in objects)
    moved_hits = sum(o.get("moved_hits_any_map", 0) for o in objects)
    return {
        "mask_recall_moved": _ratio(moved_hits, moved_labelled),
        "frames": len(record.reports),
        "frames_tracked": len(record.poses),
        "labelled_frames": record.labelled_frames,
        "true_objects": true_ids,
        "true_moving_objects": moving,
        "maps_created": len(record.object_maps),
        "maps_spurious": [m["id"] for m in maps if m["matched_true"] is None],
        "maps": maps,
        "objects": objects,
        "mask_precision": _ratio(tp, int(confusion[1:, :].sum())),
        "mask_recall": _ratio(tp, int(confusion[:, 1:].sum())),
        "object_landmarks_counted": counted,
        "object_landmarks_on_static": _ratio(on_static, counted),
        "static_landmarks_counted": static_counted,
        "static_landmarks_on_objects": _ratio(static_on_object, static_counted),
        "fps": _ratio(len(record.reports), record.seconds),
        "seconds": record.seconds,
    }


# --------------------------------------------------------------------------------------
# Table


def _fmt(value, spec: str, miss: bool = False) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, spec) + ("*" if miss else "")


def _per_object(result: dict, get, spec: str, miss) -> str:
    moving = [o for o in result["objects"] if o["true_id"] in result["true_moving_objects"]]
    if not moving:
        return "-"
    return "/".join(_fmt(get(o), spec, get(o) is not None and miss(get(o))) if get(o) is not None else "-"
                    for o in moving)


def table_rows(result: dict) -> dict[str, str]:
    """One column of the table (``result`` of :func:`score` plus the ATE fields)."""
    t = TARGETS
    moving = result["true_moving_objects"]
    moving_rows = [o for o in result["objects"] if o["true_id"] in moving]
    one_each = all(len(o["maps"]) == 1 for o in moving_rows) and result["maps_created"] == len(moving)
    pose = lambda key: lambda o: o["pose"][key] if o.get("pose") else None  # noqa: E731
    contamination = t["contamination"]
    return {
        "frames (tracked)": f"{result['frames']} ({result['frames_tracked']})",
        "maps created / moving": f"{result['maps_created']}/{len(moving)}" + ("" if one_each else "*"),
        "  maps matching no object": f"{len(result['maps_spurious'])}",
        "detection delay (frames)": _per_object(result, lambda o: o["detection_delay"], "d",
                                                lambda v: not 0 <= v <= t["detection_delay"]),
        "tracked share": _per_object(result, lambda o: o["tracked_share"], ".0%", lambda v: v < t["tracked_share"]),
        "pose error (cm)": _per_object(result, pose("translation_rmse_cm"), ".2f", lambda v: v > t["pose_cm"]),
        "pose error (deg)": _per_object(result, pose("rotation_rmse_deg"), ".2f", lambda v: v > t["pose_deg"]),
        "mask precision": _fmt(result["mask_precision"], ".3f",
                               (result["mask_precision"] or 0) < t["mask_precision"]),
        "mask recall": _fmt(result["mask_recall"], ".3f"),
        "mask recall once moved": _fmt(result["mask_recall_moved"], ".3f",
                                       (result["mask_recall_moved"] or 0) < t["mask_recall"]),
        "  precision per object": _per_object(result, lambda o: o["mask_precision"], ".2f",
                                              lambda v: v < t["mask_precision"]),
        "  recall per object": _per_object(result, lambda o: o["mask_recall"], ".2f", lambda v: False),
        "  once moved, per object": _per_object(result, lambda o: o.get("mask_recall_moved"), ".2f",
                                                lambda v: v < t["mask_recall"]),
        "object lm on static": _fmt(result["object_landmarks_on_static"], ".1%",
                                    (result["object_landmarks_on_static"] or 0) > contamination),
        "static lm on objects": _fmt(result["static_landmarks_on_objects"], ".1%",
                                     (result["static_landmarks_on_objects"] or 0) > contamination),
        "camera ATE (cm)": _fmt(None if result.get("ate") is None else result["ate"] * 100, ".2f"),
        "ATE without objects (cm)": _fmt(None if result.get("ate_twin") is None else result["ate_twin"] * 100, ".2f"),
        "ATE ratio": _fmt(result.get("ate_ratio"), ".2f", (result.get("ate_ratio") or 0) > t["ate_ratio"]),
        "  ATE, objects blanked (cm)": _fmt(None if result.get("ate_blanked") is None else result["ate_blanked"] * 100,
                                            ".2f"),
        "  ATE ratio to blanked": _fmt(result.get("ate_ratio_blanked"), ".2f"),
        "fps": _fmt(result["fps"], ".2f"),
    }


TARGET_TEXT = {
    "maps created / moving": "1 per object",
    "detection delay (frames)": f"<= {TARGETS['detection_delay']}",
    "tracked share": f">= {TARGETS['tracked_share']:.0%}",
    "pose error (cm)": f"<= {TARGETS['pose_cm']:g}",
    "pose error (deg)": f"<= {TARGETS['pose_deg']:g}",
    "mask precision": f">= {TARGETS['mask_precision']:g}",
    "mask recall once moved": f">= {TARGETS['mask_recall']:g}",
    "object lm on static": f"<= {TARGETS['contamination']:.0%}",
    "static lm on objects": f"<= {TARGETS['contamination']:.0%}",
    "ATE ratio": f"<= {TARGETS['ate_ratio']:g}",
}


def print_table(results: dict[str, dict]) -> None:
    columns = {name: table_rows(result) for name, result in results.items() if "error" not in result}
    if not columns:
        return
    labels = next(iter(columns.values())).keys()
    label_width = max(len(label) for label in labels) + 2
    widths = {name: max(len(name), *(len(v) for v in column.values())) + 2 for name, column in columns.items()}
    header = f"{'figure':<{label_width}}{'target':<14}" + "".join(f"{name:>{widths[name]}}" for name in columns)
    print(header)
    print("-" * len(header))
    for label in labels:
        print(f"{label:<{label_width}}{TARGET_TEXT.get(label, ''):<14}"
              + "".join(f"{columns[name][label]:>{widths[name]}}" for name in columns))
    print("per-object values are 'object 1/object 2/...' over the true moving objects; * misses the target")


# --------------------------------------------------------------------------------------
# Main


def benchmark_sequence(name: str, seed: int, args, config, work: Path, twins: dict) -> dict:
    """Run one sequence (synthetic ones generated with ``seed``) and its twin; returns the
    figures (or ``{"error": ...}``)."""
    open_options = dict(max_time_difference=config.input.max_time_difference,
                        min_depth=config.input.min_depth, max_depth=config.input.max_depth)
    if name in SYNTHETIC:
        frames = args.frames or DEFAULT_SYNTH_FRAMES
        path = synthetic_sequence(work, name, frames, seed, args.size)
        sequence = open_sequence(path, **open_options)
        twin_key, twin_frames = ("synth_static", frames, seed, args.size, config.seed), None
        def twin_location() -> Path:
            return synthetic_sequence(work, "synth_static", frames, seed, args.size)
    else:
        path = SHARED / name
        sequence = open_sequence(path, max_frames=args.frames, **open_options)
        twin_key, twin_frames = (REAL[name], len(sequence), config.seed), len(sequence)
        def twin_location() -> Path:
            return SHARED / REAL[name]
    print(f"  {name}: running {len(sequence)} frames ...", end="", flush=True)
    record = run_pipeline(sequence, config, path / "labels")
    result = score(record, sequence, path, config.input.max_time_difference)
    result["sequence"] = str(path)
    result["ate"] = camera_ate(record, sequence, config.input.max_time_difference)
    print(f" {result['fps']:.2f} fps", flush=True)
    if twin_key not in twins:
        twin_path = twin_location()
        if not twin_path.is_dir():
            twins[twin_key] = {"path": str(twin_path), "frames": 0, "ate": None, "note": "absent"}
            print(f"  twin {twin_path} absent: no ATE ratio")
        else:
            twin = open_sequence(twin_path, max_frames=twin_frames, **open_options)
            print(f"  {name} twin ({twin_path.name}): running {len(twin)} frames ...", end="", flush=True)
            twin_record = run_pipeline(twin, config, None)
            ate = camera_ate(twin_record, twin, config.input.max_time_difference)
            twins[twin_key] = {"path": str(twin_path), "frames": len(twin), "ate": ate,
                               "fps": _ratio(len(twin_record.reports), twin_record.seconds)}
            print(f" {twins[twin_key]['fps']:.2f} fps", flush=True)
    twin = twins[twin_key]
    result["twin"] = twin
    result["ate_twin"] = twin["ate"]
    result["ate_ratio"] = _ratio(result["ate"], twin["ate"])
    if name in REAL and (path / "labels").is_dir():
        print(f"  {name} with its objects blanked: running {len(sequence)} frames ...", end="", flush=True)
        blanked = run_pipeline(BlankedSequence(sequence, path / "labels"), config, None)
        result["ate_blanked"] = camera_ate(blanked, sequence, config.input.max_time_difference)
        result["ate_ratio_blanked"] = _ratio(result["ate"], result["ate_blanked"])
        print(f" {_ratio(len(blanked.reports), blanked.seconds):.2f} fps", flush=True)
    return result


def _json_ready(value):
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=None,
                        help=f"frames per sequence (default: synthetic {DEFAULT_SYNTH_FRAMES}, real all)")
    parser.add_argument("--sequences", default=DEFAULT_SEQUENCES, help=f"comma-separated (default {DEFAULT_SEQUENCES})")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="config override section.key=value")
    parser.add_argument("--seed", default="1",
                        help="seed of the synthetic sequences, or comma-separated seeds (one column each; default 1): "
                             "a target should hold over several")
    parser.add_argument("--pipeline-seeds", default=None,
                        help="comma-separated pipeline (RANSAC) seeds for the real sequences: one column each, and "
                             "the ratio of their mean ATEs (default: the config's seed)")
    parser.add_argument("--json", type=Path, default=None, help="also write every figure to this JSON file")
    parser.add_argument("--keep-synthetic", type=Path, default=None,
                        help="generate synthetic sequences into this folder (outside the repo) and reuse them")
    parser.add_argument("--size", default=f"{SYNTH_SIZE[0]}x{SYNTH_SIZE[1]}",
                        help="WIDTHxHEIGHT of the synthetic sequences (default %(default)s; sample_data is 320x240)")
    args = parser.parse_args()
    try:
        size = tuple(int(part) for part in args.size.lower().split("x"))
        if len(size) != 2 or min(size) < 64:
            raise ValueError
    except ValueError:
        parser.error(f"--size {args.size!r}: give WIDTHxHEIGHT, e.g. 320x240 (at least 64 each)")
    args.size = size
    names = [name.strip() for name in args.sequences.split(",") if name.strip()]
    unknown = [name for name in names if name not in SYNTHETIC and name not in REAL]
    if unknown:
        parser.error(f"unknown sequence(s) {', '.join(unknown)}; choose from {DEFAULT_SEQUENCES}")
    if args.frames is not None and args.frames < 3:
        parser.error("--frames must be >= 3")
    try:
        seeds = [int(seed) for seed in args.seed.split(",") if seed.strip()]
    except ValueError:
        parser.error(f"--seed {args.seed!r}: give an integer or comma-separated integers")
    if not seeds:
        parser.error("--seed: give at least one seed")
    try:
        pipeline_seeds = [int(seed) for seed in args.pipeline_seeds.split(",") if seed.strip()] \
            if args.pipeline_seeds else [None]
    except ValueError:
        parser.error(f"--pipeline-seeds {args.pipeline_seeds!r}: give comma-separated integers")
    config = load_config(None, args.overrides)

    print(f"object benchmark: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, "
          f"overrides {args.overrides or 'none'}", flush=True)
    results: dict[str, dict] = {}
    twins: dict = {}
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="jsr-bench-objects-") as temporary:
        work = args.keep_synthetic or Path(temporary)
        work.mkdir(parents=True, exist_ok=True)
        for name in names:
            if name in REAL and not (SHARED / name).is_dir():
                print(f"  {name}: skipped ({SHARED / name} not found)")
                continue
            runs = [(seed, None) for seed in seeds] if name in SYNTHETIC else [(seeds[0], p) for p in pipeline_seeds]
            for seed, pipeline_seed in runs:
                column = f"{name} s{seed}" if name in SYNTHETIC and len(seeds) > 1 else name
                if pipeline_seed is not None and len(pipeline_seeds) > 1:
                    column = f"{name} p{pipeline_seed}"
                run_config = config if pipeline_seed is None else load_config(None, [*args.overrides,
                                                                                     f"seed={pipeline_seed}"])
                try:
                    results[column] = benchmark_sequence(name, seed, args, run_config, work, twins)
                except Exception as error:  # the pipeline is work in progress: report and go on
                    print(f"\n  {column}: FAILED {type(error).__name__}: {error}")
                    traceback.print_exc()
                    results[column] = {"error": f"{type(error).__name__}: {error}"}
    print()
    print("sequences used:")
    for name, result in results.items():
        if "error" in result:
            print(f"  {name}: failed ({result['error']})")
            continue
        twin = result["twin"]
        print(f"  {name}: {result['frames']} frames of {result['sequence']} ({result['labelled_frames']} labelled); "
              f"twin without objects: {twin['frames']} frames of {twin['path']}")
    print()
    print_table(results)
    if len(pipeline_seeds) > 1:  # RANSAC noise moves a real sequence's ATE: compare means over seeds
        for name in names:
            columns = [r for column, r in results.items()
                       if column.startswith(f"{name} p") and r.get("ate") is not None and r.get("ate_twin")]
            if columns:
                ate, twin = np.mean([(r["ate"], r["ate_twin"]) for r in columns], axis=0)
                blanked = [r["ate_blanked"] for r in columns if r.get("ate_blanked")]
                control = f"; objects blanked {100 * np.mean(blanked):.2f} cm (ratio {ate / np.mean(blanked):.2f})" \
                    if len(blanked) == len(columns) else ""
                print(f"{name} over pipeline seeds {args.pipeline_seeds}: mean camera ATE {100 * ate:.2f} cm, "
                      f"without objects {100 * twin:.2f} cm, ratio of means {ate / twin:.2f}"
                      f"{'*' if ate / twin > TARGETS.get('ate_ratio', math.inf) else ''}{control}")
    print(f"total {time.perf_counter() - started:.0f} s")
    if args.json:
        document = {"config_overrides": args.overrides, "seed": seeds[0] if len(seeds) == 1 else seeds,
                    "targets": TARGETS,
                    "sequences": results}
        args.json.write_text(json.dumps(_json_ready(document), indent=2, allow_nan=False) + "\n")
        print(f"figures written to {args.json}")
    return 0 if results and all("error" not in r for r in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
