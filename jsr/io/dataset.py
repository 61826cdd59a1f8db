"""RGB-D sequence readers: TUM RGB-D layout (TUM, ICL-NUIM, Bonn) and discrete image sets.

A sequence is indexable: ``sequence[i]`` loads frame ``i`` lazily from disk and returns a
:class:`Frame`. Colour is RGB ``uint8 (H, W, 3)``; depth is ``float32 (H, W)`` metres with
0 where the sensor gave no depth. ``open_sequence`` picks the reader from the folder layout.

TUM layout::

    SEQ/rgb.txt, SEQ/depth.txt      "timestamp filename" lines, '#' comments
    SEQ/groundtruth.txt             optional, "timestamp tx ty tz qx qy qz qw" (camera-to-world)
    SEQ/camera.yaml                 intrinsics (or --camera / --preset)

Discrete image set (no timestamps, e.g. the paper's Scene 1)::

    SEQ/rgb/NAME.png|jpg  + SEQ/depth/NAME.png      (also color/ or colour/ or image/)
    SEQ/NAME_rgb.png      + SEQ/NAME_depth.png      (also _color / _colour)
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from jsr.errors import InputError
from jsr.io.camera import CameraIntrinsics, resolve_intrinsics
from jsr.io.text import read_user_text
from jsr.io.trajectory import read_tum_trajectory

logger = logging.getLogger(__name__)

# OpenCV's own warnings (e.g. "PNG input buffer is incomplete") would reach the terminal beside
# jsr's one-line error; jsr checks every decoded image itself.
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm")
COLOUR_FOLDERS = ("rgb", "color", "colour", "image", "images")
COLOUR_SUFFIX_TAGS = ("_rgb", "_color", "_colour")


@dataclass
class Frame:
    """One RGB-D frame.

    ``color``: ``(H, W, 3)`` uint8 RGB. ``depth``: ``(H, W)`` float32 metres, 0 = invalid.
    ``index`` is the position in the (selected) sequence, ``name`` the colour file stem,
    used to name per-frame outputs such as masks.
    """

    index: int
    timestamp: float
    color: np.ndarray
    depth: np.ndarray
    intrinsics: CameraIntrinsics
    name: str
    color_path: Path
    depth_path: Path

    @property
    def valid_depth(self) -> np.ndarray:
        """``(H, W)`` bool mask of pixels with depth."""
        return self.depth > 0


@dataclass
class FrameEntry:
    """Where a frame lives on disk, before it is loaded."""

    timestamp: float
    color_path: Path
    depth_path: Path

    @property
    def name(self) -> str:
        return self.color_path.stem


@dataclass
class SelectionReport:
    """What happened while listing a sequence (for the user and ``summary.json``)."""

    listed: int = 0
    missing_files: int = 0
    unmatched: int = 0
    selected: int = 0
    notes: list[str] = field(default_factory=list)


def read_image_list(path: Path) -> list[tuple[float, str]]:
    """Read a TUM ``rgb.txt``/``depth.txt``: ``(timestamp, relative filename)`` pairs, file order."""
    entries = []
    for line_number, line in enumerate(read_user_text(path, "image list").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.split()
        if len(fields) < 2:
            raise InputError(f"{path}:{line_number}: expected 'timestamp filename'")
        try:
            timestamp = float(fields[0])
        except ValueError:
            raise InputError(f"{path}:{line_number}: '{fields[0]}' is not a timestamp") from None
        entries.append((timestamp, fields[1]))
    return entries


def associate_timestamps(
    first: np.ndarray, second: np.ndarray, max_difference: float
) -> list[tuple[int, int]]:
    """Associate two timestamp lists one-to-one by nearest time, at most ``max_difference`` apart.

    Follows the TUM ``associate.py`` rule: all candidate pairs within the tolerance are taken
    greedily from the closest, each index used once. Returns ``(i, j)`` pairs sorted by ``i``.
    """
    first = np.asarray(first, dtype=float)
    second = np.asarray(second, dtype=float)
    order = np.argsort(second, kind="stable")
    sorted_second = second[order]
    candidates = []
    for i, time in enumerate(first):
        low = bisect.bisect_left(sorted_second, time - max_difference)
        high = bisect.bisect_right(sorted_second, time + max_difference)
        for position in range(low, high):
            candidates.append((abs(sorted_second[position] - time), i, int(order[position])))
    candidates.sort()
    used_first, used_second, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            pairs.append((i, j))
    return sorted(pairs)


class RGBDSequence:
    """A lazily loaded, possibly subsampled RGB-D sequence.

    ``len(sequence)`` frames; ``sequence[i]`` loads frame ``i`` (negative indices allowed).
    ``groundtruth`` holds ``(timestamps (M,), poses (M, 4, 4))`` camera-to-world when the
    folder has ``groundtruth.txt``.
    """

    def __init__(
        self,
        root: Path,
        entries: list[FrameEntry],
        intrinsics: CameraIntrinsics,
        kind: str,
        report: SelectionReport,
        min_depth: float = 0.0,
        max_depth: float = float("inf"),
    ):
        self.root = Path(root)
        self.entries = entries
        self.intrinsics = intrinsics
        self.kind = kind
        self.report = report
        self.min_depth = min_depth
        self.max_depth = max_depth
        groundtruth_path = self.root / "groundtruth.txt"
        self.groundtruth = read_tum_trajectory(groundtruth_path) if groundtruth_path.is_file() else None

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, index: int) -> Frame:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame {index} out of range for {len(self)} frames")
        index %= len(self)
        entry = self.entries[index]
        color = load_color_image(entry.color_path)
        depth = load_depth_image(entry.depth_path, self.intrinsics.depth_scale)
        check_frame_shapes(color, depth, self.intrinsics, entry)
        # Depth outside the sensor's working range is noise, not geometry.
        depth[(depth < self.min_depth) | (depth > self.max_depth)] = 0.0
        return Frame(index, entry.timestamp, color, depth, self.intrinsics, entry.name, entry.color_path, entry.depth_path)

    def __iter__(self):
        for index in range(len(self)):
            yield self[index]

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([entry.timestamp for entry in self.entries])

    @property
    def names(self) -> list[str]:
        return [entry.name for entry in self.entries]


def load_color_image(path: Path) -> np.ndarray:
    """Read a colour image as RGB ``uint8 (H, W, 3)``; grey images are expanded to 3 channels."""
    data = _read_file_bytes(path, "colour")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise InputError(f"colour image {path} is unreadable or truncated; replace it or remove its line")
    if image.dtype != np.uint8:
        # 16-bit colour: keep the high byte.
        image = (image / 257.0).astype(np.uint8) if image.dtype == np.uint16 else image.astype(np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.shape[2] == 4:
        image = image[:, :, :3]
    return np.ascontiguousarray(image[:, :, ::-1])


def load_depth_image(path: Path, depth_scale: float) -> np.ndarray:
    """Read a 16-bit depth PNG as float32 metres ``(H, W)``; 0 stays 0 (invalid)."""
    data = _read_file_bytes(path, "depth")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise InputError(f"depth image {path} is unreadable or truncated; replace it or remove its line")
    if image.ndim != 2:
        raise InputError(f"depth image {path} has {image.shape[2]} channels; expected a 1-channel 16-bit PNG")
    if image.dtype != np.uint16:
        raise InputError(f"depth image {path} is {image.dtype}, expected 16-bit (uint16) depth")
    return image.astype(np.float32) / np.float32(depth_scale)


def _read_file_bytes(path: Path, what: str) -> bytes:
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise InputError(f"{what} image {path} does not exist") from None
    except OSError as error:
        raise InputError(f"cannot read {what} image {path}: {error.strerror}") from None
    if not data:
        raise InputError(f"{what} image {path} is empty; replace it or remove its line")
    if data.startswith(PNG_SIGNATURE) and PNG_END not in data[-PNG_END_SEARCH:]:
        # cut short (a copy that stopped): said here, before libpng prints its own complaint
        raise InputError(f"{what} image {path} is truncated (no PNG end marker); replace it or remove its line")
    return data


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"IEND"  # the last chunk of every complete PNG: its type, then a 4-byte checksum
PNG_END_SEARCH = 64  # bytes at the end searched for it (some writers append a few bytes after it)


def check_frame_shapes(color: np.ndarray, depth: np.ndarray, intrinsics: CameraIntrinsics, entry: FrameEntry) -> None:
    """Colour and depth must have the same size, and that of the camera calibration."""
    if color.shape[:2] != depth.shape:
        raise InputError(
            f"depth {entry.depth_path} is {depth.shape[1]}x{depth.shape[0]} but colour "
            f"{entry.color_path.name} is {color.shape[1]}x{color.shape[0]}; register depth to colour first"
        )
    if (intrinsics.width, intrinsics.height) != (color.shape[1], color.shape[0]):
        raise InputError(
            f"{entry.color_path} is {color.shape[1]}x{color.shape[0]} but the camera calibration is "
            f"{intrinsics.width}x{intrinsics.height}; use a matching camera.yaml or --camera FILE"
        )


def is_tum_folder(path: Path) -> bool:
    return (Path(path) / "rgb.txt").is_file()


def list_tum_entries(root: Path, max_time_difference: float) -> tuple[list[FrameEntry], SelectionReport]:
    """Associate ``rgb.txt`` and ``depth.txt`` by nearest timestamp; skip and count missing files."""
    rgb_list, depth_list = root / "rgb.txt", root / "depth.txt"
    if not depth_list.is_file():
        raise InputError(f"{root} has rgb.txt but no depth.txt; jsr needs depth for every frame")
    colours, depths = read_image_list(rgb_list), read_image_list(depth_list)
    report = SelectionReport(listed=len(colours))
    pairs = associate_timestamps(
        np.array([t for t, _ in colours]), np.array([t for t, _ in depths]), max_time_difference
    )
    report.unmatched = len(colours) - len(pairs)
    entries = []
    missing = []
    for i, j in pairs:
        color_path, depth_path = root / colours[i][1], root / depths[j][1]
        if not color_path.is_file() or not depth_path.is_file():
            report.missing_files += 1
            missing.append(colours[i][1] if not color_path.is_file() else depths[j][1])
            continue
        entries.append(FrameEntry(colours[i][0], color_path, depth_path))
    if report.unmatched:
        report.notes.append(
            f"{report.unmatched} colour images had no depth within {max_time_difference} s and were skipped"
        )
    if report.missing_files:
        named = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
        frames = "frame" if report.missing_files == 1 else "frames"
        report.notes.append(f"{report.missing_files} listed {frames} skipped: missing file {named} in {root}")
    return entries, report


def list_image_set_entries(root: Path) -> tuple[list[FrameEntry], SelectionReport]:
    """Pair colour and depth images of a discrete image set by file name; timestamps are indices."""
    pairs: dict[str, list[Path | None]] = {}
    depth_folder = root / "depth"
    colour_folder = next((root / name for name in COLOUR_FOLDERS if (root / name).is_dir()), None)
    if colour_folder is not None and depth_folder.is_dir():
        for path in _images_in(colour_folder):
            pairs.setdefault(path.stem, [None, None])[0] = path
        for path in _images_in(depth_folder):
            pairs.setdefault(path.stem, [None, None])[1] = path
    else:
        for path in _images_in(root):
            stem = path.stem
            for tag in COLOUR_SUFFIX_TAGS:
                if stem.endswith(tag):
                    pairs.setdefault(stem[: -len(tag)], [None, None])[0] = path
            if stem.endswith("_depth"):
                pairs.setdefault(stem[: -len("_depth")], [None, None])[1] = path
    complete = sorted((name, paths) for name, paths in pairs.items() if paths[0] is not None and paths[1] is not None)
    report = SelectionReport(listed=len(pairs), unmatched=len(pairs) - len(complete))
    if report.unmatched:
        report.notes.append(f"{report.unmatched} images had no colour/depth partner of the same name and were skipped")
    entries = [FrameEntry(float(index), paths[0], paths[1]) for index, (_, paths) in enumerate(complete)]
    return entries, report


def _images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def open_sequence(
    path: Path,
    camera_file: Path | None = None,
    preset: str | None = None,
    max_time_difference: float = 0.02,
    start: int = 0,
    max_frames: int | None = None,
    stride: int = 1,
    min_depth: float = 0.0,
    max_depth: float = float("inf"),
) -> RGBDSequence:
    """Open a TUM-layout sequence or a discrete image set and select frames.

    Frames ``start, start + stride, ...`` are kept, at most ``max_frames`` of them.
    Raises :class:`InputError` with a one-line message when the folder cannot be used.
    """
    root = Path(path)
    if not root.exists():
        raise InputError(f"sequence folder {root} does not exist")
    if not root.is_dir():
        raise InputError(f"{root} is not a folder; give the sequence folder (with rgb.txt or image pairs)")
    for option, value, least in (("--start", start, 0), ("--stride", stride, 1), ("--max-frames", max_frames, 1)):
        if value is not None and value < least:
            raise InputError(f"{option} must be >= {least}, got {value}")
    if is_tum_folder(root):
        entries, report = list_tum_entries(root, max_time_difference)
        kind = "tum"
    else:
        entries, report = list_image_set_entries(root)
        kind = "image-set"
        if report.listed == 0:
            raise InputError(
                f"{root} has neither rgb.txt nor colour/depth image pairs (rgb/ + depth/ or NAME_rgb + NAME_depth)"
            )
    if not entries:
        why = f" ({'; '.join(report.notes)})" if report.notes else " (its image lists are empty)"
        raise InputError(f"{root}: no frame has both a colour and a depth image{why}")
    selected = entries[start::stride]
    if max_frames is not None:
        selected = selected[:max_frames]
    if not selected:
        raise InputError(f"--start {start} is past the last of the {len(entries)} frames of {root}")
    report.selected = len(selected)
    intrinsics, source = resolve_intrinsics(root, camera_file, preset)
    for note in report.notes:
        logger.warning("%s: %s", root, note)
    logger.info("%s: %s sequence, %d frames selected, intrinsics from %s", root, kind, len(selected), source)
    return RGBDSequence(root, selected, intrinsics, kind, report, min_depth, max_depth)


def check_first_frame(sequence: RGBDSequence) -> Frame:
    """Load the first frame and require some valid depth in it (catches wrong depth files or scale)."""
    frame = sequence[0]
    if not np.any(frame.depth > 0):
        raise InputError(
            f"first frame {frame.depth_path.name} has no valid depth; check the depth images and depth_scale"
        )
    return frame
