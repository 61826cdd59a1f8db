"""Benchmark of the front-end: milliseconds per frame for each stage.

    python bench/frontend.py [--frames N] [--serial] [--set section.key=value ...]

Runs :class:`jsr.pipeline.frontend.FrontEnd` on frames spread evenly over the shared
sequences in ``../shared/data`` (redkitchen300, bonn_crowd200, kitchen_box120; those absent
are skipped) and over a synthetic sequence when ``jsr.synth`` is available (generated into a
temporary folder), and prints the median and 90th percentile of every stage.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from jsr.config import load_config  # noqa: E402
from jsr.io.dataset import open_sequence  # noqa: E402
from jsr.pipeline.frontend import STAGES, FrontEnd  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
SEQUENCES = ("redkitchen300", "bonn_crowd200", "kitchen_box120")
WARMUP_FRAMES = 2


def run_sequence(sequence, config, frames: int, parallel: bool) -> dict[str, np.ndarray]:
    """Per-stage timings (ms) of ``frames`` frames spread over ``sequence``."""
    indices = np.unique(np.linspace(0, len(sequence) - 1, min(frames, len(sequence))).round().astype(int))
    loaded = [sequence[int(i)] for i in indices]  # load first: disk reads are not front-end time
    timings: dict[str, list[float]] = {stage: [] for stage in STAGES}
    counts = {"n_points": [], "n_points_3d": [], "n_planes": [], "n_segments": []}
    with FrontEnd(config, sequence.intrinsics, parallel=parallel) as frontend:
        for frame in loaded[:WARMUP_FRAMES]:
            frontend.process(frame)
        cpu = []
        for frame in loaded:
            cpu_start = time.process_time()
            measurements = frontend.process(frame)
            cpu.append((time.process_time() - cpu_start) * 1000.0)
            for stage in STAGES:
                timings[stage].append(measurements.timings_ms[stage])
            counts["n_points"].append(len(measurements.points))
            counts["n_points_3d"].append(int(measurements.points.has_depth.sum()))
            counts["n_planes"].append(len(measurements.planes))
            counts["n_segments"].append(len(measurements.segments))
    result = {stage: np.array(values) for stage, values in timings.items()}
    result["cpu"] = np.array(cpu)
    result.update({name: np.array(values) for name, values in counts.items()})
    return result


def synthetic_sequence(directory: Path, frames: int):
    """A sequence from ``jsr.synth`` (640x480 when its options allow), or None."""
    if importlib.util.find_spec("jsr.synth") is None:
        return None, "jsr.synth not available"
    from jsr.synth.options import SynthOptions
    from jsr.synth.write import generate_sequence

    try:
        options = SynthOptions()
        changes = {}
        for name, value in (("width", 640), ("height", 480), ("frames", frames), ("num_frames", frames)):
            if hasattr(options, name):
                changes[name] = value
        if changes:
            import dataclasses

            options = dataclasses.replace(options, **changes)
        generate_sequence(directory, options, overwrite=True)
        return open_sequence(directory), f"synthetic ({options.__class__.__name__} {changes})"
    except Exception as error:  # the generator is another module's work in progress
        return None, f"jsr.synth failed: {type(error).__name__}: {error}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30, help="frames per sequence (spread evenly)")
    parser.add_argument("--serial", action="store_true", help="run SIFT and planes one after the other")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    parser.add_argument("--no-synth", action="store_true", help="skip the synthetic sequence")
    args = parser.parse_args()
    config = load_config(None, args.overrides)

    print(f"front-end benchmark: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, "
          f"{'serial' if args.serial else 'SIFT in parallel with planes'}, overrides {args.overrides or 'none'}")
    results: list[tuple[str, int, dict[str, np.ndarray]]] = []
    for name in SEQUENCES:
        folder = SHARED / name
        if not folder.is_dir():
            print(f"  {name}: absent ({folder}), skipped")
            continue
        sequence = open_sequence(folder, min_depth=config.input.min_depth, max_depth=config.input.max_depth)
        start = time.perf_counter()
        result = run_sequence(sequence, config, args.frames, not args.serial)
        count = len(result["frontend_total"])
        print(f"  {name}: {count} frames of {len(sequence)} ({time.perf_counter() - start:.1f} s)")
        results.append((name, count, result))
    if not args.no_synth:
        with tempfile.TemporaryDirectory(prefix="jsr-bench-") as temporary:
            sequence, note = synthetic_sequence(Path(temporary) / "synth", max(args.frames, 3))
            if sequence is None:
                print(f"  synthetic: skipped ({note})")
            else:
                result = run_sequence(sequence, config, args.frames, not args.serial)
                print(f"  synthetic: {len(result['frontend_total'])} frames, {sequence.intrinsics.width}x"
                      f"{sequence.intrinsics.height} ({note})")
                results.append(("synthetic", len(result["frontend_total"]), result))
    if not results:
        print("no sequence to benchmark")
        return 1

    columns = STAGES + ("cpu",)
    header = f"{'sequence':<15}{'frames':>7}  " + "".join(f"{stage + ' ms':>19}" for stage in columns)
    print()
    print("milliseconds per frame: median / 90th percentile (wall clock; cpu = process CPU time, all threads)")
    print(header)
    print("-" * len(header))
    for name, count, result in results:
        cells = "".join(
            f"{np.median(result[stage]):>10.1f} / {np.percentile(result[stage], 90):>5.1f}" for stage in columns
        )
        print(f"{name:<15}{count:>7}  {cells}")
    print(f"load average after: {os.getloadavg()[0]:.2f} (other processes on the machine inflate wall times)")
    print()
    print(f"{'sequence':<15}{'points':>8}{'3D':>8}{'planes':>8}{'segments':>10}   (medians)")
    for name, _, result in results:
        print(f"{name:<15}{np.median(result['n_points']):>8.0f}{np.median(result['n_points_3d']):>8.0f}"
              f"{np.median(result['n_planes']):>8.0f}{np.median(result['n_segments']):>10.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
