"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments.

Values are written with Python's shortest round-trip float representation, so a
trajectory read back is the one written (full precision, readable by evo and the TUM tools).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jsr.errors import InputError
from jsr.geometry import pose_from_tum, pose_to_tum
from jsr.io.atomic import atomic_write_text
from jsr.io.text import read_user_text


def format_tum_lines(timestamps: np.ndarray, poses: np.ndarray) -> list[str]:
    """Lines of a TUM file for ``(N,)`` timestamps and ``(N, 4, 4)`` poses."""
    rows = pose_to_tum(np.asarray(poses, dtype=float).reshape(-1, 4, 4))
    return [
        " ".join(repr(float(value)) for value in (timestamp, *row))
        for timestamp, row in zip(np.asarray(timestamps, dtype=float), rows)
    ]


def write_tum_trajectory(path: Path, timestamps: np.ndarray, poses: np.ndarray, header: str | None = None) -> None:
    """Write ``(N,)`` timestamps and ``(N, 4, 4)`` poses as a TUM file, atomically."""
    timestamps = np.asarray(timestamps, dtype=float).reshape(-1)
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    if len(timestamps) != len(poses):
        raise ValueError(f"{len(timestamps)} timestamps but {len(poses)} poses")
    lines = []
    if header:
        lines += [f"# {line}" for line in header.splitlines()]
    lines.append("# timestamp tx ty tz qx qy qz qw")
    lines += format_tum_lines(timestamps, poses)
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file. Returns ``(N,)`` timestamps and ``(N, 4, 4)`` poses, in file order."""
    path = Path(path)
    timestamps, rows = [], []
    for line_number, line in enumerate(read_user_text(path, "trajectory file").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.replace(",", " ").split()
        if len(fields) != 8:
            raise InputError(f"{path}:{line_number}: expected 8 values 'timestamp tx ty tz qx qy qz qw'")
        try:
            values = [float(field) for field in fields]
        except ValueError:
            raise InputError(f"{path}:{line_number}: a value is not a number") from None
        if np.linalg.norm(values[4:8]) < 1e-9:
            raise InputError(f"{path}:{line_number}: quaternion has zero length")
        timestamps.append(values[0])
        rows.append(values[1:])
    if not rows:
        return np.zeros(0), np.zeros((0, 4, 4))
    return np.asarray(timestamps), pose_from_tum(np.asarray(rows))


def interpolate_poses(timestamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses ``(Q, 4, 4)`` of a trajectory (``(M,)`` increasing timestamps, ``(M, 4, 4)``) at
    ``(Q,)`` query times: translation linear, rotation along the geodesic (slerp) between the
    two poses around each query. A query outside the trajectory's span is extrapolated from
    its end segment at constant velocity; callers bound how far that may go."""
    from scipy.spatial.transform import Rotation

    timestamps = np.asarray(timestamps, dtype=float).reshape(-1)
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    query = np.asarray(query, dtype=float).reshape(-1)
    if len(timestamps) < 2:
        if len(timestamps) == 1:
            return np.repeat(poses[:1], len(query), axis=0)
        raise ValueError("interpolate_poses needs at least one pose")
    if np.any(np.diff(timestamps) <= 0):
        raise ValueError("interpolate_poses needs strictly increasing timestamps")
    segment = np.clip(np.searchsorted(timestamps, query, side="right") - 1, 0, len(timestamps) - 2)
    t0, t1 = timestamps[segment], timestamps[segment + 1]
    s = (query - t0) / (t1 - t0)
    start, end = poses[segment], poses[segment + 1]
    relative = Rotation.from_matrix(np.einsum("nji,njk->nik", start[:, :3, :3], end[:, :3, :3])).as_rotvec()
    result = np.zeros((len(query), 4, 4))
    result[:, :3, :3] = start[:, :3, :3] @ Rotation.from_rotvec(relative * s[:, None]).as_matrix()
    result[:, :3, 3] = start[:, :3, 3] + s[:, None] * (end[:, :3, 3] - start[:, :3, 3])
    result[:, 3, 3] = 1.0
    return result
