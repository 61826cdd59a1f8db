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
    nearest tracked one; a time outside the tracked span is an error), or of the first tracked
    frame when ``timestamp`` is None; ``timestamp`` without ``in_world`` is an error.
    Returns what was written.
    """
    if kind not in MODEL_KINDS:
        raise InputError(f"unknown model kind '{kind}'; choose one of {', '.join(MODEL_KINDS)}")
    out_path = Path(out_path)
    if out_path.suffix.lower() != ".ply":
        raise InputError(f"output {out_path} must end in .ply")
    if out_path.exists() and not overwrite:
        raise OutputError(f"{out_path} already exists; pass --overwrite or choose another file")
    model_folders = [Path(results_dir).resolve() / name for name in ("objects", "static")]
    if out_path.exists() and any(out_path.resolve().is_relative_to(folder) for folder in model_folders):
        raise OutputError(f"{out_path} is one of the models of the results folder {results_dir}; write the export "
                          "elsewhere")
    if timestamp is not None and not in_world:
        raise InputError("--timestamp picks the pose that places the object in the world: give it with --world")
    if not Path(results_dir).is_dir():
        raise InputError(f"results folder {results_dir} does not exist")
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
        if timestamp is not None:
            # a frame's worth of slack either side (one pose: 0.1 s), no more: a time outside
            # the tracked span has no pose of the object
            slack = float(np.median(np.diff(timestamps))) if len(timestamps) > 1 else 0.1
            if not timestamps[0] - slack <= timestamp <= timestamps[-1] + slack:
                raise InputError(f"object {object_id} was tracked from {timestamps[0]:.6f} to {timestamps[-1]:.6f}; "
                                 f"--timestamp {timestamp:.6f} is outside that span")
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
