"""Camera tracking benchmark: jsr's static mapping against Open3D RGB-D odometry.

Runs `jsr reconstruct` (through the library) and `jsr evaluate` on a synthetic static
sequence, ../shared/data/redkitchen300 and ../shared/data/bonn_crowd200, and, in the same run
and on the same frames, Open3D's frame-to-frame RGB-D odometry with the hybrid term. Prints
ATE RMSE and frames per second of both side by side.

jsr runs once per seed (``--seeds``, default 0,1,2): RANSAC makes single-seed figures move by
a centimetre on the real sequences, so the headline is the mean over the seeds, with each
seed's figure beside it. Open3D's odometry is deterministic and runs once.

    python bench/tracking.py [--frames N] [--sequences synthetic,redkitchen300,bonn_crowd200] [--seeds 0,1,2]
"""

from __future__ import annotations

import argparse
import dataclasses
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
from jsr.pipeline.run import run_reconstruction  # noqa: E402

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=None, help="frames per sequence (default: all)")
    parser.add_argument("--synthetic-frames", type=int, default=100)
    parser.add_argument("--sequences", default="synthetic,redkitchen300,bonn_crowd200")
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
            else:
                path = SHARED / name
                if not path.is_dir():
                    print(f"skipping {name}: {path} not found")
                    continue
            sequence = open_sequence(path, max_frames=args.frames, max_time_difference=config.input.max_time_difference,
                                     min_depth=config.input.min_depth, max_depth=config.input.max_depth)
            ates, fps, lost, keyframes = [], [], [], []
            for seed in seeds:
                out = temporary / f"run_{name}_seed{seed}"
                out.mkdir()
                summary = run_reconstruction(sequence, dataclasses.replace(config, seed=seed), out,
                                             dense_models=False)
                ates.append(evaluate_run(out, path)["camera"]["ate"]["rmse"])
                fps.append(summary["fps"])
                lost.append(summary["frames_lost"])
                keyframes.append(summary["maps"]["static"]["keyframes"])
            gt_t, gt_poses = sequence.groundtruth
            o3d_t, o3d_poses, o3d_fps = open3d_odometry(sequence)
            _, est, gt = associate_poses(o3d_t, o3d_poses, gt_t, gt_poses)
            o3d_ate = absolute_trajectory_error(est, gt).rmse
            rows.append((name, len(sequence), ates, float(np.mean(fps)), max(lost), round(float(np.mean(keyframes))),
                         o3d_ate, o3d_fps))
    print()
    print(f"jsr over seeds {args.seeds}: mean ATE, and each seed's; fps and keyframes are means, lost the most")
    print(f"{'sequence':<16}{'frames':>7}{'jsr ATE cm':>12}  {'per seed':<20}{'jsr fps':>9}{'lost':>6}{'kf':>5}"
          f"{'O3D ATE cm':>12}{'O3D fps':>9}")
    for name, frames, ates, fps, lost, keyframes, o3d_ate, o3d_fps in rows:
        per_seed = " / ".join(f"{ate * 100:.2f}" for ate in ates)
        print(f"{name:<16}{frames:>7}{np.mean(ates) * 100:>12.2f}  {per_seed:<20}{fps:>9.2f}{lost:>6}{keyframes:>5}"
              f"{o3d_ate * 100:>12.2f}{o3d_fps:>9.2f}")


if __name__ == "__main__":
    main()
