"""Small builders of sequence folders for tests (no dependency on the synthetic generator)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml


def write_tiny_tum(
    root: Path,
    frames: int = 4,
    width: int = 32,
    height: int = 24,
    depth_time_offset: float = 0.004,
    seed: int = 0,
) -> Path:
    """A minimal TUM-layout sequence: random colour, a constant 1.5 m depth, camera.yaml.

    Depth timestamps are offset by ``depth_time_offset`` seconds from colour ones, as on
    a real sensor. Returns ``root``.
    """
    rng = np.random.default_rng(seed)
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines, gt_lines = ["# timestamp filename"], ["# timestamp filename"], []
    for index in range(frames):
        t_colour = 100.0 + index / 30.0
        t_depth = t_colour + depth_time_offset
        colour = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        depth = np.full((height, width), 7500, dtype=np.uint16)
        cv2.imwrite(str(root / "rgb" / f"{t_colour:.6f}.png"), colour)
        cv2.imwrite(str(root / "depth" / f"{t_depth:.6f}.png"), depth)
        rgb_lines.append(f"{t_colour:.6f} rgb/{t_colour:.6f}.png")
        depth_lines.append(f"{t_depth:.6f} depth/{t_depth:.6f}.png")
        gt_lines.append(f"{t_colour:.6f} {0.01 * index} 0 0 0 0 0 1")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    camera = {"fx": 30.0, "fy": 30.0, "cx": width / 2, "cy": height / 2, "width": width, "height": height,
              "depth_scale": 5000.0}
    (root / "camera.yaml").write_text(yaml.safe_dump(camera))
    return root


def colour_paths(root: Path) -> list[Path]:
    return sorted((root / "rgb").iterdir())


def depth_paths(root: Path) -> list[Path]:
    return sorted((root / "depth").iterdir())
