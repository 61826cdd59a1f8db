"""Result writers: PLY point clouds and meshes (binary, via Open3D), CSV, JSON and YAML.

All of them write atomically (see :mod:`jsr.io.atomic`): an interrupted run never
leaves a half-written file behind.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import yaml

from jsr.io.atomic import atomic_path, atomic_write_bytes, atomic_write_text


def open3d_quiet():
    # Imported lazily: Open3D takes about a second to load and most commands never need it.
    import open3d

    # Open3D's C++ warnings go to stdout, where they would corrupt --json output; jsr reports
    # failures itself.
    open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
    return open3d


def make_point_cloud(points: np.ndarray, colors: np.ndarray | None = None, normals: np.ndarray | None = None):
    """An ``open3d.geometry.PointCloud`` from ``(N, 3)`` points, colours in [0, 1] or uint8, normals."""
    o3d = open3d_quiet()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64).reshape(-1, 3)))
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype == np.uint8:
            colors = colors.astype(np.float64) / 255.0
        cloud.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64).reshape(-1, 3))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    return cloud


def write_point_cloud_ply(
    path: Path, points: np.ndarray, colors: np.ndarray | None = None, normals: np.ndarray | None = None
) -> None:
    """Write a binary PLY point cloud with optional per-point colours and normals."""
    write_geometry_ply(path, make_point_cloud(points, colors, normals))


EMPTY_PLY = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


def write_geometry_ply(path: Path, geometry) -> None:
    """Write an Open3D ``PointCloud`` or ``TriangleMesh`` as binary PLY, atomically.

    An empty geometry gives a valid PLY with no vertices (Open3D refuses to write one).
    """
    o3d = open3d_quiet()
    vertices = geometry.vertices if isinstance(geometry, o3d.geometry.TriangleMesh) else geometry.points
    if len(vertices) == 0:
        atomic_write_bytes(Path(path), EMPTY_PLY)
        return
    with atomic_path(Path(path)) as temporary:
        if isinstance(geometry, o3d.geometry.TriangleMesh):
            written = o3d.io.write_triangle_mesh(str(temporary), geometry, write_ascii=False)
        else:
            written = o3d.io.write_point_cloud(str(temporary), geometry, write_ascii=False)
        if not written:
            raise OSError(f"Open3D could not write {path}")


def read_geometry_ply(path: Path):
    """Read a PLY file as a ``TriangleMesh`` if it has faces, else as a ``PointCloud``."""
    o3d = open3d_quiet()
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) > 0:
        return mesh
    return o3d.io.read_point_cloud(str(path))


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Write a CSV file with a header row, atomically. Floats keep full precision."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow([repr(value) if isinstance(value, float) else value for value in row])
    atomic_write_text(Path(path), buffer.getvalue())


def read_csv(path: Path) -> list[dict[str, str]]:
    """Read a CSV file with a header row into a list of dicts (values as strings)."""
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def to_json_text(data: object) -> str:
    """JSON text of ``data`` (numpy scalars, arrays and paths allowed)."""
    return json.dumps(data, indent=2, default=_json_default) + "\n"


def write_json(path: Path, data: object) -> None:
    """Write ``data`` as indented JSON, atomically."""
    atomic_write_text(Path(path), to_json_text(data))


def write_yaml(path: Path, data: object) -> None:
    """Write ``data`` as YAML (keys in insertion order), atomically."""
    atomic_write_text(Path(path), yaml.safe_dump(data, sort_keys=False))
