"""Bundle adjustment benchmark: how long each solve takes, and how long frames wait for it.

Runs the pipeline (default config, objects on) on shared real sequences and prints, per
sequence, every map's bundle adjustment runs: how many, the problem sizes (free keyframes,
points solved for, points seen once and carried, observations), solver evaluations, the solve's
wall and CPU time (median and max), and the frames' wait for a solve (``bundle_wait``: the
solve runs beside the next frame's front-end and is applied at its start); and the sensor's
noise as the static map's last run estimated it (``bundle_adjustment.estimate_noise``: each
kind of residual's sigma as a multiple of the configured one) with the solves a run took.

    python bench/bundle.py [--sequences redkitchen300,bonn_crowd_people] [--frames N] [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from jsr.config import load_config  # noqa: E402
from jsr.io.dataset import open_sequence  # noqa: E402
from jsr.pipeline.bundle_noise import GROUPS  # noqa: E402
from jsr.pipeline.reconstruct import Reconstructor  # noqa: E402
from jsr.pipeline.run import single_threaded_blas  # noqa: E402

SHARED = REPO.parent / "shared" / "data"


def run(path: Path, config, frames: int | None) -> tuple[list, np.ndarray, int, np.ndarray | None]:
    """Bundle adjustment results, per-frame ``bundle_wait`` (ms), the frame count and the
    sensor's noise components at the end (None if none was estimated)."""
    sequence = open_sequence(path, max_frames=frames, max_time_difference=config.input.max_time_difference,
                             min_depth=config.input.min_depth, max_depth=config.input.max_depth)
    reconstructor = Reconstructor(config, sequence.intrinsics)
    try:
        waits = []
        for index in range(len(sequence)):
            report = reconstructor.process(sequence[index])
            waits.append(report.timings_ms.get("bundle_wait", 0.0))
        reconstructor.finish()
        bundle = reconstructor.state.bundle
        return list(bundle.results), np.array(waits), len(sequence), bundle.noise_components
    finally:
        reconstructor.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequences", default="redkitchen300,bonn_crowd_people")
    parser.add_argument("--frames", type=int, default=None, help="frames per sequence (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], help="config override section.key=value")
    args = parser.parse_args()
    config = dataclasses.replace(load_config(REPO / "configs" / "default.yaml", args.set), seed=args.seed)

    print(f"{'sequence':<18}{'frames':>7}{'runs':>6}{'free kf':>8}{'points':>8}{'carried':>8}{'obs':>7}"
          f"{'evals':>6}{'solves':>7}{'solve s med/max':>17}{'cpu s total':>12}{'wait s max':>11}{'waits>0.5s':>11}"
          f"  noise x ({', '.join(GROUPS)})")
    for name in [n for n in args.sequences.split(",") if n]:
        path = SHARED / name
        if not path.is_dir():
            print(f"skipping {name}: {path} not found")
            continue
        with single_threaded_blas():
            results, waits, frames, noise = run(path, config, args.frames)
        done = [r for r in results if r.success]
        if not done:
            print(f"{name:<18}{frames:>7}{0:>6}")
            continue
        mean = lambda values: float(np.mean(values))  # noqa: E731
        seconds = np.array([r.seconds for r in done])
        print(f"{name:<18}{frames:>7}{len(done):>6}{mean([r.keyframes_optimised for r in done]):>8.1f}"
              f"{mean([r.landmarks_optimised for r in done]):>8.0f}"
              f"{mean([r.points_carried for r in done]):>8.0f}"
              f"{mean([r.observations for r in done]):>7.0f}{mean([r.iterations for r in done]):>6.1f}"
              f"{mean([r.passes for r in done]):>7.1f}"
              f"{np.median(seconds):>9.3f} /{seconds.max():>6.3f}{sum(r.cpu_seconds for r in done):>12.2f}"
              f"{waits.max() / 1000:>11.2f}{int(np.sum(waits > 500)):>11}"
              f"  {'-' if noise is None else ' '.join(f'{value:.2f}' for value in noise)}")
    print("points, carried, obs, evals, solves: means per run; solve: wall time of one run (all its solves) "
          "in the worker thread")


if __name__ == "__main__":
    main()
