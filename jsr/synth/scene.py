"""The plan of a synthetic sequence: everything except the pixels.

The room and its furniture (:class:`Shape`), the rigid objects on the table top and their
per-frame poses ``T_w_o`` (moved as :mod:`jsr.synth.motion` plans), the hand-held-like camera path ``T_w_c`` and
the timestamps, gathered in a :class:`ScenePlan` by :func:`build_scene_plan`. The world
frame is the room frame: z up, floor at z = 0, table centre above the origin.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from jsr.geometry import look_at, make_transform, rotation_about_axis
from jsr.io.camera import CameraIntrinsics
from jsr.synth.motion import TableTop, plan_object_motion
from jsr.synth.options import SynthOptions, validate_options
from jsr.synth.randomness import STREAM_PLAN, seeded_rng

logger = logging.getLogger(__name__)

TIMESTAMP_START = 1000.0
DEPTH_SCALE = 5000.0

# Room layout (metres). World z is up, the floor is z = 0.
ROOM_HALF_X, ROOM_HALF_Y, ROOM_HEIGHT = 2.5, 2.2, 2.6
WALL_THICKNESS = 0.1
TABLE_SIZE = (1.2, 0.8)
TABLE_TOP = 0.75
TABLE_TOP_THICKNESS = 0.04
TABLE_MARGIN = 0.02


@dataclass(eq=False)
class Shape:
    """A textured solid: a box, sphere or cylinder centred on its local origin.

    ``size`` is the local bounding box ``(x, y, z)`` extent (sphere: ``2r`` each; cylinder:
    ``(2r, 2r, h)`` with its axis along local z). ``pose`` is ``T_w_s`` for static shapes
    and the identity for objects (their poses are per frame). ``label`` is 0 for static
    geometry, ``k`` for object ``k``. ``texel`` is the texture resolution in metres.
    """

    name: str
    kind: str
    size: tuple[float, float, float]
    pose: np.ndarray
    label: int
    texel: float
    style: str
    texture_key: int
    hidden_faces: tuple[int, ...] = ()  # faces never seen (outside of the room): no texture

    @property
    def radius(self) -> float:
        return 0.5 * self.size[0]

    def legacy_mesh(self):
        """``open3d.geometry.TriangleMesh`` in the local frame."""
        import open3d as o3d

        sx, sy, sz = self.size
        if self.kind == "box":
            mesh = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
            mesh.translate((-sx / 2, -sy / 2, -sz / 2))
        elif self.kind == "sphere":
            mesh = o3d.geometry.TriangleMesh.create_sphere(radius=sx / 2, resolution=48)
        elif self.kind == "cylinder":
            mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=sx / 2, height=sz, resolution=96, split=1)
        else:  # pragma: no cover - shapes are built by this module only
            raise ValueError(f"unknown shape kind {self.kind}")
        return mesh

    def mesh_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Local-frame ``(V, 3)`` float64 vertices and ``(T, 3)`` int triangles."""
        mesh = self.legacy_mesh()
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)

    def signed_distance(self, points_local: np.ndarray) -> np.ndarray:
        """Exact signed distance of ``(N, 3)`` local points to the ideal solid (negative inside)."""
        p = np.asarray(points_local, dtype=float).reshape(-1, 3)
        if self.kind == "sphere":
            return np.linalg.norm(p, axis=1) - self.radius
        if self.kind == "box":
            q = np.abs(p) - np.asarray(self.size) / 2.0
        else:
            q = np.column_stack([np.hypot(p[:, 0], p[:, 1]) - self.radius, np.abs(p[:, 2]) - self.size[2] / 2.0])
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return outside + inside


@dataclass(eq=False)
class ScenePlan:
    """Everything about a sequence except the pixels: geometry, poses, timestamps, camera.

    ``camera_poses`` ``(N, 4, 4)`` are ``T_w_c``; ``object_poses`` ``(K, N, 4, 4)`` are
    ``T_w_o`` of object ``k + 1`` at each frame. ``moving_frames[k]`` lists the frames whose
    object pose differs from the previous frame's; ``first_motion_frames[k]`` is the first of
    them (None when the object never moves).
    """

    options: SynthOptions
    intrinsics: CameraIntrinsics
    timestamps: np.ndarray
    names: list[str]
    camera_poses: np.ndarray
    object_poses: np.ndarray
    static_shapes: list[Shape]
    object_shapes: list[Shape]
    light_direction: np.ndarray
    moving_frames: list[list[int]] = field(default_factory=list)

    @property
    def first_motion_frames(self) -> list[int | None]:
        return [frames[0] if frames else None for frames in self.moving_frames]

    @property
    def shapes(self) -> list[Shape]:
        return self.static_shapes + self.object_shapes

    def shape_poses(self, index: int) -> np.ndarray:
        """``(S, 4, 4)`` world poses of :attr:`shapes` at frame ``index``."""
        poses = [shape.pose for shape in self.static_shapes]
        poses += [self.object_poses[k, index] for k in range(len(self.object_shapes))]
        return np.stack(poses) if poses else np.zeros((0, 4, 4))


def synth_intrinsics(width: int, height: int) -> CameraIntrinsics:
    """PrimeSense-like intrinsics scaled to ``width``: ``fx = fy = 525 width / 640``."""
    focal = 525.0 * width / 640.0
    return CameraIntrinsics(focal, focal, (width - 1) / 2.0, (height - 1) / 2.0, width, height, DEPTH_SCALE)


def _pose(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    return make_transform(rotation_about_axis(np.array([0.0, 0.0, 1.0]), yaw), (x, y, z))


def _static_shapes(rng: np.random.Generator) -> list[Shape]:
    """The room and its furniture (fixed layout; the seed only jitters books and textures)."""
    shapes: list[Shape] = []

    def add(name, kind, size, pose, texel, style, hidden=()):
        size = tuple(float(s) for s in size)
        shapes.append(Shape(name, kind, size, pose, 0, texel, style, len(shapes), hidden))

    hx, hy, h, t = ROOM_HALF_X, ROOM_HALF_Y, ROOM_HEIGHT, WALL_THICKNESS
    add("floor", "box", (2 * hx + 2 * t, 2 * hy + 2 * t, t), _pose(0, 0, -t / 2), 0.008, "floor", (4,))
    add("ceiling", "box", (2 * hx + 2 * t, 2 * hy + 2 * t, t), _pose(0, 0, h + t / 2), 0.012, "ceiling", (5,))
    add("wall +x", "box", (t, 2 * hy, h), _pose(hx + t / 2, 0, h / 2), 0.008, "wall", (1,))
    add("wall -x", "box", (t, 2 * hy, h), _pose(-hx - t / 2, 0, h / 2), 0.008, "wall", (0,))
    add("wall +y", "box", (2 * hx, t, h), _pose(0, hy + t / 2, h / 2), 0.008, "wall", (3,))
    add("wall -y", "box", (2 * hx, t, h), _pose(0, -hy - t / 2, h / 2), 0.008, "wall", (2,))
    add("picture", "box", (1.0, 0.02, 0.7), _pose(-0.7, hy - 0.01, 1.6), 0.004, "furniture")

    # Table: top and four legs.
    tx, ty = TABLE_SIZE
    top_centre = TABLE_TOP - TABLE_TOP_THICKNESS / 2
    add("table top", "box", (tx, ty, TABLE_TOP_THICKNESS), _pose(0, 0, top_centre), 0.004, "wood")
    leg_height = TABLE_TOP - TABLE_TOP_THICKNESS
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg_pose = _pose(sx * (tx / 2 - 0.06), sy * (ty / 2 - 0.06), leg_height / 2)
            add("table leg", "box", (0.05, 0.05, leg_height), leg_pose, 0.004, "wood")

    # Cabinet against the +y wall, a box and a vase on it.
    cab = (0.9, 0.45, 0.9)
    add("cabinet", "box", cab, _pose(0.75, hy - cab[1] / 2 - 0.01, cab[2] / 2), 0.005, "furniture")
    add("storage box", "box", (0.35, 0.3, 0.25), _pose(0.6, hy - 0.22, cab[2] + 0.125, 0.15), 0.004, "furniture")
    add("vase", "cylinder", (0.14, 0.14, 0.3), _pose(1.02, hy - 0.2, cab[2] + 0.15), 0.003, "furniture")

    # Shelf against the +x wall: back, two sides, four boards, books.
    depth, width, height = 0.35, 1.1, 1.6
    sx0, sy0 = hx - depth / 2 - 0.01, 0.95
    add("shelf back", "box", (0.02, width, height), _pose(hx - 0.02, sy0, height / 2), 0.005, "wood")
    for side in (-1, 1):
        side_pose = _pose(sx0, sy0 + side * (width / 2 - 0.015), height / 2)
        add("shelf side", "box", (depth, 0.03, height), side_pose, 0.005, "wood")
    boards = (0.02, 0.55, 1.08, 1.585)
    for z in boards:
        add("shelf board", "box", (depth, width - 0.06, 0.03), _pose(sx0, sy0, z), 0.005, "wood")
    for z in boards[:3]:
        y = sy0 - width / 2 + 0.06
        while True:
            thickness = rng.uniform(0.03, 0.08)
            book_height = rng.uniform(0.18, 0.4)
            if y + thickness > sy0 + width / 2 - 0.06:
                break
            book_depth = rng.uniform(0.18, 0.3)
            pose = _pose(hx - 0.03 - book_depth / 2, y + thickness / 2, z + 0.015 + book_height / 2)
            add("book", "box", (book_depth, thickness, book_height), pose, 0.003, "furniture")
            y += thickness + rng.uniform(0.0, 0.03)

    # Non-planar furniture: a ball on the floor and a bin.
    add("ball", "sphere", (0.44, 0.44, 0.44), _pose(1.35, 1.45, 0.22), 0.004, "furniture")
    add("bin", "cylinder", (0.4, 0.4, 0.7), _pose(-1.55, 1.5, 0.35), 0.005, "furniture")
    add("stool", "cylinder", (0.5, 0.5, 0.45), _pose(-1.95, 0.2, 0.225), 0.005, "wood")
    return shapes


def object_shapes(rng: np.random.Generator, count: int, texture_key_base: int = 1000) -> list[Shape]:
    """Rigid textured objects 10-30 cm: object 1 is a box; further objects alternate cylinder /
    box. Object ``k``'s textures are drawn with key ``texture_key_base + k``."""
    scale = 1.0 if count <= 3 else math.sqrt(3.0 / count)
    shapes = []
    for k in range(1, count + 1):
        if k % 2 == 1:
            size = (rng.uniform(0.15, 0.3) * scale, rng.uniform(0.15, 0.3) * scale, rng.uniform(0.12, 0.25) * scale)
            kind = "box"
        else:
            diameter = rng.uniform(0.12, 0.18) * scale
            size = (diameter, diameter, rng.uniform(0.15, 0.28) * scale)
            kind = "cylinder"
        shapes.append(Shape(f"object {k}", kind, size, np.eye(4), k, 0.0025, "object", texture_key_base + k))
    return shapes


def footprint_radius(shape: Shape) -> float:
    """Radius of a vertical cylinder containing the object for any rotation about z."""
    if shape.kind == "box":
        return 0.5 * math.hypot(shape.size[0], shape.size[1])
    return shape.radius


def _plan_objects(
    options: SynthOptions, shapes: list[Shape], rng: np.random.Generator
) -> tuple[np.ndarray, list[list[int]]]:
    """Per-frame object poses ``(K, N, 4, 4)`` on the table top and the frames where each pose changes."""
    radii = [footprint_radius(shape) for shape in shapes]
    trajectory, moving = plan_object_motion(options, radii, TableTop(TABLE_SIZE, TABLE_MARGIN, radii), rng)
    poses = np.zeros((len(shapes), options.frames, 4, 4))
    for k, shape in enumerate(shapes):
        for f in range(options.frames):
            x, y, yaw = trajectory[k, f]
            poses[k, f] = _pose(x, y, TABLE_TOP + shape.size[2] / 2, yaw)
    return poses, moving


def _camera_trajectory(frames: int, rng: np.random.Generator) -> np.ndarray:
    """Hand-held-like ``(N, 4, 4)`` ``T_w_c``: an arc around the table, looking at it."""
    index = np.arange(frames, dtype=float)
    s = index / (frames - 1)

    def wobble(amplitude: float, period_low: float, period_high: float, terms: int = 3) -> np.ndarray:
        total = np.zeros(frames)
        for _ in range(terms):
            period = rng.uniform(period_low, period_high)
            total += np.sin(2.0 * math.pi * index / period + rng.uniform(0.0, 2.0 * math.pi))
        return amplitude * total / math.sqrt(terms)

    # About 1.5 degrees of arc per frame (5 cm at 1.6 m), 10 to 110 degrees in all.
    sweep = math.radians(float(np.clip(1.5 * (frames - 1), 10.0, 110.0)))
    azimuth0 = math.radians(-90.0 + rng.uniform(-12.0, 12.0))
    azimuth = azimuth0 + sweep * (s - 0.5) + wobble(math.radians(1.0), 20.0, 60.0)
    radius = 1.6 + 0.22 * np.sin(2.0 * math.pi * index / rng.uniform(70.0, 120.0) + rng.uniform(0, 2 * math.pi))
    radius += wobble(0.01, 6.0, 18.0)
    height = 1.42 + 0.08 * np.sin(2.0 * math.pi * index / rng.uniform(50.0, 100.0) + rng.uniform(0, 2 * math.pi))
    height += wobble(0.006, 5.0, 15.0)
    roll = wobble(math.radians(2.5), 25.0, 80.0) + wobble(math.radians(0.3), 4.0, 10.0)
    target_x = wobble(0.05, 30.0, 90.0)
    target_y = 0.05 + wobble(0.04, 30.0, 90.0)
    target_z = TABLE_TOP + 0.08 + wobble(0.03, 20.0, 60.0)

    poses = np.zeros((frames, 4, 4))
    for i in range(frames):
        eye = np.array([radius[i] * math.cos(azimuth[i]), radius[i] * math.sin(azimuth[i]), height[i]])
        T = look_at(eye, np.array([target_x[i], target_y[i], target_z[i]]))
        poses[i] = T @ make_transform(rotation_about_axis(np.array([0.0, 0.0, 1.0]), roll[i]), np.zeros(3))
    return poses


def build_scene_plan(options: SynthOptions) -> ScenePlan:
    """The deterministic scene, camera and object poses for ``options`` (no rendering)."""
    options = validate_options(options)
    layout_rng, object_rng, motion_rng, camera_rng = (seeded_rng(options.seed, STREAM_PLAN, i) for i in range(4))
    static_shapes = _static_shapes(layout_rng)
    objects = object_shapes(object_rng, options.objects)
    object_poses, moving = _plan_objects(options, objects, motion_rng)
    still = [k + 1 for k, frames in enumerate(moving) if not frames]
    if options.motion != "static" and still:
        logger.warning(
            "object(s) %s never move: %d frames are too few for %d objects; use more frames or --simultaneous",
            ", ".join(map(str, still)), options.frames, options.objects,
        )
    names = [f"{TIMESTAMP_START + i / options.fps:.6f}" for i in range(options.frames)]
    light = np.array([0.35, -0.5, 0.8])
    return ScenePlan(
        options=options,
        intrinsics=synth_intrinsics(options.width, options.height),
        timestamps=np.array([float(name) for name in names]),
        names=names,
        camera_poses=_camera_trajectory(options.frames, camera_rng),
        object_poses=object_poses.reshape(len(objects), options.frames, 4, 4),
        static_shapes=static_shapes,
        object_shapes=objects,
        light_direction=light / np.linalg.norm(light),
        moving_frames=moving,
    )
