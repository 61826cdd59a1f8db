"""Plots of a results folder: the paper's Figure 7 and the camera trajectory.

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


def _map_colour(name: str, index: int) -> str:
    # Static in red and objects in blues/greens, as in the paper's Figure 7.
    if name == "static":
        return "tab:red"
    return ("tab:blue", "tab:green", "tab:purple", "tab:cyan", "tab:olive")[index % 5]


def plot_landmark_counts(landmarks_csv: Path, out_png: Path, title: str | None = None) -> Path:
    """Figure 7: keyframes (left) and landmarks (right) per map over the input frames."""
    counts = read_landmark_counts(landmarks_csv)
    if not counts:
        raise InputError(f"{landmarks_csv} has no rows to plot")
    plt = _pyplot()
    figure, (keyframe_axis, landmark_axis) = plt.subplots(1, 2, figsize=(11, 4))
    object_index = 0
    for name in sorted(counts, key=lambda n: (n != "static", n)):
        series = counts[name]
        colour = _map_colour(name, object_index)
        object_index += name != "static"
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


def plot_trajectory(camera_tum: Path, out_png: Path, groundtruth_tum: Path | None = None) -> Path:
    """Top view (x-z of the first camera frame) of the estimated and, if given, true trajectory."""
    _, poses = read_tum_trajectory(Path(camera_tum))
    if len(poses) == 0:
        raise InputError(f"{camera_tum} holds no poses")
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(6, 5))
    axis.plot(poses[:, 0, 3], poses[:, 2, 3], color="tab:red", label="estimate")
    if groundtruth_tum is not None:
        from jsr.evaluate.trajectory import associate_poses, absolute_trajectory_error

        est_t, est_poses = read_tum_trajectory(Path(camera_tum))
        gt_t, gt_poses = read_tum_trajectory(Path(groundtruth_tum))
        _, matched_est, matched_gt = associate_poses(est_t, est_poses, gt_t, gt_poses)
        if len(matched_gt) >= 3:
            # Ground truth shown in the estimate's frame (inverse of the ATE alignment).
            alignment = absolute_trajectory_error(matched_est, matched_gt).alignment
            gt_in_est = np.linalg.inv(alignment) @ gt_poses
            axis.plot(gt_in_est[:, 0, 3], gt_in_est[:, 2, 3], color="black", linestyle="--", label="ground truth")
    axis.set(xlabel="x [m]", ylabel="z [m]", title="Camera trajectory (top view)")
    axis.set_aspect("equal", adjustable="datalim")
    axis.grid(alpha=0.3)
    axis.legend()
    figure.tight_layout()
    return _save(figure, plt, Path(out_png))


def _save(figure, plt, out_png: Path) -> Path:
    with atomic_path(out_png) as temporary:
        figure.savefig(temporary, dpi=120)
    plt.close(figure)
    return out_png
