"""Dense models: fuse the keyframes of each map into a TSDF (Open3D) and write mesh and cloud.

The sparse maps hold landmarks only; the user wants surfaces. Every keyframe of a map is
re-read from the sequence and integrated with its (bundle-adjusted) pose ``T_map_cam``, so the
model is expressed in the map's frame. Pixels a keyframe did not give to this map can be
masked out (``pixel_masks``), which keeps moving objects out of the static model.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import numpy as np

from jsr.config import Config
from jsr.io.dataset import RGBDSequence
from jsr.io.writers import write_geometry_ply
from jsr.pipeline.maps import Map, map_folder

logger = logging.getLogger(__name__)

MIN_FUSED_PIXELS = 100  # a keyframe with fewer valid pixels for a map adds nothing to its model
# Voxel blocks the TSDF grid reserves at first. Its hash map grows as blocks are activated
# (same output, checked byte for byte), so this only sets the first allocation: 50000 blocks
# of 16^3 voxels (tsdf, weight, colour: 20 bytes each) were 4.1 GB, 1.5-4 s per map to
# allocate, for a room at 1 cm that activates about 3000.
INITIAL_VOXEL_BLOCKS = 2000


def fuse_keyframes(
    map_: Map,
    sequence: RGBDSequence,
    voxel_size: float,
    max_depth: float,
    pixel_mask: Callable[[int], np.ndarray | None] | None = None,
):
    """TSDF-fuse the keyframes of ``map_``; returns legacy Open3D ``(mesh, cloud)`` in the map frame.

    ``pixel_mask(keyframe_id)`` may return an ``(H, W)`` bool mask of the pixels to use.
    Uses Open3D's tensor ``VoxelBlockGrid`` (the legacy ``ScalableTSDFVolume`` of Open3D 0.20
    extracts nothing from float depth here). Surfaces are kept where the summed TSDF weight
    reaches ``min(3, keyframes // 3)`` (at least 1), which drops one-off noise in long maps.
    """
    import open3d.core as o3c

    from jsr.io.writers import open3d_quiet

    o3d = open3d_quiet()
    device = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=voxel_size,
        block_resolution=16,
        block_count=INITIAL_VOXEL_BLOCKS,
        device=device,
    )
    calibration = o3c.Tensor(sequence.intrinsics.matrix, o3c.float64)
    for keyframe in map_.keyframes:
        frame = sequence[keyframe.frame_index]
        depth = frame.depth.copy()
        if pixel_mask is not None:
            mask = pixel_mask(keyframe.keyframe_id)
            if mask is not None:
                depth[~mask] = 0.0
        if np.count_nonzero((depth > 0) & (depth <= max_depth)) < MIN_FUSED_PIXELS:
            continue  # nothing (or next to nothing) of this map in this keyframe
        extrinsic = o3c.Tensor(np.linalg.inv(keyframe.T_map_cam), o3c.float64)  # map -> camera
        depth_image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth)))
        color_image = o3d.t.geometry.Image(o3c.Tensor(frame.color.astype(np.float32) / 255.0))
        try:
            blocks = grid.compute_unique_block_coordinates(depth_image, calibration, extrinsic, 1.0, max_depth)
            grid.integrate(blocks, depth_image, color_image, calibration, extrinsic, 1.0, max_depth)
        except RuntimeError as error:  # Open3D refuses a depth image that touches no voxel block
            logger.warning("%s: keyframe %d not fused (%s)", map_.name, keyframe.keyframe_id,
                           str(error).splitlines()[0][-120:])
    weight_threshold = float(max(1, min(3, len(map_.keyframes) // 3)))
    mesh = _sorted_mesh(grid.extract_triangle_mesh(weight_threshold=weight_threshold).to_legacy(), o3d)
    mesh.compute_vertex_normals()
    cloud = _sorted_cloud(grid.extract_point_cloud(weight_threshold=weight_threshold).to_legacy(), o3d)
    return mesh, cloud


def _vertex_order(points: np.ndarray) -> np.ndarray:
    # The voxel grid's hash map hands out vertices in an order that varies between runs;
    # sorting by coordinates makes the written files identical for identical input.
    return np.lexsort(points.T[::-1]) if len(points) else np.zeros(0, dtype=np.int64)


def _sorted_cloud(cloud, o3d):
    points = np.asarray(cloud.points)
    order = _vertex_order(points)
    sorted_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[order]))
    if cloud.has_colors():
        sorted_cloud.colors = o3d.utility.Vector3dVector(np.asarray(cloud.colors)[order])
    if cloud.has_normals():
        sorted_cloud.normals = o3d.utility.Vector3dVector(np.asarray(cloud.normals)[order])
    return sorted_cloud


def _sorted_mesh(mesh, o3d):
    vertices = np.asarray(mesh.vertices)
    order = _vertex_order(vertices)
    new_index = np.empty(len(order), dtype=np.int64)
    new_index[order] = np.arange(len(order))
    triangles = new_index[np.asarray(mesh.triangles)]
    triangles = triangles[np.lexsort(triangles.T[::-1])] if len(triangles) else triangles
    sorted_mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices[order]), o3d.utility.Vector3iVector(triangles.astype(np.int32))
    )
    if mesh.has_vertex_colors():
        sorted_mesh.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_colors)[order])
    return sorted_mesh


def write_dense_models(reconstructor, sequence: RGBDSequence, config: Config, out_dir: Path) -> None:
    """Write ``mesh.ply`` and ``cloud.ply`` of every map into its folder of ``out_dir``."""
    for map_ in reconstructor.maps:
        if not map_.keyframes:
            continue
        folder = Path(out_dir) / map_folder(map_)
        mask_of = getattr(reconstructor, "keyframe_pixel_mask", None)
        mesh, cloud = fuse_keyframes(
            map_,
            sequence,
            config.output.mesh_voxel_size,
            config.input.max_depth,
            None if mask_of is None else (lambda keyframe_id, m=map_: mask_of(m, keyframe_id)),
        )
        if len(mesh.vertices) == 0:
            logger.warning("%s: the keyframes fused into an empty model; no mesh.ply written", map_.name)
            continue
        write_geometry_ply(folder / "mesh.ply", mesh)
        write_geometry_ply(folder / "cloud.ply", cloud)
        logger.info("%s: mesh with %d vertices from %d keyframes", map_.name, len(mesh.vertices), len(map_.keyframes))
