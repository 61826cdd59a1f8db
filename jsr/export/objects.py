"""Export the model of one reconstructed object, in its own frame or placed in the world."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from jsr.errors import InputError, OutputError
from jsr.io.trajectory import read_tum_trajectory
from jsr.io.writers import read_geometry_ply, write_geometry_ply

logger = logging.getLogger(__name__)

MODEL_KINDS = ("mesh", "cloud", "landmarks")


def object_folder(results_dir: Path, object_id: int) -> Path:
    """``RESULTS/objects/object_K``, or an :class:`InputError` listing the objects there are."""
    folder = Path(results_dir) / "objects" / f"object_{object_id}"
    if not folder.is_dir():
        existing = sorted(p.name for p in (Path(results_dir) / "objects").glob("object_*")) if (
            Path(results_dir) / "objects"
        ).is_dir() else []
        listing = ", ".join(existing) if existing else "none"
        raise InputError(f"{results_dir} has no object {object_id} (objects there: {listing})")
    return folder


def export_object(
    results_dir: Path,
    object_id: int,
    out_path: Path,
    kind: str = "mesh",
    in_world: bool = False,
    timestamp: float | None = None,
    overwrite: bool = False,
) -> dict:
    """Copy object K's model to ``out_path`` (PLY), optionally placed in the world frame.

    ``kind`` picks ``mesh.ply``, ``cloud.ply`` or ``landmarks.ply`` (object frame). With
    ``in_world`` the model is moved by ``T_w_o`` of the frame at ``timestamp`` (the
    nearest tracked one), or of the first tracked frame when ``timestamp`` is None.
    Returns what was written.
    """
    if kind not in MODEL_KINDS:
        raise InputError(f"unknown model kind '{kind}'; choose one of {', '.join(MODEL_KINDS)}")
    out_path = Path(out_path)
    if out_path.suffix.lower() != ".ply":
        raise InputError(f"output {out_path} must end in .ply")
    if out_path.exists() and not overwrite:
        raise OutputError(f"{out_path} already exists; pass --overwrite or choose another file")
    folder = object_folder(results_dir, object_id)
    source = folder / f"{kind}.ply"
    if not source.is_file():
        raise InputError(f"{source} does not exist; this run wrote no {kind} for object {object_id}")
    geometry = read_geometry_ply(source)
    pose = np.eye(4)
    chosen_timestamp = None
    if in_world:
        timestamps, poses = read_tum_trajectory(folder / "trajectory.tum")
        if len(poses) == 0:
            raise InputError(f"object {object_id} was never tracked; it has no pose in the world")
        index = 0 if timestamp is None else int(np.argmin(np.abs(timestamps - timestamp)))
        pose, chosen_timestamp = poses[index], float(timestamps[index])
        geometry.transform(pose)
    write_geometry_ply(out_path, geometry)
    logger.info("exported %s of object %d to %s", kind, object_id, out_path)
    return {
        "object": object_id,
        "kind": kind,
        "source": str(source),
        "output": str(out_path),
        "frame": "world" if in_world else "object",
        "timestamp": chosen_timestamp,
    }
