"""Camera trajectory metrics: pose association by timestamp, absolute trajectory error
(ATE, after a rigid Umeyama alignment) and relative pose error (RPE)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jsr.evaluate.stats import angle_degrees, matrix, number, rms
from jsr.geometry import invert_transform, transform_points, umeyama_alignment
from jsr.io.dataset import associate_timestamps


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
            "rmse": number(self.rmse),
            "mean": number(self.mean),
            "median": number(self.median),
            "max": number(self.max),
            "count": int(self.count),
            "alignment": matrix(self.alignment),
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
        rmse=rms(errors),
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
            "translation_rmse": number(self.translation_rmse),
            "rotation_rmse": number(self.rotation_rmse),
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
    rotation = angle_degrees(errors[:, :3, :3])
    return RelativePoseError(rms(translation), rms(rotation), len(errors), delta)
