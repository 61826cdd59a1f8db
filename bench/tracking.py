"""Camera tracking benchmark: jsr's static mapping against Open3D RGB-D odometry.

Runs `jsr reconstruct` (through the library) and `jsr evaluate` on a synthetic static
sequence, ../shared/data/redkitchen300, bonn_crowd200 and bonn_crowd_people, and
``redkitchen300_back``: redkitchen300 played forward and then back to its first frame (599
frames, links to its images, made in a temporary folder), where the camera comes back to
places it mapped 10-20 s before, for loop closure. In the same run and on the same frames it
times Open3D's frame-to-frame RGB-D odometry with the hybrid term. Prints, side by side, ATE
RMSE, RPE (translation RMSE between consecutive frames), frames lost, loops closed, keyframes
and frames per second.

jsr runs once per seed (``--seeds``, default 0,1,2): RANSAC makes single-seed figures move by
a centimetre on the real sequences, so the headline is the mean over the seeds, with each
seed's figure beside it. Open3D's odometry is deterministic and runs once.

    python bench/tracking.py [--frames N] [--seeds 0,1,2]
        [--sequences synthetic,redkitchen300,bonn_crowd200,bonn_crowd_people,redkitchen300_back]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from jsr.config import load_config  # noqa: E402
from jsr.evaluate.run import evaluate_run  # noqa: E402
from jsr.evaluate.trajectory import absolute_trajectory_error, associate_poses  # noqa: E402
from jsr.io.dataset import open_sequence  # noqa: E402
from jsr.pipeline.run import run_reconstruction, single_threaded_blas  # noqa: E402

SHARED = REPO.parent / "shared" / "data"


def open3d_odometry(sequence) -> tuple[np.ndarray, np.ndarray, float]:
    """Frame-to-frame Open3D RGB-D odometry (hybrid term); returns timestamps, T_w_c, fps."""
    import open3d as o3d

    intr = sequence.intrinsics
    camera = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    option = o3d.pipelines.odometry.OdometryOption()
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(frame):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(frame.color)), o3d.geometry.Image(frame.depth),
            depth_scale=1.0, depth_trunc=4.0, convert_rgb_to_intensity=True)

    started = time.perf_counter()
    poses, timestamps = [np.eye(4)], [sequence[0].timestamp]
    previous = rgbd(sequence[0])
    for index in range(1, len(sequence)):
        frame = sequence[index]
        current = rgbd(frame)
        ok, T_prev_curr, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            current, previous, camera, np.eye(4), jacobian, option)
        poses.append(poses[-1] @ (T_prev_curr if ok else np.eye(4)))
        timestamps.append(frame.timestamp)
        previous = current
    seconds = time.perf_counter() - started
    return np.array(timestamps), np.array(poses), len(sequence) / seconds


def synthetic_static(root: Path, frames: int) -> Path:
    from jsr.synth.options import SynthOptions
    from jsr.synth.write import generate_sequence

    out = root / "synthetic_static"
    generate_sequence(out, SynthOptions(frames=frames, objects=0, motion="static", seed=1))
    return out


def there_and_back(source: Path, root: Path) -> Path:
    """A TUM folder playing ``source`` forward and then back to its first frame (links to its
    images, its ground truth in the same order; timestamps continue at the same rate)."""
    def rows(name):
        return [line.split() for line in (source / name).read_text().splitlines()
                if line.strip() and not line.startswith("#")]

    colour, depth, truth = rows("rgb.txt"), rows("depth.txt"), rows("groundtruth.txt")
    truth_times = np.array([float(row[0]) for row in truth])
    order = list(range(len(colour))) + list(range(len(colour) - 2, -1, -1))
    step = float(colour[1][0]) - float(colour[0][0])
    root.mkdir(parents=True)
    for folder in ("rgb", "depth"):
        (root / folder).mkdir()
    depth_times = np.array([float(row[0]) for row in depth])
    lines = {"rgb.txt": [], "depth.txt": [], "groundtruth.txt": []}
    for k, i in enumerate(order):
        stamp = f"{float(colour[0][0]) + k * step:.6f}"
        taken = float(colour[i][0])
        nearest = int(np.argmin(np.abs(depth_times - taken)))  # as the sequence reader associates them
        for name, image, folder in (("rgb.txt", colour[i][1], "rgb"), ("depth.txt", depth[nearest][1], "depth")):
            link = Path(folder) / f"{k:05d}{Path(image).suffix}"
            os.symlink(source / image, root / link)
            lines[name].append(f"{stamp} {link}")
        closest = int(np.argmin(np.abs(truth_times - taken)))
        if abs(truth_times[closest] - taken) <= 0.02:
            lines["groundtruth.txt"].append(" ".join([stamp, *truth[closest][1:]]))
    for name, content in lines.items():
        (root / name).write_text("\n".join(content) + "\n")
    os.symlink(source / "camera.yaml", root / "camera.yaml")
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=None, help="frames per sequence (default: all)")
    parser.add_argument("--synthetic-frames", type=int, default=100)
    parser.add_argument("--sequences",
                        default="synthetic,redkitchen300,bonn_crowd200,bonn_crowd_people,redkitchen300_back")
    parser.add_argument("--set", action="append", default=[], help="config override section.key=value")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds jsr runs with (mean reported)")
    args = parser.parse_args()
    try:
        seeds = [int(seed) for seed in args.seeds.split(",") if seed.strip()]
    except ValueError:
        parser.error(f"--seeds {args.seeds!r}: give comma-separated integers")
    if not seeds:
        parser.error("--seeds: give at least one seed")
    config = load_config(REPO / "configs" / "default.yaml", args.set)

    rows = []
    with tempfile.TemporaryDirectory() as temporary:
        temporary = Path(temporary)
        for name in args.sequences.split(","):
            if name == "synthetic":
                path = synthetic_static(temporary, args.synthetic_frames)
            elif name.endswith("_back") and (SHARED / name[: -len("_back")]).is_dir():
                path = there_and_back(SHARED / name[: -len("_back")], temporary / name)
            else:
                path = SHARED / name
                if not path.is_dir():
                    print(f"skipping {name}: {path} not found")
                    continue
            sequence = open_sequence(path, max_frames=args.frames, max_time_difference=config.input.max_time_difference,
                                     min_depth=config.input.min_depth, max_depth=config.input.max_depth)
            ates, rpes, fps, lost, loops, keyframes = [], [], [], [], [], []
            for seed in seeds:
                out = temporary / f"run_{name}_seed{seed}"
                out.mkdir()
                with single_threaded_blas():  # as jsr reconstruct runs (the same figures)
                    summary = run_reconstruction(sequence, dataclasses.replace(config, seed=seed), out,
                                                 dense_models=False)
                camera = evaluate_run(out, path)["camera"]
                ates.append(camera["ate"]["rmse"])
                rpes.append(camera["rpe"]["translation_rmse"])
                fps.append(summary["fps"])
                lost.append(summary["frames_lost"])
                loops.append(len(summary["loops_closed"]))
                keyframes.append(summary["maps"]["static"]["keyframes"])
            gt_t, gt_poses = sequence.groundtruth
            o3d_t, o3d_poses, o3d_fps = open3d_odometry(sequence)
            _, est, gt = associate_poses(o3d_t, o3d_poses, gt_t, gt_poses)
            o3d_ate = absolute_trajectory_error(est, gt).rmse
            rows.append((name, len(sequence), ates, float(np.mean(rpes)), float(np.mean(fps)), max(lost), loops,
                         round(float(np.mean(keyframes))), o3d_ate, o3d_fps))
    print()
    print(f"jsr over seeds {args.seeds}: mean ATE, and each seed's; RPE, fps and keyframes are means, lost the "
          "most, loops per seed")
    print(f"{'sequence':<20}{'frames':>7}{'jsr ATE cm':>12}  {'per seed':<22}{'RPE cm':>7}{'jsr fps':>8}{'lost':>5}"
          f"{'loops':>8}{'kf':>5}{'O3D ATE cm':>12}{'O3D fps':>9}")
    for name, frames, ates, rpe, fps, lost, loops, keyframes, o3d_ate, o3d_fps in rows:
        per_seed = " / ".join(f"{ate * 100:.2f}" for ate in ates)
        loop_counts = "/".join(str(count) for count in loops)
        print(f"{name:<20}{frames:>7}{np.mean(ates) * 100:>12.2f}  {per_seed:<22}{rpe * 100:>7.2f}{fps:>8.2f}"
              f"{lost:>5}{loop_counts:>8}{keyframes:>5}{o3d_ate * 100:>12.2f}{o3d_fps:>9.2f}")


if __name__ == "__main__":
    main()
