"""Plots of a results folder: the paper's Figure 7 and the camera and object trajectories.

``landmarks.csv`` has one row per frame and map with the columns
``frame, timestamp, map, keyframes, point_landmarks, plane_landmarks, tracked``
(``map`` is ``static`` or ``object_K``).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from jsr.errors import InputError
from jsr.io.atomic import atomic_path
from jsr.io.trajectory import read_tum_trajectory
from jsr.io.writers import read_csv

LANDMARK_COLUMNS = ("frame", "timestamp", "map", "keyframes", "point_landmarks", "plane_landmarks", "tracked")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only; never needs a screen
    import matplotlib.pyplot as plt

    return plt


def read_landmark_counts(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """Per map: arrays ``frame``, ``keyframes``, ``point_landmarks``, ``plane_landmarks``, ``tracked``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path} does not exist; run 'jsr reconstruct' first")
    rows = read_csv(path)
    if rows and not set(LANDMARK_COLUMNS) <= set(rows[0]):
        missing = sorted(set(LANDMARK_COLUMNS) - set(rows[0]))
        raise InputError(f"{path} lacks column(s) {', '.join(missing)}; is it a jsr landmarks.csv?")
    columns: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    try:
        for row in rows:
            series = columns[row["map"]]
            for key in ("frame", "keyframes", "point_landmarks", "plane_landmarks"):
                series[key].append(int(row[key]))
            series["tracked"].append(row["tracked"].strip().lower() in ("1", "true", "yes"))
    except ValueError as error:
        raise InputError(f"{path}: a count is not a whole number ({error})") from None
    return {name: {key: np.asarray(values) for key, values in series.items()} for name, series in columns.items()}


def _map_colour(name: str) -> str:
    # Static in red and objects in blues/greens, as in the paper's Figure 7.
    from jsr.export.colours import STATIC_COLOUR, object_colour

    number = name.removeprefix("object_")
    return STATIC_COLOUR if name == "static" or not number.isdigit() else object_colour(int(number))


def plot_landmark_counts(landmarks_csv: Path, out_png: Path, title: str | None = None) -> Path:
    """Figure 7: keyframes (left) and landmarks (right) per map over the input frames."""
    counts = read_landmark_counts(landmarks_csv)
    if not counts:
        raise InputError(f"{landmarks_csv} has no rows to plot")
    plt = _pyplot()
    figure, (keyframe_axis, landmark_axis) = plt.subplots(1, 2, figsize=(11, 4))
    for name in sorted(counts, key=lambda n: (n != "static", n)):
        series = counts[name]
        colour = _map_colour(name)
        keyframe_axis.plot(series["frame"], series["keyframes"], color=colour, label=name)
        landmark_axis.plot(series["frame"], series["point_landmarks"], color=colour, label=f"{name} points")
        landmark_axis.plot(
            series["frame"], series["plane_landmarks"], color=colour, linestyle="--", label=f"{name} planes"
        )
    keyframe_axis.set(xlabel="frame", ylabel="keyframes", title="Keyframes per map")
    landmark_axis.set(xlabel="frame", ylabel="landmarks", title="Landmarks per map")
    from matplotlib.ticker import MaxNLocator

    for axis in (keyframe_axis, landmark_axis):
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
        axis.yaxis.set_major_locator(MaxNLocator(integer=True))  # counts: no 1.5 keyframes
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return _save(figure, plt, Path(out_png))


def object_centre(folder: Path) -> np.ndarray | None:
    """Centre ``(3,)`` of the bounding box of object K's model in its own frame (``mesh.ply``,
    else ``landmarks.ply`` of ``folder``), or None when it has neither. An object frame's origin
    is the camera of the detecting frame, a metre or more from the object: its trajectory is
    drawn at this centre."""
    from jsr.io.writers import read_geometry_ply

    for name in ("mesh.ply", "landmarks.ply"):
        if (Path(folder) / name).is_file():
            geometry = read_geometry_ply(Path(folder) / name)
            points = np.asarray(geometry.vertices if hasattr(geometry, "triangles") else geometry.points)
            if len(points):
                return 0.5 * (points.min(axis=0) + points.max(axis=0))
    return None


def estimated_object_paths(results_dir: Path) -> dict[int, np.ndarray]:
    """Object id -> ``(M, 3)`` world positions of its model's centre in the frames it was tracked."""
    from jsr.export.objects import object_folder

    paths = {}
    folder = Path(results_dir) / "objects"
    names = sorted(folder.glob("object_*")) if folder.is_dir() else []
    for path in names:
        number = path.name.removeprefix("object_")
        if not number.isdigit() or not (path / "trajectory.tum").is_file():
            continue
        centre = object_centre(object_folder(results_dir, int(number)))
        _, poses = read_tum_trajectory(path / "trajectory.tum")
        if centre is not None and len(poses):
            paths[int(number)] = poses[:, :3, :3] @ centre + poses[:, :3, 3]
    return dict(sorted(paths.items()))


def true_object_paths(sequence_dir: Path) -> dict[int, np.ndarray]:
    """True object id -> ``(N, 3)`` positions of its origin (its centre) in the ground-truth
    world, from ``SEQ/objects/object_k.txt``."""
    paths = {}
    folder = Path(sequence_dir) / "objects"
    for path in sorted(folder.glob("object_*.txt")) if folder.is_dir() else []:
        number = path.stem.removeprefix("object_")
        if number.isdigit():
            paths[int(number)] = read_tum_trajectory(path)[1][:, :3, 3]
    return dict(sorted(paths.items()))


def plot_trajectory(camera_tum: Path, out_png: Path, groundtruth_tum: Path | None = None,
                    object_paths: dict[int, np.ndarray] | None = None,
                    true_object_paths: dict[int, np.ndarray] | None = None) -> Path:
    """Top view (x-z of the first camera frame) of the estimated camera trajectory and, if
    given, the true one; ``object_paths`` (object id -> ``(M, 3)`` world positions) are drawn
    in the objects' colours, ``true_object_paths`` (in the ground-truth world) dashed.

    The ground truth is brought into the estimate's world by the inverse of the rigid
    alignment ``jsr evaluate`` computes for the ATE (timestamps associated within 0.02 s,
    Umeyama on the positions), so the drawing shows the error the ATE measures."""
    from jsr.export.colours import STATIC_COLOUR, object_colour

    _, poses = read_tum_trajectory(Path(camera_tum))
    if len(poses) == 0:
        raise InputError(f"{camera_tum} holds no poses")
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(7, 6))
    axis.plot(poses[:, 0, 3], poses[:, 2, 3], color=STATIC_COLOUR, label="camera")
    gt_to_estimate = None
    if groundtruth_tum is not None:
        from jsr.evaluate.trajectory import absolute_trajectory_error, associate_poses

        est_t, est_poses = read_tum_trajectory(Path(camera_tum))
        gt_t, gt_poses = read_tum_trajectory(Path(groundtruth_tum))
        _, matched_est, matched_gt = associate_poses(est_t, est_poses, gt_t, gt_poses)
        if len(matched_gt) >= 3:
            ate = absolute_trajectory_error(matched_est, matched_gt)
            gt_to_estimate = np.linalg.inv(ate.alignment)
            gt_in_est = gt_to_estimate @ gt_poses
            axis.plot(gt_in_est[:, 0, 3], gt_in_est[:, 2, 3], color="black", linestyle="--",
                      label=f"camera, ground truth (ATE {100 * ate.rmse:.2f} cm)")
    for object_id, positions in (object_paths or {}).items():
        axis.plot(positions[:, 0], positions[:, 2], color=object_colour(object_id), marker=".", markersize=4,
                  linewidth=1, label=f"object {object_id}")
    if gt_to_estimate is not None:
        for true_id, positions in (true_object_paths or {}).items():
            aligned = positions @ gt_to_estimate[:3, :3].T + gt_to_estimate[:3, 3]
            axis.plot(aligned[:, 0], aligned[:, 2], color="grey", linestyle="--", marker="x", markersize=4,
                      linewidth=1, label=f"true object {true_id}")
    axis.set(xlabel="x [m]", ylabel="z [m]", title="Trajectories (top view, first camera frame)")
    axis.set_aspect("equal", adjustable="datalim")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    return _save(figure, plt, Path(out_png))


def plot_results(results_dir: Path, out_dir: Path | None = None, sequence_dir: Path | None = None,
                 groundtruth_tum: Path | None = None) -> list[Path]:
    """``landmarks.png`` (Figure 7) and ``trajectory.png`` of a results folder, into
    ``out_dir`` (default ``RESULTS/plots``). The ground truth is ``groundtruth_tum`` or else
    ``SEQ/groundtruth.txt`` of ``sequence_dir``, or of the sequence the run read (its
    ``summary.json``) when that folder is there; true object trajectories come from the same
    sequence folder."""
    results_dir = Path(results_dir)
    out_dir = Path(out_dir) if out_dir is not None else results_dir / "plots"
    written = [plot_landmark_counts(results_dir / "landmarks.csv", out_dir / "landmarks.png")]
    if not (results_dir / "camera.tum").is_file():
        return written
    sequence_dir = Path(sequence_dir) if sequence_dir is not None else _sequence_of_run(results_dir)
    if groundtruth_tum is None and sequence_dir is not None and (sequence_dir / "groundtruth.txt").is_file():
        groundtruth_tum = sequence_dir / "groundtruth.txt"
    written.append(plot_trajectory(
        results_dir / "camera.tum", out_dir / "trajectory.png", groundtruth_tum, estimated_object_paths(results_dir),
        true_object_paths(sequence_dir) if sequence_dir is not None else None))
    return written


def _sequence_of_run(results_dir: Path) -> Path | None:
    """The sequence folder ``summary.json`` names, when it is there (a relative path is taken
    from the current folder, as the run was likely started from it)."""
    import json

    try:
        folder = Path(json.loads((results_dir / "summary.json").read_text())["input"]["sequence"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return folder if folder.is_dir() else None


def _save(figure, plt, out_png: Path) -> Path:
    with atomic_path(out_png) as temporary:
        figure.savefig(temporary, dpi=120)
    plt.close(figure)
    return out_png
