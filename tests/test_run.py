"""Running a whole sequence: the results folder, also after an interruption."""

import json
import logging
import shutil

import cv2
import numpy as np
import pytest

from jsr.config import load_config
from jsr.io.dataset import open_sequence
from jsr.io.trajectory import read_tum_trajectory
from jsr.io.writers import read_csv
from jsr.pipeline.bundle_noise import BOUNDS, GROUPS
from jsr.pipeline.reconstruct import Reconstructor
from jsr.pipeline.run import run_reconstruction


def test_interrupted_run_leaves_valid_results(synth_sequence, tmp_path):
    sequence = open_sequence(synth_sequence)

    def interrupt_after_five(report):
        if report.frame_index == 4:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_reconstruction(sequence, load_config(), tmp_path, on_frame=interrupt_after_five, flush_every=0)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "interrupted"
    assert summary["frames_processed"] == 5
    timestamps, poses = read_tum_trajectory(tmp_path / "camera.tum")
    assert len(timestamps) == summary["frames_tracked"] and len(poses) == len(timestamps)
    rows = read_csv(tmp_path / "landmarks.csv")
    assert {int(r["frame"]) for r in rows} == set(range(5))
    # no temporary files left behind
    assert not [p for p in tmp_path.rglob(".*")]


def test_complete_run_files_agree(synth_sequence, tmp_path):
    sequence = open_sequence(synth_sequence, max_frames=8)
    summary = run_reconstruction(sequence, load_config(), tmp_path, dense_models=False)
    assert summary["status"] == "complete"
    rows = read_csv(tmp_path / "landmarks.csv")
    last = [r for r in rows if int(r["frame"]) == 7 and r["map"] == "static"][0]
    assert int(last["keyframes"]) == summary["maps"]["static"]["keyframes"]
    keyframe_times, keyframe_poses = read_tum_trajectory(tmp_path / "static" / "keyframes.tum")
    assert len(keyframe_times) == summary["maps"]["static"]["keyframes"]
    assert np.allclose(keyframe_poses[0], np.eye(4))
    timings = read_csv(tmp_path / "timings.csv")
    assert len(timings) == 8 and "sift_ms" in timings[0]


@pytest.mark.parametrize("estimate", [True, False])
def test_summary_records_the_estimated_sensor_noise(synth_sequence, tmp_path, estimate):
    """summary.json's ``sensor_noise``: each kind of residual's sigma as a multiple of the
    configured one, as the static map's bundle adjustment estimated it; null when not estimated."""
    sequence = open_sequence(synth_sequence, max_frames=8)
    config = load_config(None, ["bundle_adjustment.every_keyframes=2", f"bundle_adjustment.estimate_noise={estimate}"])
    run_reconstruction(sequence, config, tmp_path, dense_models=False)
    noise = json.loads((tmp_path / "summary.json").read_text())["sensor_noise"]
    if not estimate:
        assert noise is None
        return
    assert list(noise) == list(GROUPS)
    assert all(BOUNDS[0] <= value <= BOUNDS[1] for value in noise.values())
    # the synthetic sequence's keypoints are far more precise than the configured 1 px
    assert noise["reprojection"] < 0.5



@pytest.mark.parametrize("final_global", [True, False])
def test_finish_adjusts_the_whole_static_map_once(synth_sequence, final_global):
    """``bundle_adjustment.final_global``: ``finish`` ends with one run over all the static
    map's keyframes but the first; the camera trajectory follows it."""
    sequence = open_sequence(synth_sequence, max_frames=12)
    config = load_config(None, ["bundle_adjustment.every_keyframes=2", "bundle_adjustment.window_keyframes=2",
                                f"bundle_adjustment.final_global={final_global}"])
    reconstructor = Reconstructor(config, sequence.intrinsics)
    try:
        for index in range(len(sequence)):
            reconstructor.process(sequence[index])
        poses_before = [reconstructor.current_pose(report) for report in reconstructor.reports]
        windowed_runs = len(reconstructor.state.bundle.results)
        reconstructor.finish()
    finally:
        reconstructor.close()
    keyframes = len(reconstructor.static_map.keyframes)
    results = reconstructor.state.bundle.results
    assert keyframes > config.bundle_adjustment.window_keyframes + 1
    if not final_global:
        assert all(r.keyframes_optimised < keyframes - 1 for r in results)
        return
    assert len(results) >= windowed_runs + 1
    last = results[-1]
    assert last.success and last.keyframes_optimised == keyframes - 1 and last.keyframes_fixed == 1
    poses_after = [reconstructor.current_pose(report) for report in reconstructor.reports]
    moved = [np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(poses_after, poses_before)]
    assert 0.0 < max(moved) < 0.01  # a correction of the windows' leftovers, not a new trajectory


def test_summary_records_the_dependency_versions(synth_sequence, tmp_path):
    """summary.json's ``dependencies``: the versions the imported modules report, so a figure
    that moved between two machines can be traced to a dependency (constraints.txt)."""
    import platform

    import open3d
    import scipy

    sequence = open_sequence(synth_sequence, max_frames=2)
    run_reconstruction(sequence, load_config(), tmp_path, dense_models=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["dependencies"] == {"python": platform.python_version(), "numpy": np.__version__,
                                       "opencv": cv2.__version__, "open3d": open3d.__version__,
                                       "scipy": scipy.__version__}


def test_same_input_config_and_seed_give_identical_files(synth_sequence, tmp_path):
    sequence = open_sequence(synth_sequence, max_frames=8)
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        run_reconstruction(sequence, load_config(), tmp_path / name)
    compared = ["config.yaml", "camera.tum", "landmarks.csv", "static/keyframes.tum", "static/landmarks.ply",
                "static/mesh.ply", "static/cloud.ply"]
    for relative in compared:
        assert (tmp_path / "a" / relative).read_bytes() == (tmp_path / "b" / relative).read_bytes(), relative


def test_ctrl_c_while_saving_does_not_cut_the_save(synth_sequence, tmp_path, monkeypatch):
    """A second Ctrl-C, pressed while the results of an interrupted run are written, is
    ignored until they are: summary.json and every map file are still there."""
    import os
    import signal

    from jsr.pipeline.run import ResultsWriter

    sequence = open_sequence(synth_sequence)
    write_tables = ResultsWriter.write_tables
    presses = []

    def impatient_write_tables(self, reconstructor):
        if reconstructor.reports and len(reconstructor.reports) == 3 and not presses:
            presses.append(1)
            os.kill(os.getpid(), signal.SIGINT)  # the second Ctrl-C, mid-save
        write_tables(self, reconstructor)

    def interrupt_after_three(report):
        if report.frame_index == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(ResultsWriter, "write_tables", impatient_write_tables)
    handler_before = signal.getsignal(signal.SIGINT)  # SIG_IGN in a job started in the background
    with pytest.raises(KeyboardInterrupt):
        run_reconstruction(sequence, load_config(), tmp_path, on_frame=interrupt_after_three, flush_every=0)
    assert presses
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["frames_processed"] == 3
    assert (tmp_path / "static" / "landmarks.ply").is_file()
    assert signal.getsignal(signal.SIGINT) is handler_before  # restored


def test_frame_without_valid_depth_mid_sequence_is_reported(synth_sequence, tmp_path, caplog):
    root = tmp_path / "sequence"
    shutil.copytree(synth_sequence, root)
    sequence = open_sequence(root, max_frames=6)
    blank = sequence[3].depth_path
    cv2.imwrite(str(blank), np.zeros_like(cv2.imread(str(blank), cv2.IMREAD_UNCHANGED)))
    with caplog.at_level(logging.WARNING, logger="jsr"):
        summary = run_reconstruction(open_sequence(root, max_frames=6), load_config(), tmp_path / "out",
                                     dense_models=False)
    assert summary["status"] == "complete" and summary["frames_processed"] == 6
    warnings = [r.getMessage() for r in caplog.records if "no valid depth" in r.getMessage()]
    assert warnings == [f"frame 3: depth image {blank.name} has no valid depth; check it (the frame can only be "
                        "placed from 2D matches)"]


def test_blas_runs_on_one_thread_within_the_block_and_as_before_after():
    from threadpoolctl import threadpool_info

    from jsr.pipeline.run import single_threaded_blas

    def blas_threads():
        return [info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"]

    with single_threaded_blas():
        pass  # SciPy's BLAS is loaded now
    before = blas_threads()
    with single_threaded_blas():
        assert blas_threads() == [1] * len(before)
    assert blas_threads() == before


def test_folders_of_objects_dropped_since_a_flush_are_removed(synth_sequence, tmp_path):
    """An object written at a flush and merged or dropped as non-rigid later leaves no folder:
    ``objects/`` lists exactly the objects of ``summary.json``."""
    from jsr.pipeline.run import ResultsWriter, remove_dropped_object_folders

    for name in ("object_2", "object_7"):  # as earlier flushes would have left them
        (tmp_path / "objects" / name).mkdir(parents=True)
        (tmp_path / "objects" / name / "trajectory.tum").write_text(f"# {name}\n")
    assert remove_dropped_object_folders(tmp_path, {"objects/object_7"}) == ["objects/object_2"]
    assert [p.name for p in (tmp_path / "objects").iterdir()] == ["object_7"]
    assert (tmp_path / "objects" / "object_7" / "trajectory.tum").is_file()

    # the writer removes them: this run's reconstructor has no object (its first 3 frames)
    sequence = open_sequence(synth_sequence, max_frames=3)
    reconstructor = Reconstructor(load_config(), sequence.intrinsics)
    for index in range(len(sequence)):
        reconstructor.process(sequence[index])
    assert not reconstructor.object_maps
    ResultsWriter(tmp_path, sequence, load_config()).write_tables(reconstructor)
    reconstructor.close()
    assert not list((tmp_path / "objects").iterdir())
    assert (tmp_path / "static" / "keyframes.tum").is_file()
