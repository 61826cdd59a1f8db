"""A real RGB-D sequence used as the background of a composite: its frames, camera and
ground-truth camera poses.

The background is a TUM-layout folder with ``groundtruth.txt`` (``T_w_c``) and
``camera.yaml``. Colour and depth are associated as :func:`jsr.io.dataset.open_sequence` does;
each frame keeps both of its timestamps, since real sensors take colour and depth at slightly
different times (Bonn: up to 16 ms apart): the camera pose is interpolated in the ground truth
at each of them, so that what is rendered into the depth image lines up with the real depth,
and what is rendered into the colour image with the real colour.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from jsr.errors import InputError
from jsr.io.camera import CameraIntrinsics, load_camera_yaml
from jsr.io.dataset import FrameEntry, is_tum_folder, load_color_image, open_sequence, read_image_list
from jsr.io.trajectory import interpolate_poses, read_tum_trajectory

logger = logging.getLogger(__name__)

# How far past either end of the ground truth a frame may lie (in units of the ground truth's
# median spacing): its pose is extrapolated at constant velocity over at most that gap.
MAX_EXTRAPOLATION_STEPS = 1.0


@dataclass
class BackgroundFrame(FrameEntry):
    """One frame of the background: its files, ``timestamp`` (colour) and ``depth_timestamp``.
    ``name`` (the colour file's stem) names the frame's labels image."""

    depth_timestamp: float = 0.0


@dataclass
class Background:
    """The selected frames of a real sequence and the camera at each.

    ``colour_poses`` and ``depth_poses`` ``(N, 4, 4)`` are ``T_w_c`` at each frame's colour and
    depth timestamp, in the world of the background's ground truth.
    """

    root: Path
    intrinsics: CameraIntrinsics
    frames: list[BackgroundFrame]
    colour_poses: np.ndarray
    depth_poses: np.ndarray
    start: int
    total_frames: int  # frames of the whole background (before the selection)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def colour_format(self) -> str:
        """``jpg`` when the background's colour images are JPEG, else ``png``."""
        suffix = self.frames[0].color_path.suffix.lower()
        return "jpg" if suffix in (".jpg", ".jpeg") else "png"

    @property
    def colour_timestamps(self) -> np.ndarray:
        return np.array([frame.timestamp for frame in self.frames])

    def colour(self, index: int) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB colour of frame ``index``."""
        return load_color_image(self.frames[index].color_path)

    def depth_raw(self, index: int) -> np.ndarray:
        """``(H, W)`` uint16 depth of frame ``index`` as stored (``depth_scale`` per metre, 0 invalid)."""
        path = self.frames[index].depth_path
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None or image.ndim != 2 or image.dtype != np.uint16:
            raise InputError(f"depth image {path} is unreadable or not a 16-bit PNG; replace it or remove its line")
        if image.shape != (self.intrinsics.height, self.intrinsics.width):
            raise InputError(
                f"depth image {path} is {image.shape[1]}x{image.shape[0]} but {self.root / 'camera.yaml'} says "
                f"{self.intrinsics.width}x{self.intrinsics.height}"
            )
        return image

    def depth(self, index: int) -> np.ndarray:
        """``(H, W)`` float64 metres of frame ``index``, 0 where the sensor gave no depth."""
        return self.depth_raw(index).astype(np.float64) / self.intrinsics.depth_scale


def open_background(path: Path | str, start: int, frames: int, max_time_difference: float = 0.02) -> Background:
    """Frames ``start .. start + frames - 1`` of the TUM-layout sequence at ``path``, with the
    ground-truth camera at each. Raises :class:`InputError` (one line) when the folder is not a
    TUM sequence with ``groundtruth.txt`` and ``camera.yaml``, has too few frames, or its ground
    truth does not cover the frames."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"background {root} is not a folder; give a TUM RGB-D sequence folder")
    if not is_tum_folder(root):
        raise InputError(f"background {root} has no rgb.txt; it must be a TUM RGB-D sequence (rgb.txt, depth.txt)")
    for name, why in (("groundtruth.txt", "the camera's ground-truth poses"), ("camera.yaml", "its intrinsics")):
        if not (root / name).is_file():
            raise InputError(f"background {root} has no {name}; compositing needs {why}")
    intrinsics = load_camera_yaml(root / "camera.yaml")
    sequence = open_sequence(root, max_time_difference=max_time_difference)
    total = len(sequence)
    if start + frames > total:
        raise InputError(
            f"--start {start} --frames {frames} needs {start + frames} frames but background {root} has {total}; "
            "choose fewer frames or an earlier --start"
        )
    depth_times = {(root / name).resolve(): timestamp for timestamp, name in read_image_list(root / "depth.txt")}
    selected = [
        BackgroundFrame(entry.timestamp, entry.color_path, entry.depth_path, depth_times[entry.depth_path.resolve()])
        for entry in sequence.entries[start : start + frames]
    ]
    gt_times, gt_poses = read_tum_trajectory(root / "groundtruth.txt")
    colour_times = np.array([frame.timestamp for frame in selected])
    depth_times_selected = np.array([frame.depth_timestamp for frame in selected])
    gt_times, gt_poses = _increasing(gt_times, gt_poses, root)
    _check_covered(gt_times, np.concatenate([colour_times, depth_times_selected]), root, start, frames)
    return Background(
        root=root,
        intrinsics=intrinsics,
        frames=selected,
        colour_poses=interpolate_poses(gt_times, gt_poses, colour_times),
        depth_poses=interpolate_poses(gt_times, gt_poses, depth_times_selected),
        start=start,
        total_frames=total,
    )


def _increasing(times: np.ndarray, poses: np.ndarray, root: Path) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth sorted by time, repeated timestamps dropped (the first kept)."""
    if len(times) < 2:
        raise InputError(f"background {root}: groundtruth.txt has {len(times)} poses; compositing needs at least 2")
    order = np.argsort(times, kind="stable")
    times, poses = times[order], poses[order]
    keep = np.concatenate([[True], np.diff(times) > 0])
    return times[keep], poses[keep]


def _check_covered(gt_times: np.ndarray, query: np.ndarray, root: Path, start: int, frames: int) -> None:
    """Every query time lies within the ground truth, or past an end by at most one step."""
    step = float(np.median(np.diff(gt_times)))
    allowed = MAX_EXTRAPOLATION_STEPS * step + 1e-6
    outside = (query < gt_times[0] - allowed) | (query > gt_times[-1] + allowed)
    # Inside the span, a gap in the ground truth (tracking lost) must not be bridged either.
    position = np.clip(np.searchsorted(gt_times, query), 1, len(gt_times) - 1)
    gap = gt_times[position] - gt_times[position - 1]
    inside = (query >= gt_times[0]) & (query <= gt_times[-1])
    outside |= inside & (gap > 10.0 * step)
    if np.any(outside):
        first = float(query[np.argmax(outside)])
        raise InputError(
            f"background {root}: frame time {first:.6f} (frames {start}..{start + frames - 1}) has no ground-truth "
            f"pose near it (groundtruth.txt spans {gt_times[0]:.6f}..{gt_times[-1]:.6f}); choose other frames"
        )
    logger.debug("%s: ground truth covers the selected frames (median spacing %.4f s)", root, step)
