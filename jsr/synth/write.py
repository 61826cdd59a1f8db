"""Writing a synthetic sequence folder (TUM RGB-D layout) and clearing a previous one.

:func:`generate_sequence` renders every frame of the plan and writes the colour, depth and
label images, the camera and object trajectories, ``camera.yaml`` and ``synth.yaml``; the
image lists come last, so a sequence is only readable once every frame is on disk.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from jsr.errors import OutputError
from jsr.io.atomic import atomic_path, atomic_write_text
from jsr.io.camera import write_camera_yaml
from jsr.io.trajectory import write_tum_trajectory
from jsr.synth.options import SynthOptions, validate_options
from jsr.synth.render import SynthRenderer
from jsr.synth.scene import DEPTH_SCALE, TABLE_TOP, ScenePlan, build_scene_plan

logger = logging.getLogger(__name__)

JPEG_QUALITY = 95

GENERATED_FILES = ("rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "synth.yaml")
GENERATED_FOLDERS = ("rgb", "depth", "labels", "objects")
# Timestamp names (a composite keeps its background's, e.g. 1548339819.87426), and their temporary files.
_GENERATED_IMAGE = re.compile(r"^\.?\d+(\.\d+)?(\.[^.]+)?\.(png|jpg)$")
_GENERATED_OBJECT = re.compile(r"^\.?object_\d+(\.[^.]+)?\.txt$")


def encode_depth(depth: np.ndarray, depth_scale: float = DEPTH_SCALE) -> np.ndarray:
    """Metres to the 16-bit PNG values (``depth_scale`` per metre, 5000 by default; 0 = invalid)."""
    return np.clip(np.round(np.asarray(depth) * depth_scale), 0, 65535).astype(np.uint16)


def _is_generated(path: Path, root: Path) -> bool:
    relative = path.relative_to(root)
    if len(relative.parts) == 1:
        return relative.name in GENERATED_FILES
    if len(relative.parts) == 2 and relative.parts[0] in ("rgb", "depth", "labels"):
        return bool(_GENERATED_IMAGE.match(relative.name))
    if len(relative.parts) == 2 and relative.parts[0] == "objects":
        return bool(_GENERATED_OBJECT.match(relative.name))
    return False


def check_output_folder(out_dir: Path, overwrite: bool) -> None:
    """Raise :class:`OutputError` when :func:`generate_sequence` could not write into
    ``out_dir`` (a file, or a folder with files and no ``overwrite``); changes nothing."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir} is a file; give a folder for the synthetic sequence")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise OutputError(f"{out_dir} is not empty; pass --overwrite to replace it or choose another folder")


def prepare_output(out_dir: Path, overwrite: bool) -> None:
    """Make ``out_dir`` ready for a sequence: checked as :func:`check_output_folder` does; with
    ``overwrite``, the files jsr synth writes are removed (others are kept)."""
    check_output_folder(out_dir, overwrite)
    if out_dir.is_dir() and any(out_dir.iterdir()):
        removed = 0
        for path in sorted(out_dir.rglob("*"), reverse=True):
            if path.is_file() and _is_generated(path, out_dir):
                path.unlink()
                removed += 1
        for name in GENERATED_FOLDERS:
            folder = out_dir / name
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        logger.info("%s: removed %d files of a previous synthetic sequence", out_dir, removed)
        if any(out_dir.iterdir()):
            logger.info("%s: keeping files that jsr synth did not write", out_dir)
    try:
        for name in GENERATED_FOLDERS:
            (out_dir / name).mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OutputError(f"cannot create {out_dir}: {error.strerror}; choose a writable folder") from None


def write_image(path: Path, image: np.ndarray, image_format: str) -> None:
    """Write an image atomically: ``png`` (compression 6) or ``jpg`` (quality ``JPEG_QUALITY``);
    ``image`` is BGR colour, or one channel (uint8 labels, uint16 depth)."""
    params = (cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY) if image_format == "jpg" else (cv2.IMWRITE_PNG_COMPRESSION, 6)
    with atomic_path(path) as temporary:
        if not cv2.imwrite(str(temporary), image, list(params)):
            raise OutputError(f"cannot write {path}; check the free disk space and permissions")


def image_list_text(
    kind: str, timestamps: list[str], names: list[str], folder: str, suffix: str, header: str
) -> str:
    """A TUM ``rgb.txt``/``depth.txt``: ``timestamp folder/name.suffix`` lines under ``header``."""
    lines = [f"# {kind} images", f"# {header}", "# timestamp filename"]
    lines += [f"{timestamp} {folder}/{name}.{suffix}" for timestamp, name in zip(timestamps, names)]
    return "\n".join(lines) + "\n"


def object_records(plan: ScenePlan) -> list[dict]:
    """``synth.yaml``'s description of each object: id, shape, size, when it moves."""
    return [
        {
            "id": k + 1,
            "shape": shape.kind,
            "size": [round(float(s), 6) for s in shape.size],
            "first_motion_frame": plan.first_motion_frames[k],
            "moving_frames": plan.moving_frames[k],
        }
        for k, shape in enumerate(plan.object_shapes)
    ]


def generate_sequence(
    out_dir: Path,
    options: SynthOptions,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Write the sequence of ``options`` to ``out_dir``; returns a JSON-ready summary dict.

    Raises :class:`InputError` for invalid options and :class:`OutputError` when
    ``out_dir`` is not empty (unless ``overwrite``: then only files this generator writes
    are removed first) or cannot be written.
    """
    from jsr import __version__

    started = time.perf_counter()
    options = validate_options(options)
    out_dir = Path(out_dir)
    prepare_output(out_dir, overwrite)
    plan = build_scene_plan(options)
    renderer = SynthRenderer(plan)
    suffix = options.image_format

    write_camera_yaml(out_dir / "camera.yaml", plan.intrinsics)
    metadata = {
        "generator": "jsr synth",
        "version": __version__,
        "options": asdict(options),
        "world_frame": "room frame, z up, floor at z = 0, table top at z = %.2f" % TABLE_TOP,
        "labels": "0 static scene, k object k",
        "objects": object_records(plan),
    }
    import yaml

    atomic_write_text(out_dir / "synth.yaml", yaml.safe_dump(metadata, sort_keys=False))

    for index, name in enumerate(plan.names):
        frame = renderer.render(index)
        write_image(out_dir / "rgb" / f"{name}.{suffix}", frame.color[:, :, ::-1], suffix)
        write_image(out_dir / "depth" / f"{name}.png", encode_depth(frame.depth), "png")
        write_image(out_dir / "labels" / f"{name}.png", frame.labels, "png")
        if progress is not None:
            progress(index + 1, options.frames)

    header = f"synthetic sequence by jsr synth (seed {options.seed})"
    camera_header = header + "\ncamera-to-world T_w_c"
    write_tum_trajectory(out_dir / "groundtruth.txt", plan.timestamps, plan.camera_poses, camera_header)
    for k in range(options.objects):
        write_tum_trajectory(
            out_dir / "objects" / f"object_{k + 1}.txt",
            plan.timestamps,
            plan.object_poses[k],
            header + f"\nobject {k + 1}: object-to-world T_w_o, origin at the object centre",
        )
    # The lists come last: a sequence is only readable once every frame is on disk.
    atomic_write_text(out_dir / "depth.txt", image_list_text("depth", plan.names, plan.names, "depth", "png", header))
    atomic_write_text(out_dir / "rgb.txt", image_list_text("colour", plan.names, plan.names, "rgb", suffix, header))

    seconds = time.perf_counter() - started
    logger.info("%s: %d synthetic frames written in %.1f s", out_dir, options.frames, seconds)
    return {
        "out_dir": str(out_dir),
        "frames": options.frames,
        "objects": options.objects,
        "motion": options.motion,
        "simultaneous": options.simultaneous,
        "width": options.width,
        "height": options.height,
        "seed": options.seed,
        "image_format": suffix,
        "first_motion_frame": plan.first_motion_frames,
        "moving_frames": plan.moving_frames,
        "seconds": round(seconds, 3),
        "seconds_per_frame": round(seconds / options.frames, 4),
    }
