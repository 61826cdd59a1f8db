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


PLY_TYPE_BYTES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
                  "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8,
                  "float64": 8}


def _ply_header(path: Path) -> tuple[dict[str, int], int]:
    """``({element: count}, least size in bytes)`` of a PLY file from its header; the least
    size is that of a binary file whose faces are triangles (0 for ASCII). Raises
    :class:`InputError` when there is no complete PLY header."""
    from jsr.errors import InputError

    with open(path, "rb") as handle:
        head = handle.read(1 << 16)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        raise InputError(f"{path} is not a PLY file or its header is cut short; re-run jsr reconstruct")
    file_format, counts, sizes, element = "", {}, {}, None
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            file_format = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            element = words[1]
            counts[element], sizes[element] = int(words[2]), 0
        elif words[:1] == ["property"] and element is not None:
            if words[1] == "list" and len(words) == 5:  # count type, item type: a triangle's 3 items
                sizes[element] += PLY_TYPE_BYTES.get(words[2], 1) + 3 * PLY_TYPE_BYTES.get(words[3], 4)
            elif len(words) == 3:
                sizes[element] += PLY_TYPE_BYTES.get(words[1], 4)
    least = 0 if file_format == "ascii" else end + len(b"end_header\n") + sum(
        counts[name] * sizes[name] for name in counts)
    return counts, least


def read_geometry_ply(path: Path):
    """Read a PLY file as a ``TriangleMesh`` if it has faces, else as a ``PointCloud``.

    Raises :class:`~jsr.errors.InputError` for a file cut short or whose vertex or face count
    disagrees with its header (Open3D would return the part it could read)."""
    from jsr.errors import InputError

    path = Path(path)
    counts, least = _ply_header(path)
    if path.stat().st_size < least:
        raise InputError(f"{path} is truncated ({path.stat().st_size} of at least {least} bytes); "
                         "re-run jsr reconstruct to write it again")
    o3d = open3d_quiet()
    mesh = o3d.io.read_triangle_mesh(str(path))
    geometry = mesh if len(mesh.triangles) > 0 else o3d.io.read_point_cloud(str(path))
    vertices = len(geometry.vertices if geometry is mesh else geometry.points)
    faces = len(mesh.triangles)
    if vertices != counts.get("vertex", 0) or faces != counts.get("face", 0):
        raise InputError(f"{path} is corrupt: {vertices} vertices and {faces} faces read where its header declares "
                         f"{counts.get('vertex', 0)} and {counts.get('face', 0)}; re-run jsr reconstruct")
    return geometry


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
