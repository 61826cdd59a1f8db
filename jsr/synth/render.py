"""Ray casting of a synthetic sequence's frames and the Kinect-like depth sensor model.

:class:`SynthRenderer` builds the texture atlas of a :class:`~jsr.synth.scene.ScenePlan`
once, then renders frame by frame: colour (triplanar, trilinear texture lookup and simple
shading), exact depth, sensor depth (axial noise, dropouts) and labels. Rays leave through
the pixels of the plan's camera, lens distortion included, so that a rendering lines up
with a real camera's images (composites, :mod:`jsr.synth.composite`).
:func:`sensor_depth_model` is the sensor model alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from jsr.geometry import KINECT_SIGMA_Z_COEFFICIENT
from jsr.synth.randomness import STREAM_FRAME, STREAM_TEXTURE, seeded_rng
from jsr.synth.scene import ScenePlan
from jsr.synth.textures import half_size, make_texture

MIN_RANGE, MAX_RANGE = 0.3, 6.0
GRAZING_LIMIT_DEGREES = 80.0
EDGE_DROP_PROBABILITY = 0.5
MIP_LEVELS = 4  # texture pyramid levels (>= 2), against aliasing of distant textures

# The texture of face (axis a, sign) of a shape is indexed by the two other local axes.
_FACE_AXES = ((1, 2), (0, 2), (0, 1))


@dataclass
class ExactFrame:
    """What the ray caster sees, before the depth sensor: ``depth`` is the exact z of the
    visible surface (0 where nothing is hit), ``grazing`` marks surfaces seen at more than
    ``GRAZING_LIMIT_DEGREES`` from their normal (the sensor gives no depth there)."""

    color: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float64 metres
    grazing: np.ndarray  # (H, W) bool
    labels: np.ndarray  # (H, W) uint8


@dataclass
class SensorDepth:
    """The depth sensor's view of exact depth: ``depth`` with axial noise everywhere (not
    masked), ``kept`` where the sensor gives depth before edge dropouts (in range, not grazing,
    not dropped at random), ``edge_dropped`` where depth goes missing along a discontinuity.
    The sensor's depth image is ``depth`` where ``kept & ~edge_dropped``, 0 elsewhere."""

    depth: np.ndarray  # (H, W) float64 metres
    kept: np.ndarray  # (H, W) bool
    edge_dropped: np.ndarray  # (H, W) bool

    def image(self) -> np.ndarray:
        """``(H, W)`` float64 metres, 0 where the sensor gives no depth."""
        return np.where(self.kept & ~self.edge_dropped, self.depth, 0.0)


def camera_rays(intrinsics) -> np.ndarray:
    """``(H * W, 3)`` camera-frame ray directions with z = 1, row by row, through the pixel
    centres of a :class:`~jsr.io.camera.CameraIntrinsics` (lens distortion undone)."""
    u, v = np.meshgrid(np.arange(intrinsics.width, dtype=float), np.arange(intrinsics.height, dtype=float))
    if intrinsics.has_distortion:
        ideal = intrinsics.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]))
        u, v = ideal[:, 0].reshape(u.shape), ideal[:, 1].reshape(v.shape)
    # z = 1, so that a ray parameter t_hit is the depth z.
    return np.stack(
        [(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)], axis=-1
    ).reshape(-1, 3)


def field_of_view(intrinsics) -> tuple[float, float, float, float]:
    """``(x_min, x_max, y_min, y_max)``: the normalised image coordinates (x/z, y/z) the image's
    border pixels see, lens distortion undone. A point beyond them is out of view even if
    OpenCV's projection brings it into the image: a distortion polynomial folds points far
    outside the field of view back inside."""
    width, height = intrinsics.width, intrinsics.height
    columns, rows = np.arange(width, dtype=float), np.arange(height, dtype=float)
    border = np.concatenate([
        np.column_stack([columns, np.zeros(width)]), np.column_stack([columns, np.full(width, height - 1.0)]),
        np.column_stack([np.zeros(height), rows]), np.column_stack([np.full(height, width - 1.0), rows]),
    ])
    ideal = intrinsics.undistort_pixels(border)
    x = (ideal[:, 0] - intrinsics.cx) / intrinsics.fx
    y = (ideal[:, 1] - intrinsics.cy) / intrinsics.fy
    return float(x.min()), float(x.max()), float(y.min()), float(y.max())


def sensor_depth_model(
    depth_clean: np.ndarray, grazing: np.ndarray, seed: int, index: int, depth_noise: bool, dropout: float
) -> SensorDepth:
    """Kinect-like depth of ``(H, W)`` exact depth (metres, 0 = nothing): axial noise
    ``sigma_Z = 1.425e-3 Z^2``, out-of-range, grazing, edge and random dropouts. The draws
    come from frame ``index``'s streams of ``seed`` (the same frame gives the same noise)."""
    depth = depth_clean.copy()
    kept = (depth_clean >= MIN_RANGE) & (depth_clean <= MAX_RANGE) & ~grazing
    edge_dropped = np.zeros(depth_clean.shape, dtype=bool)
    if depth_noise:
        noise = seeded_rng(seed, STREAM_FRAME, index, 0).standard_normal(depth.shape)
        depth = depth + noise * KINECT_SIGMA_Z_COEFFICIENT * depth_clean**2
    if dropout > 0.0:
        kept &= seeded_rng(seed, STREAM_FRAME, index, 1).random(depth.shape) >= dropout
        # Thin bands along strong depth discontinuities go missing now and then.
        far = np.where(depth_clean > 0, depth_clean, MAX_RANGE * 2).astype(np.float32)
        kernel = np.ones((3, 3), np.uint8)
        jump = cv2.dilate(far, kernel) - cv2.erode(far, kernel)
        edges = jump > np.maximum(0.05, 0.04 * far)
        drop = seeded_rng(seed, STREAM_FRAME, index, 2).random(depth.shape) < EDGE_DROP_PROBABILITY
        edge_dropped = edges & drop
    return SensorDepth(depth, kept, edge_dropped)


@dataclass
class RenderedFrame:
    """One rendered frame. ``depth`` is what the sensor gives (noise, dropouts; 0 = invalid),
    ``depth_clean`` the exact z of the visible surface (0 where nothing is hit)."""

    color: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float64 metres
    depth_clean: np.ndarray  # (H, W) float64 metres
    labels: np.ndarray  # (H, W) uint8


class SynthRenderer:
    """Ray casts the frames of a :class:`ScenePlan` (textures are built once, here)."""

    def __init__(self, plan: ScenePlan):
        self.plan = plan
        self.shapes = plan.shapes
        self._meshes = [shape.mesh_arrays() for shape in self.shapes]
        self._static_world = [
            ((vertices @ shape.pose[:3, :3].T + shape.pose[:3, 3]).astype(np.float32), triangles.astype(np.uint32))
            for shape, (vertices, triangles) in zip(plan.static_shapes, self._meshes)
        ]
        self._labels = np.array([shape.label for shape in self.shapes], dtype=np.uint8)
        self._kinds = np.array([{"box": 0, "sphere": 1, "cylinder": 2}[shape.kind] for shape in self.shapes])
        self._sizes = np.array([shape.size for shape in self.shapes], dtype=np.float64).reshape(-1, 3)
        self._texels = np.array([shape.texel for shape in self.shapes], dtype=np.float64)
        self._build_atlas()
        self._directions = camera_rays(plan.intrinsics)

    def _build_atlas(self) -> None:
        """One flat texel array per mip level; tile ``6 s + 2 axis + positive`` of shape ``s``."""
        tiles = []
        seed = self.plan.options.seed
        for shape in self.shapes:
            for face in range(6):
                axis_u, axis_v = _FACE_AXES[face // 2]
                if face in shape.hidden_faces:
                    tiles.append(np.full((2, 2, 3), 128, np.uint8))
                    continue
                width = math.ceil(shape.size[axis_u] / shape.texel) + 2
                height = math.ceil(shape.size[axis_v] / shape.texel) + 2
                tile_rng = seeded_rng(seed, STREAM_TEXTURE, shape.texture_key, face)
                tiles.append(make_texture(tile_rng, height, width, shape.style))
        self._levels = []
        for level in range(MIP_LEVELS):
            if level:
                tiles = [half_size(tile) for tile in tiles]
            widths = np.array([tile.shape[1] for tile in tiles], dtype=np.int64)
            heights = np.array([tile.shape[0] for tile in tiles], dtype=np.int64)
            offsets = np.concatenate([[0], np.cumsum(widths * heights)[:-1]]).astype(np.int64)
            flat = np.concatenate([tile.reshape(-1, 3) for tile in tiles]) if tiles else np.zeros((1, 3), np.uint8)
            self._levels.append((flat, offsets, widths, heights))

    def _cast(self, index: int, camera_pose: np.ndarray) -> dict:
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        for vertices, triangles in self._static_world:
            scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
        for k in range(len(self.plan.object_shapes)):
            vertices, triangles = self._meshes[len(self.plan.static_shapes) + k]
            pose = self.plan.object_poses[k, index]
            world = (vertices @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
            scene.add_triangles(o3d.core.Tensor(world), o3d.core.Tensor(triangles.astype(np.uint32)))
        directions = self._directions @ camera_pose[:3, :3].T
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = camera_pose[:3, 3]
        rays[:, 3:] = directions
        result = scene.cast_rays(o3d.core.Tensor(rays))
        return {
            "t_hit": result["t_hit"].numpy().astype(np.float64),
            "geometry_ids": result["geometry_ids"].numpy().astype(np.int64),
            "normals": result["primitive_normals"].numpy().astype(np.float64),
            "directions": directions,
            "origin": camera_pose[:3, 3],
        }

    def render(self, index: int, depth_noise: bool | None = None, dropout: float | None = None) -> RenderedFrame:
        """Render frame ``index``; ``depth_noise`` and ``dropout`` default to the plan's options."""
        options = self.plan.options
        depth_noise = options.depth_noise if depth_noise is None else depth_noise
        dropout = options.dropout if dropout is None else dropout
        exact = self.render_exact(index)
        sensor = sensor_depth_model(exact.depth, exact.grazing, options.seed, index, depth_noise, dropout)
        return RenderedFrame(exact.color, sensor.image(), exact.depth, exact.labels)

    def render_exact(self, index: int, camera_pose: np.ndarray | None = None) -> ExactFrame:
        """Colour, exact depth, grazing surfaces and labels of frame ``index``, seen from
        ``camera_pose`` ``T_w_c`` (default: the plan's camera at that frame)."""
        options = self.plan.options
        height, width = options.height, options.width
        camera_pose = self.plan.camera_poses[index] if camera_pose is None else np.asarray(camera_pose, dtype=float)
        cast = self._cast(index, camera_pose)
        t_hit, ids = cast["t_hit"], cast["geometry_ids"]
        hit = np.isfinite(t_hit) & (ids >= 0) & (ids < len(self.shapes))
        shape_index = np.where(hit, ids, 0)
        depth_clean = np.where(hit, t_hit, 0.0)

        color = np.zeros((len(t_hit), 3), dtype=np.float32)
        labels = np.zeros(len(t_hit), dtype=np.uint8)
        grazing = np.zeros(len(t_hit), dtype=bool)
        if np.any(hit):
            rows = np.flatnonzero(hit)
            sid = shape_index[rows]
            directions = cast["directions"][rows]
            points = cast["origin"] + directions * t_hit[rows, None]
            poses = self.plan.shape_poses(index)
            rotations = poses[sid, :3, :3]
            local = np.einsum("nji,nj->ni", rotations, points - poses[sid, :3, 3])
            normals_world = cast["normals"][rows]
            facing = np.einsum("ni,ni->n", normals_world, directions) > 0
            normals_world[facing] *= -1.0
            unit_directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
            cos_incidence = -np.einsum("ni,ni->n", normals_world, unit_directions)
            grazing[rows] = cos_incidence < math.cos(math.radians(GRAZING_LIMIT_DEGREES))
            local_normals = self._shading_normals(sid, local, np.einsum("nji,nj->ni", rotations, normals_world))
            # Metres of surface seen by one pixel, larger on oblique surfaces: picks the mip level.
            footprint = t_hit[rows] / self.plan.intrinsics.fx / np.sqrt(np.clip(cos_incidence, 0.2, 1.0))
            albedo = self._lookup(sid, local, local_normals, footprint)
            shading_world = np.einsum("nij,nj->ni", rotations, local_normals)
            light = self.plan.light_direction
            lambert = np.clip(shading_world @ light, 0.0, None)
            fill = np.clip(shading_world @ (-light * np.array([1.0, 1.0, -0.3])), 0.0, None)
            shade = 0.45 + 0.55 * lambert + 0.15 * fill
            color[rows] = albedo * shade[:, None]
            labels[rows] = self._labels[sid]

        color_image = np.round(np.clip(color, 0.0, 1.0) * 255.0).astype(np.uint8).reshape(height, width, 3)
        return ExactFrame(
            color_image, depth_clean.reshape(height, width), grazing.reshape(height, width), labels.reshape(height, width)
        )

    def _shading_normals(self, sid: np.ndarray, local: np.ndarray, local_normals: np.ndarray) -> np.ndarray:
        """Exact normals of spheres and cylinder sides (the meshes are faceted)."""
        kinds = self._kinds[sid]
        normals = local_normals.copy()
        sphere = kinds == 1
        if np.any(sphere):
            normals[sphere] = local[sphere] / np.linalg.norm(local[sphere], axis=1, keepdims=True)
        side = (kinds == 2) & (np.abs(local_normals[:, 2]) < 0.5)
        if np.any(side):
            radial = local[side].copy()
            radial[:, 2] = 0.0
            normals[side] = radial / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)
        return normals

    def _lookup(self, sid: np.ndarray, local: np.ndarray, normals: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Triplanar texture lookup in the shape's frame (the dominant normal axis picks the
        tile), trilinear: bilinear in the two mip levels around ``footprint`` (metres per pixel)."""
        axis = np.argmax(np.abs(normals), axis=1)
        positive = np.take_along_axis(normals, axis[:, None], axis=1)[:, 0] > 0
        tile = sid * 6 + axis * 2 + positive
        axes = np.array(_FACE_AXES)[axis]
        half = self._sizes[sid] / 2.0
        texel = self._texels[sid]
        # Continuous level-0 texel coordinates; texel i covers [i, i + 1), one texel of margin.
        plane = np.take_along_axis(local, axes, 1) + np.take_along_axis(half, axes, 1)
        u = plane[:, 0] / texel + 1.0
        v = plane[:, 1] / texel + 1.0
        level = np.clip(np.log2(np.maximum(footprint / texel, 1e-6)), 0.0, MIP_LEVELS - 1.0)
        low = np.minimum(np.floor(level).astype(np.int64), MIP_LEVELS - 2)
        weight = (level - low).astype(np.float32)[:, None]
        result = np.zeros((len(sid), 3), dtype=np.float32)
        base_widths, base_heights = self._levels[0][2], self._levels[0][3]
        for number in range(MIP_LEVELS):
            parts = ((np.flatnonzero(low == number), 1.0 - weight), (np.flatnonzero(low + 1 == number), weight))
            for rows, factor in parts:
                if len(rows) == 0:
                    continue
                flat, offsets, widths, heights = self._levels[number]
                t = tile[rows]
                w, h = widths[t], heights[t]
                x = np.clip(u[rows] * (w / base_widths[t]) - 0.5, 0.0, w - 1.001)
                y = np.clip(v[rows] * (h / base_heights[t]) - 0.5, 0.0, h - 1.001)
                x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
                fx, fy = (x - x0).astype(np.float32)[:, None], (y - y0).astype(np.float32)[:, None]
                start = offsets[t] + y0 * w + x0

                def texels(index: np.ndarray) -> np.ndarray:
                    return np.take(flat, index, axis=0).astype(np.float32)  # np.take: fast row gather

                top = texels(start) * (1 - fx) + texels(start + 1) * fx
                bottom = texels(start + w) * (1 - fx) + texels(start + w + 1) * fx
                result[rows] += factor[rows] * (top * (1 - fy) + bottom * fy)
        return result * np.float32(1.0 / 255.0)
