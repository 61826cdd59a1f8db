import numpy as np
import pytest
from typer.testing import CliRunner

from jsr.cli import app
from jsr.errors import InputError, OutputError
from jsr.export.objects import export_object
from jsr.export.plots import plot_landmark_counts, plot_trajectory, read_landmark_counts
from jsr.geometry import make_transform, rotation_about_axis
from jsr.io.trajectory import write_tum_trajectory
from jsr.io.writers import read_geometry_ply, write_csv, write_point_cloud_ply


def make_results(root):
    """A results folder as 'jsr reconstruct' lays it out, with one object."""
    folder = root / "objects" / "object_1"
    folder.mkdir(parents=True)
    points = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.2, 0], [0, 0, 0.3]])
    write_point_cloud_ply(folder / "landmarks.ply", points)
    poses = np.stack([make_transform(rotation_about_axis([0, 0, 1], a), [1.0 + a, 2.0, 0.5]) for a in (0.0, 0.5, 1.0)])
    write_tum_trajectory(folder / "trajectory.tum", np.array([10.0, 10.1, 10.2]), poses)
    write_tum_trajectory(root / "camera.tum", np.array([10.0, 10.1, 10.2]), np.stack([np.eye(4)] * 3))
    rows = []
    for frame in range(5):
        rows.append([frame, 10 + frame / 10, "static", 1 + frame // 2, 100 + 10 * frame, 3, 1])
        rows.append([frame, 10 + frame / 10, "object_1", 1, 20 + frame, 1, int(frame > 1)])
    write_csv(root / "landmarks.csv", ["frame", "timestamp", "map", "keyframes", "point_landmarks",
                                      "plane_landmarks", "tracked"], rows)
    return points, poses


def test_export_object_in_object_and_world_frames(tmp_path):
    points, poses = make_results(tmp_path)
    out = tmp_path / "box.ply"
    export_object(tmp_path, 1, out, kind="landmarks")
    assert np.allclose(np.asarray(read_geometry_ply(out).points), points, atol=1e-6)
    with pytest.raises(OutputError):
        export_object(tmp_path, 1, out, kind="landmarks")
    info = export_object(tmp_path, 1, out, kind="landmarks", in_world=True, timestamp=10.11, overwrite=True)
    assert info["timestamp"] == pytest.approx(10.1)
    expected = points @ poses[1][:3, :3].T + poses[1][:3, 3]
    assert np.allclose(np.asarray(read_geometry_ply(out).points), expected, atol=1e-6)
    with pytest.raises(InputError, match="wrote no mesh"):
        export_object(tmp_path, 1, tmp_path / "m.ply", kind="mesh")
    with pytest.raises(InputError, match="objects there: object_1"):
        export_object(tmp_path, 2, tmp_path / "m.ply")


def test_plots_figure7_and_trajectory(tmp_path):
    make_results(tmp_path)
    counts = read_landmark_counts(tmp_path / "landmarks.csv")
    assert list(counts["static"]["keyframes"]) == [1, 1, 2, 2, 3]
    assert list(counts["object_1"]["tracked"]) == [False, False, True, True, True]
    png = plot_landmark_counts(tmp_path / "landmarks.csv", tmp_path / "plots" / "landmarks.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    png = plot_trajectory(tmp_path / "camera.tum", tmp_path / "plots" / "trajectory.png")
    assert png.stat().st_size > 1000


def test_cli_plot_and_export(tmp_path):
    make_results(tmp_path)
    runner = CliRunner()
    result = runner.invoke(app, ["plot", str(tmp_path), "-q"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "plots" / "landmarks.png").is_file()
    result = runner.invoke(app, ["export-object", str(tmp_path), "1", "--kind", "landmarks", "--out",
                                 str(tmp_path / "o.ply"), "--world"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "o.ply").is_file()


def test_landmarks_csv_with_wrong_columns(tmp_path):
    write_csv(tmp_path / "landmarks.csv", ["frame", "count"], [[0, 1]])
    with pytest.raises(InputError, match="lacks column"):
        read_landmark_counts(tmp_path / "landmarks.csv")


def test_tsdf_grid_grows_past_its_first_allocation(synth_sequence, monkeypatch):
    """The dense model does not depend on how many voxel blocks the grid reserves at first:
    the hash map grows as blocks are activated (the reservation was once 4 GB)."""
    from types import SimpleNamespace

    import jsr.export.meshes as meshes
    from jsr.io.dataset import open_sequence
    from jsr.io.trajectory import read_tum_trajectory

    sequence = open_sequence(synth_sequence)
    _, poses = read_tum_trajectory(synth_sequence / "groundtruth.txt")
    keyframes = [SimpleNamespace(keyframe_id=k, frame_index=index, T_map_cam=poses[index])
                 for k, index in enumerate(range(0, len(sequence), 5))]
    map_ = SimpleNamespace(name="static", keyframes=keyframes)
    reference, reference_cloud = meshes.fuse_keyframes(map_, sequence, 0.02, 4.0)
    monkeypatch.setattr(meshes, "INITIAL_VOXEL_BLOCKS", 1)
    grown, cloud = meshes.fuse_keyframes(map_, sequence, 0.02, 4.0)
    assert len(reference.vertices) > 1000 and len(cloud.points) > 1000
    assert np.array_equal(np.asarray(grown.vertices), np.asarray(reference.vertices))
    assert np.array_equal(np.asarray(grown.triangles), np.asarray(reference.triangles))
    assert np.array_equal(np.asarray(grown.vertex_colors), np.asarray(reference.vertex_colors))
    assert np.array_equal(np.asarray(cloud.points), np.asarray(reference_cloud.points))
    assert np.array_equal(np.asarray(cloud.colors), np.asarray(reference_cloud.colors))


def test_plot_results_overlays_ground_truth_and_objects(tmp_path):
    from jsr.export.plots import estimated_object_paths, plot_results, true_object_paths

    points, poses = make_results(tmp_path / "results")
    sequence = tmp_path / "seq"
    shift = make_transform(rotation_about_axis([0, 1, 0], 0.3), [0.5, 0.0, 0.2])  # another world
    cameras = np.stack([make_transform(np.eye(3), [0.1 * i, 0, 0]) for i in range(3)])
    write_tum_trajectory(tmp_path / "results" / "camera.tum", np.array([10.0, 10.1, 10.2]), cameras)
    write_tum_trajectory(sequence / "groundtruth.txt", np.array([10.0, 10.1, 10.2]), shift @ cameras)
    write_tum_trajectory(sequence / "objects" / "object_1.txt", np.array([10.0, 10.1, 10.2]), shift @ poses)
    paths = estimated_object_paths(tmp_path / "results")
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))  # of the landmarks: this object has no mesh
    np.testing.assert_allclose(paths[1], poses[:, :3, :3] @ centre + poses[:, :3, 3])
    np.testing.assert_allclose(true_object_paths(sequence)[1], (shift @ poses)[:, :3, 3])
    plain = plot_results(tmp_path / "results", tmp_path / "plain")
    overlaid = plot_results(tmp_path / "results", tmp_path / "overlaid", sequence_dir=sequence)
    assert [p.name for p in overlaid] == ["landmarks.png", "trajectory.png"]
    assert overlaid[1].read_bytes() != plain[1].read_bytes()
