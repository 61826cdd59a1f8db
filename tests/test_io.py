import json

import numpy as np
import pytest

from jsr.errors import InputError, OutputError
from jsr.geometry import make_transform, pose_from_tum, pose_to_tum
from jsr.io.atomic import atomic_path, atomic_write_text
from jsr.io.run_folder import prepare_output_folder
from jsr.io.trajectory import read_tum_trajectory, write_tum_trajectory
from jsr.io.writers import read_csv, read_geometry_ply, write_csv, write_json, write_point_cloud_ply
from scipy.spatial.transform import Rotation


def random_poses(count, seed=0):
    rng = np.random.default_rng(seed)
    rotations = Rotation.random(count, random_state=seed).as_matrix()
    return np.stack([make_transform(r, rng.normal(size=3) * 3) for r in rotations])


def test_tum_round_trip_full_precision(tmp_path):
    poses = random_poses(20)
    timestamps = 1548339819.87426 + np.arange(20) / 30.0
    path = tmp_path / "traj.tum"
    write_tum_trajectory(path, timestamps, poses, header="test")
    read_timestamps, read_poses = read_tum_trajectory(path)
    assert np.array_equal(read_timestamps, timestamps)  # exact, not 4 decimals
    assert np.allclose(read_poses, poses, atol=1e-14)
    # the text is exactly what evo's np.loadtxt would parse
    table = np.loadtxt(path)
    assert table.shape == (20, 8)
    assert np.array_equal(table[:, 1:], pose_to_tum(poses))


def test_pose_tum_conversion_round_trip():
    poses = random_poses(5, seed=3)
    assert np.allclose(pose_from_tum(pose_to_tum(poses)), poses, atol=1e-14)
    assert np.all(pose_to_tum(poses)[:, 6] >= 0)


def test_read_tum_rejects_malformed_lines(tmp_path):
    path = tmp_path / "bad.tum"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0\n")
    with pytest.raises(InputError, match="bad.tum:3"):
        read_tum_trajectory(path)
    path.write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match="zero length"):
        read_tum_trajectory(path)


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    path = tmp_path / "data.csv"
    atomic_write_text(path, "old\n")
    with pytest.raises(RuntimeError):
        with atomic_path(path) as temporary:
            temporary.write_text("half")
            raise RuntimeError("crash mid-write")
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["data.csv"]


def test_ply_point_cloud_with_colours_and_normals(tmp_path):
    rng = np.random.default_rng(1)
    points = rng.normal(size=(50, 3))
    colours = rng.integers(0, 256, size=(50, 3), dtype=np.uint8)
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    path = tmp_path / "cloud.ply"
    write_point_cloud_ply(path, points, colours, normals)
    assert b"binary_little_endian" in path.read_bytes()[:200]
    cloud = read_geometry_ply(path)
    assert np.allclose(np.asarray(cloud.points), points, atol=1e-6)
    assert np.allclose(np.asarray(cloud.colors) * 255, colours, atol=0.51)
    assert np.allclose(np.asarray(cloud.normals), normals, atol=1e-6)


def test_mesh_ply_keeps_faces(tmp_path):
    import open3d as o3d

    from jsr.io.writers import write_geometry_ply

    mesh = o3d.geometry.TriangleMesh.create_box(0.2, 0.1, 0.3)
    path = tmp_path / "mesh.ply"
    write_geometry_ply(path, mesh)
    read = read_geometry_ply(path)
    assert len(read.triangles) == len(mesh.triangles)


def test_csv_and_json(tmp_path):
    write_csv(tmp_path / "t.csv", ["frame", "ms"], [[0, 1.25], [1, 0.1 + 0.2]])
    rows = read_csv(tmp_path / "t.csv")
    assert rows[1] == {"frame": "1", "ms": repr(0.1 + 0.2)}
    write_json(tmp_path / "s.json", {"a": np.float64(1.5), "b": np.arange(3), "c": tmp_path})
    assert json.loads((tmp_path / "s.json").read_text())["b"] == [0, 1, 2]


def test_output_folder_rules(tmp_path):
    out = prepare_output_folder(tmp_path / "run")
    (out / "config.yaml").write_text("seed: 0\n")
    (out / "static").mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="--overwrite"):
        prepare_output_folder(out)
    prepare_output_folder(out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # user files survive
    other = tmp_path / "other"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    with pytest.raises(OutputError, match="holds no jsr results"):
        prepare_output_folder(other, overwrite=True)
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a file"):
        prepare_output_folder(tmp_path / "file")
