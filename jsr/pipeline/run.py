"""Run a whole sequence through the :class:`Reconstructor` and write the results folder.

Results are flushed every ``flush_every`` frames and once more at the end, also when the
run is interrupted (Ctrl-C) or crashes: the folder always holds valid files for the frames
done, and ``summary.json`` says whether the run completed.

Layout written (``DIR``)::

    config.yaml             resolved configuration
    summary.json            version, input, frames, fps, per-map counts, timings, status, dependency versions
    camera.tum              T_w_c of every tracked frame (world = first camera frame)
    landmarks.csv           per frame and map: keyframes, point and plane landmarks, tracked
    timings.csv             per frame: milliseconds per stage
    static/keyframes.tum    T_w_c of the static map's keyframes
    static/landmarks.ply    active point landmarks of the static map (world frame)
    static/cloud.ply, static/mesh.ply   dense model fused from the keyframes (end of run)
    objects/object_K/trajectory.tum      T_w_o of object K in every frame it was tracked (world frame, after
                                         bundle adjustment of the static map and of object K's map; a rest
                                         takes the mean correction of its keyframes, so at the detection
                                         frame T_w_o may differ from T_w_c by the mean's share of the
                                         others' corrections: a few tenths of a degree and up to about
                                         a centimetre on the synthetic sequences)
    objects/object_K/keyframes.tum       T_o_c of its keyframes (object frame = camera frame at detection)
    objects/object_K/landmarks.ply       its active point landmarks (object frame)
    objects/object_K/cloud.ply, mesh.ply its dense model (object frame; end of run)
    masks/<colour stem>.png              with save_masks: 0 static, K pixels given to object K
"""

from __future__ import annotations

import logging
import platform
import shutil
import signal
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

import numpy as np

from jsr import __version__
from jsr.config import Config, config_to_yaml
from jsr.io.atomic import atomic_write_bytes, atomic_write_text
from jsr.io.dataset import RGBDSequence, open_sequence
from jsr.io.trajectory import write_tum_trajectory
from jsr.export.meshes import write_dense_models
from jsr.io.writers import write_csv, write_json, write_point_cloud_ply
from jsr.pipeline.maps import Map, map_folder
from jsr.pipeline.reconstruct import Reconstructor
from jsr.pipeline.state import FrameReport

logger = logging.getLogger(__name__)

LANDMARK_HEADER = ["frame", "timestamp", "map", "keyframes", "point_landmarks", "plane_landmarks", "tracked"]
STAGE_ORDER = ["sift", "depth_lookup", "planes", "segments", "frontend_total", "matching", "registration", "map_update",
               "frame_total"]


def _ordered_stages(reports: list[FrameReport]) -> list[str]:
    seen = {key for report in reports for key in report.timings_ms}
    return [s for s in STAGE_ORDER if s in seen] + sorted(seen - set(STAGE_ORDER))


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write an ``(H, W)`` uint8 ownership mask as a PNG, atomically."""
    import cv2

    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(mask, dtype=np.uint8))
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise RuntimeError(f"could not encode {path}")
    atomic_write_bytes(path, encoded.tobytes())


def dependency_versions() -> dict[str, str]:
    """Versions of Python and of the libraries whose numerics shape the results, as the
    imported modules report them (``summary.json``'s ``dependencies``): a figure that moved
    between two machines may be a dependency's doing (constraints.txt pins the tested ones)."""
    import cv2
    import open3d  # already loaded: write_tables wrote the map files with it
    import scipy

    return {"python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
            "open3d": open3d.__version__, "scipy": scipy.__version__}


def remove_dropped_object_folders(out_dir: Path, kept: set[str]) -> list[str]:
    """Remove the ``objects/object_K`` folders of ``out_dir`` not in ``kept`` (``map_folder``
    names), and return their names. An object written at an earlier flush may since have been
    merged into another or dropped as non-rigid; its folder would otherwise outlive it and
    disagree with ``summary.json``. The folder was empty of results when the run began, so
    every ``object_*`` folder in it is this run's."""
    objects = Path(out_dir) / "objects"
    removed = []
    if objects.is_dir():
        for folder in sorted(objects.glob("object_*")):
            name = f"objects/{folder.name}"
            if folder.is_dir() and name not in kept:
                shutil.rmtree(folder)
                removed.append(name)
                logger.debug("removed %s: the object was merged or dropped since it was written", name)
    return removed


class ResultsWriter:
    """Writes the files of a results folder from the reconstructor's state (atomically)."""

    def __init__(self, out_dir: Path, sequence: RGBDSequence, config: Config):
        self.out_dir = Path(out_dir)
        self.sequence = sequence
        self.config = config

    def write_config(self) -> None:
        atomic_write_text(self.out_dir / "config.yaml", config_to_yaml(self.config))

    def write_tables(self, reconstructor: Reconstructor) -> None:
        """camera.tum, landmarks.csv, timings.csv and the sparse map files."""
        reports = reconstructor.reports
        tracked = [r for r in reports if r.tracked]
        write_tum_trajectory(
            self.out_dir / "camera.tum",
            np.array([r.timestamp for r in tracked]),
            np.array([reconstructor.current_pose(r) for r in tracked]).reshape(-1, 4, 4),
            header="camera-to-world T_w_c of every tracked frame (after bundle adjustment); world = first camera frame",
        )
        rows = []
        for report in reports:
            for name, counts in report.maps.items():
                rows.append([report.frame_index, report.timestamp, name, counts.keyframes, counts.point_landmarks,
                             counts.plane_landmarks, int(counts.tracked)])
        write_csv(self.out_dir / "landmarks.csv", LANDMARK_HEADER, rows)
        stages = _ordered_stages(reports)
        write_csv(
            self.out_dir / "timings.csv",
            ["frame", "timestamp"] + [f"{stage}_ms" for stage in stages],
            ([r.frame_index, r.timestamp] + [round(r.timings_ms.get(s, float("nan")), 3) for s in stages]
             for r in reports),
        )
        for map_ in reconstructor.maps:
            self.write_sparse_map(map_, self.out_dir / map_folder(map_))
        remove_dropped_object_folders(self.out_dir, {map_folder(m) for m in reconstructor.object_maps})
        for object_map in reconstructor.object_maps:
            timestamps, poses = reconstructor.object_trajectory(object_map)
            write_tum_trajectory(
                self.out_dir / map_folder(object_map) / "trajectory.tum",
                timestamps,
                poses,
                header=f"object {object_map.object_id}: object-to-world T_w_o in every frame it was tracked "
                "(after bundle adjustment); world = first camera frame, object frame = camera frame at detection",
            )

    def write_mask(self, report: FrameReport) -> None:
        """``masks/<colour stem>.png`` of one frame."""
        if report.mask is not None:
            (self.out_dir / "masks").mkdir(parents=True, exist_ok=True)
            write_mask(self.out_dir / "masks" / f"{report.name}.png", report.mask)

    def write_sparse_map(self, map_: Map, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        write_tum_trajectory(
            folder / "keyframes.tum",
            np.array([kf.timestamp for kf in map_.keyframes]),
            map_.keyframe_poses,
            header=f"keyframes of map '{map_.name}': T_map_cam",
        )
        active = map_.points.active
        write_point_cloud_ply(folder / "landmarks.ply", map_.points.positions[active], map_.points.colors[active])

    def write_summary(self, reconstructor: Reconstructor, status: str, seconds: float, error: str = "") -> dict:
        """``summary.json``; ``seconds`` is the time spent on the frames (fps = frames / seconds)."""
        reports = reconstructor.reports
        stages = _ordered_stages(reports)
        timing_summary = {}
        for stage in stages:
            values = np.array([r.timings_ms[stage] for r in reports if stage in r.timings_ms])
            timing_summary[stage] = {"median_ms": float(np.median(values)), "p90_ms": float(np.percentile(values, 90))}
        summary = {
            "version": __version__,
            "status": status,
            "error": error,
            "output": str(self.out_dir),
            "input": {
                "sequence": str(self.sequence.root),
                "kind": self.sequence.kind,
                "frames_selected": len(self.sequence),
                "skipped_entries": self.sequence.report.missing_files + self.sequence.report.unmatched,
                "intrinsics": self.sequence.intrinsics.to_dict(),
            },
            "frames_processed": len(reports),
            "frames_tracked": sum(r.tracked for r in reports),
            "frames_lost": sum(not r.tracked for r in reports),
            "relocalisations": sum(r.relocalised for r in reports),
            "frames_bridged": sum(r.bridged for r in reports),
            "frames_by_depth": sum(r.by_depth for r in reports),
            "seconds": seconds,
            "fps": len(reports) / seconds if seconds > 0 else 0.0,
            "maps": {
                m.name: {"keyframes": len(m.keyframes), "point_landmarks": m.points.active_count,
                         "plane_landmarks": len(m.planes)}
                for m in reconstructor.maps
            },
            "objects": [
                {"id": m.object_id, "created_at_frame": m.created_at_frame, "frames_tracked": m.frames_tracked,
                 "keyframes": len(m.keyframes), "point_landmarks": m.points.active_count}
                for m in reconstructor.object_maps
            ],
            "objects_merged": {str(k): v for k, v in sorted(reconstructor.merged_into.items())},
            "objects_dissolved": list(reconstructor.objects_dissolved),
            "objects_non_rigid": list(reconstructor.objects_non_rigid),
            "dynamic_pixels": {
                "frames": sum(r.dynamic_pixels > 0 for r in reports),
                "per_frame": [r.dynamic_pixels for r in reports],
            },
            "sensor_noise": reconstructor.sensor_noise,
            "loops_closed": [loop.summary() for loop in reconstructor.loops_closed],
            "timings": timing_summary,
            "platform": platform.platform(),
            "dependencies": dependency_versions(),
        }
        write_json(self.out_dir / "summary.json", summary)
        return summary


def open_configured_sequence(path: Path, config: Config, camera_file: Path | None = None, preset: str | None = None,
                             start: int = 0, max_frames: int | None = None, stride: int = 1) -> RGBDSequence:
    """Open a sequence with the input settings of ``config`` (timestamp association, depth
    range), as ``jsr reconstruct`` and ``jsr batch`` do."""
    return open_sequence(
        path,
        camera_file=camera_file,
        preset=preset,
        max_time_difference=config.input.max_time_difference,
        start=start,
        max_frames=max_frames,
        stride=stride,
        min_depth=config.input.min_depth,
        max_depth=config.input.max_depth,
    )


@contextmanager
def single_threaded_blas():
    """Within the block, the BLAS libraries numpy and SciPy loaded use one thread (the limit is
    process-wide; enter and leave the block in one thread, and not in several threads at once:
    OpenBLAS restores a limit reliably only from the thread that set it).

    A large product's sums are split among BLAS threads, so a reconstruction's results change
    in their last digits with the thread count: kitchen_box120 (120 frames) differed by 1e-7 m
    from frame 43 on between 2 threads and 1. ``jsr reconstruct`` runs inside this block, as
    Dask's worker processes run with ``OPENBLAS_NUM_THREADS=1``, so that a sequence gives the
    same files in ``jsr batch`` as on the command line, on any number of cores. The
    reconstruction's own threads keep the cores busy: side by side on 2 cores, kitchen_box120
    took 426 s with one BLAS thread against 468 s with two."""
    import scipy.linalg  # noqa: F401  (loads SciPy's BLAS, so that the limit reaches it too)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


@contextmanager
def interrupts_deferred():
    """Within the block, SIGINT (Ctrl-C) and SIGTERM are noted and logged, not raised: the
    results of the frames done are being written, and a second Ctrl-C must not leave them
    half written. Only the main thread can set signal handlers; elsewhere it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def note(signum, _frame) -> None:
        received.append(signum)
        logger.warning("still saving the results of the frames done; %s ignored until they are written",
                       signal.Signals(signum).name)

    previous = {signum: signal.signal(signum, note) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def run_reconstruction(
    sequence: RGBDSequence,
    config: Config,
    out_dir: Path,
    on_frame: Callable[[FrameReport], None] | None = None,
    flush_every: int = 25,
    dense_models: bool = True,
    save_masks: bool = False,
    init_object_mask: np.ndarray | None = None,
) -> dict:
    """Reconstruct ``sequence`` into ``out_dir`` (which must exist and be empty of results).

    ``on_frame`` is called after every frame (progress display). ``save_masks`` writes the
    ownership mask of every frame to ``masks/``; ``init_object_mask`` ``(H, W)`` bool starts
    object map 1 on the first frame (see :class:`Reconstructor`). Returns the summary dict
    (also written to ``summary.json``). A KeyboardInterrupt or any exception is re-raised after
    the results of the frames done have been written; further Ctrl-C or SIGTERM while they are
    written are ignored (:func:`interrupts_deferred`). For results that do not depend on the
    number of cores, run it inside :func:`single_threaded_blas` (``jsr reconstruct`` does).
    """
    writer = ResultsWriter(out_dir, sequence, config)
    writer.write_config()
    reconstructor = Reconstructor(config, sequence.intrinsics, init_object_mask=init_object_mask)
    started = time.perf_counter()
    status, error = "running", ""
    tracking_seconds = None
    try:
        for index in range(len(sequence)):
            report = reconstructor.process(sequence[index])
            if save_masks:
                writer.write_mask(report)
            if on_frame is not None:
                on_frame(report)
            report.mask = None  # written; the keyframes' masks are kept by the reconstructor
            if flush_every and (index + 1) % flush_every == 0:
                writer.write_tables(reconstructor)
                writer.write_summary(reconstructor, status, time.perf_counter() - started)
        reconstructor.finish()
        tracking_seconds = time.perf_counter() - started
        writer.write_tables(reconstructor)
        if dense_models:
            write_dense_models(reconstructor, sequence, config, out_dir)
        status = "complete"
    except KeyboardInterrupt as interrupt:
        status, error = "interrupted", str(interrupt) or "interrupted by the user"
        raise
    except Exception as exception:  # a bug or a bad frame: keep what was done, then re-raise
        status, error = "failed", f"{type(exception).__name__}: {exception}"
        raise
    finally:
        with interrupts_deferred():
            seconds = time.perf_counter() - started if tracking_seconds is None else tracking_seconds
            if status != "complete":
                writer.write_tables(reconstructor)
            summary = writer.write_summary(reconstructor, status, seconds, error)
            reconstructor.close()
    return summary
