"""Camera intrinsics: ``camera.yaml``, named presets, and undistortion.

``camera.yaml`` (the format of ``../shared/data``)::

    fx: 585.0
    fy: 585.0
    cx: 320.0
    cy: 240.0
    width: 640
    height: 480
    depth_scale: 5000.0          # depth PNG units per metre
    distortion: [k1, k2, p1, p2, k3]   # optional, OpenCV order
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from jsr.errors import InputError
from jsr.io.atomic import atomic_write_text
from jsr.io.text import describe_yaml_error, read_user_text


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the colour image that depth is registered to.

    ``distortion`` holds OpenCV's ``(k1, k2, p1, p2, k3)``; empty or all zero means none.
    ``depth_scale`` converts the 16-bit depth PNG values to metres (value / depth_scale).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    depth_scale: float = 5000.0
    distortion: tuple[float, ...] = field(default_factory=tuple)

    @property
    def matrix(self) -> np.ndarray:
        """The ``(3, 3)`` calibration matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(k) > 0.0 for k in self.distortion)

    @property
    def distortion_coefficients(self) -> np.ndarray:
        """OpenCV distortion vector ``(5,)`` (zeros when the lens has none)."""
        coefficients = np.zeros(5)
        values = np.asarray(self.distortion, dtype=float)[:5]
        coefficients[: len(values)] = values
        return coefficients

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Map ``(N, 2)`` distorted pixel coordinates to ideal pinhole pixel coordinates."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(pixels) == 0:
            return pixels.copy()
        import cv2

        undistorted = cv2.undistortPoints(
            pixels.reshape(-1, 1, 2), self.matrix, self.distortion_coefficients, P=self.matrix
        )
        return undistorted.reshape(-1, 2)

    def with_resolution(self, width: int, height: int) -> "CameraIntrinsics":
        """The same camera rescaled to another image size (e.g. a downsampled sequence)."""
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=width,
            height=height,
        )

    def to_dict(self) -> dict:
        data = {
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "width": int(self.width),
            "height": int(self.height),
            "depth_scale": float(self.depth_scale),
        }
        if self.has_distortion:
            data["distortion"] = [float(k) for k in self.distortion]
        return data


# Published calibrations (TUM RGB-D benchmark, ICL-NUIM, Bonn RGB-D Dynamic, PrimeSense
# factory default). Depth in all of them is 5000 PNG units per metre (TUM layout).
CAMERA_PRESETS: dict[str, CameraIntrinsics] = {
    "tum-fr1": CameraIntrinsics(
        517.3, 516.5, 318.6, 255.3, 640, 480, 5000.0, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    ),
    "tum-fr2": CameraIntrinsics(
        520.9, 521.0, 325.1, 249.7, 640, 480, 5000.0, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)
    ),
    "tum-fr3": CameraIntrinsics(535.4, 539.2, 320.1, 247.6, 640, 480, 5000.0),
    # ICL-NUIM in TUM layout; its fy is -480 in the renderer's frame, +480 once flipped to the
    # TUM convention its PNGs use.
    "icl-nuim": CameraIntrinsics(481.20, 480.00, 319.50, 239.50, 640, 480, 5000.0),
    "bonn": CameraIntrinsics(
        542.822841,
        542.576870,
        315.593520,
        237.756098,
        640,
        480,
        5000.0,
        (0.039903, -0.099343, -0.000730, -0.000144, 0.0),
    ),
    "primesense": CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480, 5000.0),
}

_REQUIRED_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


def camera_from_dict(data: object, source: str) -> CameraIntrinsics:
    """Validate a parsed ``camera.yaml`` mapping; ``source`` names it in error messages."""
    if not isinstance(data, dict):
        raise InputError(f"{source}: expected a mapping with fx, fy, cx, cy, width, height")
    unknown = sorted(set(data) - set(_REQUIRED_KEYS) - {"depth_scale", "distortion"})
    if unknown:
        raise InputError(
            f"{source}: unknown key(s) {', '.join(unknown)}; "
            "allowed: fx, fy, cx, cy, width, height, depth_scale, distortion"
        )
    missing = [key for key in _REQUIRED_KEYS if key not in data]
    if missing:
        raise InputError(f"{source}: missing {', '.join(missing)}; add them to the file")
    for key in ("width", "height"):
        if isinstance(data[key], bool) or not isinstance(data[key], int):
            raise InputError(f"{source}: {key} must be a whole number of pixels, got {data[key]!r}")
    def number(key: str, value) -> float:
        try:
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        except (TypeError, ValueError):
            raise InputError(f"{source}: {key} must be a number, got {value!r}") from None

    values = {key: number(key, data[key]) for key in ("fx", "fy", "cx", "cy")}
    width, height = int(data["width"]), int(data["height"])
    depth_scale = number("depth_scale", data.get("depth_scale", 5000.0))
    raw_distortion = data.get("distortion") or ()
    if not isinstance(raw_distortion, (list, tuple)):
        raise InputError(f"{source}: distortion must be a list [k1, k2, p1, p2, k3], got {raw_distortion!r}")
    distortion = tuple(number("distortion", k) for k in raw_distortion)
    if not np.all(np.isfinite(list(values.values()) + [depth_scale, *distortion])):
        raise InputError(f"{source}: every value must be a finite number")
    if width <= 0 or height <= 0 or values["fx"] <= 0 or values["fy"] <= 0 or depth_scale <= 0:
        raise InputError(f"{source}: fx, fy, width, height and depth_scale must be positive")
    if len(distortion) not in (0, 4, 5):
        raise InputError(f"{source}: distortion needs 4 or 5 values (k1 k2 p1 p2 [k3])")
    return CameraIntrinsics(width=width, height=height, depth_scale=depth_scale, distortion=distortion, **values)


def load_camera_yaml(path: Path) -> CameraIntrinsics:
    """Read a ``camera.yaml`` file; raises :class:`InputError` naming the problem."""
    path = Path(path)
    text = read_user_text(path, "camera file")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise InputError(f"camera file {path} is not valid YAML: {describe_yaml_error(error)}") from None
    return camera_from_dict(data, str(path))


def write_camera_yaml(path: Path, intrinsics: CameraIntrinsics) -> None:
    """Write ``camera.yaml`` atomically."""
    atomic_write_text(Path(path), yaml.safe_dump(intrinsics.to_dict(), sort_keys=False))


def resolve_intrinsics(
    sequence_dir: Path, camera_file: Path | None = None, preset: str | None = None
) -> tuple[CameraIntrinsics, str]:
    """Pick the intrinsics of a sequence: ``--camera`` file, then ``--preset``, then ``camera.yaml``.

    Returns the intrinsics and a short description of where they came from.
    """
    if camera_file is not None and preset is not None:
        raise InputError("give either --camera or --preset, not both")
    if camera_file is not None:
        return load_camera_yaml(Path(camera_file)), str(camera_file)
    if preset is not None:
        key = preset.lower()
        if key not in CAMERA_PRESETS:
            raise InputError(f"unknown camera preset '{preset}'; choose one of {', '.join(CAMERA_PRESETS)}")
        return CAMERA_PRESETS[key], f"preset {key}"
    default_file = Path(sequence_dir) / "camera.yaml"
    if default_file.is_file():
        return load_camera_yaml(default_file), str(default_file)
    raise InputError(
        f"no camera.yaml in {sequence_dir}; add one, pass --camera FILE, "
        f"or --preset one of {', '.join(CAMERA_PRESETS)}"
    )
