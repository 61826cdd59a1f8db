"""Dense surface samples of object views and the voxel surface models built from them.

Every object keyframe keeps a subsampled coloured surface of the object's pixels
(:func:`sample_surface`); the samples of an object's keyframes, placed in its map frame, make
its surface model (:func:`build_model`), and a region of the current frame is one in its camera
frame (:func:`region_model`). Aligning a region to a model is
:mod:`jsr.pipeline.surface_alignment`; judging such a fit, :mod:`jsr.pipeline.surface_evidence`.

Frames: ``camera`` is the frame of the view a sample was taken in; ``model`` is the object
map's frame. Transforms are ``(4, 4)`` and map points of the right-hand frame into the left.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jsr.geometry import backproject_pixels, transform_points


@dataclass
class SurfaceSample:
    """Object pixels of one view: ``points`` ``(N, 3)`` camera frame (float32), ``colors``
    ``(N, 3)`` uint8 RGB."""

    points: np.ndarray
    colors: np.ndarray


@dataclass
class SurfaceModel:
    """An object's surface in its map frame: ``points`` ``(N, 3)``, ``normals`` ``(N, 3)``
    (unit, facing the cameras that saw them), ``colors`` ``(N, 3)`` float in [0, 1].
    ``derived`` keeps what is computed from these arrays (which are never changed in place) for
    reuse, e.g. the descriptors of surface alignment by voxel."""

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    derived: dict = field(default_factory=dict, compare=False, repr=False)


def sample_surface(depth: np.ndarray, color: np.ndarray, mask: np.ndarray, intrinsics, stride: int,
                   voxel: float) -> SurfaceSample:
    """The pixels of ``mask`` ``(H, W)`` bool with valid ``depth`` ``(H, W)`` metres, every
    ``stride``-th row and column, back-projected and thinned to one point per ``voxel`` cube."""
    sub_mask = mask[::stride, ::stride] & (depth[::stride, ::stride] > 0)
    rows, cols = np.nonzero(sub_mask)
    z = depth[::stride, ::stride][rows, cols].astype(np.float64)
    points = backproject_pixels(cols * stride, rows * stride, z, intrinsics.fx, intrinsics.fy, intrinsics.cx,
                                intrinsics.cy)
    colors = color[rows * stride, cols * stride] if color.ndim == 3 else np.repeat(
        color[rows * stride, cols * stride, None], 3, axis=1)
    keep = _one_per_voxel(points, voxel)
    return SurfaceSample(points[keep].astype(np.float32), np.asarray(colors[keep], dtype=np.uint8))


def _one_per_voxel(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of the first point in each occupied ``voxel`` cube (in input order: deterministic)."""
    if not len(points):
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def build_model(views: list[tuple[np.ndarray, SurfaceSample]], voxel: float) -> SurfaceModel | None:
    """One surface from samples ``[(T_model_camera, sample), ...]``, thinned to ``voxel``;
    None when fewer than 20 points remain."""
    points, colors, centres = [], [], []
    for T_model_camera, sample in views:
        if not len(sample.points):
            continue
        points.append(transform_points(T_model_camera, sample.points.astype(np.float64)))
        colors.append(sample.colors)
        centres.append(np.repeat(T_model_camera[None, :3, 3], len(sample.points), axis=0))
    if not points:
        return None
    points, colors, centres = np.concatenate(points), np.concatenate(colors), np.concatenate(centres)
    keep = _one_per_voxel(points, voxel)
    if len(keep) < 20:
        return None
    points, colors, centres = points[keep], colors[keep], centres[keep]
    normals = _normals(points, voxel)
    # face the camera each point was seen from (FPFH depends on the normals' sign)
    flip = np.einsum("ij,ij->i", normals, centres - points) < 0
    normals[flip] *= -1
    return SurfaceModel(points, normals, colors.astype(np.float64) / 255.0)


def region_model(sample: SurfaceSample, voxel: float) -> SurfaceModel | None:
    """A region of the current frame as a :class:`SurfaceModel` in its camera frame."""
    return build_model([(np.eye(4), sample)], voxel)


def thinned(surface: SurfaceModel, voxel: float) -> SurfaceModel:
    """``surface`` with one point per ``voxel`` cube (the first of each, in order)."""
    keep = _one_per_voxel(surface.points, voxel)
    return SurfaceModel(surface.points[keep], surface.normals[keep], surface.colors[keep])


def _normals(points: np.ndarray, voxel: float) -> np.ndarray:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    return np.asarray(cloud.normals).copy()
