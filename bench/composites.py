"""Composites (`jsr synth --background`): how consistent they are, measured on the files.

Part 1, the backgrounds: a composited object rests exactly in the ground truth's world, so it
stays put against the real scene only as far as the ground truth does. For frames ``gap`` apart,
the depth of one frame is moved into the other with the ground-truth poses (at the depth
timestamps, lens distortion included) and compared with the depth seen there: the median
disagreement (1 frame apart it is mostly sensor noise; it grows with the ground truth's error).

Part 2, each composite folder: frames, the supporting surface, frames each object is in view
(labels), how far its labelled pixels, back-projected with the ground truth (depth timestamp),
lie from its surface at its pose in ``objects/`` (sensor noise: about 1.4e-3 Z^2), and how far
the real scene around its footprint (a ring 0-8 cm outside it, within 10 cm of the surface) lies
from the surface it stands on (median over frames; the contact of object and surface).

    python bench/composites.py [--data ../shared/data] [--backgrounds redkitchen300,bonn_crowd200] [COMPOSITE ...]

Without COMPOSITE folders, those under /tmp/composites are measured.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from jsr.geometry import invert_transform, transform_points  # noqa: E402
from jsr.io.trajectory import read_tum_trajectory  # noqa: E402
from jsr.synth.background import open_background  # noqa: E402
from jsr.synth.render import camera_rays, field_of_view  # noqa: E402
from jsr.synth.scene import Shape, footprint_radius  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
GAPS = (1, 10, 30)


def ground_truth_consistency(root: Path, pairs: int = 14) -> dict[int, float]:
    """Median |depth disagreement| (cm) between frames ``gap`` apart placed with the ground truth."""
    total = open_background(root, 0, 2).total_frames
    background = open_background(root, 0, total)
    intrinsics = background.intrinsics
    rays = camera_rays(intrinsics)
    field = field_of_view(intrinsics)  # points beyond it would be folded into the image by the distortion
    result = {}
    for gap in GAPS:
        medians = []
        for first in np.linspace(0, total - 1 - gap, pairs).round().astype(int):
            second = first + gap
            depth = background.depth(first).ravel()
            valid = (depth > 0.3) & (depth < 3.5)
            points = rays[valid] * depth[valid, None]
            T = invert_transform(background.depth_poses[second]) @ background.depth_poses[first]
            moved = transform_points(T, points)
            x_min, x_max, y_min, y_max = field
            x, y = moved[:, 0] / moved[:, 2], moved[:, 1] / moved[:, 2]
            ahead = (moved[:, 2] > 0.1) & (x >= x_min) & (x <= x_max) & (y >= y_min) & (y <= y_max)
            pixels, _ = cv2.projectPoints(moved[ahead].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intrinsics.matrix,
                                          intrinsics.distortion_coefficients)
            pixels = np.round(pixels.reshape(-1, 2)).astype(int)
            inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < intrinsics.width) & (pixels[:, 1] >= 0) & (
                pixels[:, 1] < intrinsics.height)
            seen = background.depth(second)[pixels[inside, 1], pixels[inside, 0]]
            difference = seen - moved[ahead][inside, 2]
            usable = (seen > 0) & (np.abs(difference) < 0.15)  # beyond: occlusion, not error
            medians.append(np.median(np.abs(difference[usable])))
        result[gap] = 100.0 * float(np.mean(medians))
    return result


def _shapes(metadata: dict) -> list[Shape]:
    return [Shape(f"object {o['id']}", o["shape"], tuple(o["size"]), np.eye(4), o["id"], 0.0025, "object", 0)
            for o in metadata["objects"]]


def measure_composite(folder: Path) -> dict:
    metadata = yaml.safe_load((folder / "synth.yaml").read_text())
    options = metadata["options"]
    source = open_background(options["background"], options["start"], options["frames"])
    intrinsics = source.intrinsics
    rays = camera_rays(intrinsics).reshape(intrinsics.height, intrinsics.width, 3)
    shapes = _shapes(metadata)
    poses = [read_tum_trajectory(folder / "objects" / f"object_{k + 1}.txt")[1] for k in range(len(shapes))]
    T_s_w = invert_transform(np.array(metadata["surface"]["T_w_s"]))
    distances, contact = [], []
    for index, frame in enumerate(source.frames):
        labels = cv2.imread(str(folder / "labels" / f"{frame.name}.png"), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(folder / "depth" / frame.depth_path.name), cv2.IMREAD_UNCHANGED) / intrinsics.depth_scale
        T_w_c = source.depth_poses[index]
        world = transform_points(T_w_c, (rays * depth[:, :, None]).reshape(-1, 3)).reshape(rays.shape)
        real = (labels == 0) & (depth > 0)
        real_local = transform_points(T_s_w, world[real])
        for k, shape in enumerate(shapes):
            mine = (labels == k + 1) & (depth > 0)
            if np.count_nonzero(mine) < 50:
                continue
            local = transform_points(invert_transform(poses[k][index]), world[mine])
            distances.append(np.abs(shape.signed_distance(local)))
            centre = transform_points(T_s_w, poses[k][index][:3, 3][None])[0]
            ring = np.linalg.norm(real_local[:, :2] - centre[:2], axis=1) - footprint_radius(shape)
            near = (ring > 0) & (ring < 0.08) & (np.abs(real_local[:, 2]) < 0.1)
            if np.count_nonzero(near) > 50:
                contact.append(np.median(real_local[near, 2]))
    distances = np.concatenate(distances) if distances else np.zeros(1)
    return {
        "name": folder.name,
        "background": Path(options["background"]).name,
        "frames": f"{options['start']}-{options['start'] + options['frames'] - 1}",
        "objects": ", ".join(f"{o['shape']}" for o in metadata["objects"]),
        "surface_m2": metadata["surface"]["free_area_m2"],
        "in_view": "/".join(str(o["frames_in_view"]) for o in metadata["objects"]),
        "pixels": "/".join(str(o["median_pixels_in_view"]) for o in metadata["objects"]),
        "on_object_mm": f"{1000 * np.median(distances):.1f} ({1000 * np.percentile(distances, 95):.1f})",
        "contact_cm": f"{100 * np.median(np.abs(contact)):.1f} ({100 * np.percentile(np.abs(contact), 95):.1f})"
        if contact else "-",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("composites", nargs="*", type=Path)
    parser.add_argument("--backgrounds", default="redkitchen300,bonn_crowd200")
    parser.add_argument("--data", type=Path, default=SHARED, help="folder of the shared real sequences")
    args = parser.parse_args()
    print("Ground-truth consistency: median |depth disagreement| (cm) between frames placed with the ground truth")
    print(f"{'background':16} {'frames':>6} " + " ".join(f"{f'gap {gap}':>8}" for gap in GAPS))
    for name in [n for n in args.backgrounds.split(",") if n]:
        figures = ground_truth_consistency(args.data / name)
        total = open_background(args.data / name, 0, 2).total_frames
        print(f"{name:16} {total:6d} " + " ".join(f"{figures[gap]:8.2f}" for gap in GAPS))
    folders = args.composites or sorted(p for p in Path("/tmp/composites").iterdir() if (p / "synth.yaml").is_file())
    if not folders:
        return
    print()
    print("Composites: in view = frames with the object's labels; pixels = median labelled pixels; on object =")
    print("labelled depth to the object's surface, median (p95) mm; contact = real surface around the footprint")
    print("to the plane the object stands on, median (p95) cm over frames")
    columns = ("name", "background", "frames", "objects", "surface_m2", "in_view", "pixels", "on_object_mm",
               "contact_cm")
    widths = (22, 14, 8, 15, 10, 8, 9, 13, 10)
    print(" ".join(f"{c:{w}}" for c, w in zip(columns, widths)))
    for folder in folders:
        row = measure_composite(folder)
        print(" ".join(f"{str(row[c]):{w}}" for c, w in zip(columns, widths)))


if __name__ == "__main__":
    main()
