"""Seeded, deterministic synthetic RGB-D sequences with exact ground truth.

A textured room (floor, walls, ceiling) with a table, a cabinet, a shelf with books, a
ball and a bin, plus ``K`` rigid textured objects resting on the table top and moved
between views ("jump"), continuously ("smooth") or never ("static"). A hand-held-like
camera circles the table. Every frame is ray cast with Open3D's ``RaycastingScene``.

Written in the TUM RGB-D layout that :func:`jsr.io.dataset.open_sequence` reads::

    OUT/rgb/<ts>.png|jpg, OUT/depth/<ts>.png (16 bit, 5000 per metre), OUT/labels/<ts>.png
    OUT/rgb.txt, OUT/depth.txt, OUT/groundtruth.txt (T_w_c), OUT/objects/object_<k>.txt (T_w_o)
    OUT/camera.yaml, OUT/synth.yaml (options and version)

Labels are 0 for the static scene and ``k`` for object ``k`` (1-based). The world frame is
the room frame: z up, floor at z = 0, table centre above the origin. Object origins are the
object centres.

Randomness: every draw comes from generators derived from ``options.seed`` with
:class:`numpy.random.SeedSequence` spawn keys (plan, per-texture-tile, per-frame), so a
result does not depend on the order in which frames or textures are computed.
"""

from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from jsr.errors import InputError, OutputError
from jsr.geometry import KINECT_SIGMA_Z_COEFFICIENT, look_at, make_transform, rotation_about_axis
from jsr.io.atomic import atomic_path, atomic_write_text
from jsr.io.camera import CameraIntrinsics, write_camera_yaml
from jsr.io.trajectory import write_tum_trajectory

logger = logging.getLogger(__name__)

MOTIONS = ("jump", "smooth", "static")
IMAGE_FORMATS = ("png", "jpg")
MAX_OBJECTS = 6
MIN_WIDTH, MIN_HEIGHT = 32, 24
MAX_SIDE = 4096
MAX_FRAMES = 100_000

TIMESTAMP_START = 1000.0
DEPTH_SCALE = 5000.0
MIN_RANGE, MAX_RANGE = 0.3, 6.0
GRAZING_LIMIT_DEGREES = 80.0
EDGE_DROP_PROBABILITY = 0.5
JPEG_QUALITY = 95
MIP_LEVELS = 4  # texture pyramid levels (>= 2), against aliasing of distant textures

GENERATED_FILES = ("rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "synth.yaml")
GENERATED_FOLDERS = ("rgb", "depth", "labels", "objects")
_GENERATED_IMAGE = re.compile(r"^\.?\d+\.\d{6}(\.[^.]+)?\.(png|jpg)$")
_GENERATED_OBJECT = re.compile(r"^\.?object_\d+(\.[^.]+)?\.txt$")

# Room layout (metres). World z is up, the floor is z = 0.
ROOM_HALF_X, ROOM_HALF_Y, ROOM_HEIGHT = 2.5, 2.2, 2.6
WALL_THICKNESS = 0.1
TABLE_SIZE = (1.2, 0.8)
TABLE_TOP = 0.75
TABLE_TOP_THICKNESS = 0.04
TABLE_MARGIN = 0.02
OBJECT_GAP = 0.03

# Randomness streams (first element of the SeedSequence spawn key).
_STREAM_PLAN, _STREAM_TEXTURE, _STREAM_FRAME = 0, 1, 2


@dataclass
class SynthOptions:
    """What :func:`generate_sequence` renders. The defaults are a 640x480, 60-frame sequence."""

    frames: int = 60
    objects: int = 1  # K rigid textured objects (0: static scene)
    motion: str = "jump"  # "jump", "smooth" or "static"
    simultaneous: bool = False  # with objects >= 2: all objects move in the same frames
    width: int = 640
    height: int = 480
    depth_noise: bool = True  # sigma_Z = 1.425e-3 Z^2 m, then quantisation to 1/5000 m
    dropout: float = 0.02  # random fraction of valid depth pixels dropped (plus systematic dropouts)
    seed: int = 0
    fps: float = 30.0
    image_format: str = "png"  # colour format: "png" or "jpg"


# --------------------------------------------------------------------------------------
# Scene description


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


def validate_options(options: SynthOptions) -> SynthOptions:
    """Check ``options``; returns a normalised copy or raises :class:`InputError`."""
    if not isinstance(options, SynthOptions):
        raise InputError("options must be a SynthOptions")
    motion = str(options.motion).strip().lower()
    image_format = str(options.image_format).strip().lower().lstrip(".")
    image_format = "jpg" if image_format == "jpeg" else image_format

    def integer(name: str) -> int:
        value = getattr(options, name)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InputError(f"--{name} must be an integer, got {value!r}")
        return int(value)

    frames, objects, width, height, seed = (integer(n) for n in ("frames", "objects", "width", "height", "seed"))
    if not 2 <= frames <= MAX_FRAMES:
        raise InputError(f"--frames must be between 2 and {MAX_FRAMES}, got {frames}")
    if not 0 <= objects <= MAX_OBJECTS:
        raise InputError(f"--objects must be between 0 and {MAX_OBJECTS}, got {objects}")
    if motion not in MOTIONS:
        raise InputError(f"unknown --motion '{options.motion}'; choose one of {', '.join(MOTIONS)}")
    if not (MIN_WIDTH <= width <= MAX_SIDE and MIN_HEIGHT <= height <= MAX_SIDE):
        raise InputError(
            f"resolution {width}x{height} is out of range; use at least {MIN_WIDTH}x{MIN_HEIGHT} "
            f"and at most {MAX_SIDE} pixels a side"
        )
    try:
        dropout = float(options.dropout)
        fps = float(options.fps)
    except (TypeError, ValueError):
        raise InputError("--dropout and fps must be numbers") from None
    if not 0.0 <= dropout < 1.0:
        raise InputError(f"--dropout must be in [0, 1), got {options.dropout}")
    if not (math.isfinite(fps) and 0.0 < fps <= 1000.0):
        raise InputError(f"fps must be in (0, 1000] (timestamps have 6 decimals), got {options.fps}")
    if seed < 0:
        raise InputError(f"--seed must be >= 0, got {seed}")
    if image_format not in IMAGE_FORMATS:
        raise InputError(f"unknown --format '{options.image_format}'; choose png or jpg")
    return replace(
        options,
        frames=frames,
        objects=objects,
        motion=motion,
        simultaneous=bool(options.simultaneous),
        width=width,
        height=height,
        depth_noise=bool(options.depth_noise),
        dropout=dropout,
        seed=seed,
        fps=fps,
        image_format=image_format,
    )


def _rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=tuple(int(k) for k in key)))


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


def _object_shapes(rng: np.random.Generator, count: int) -> list[Shape]:
    """Object 1 is a box; further objects alternate cylinder / box."""
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
        shapes.append(Shape(f"object {k}", kind, size, np.eye(4), k, 0.0025, "object", 1000 + k))
    return shapes


def _footprint_radius(shape: Shape) -> float:
    """Radius of a vertical cylinder containing the object for any rotation about z."""
    if shape.kind == "box":
        return 0.5 * math.hypot(shape.size[0], shape.size[1])
    return shape.radius


def _inside_table(x: float, y: float, radius: float) -> bool:
    return (
        abs(x) + radius <= TABLE_SIZE[0] / 2 - TABLE_MARGIN
        and abs(y) + radius <= TABLE_SIZE[1] / 2 - TABLE_MARGIN
    )


def _min_path_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> float:
    """Smallest distance between two points moving linearly (same timing) from *0 to *1."""
    start = a0 - b0
    velocity = (a1 - a0) - (b1 - b0)
    speed2 = float(velocity @ velocity)
    s = 0.0 if speed2 < 1e-18 else float(np.clip(-(start @ velocity) / speed2, 0.0, 1.0))
    return float(np.linalg.norm(start + s * velocity))


def _motion_schedule(options: SynthOptions, rng: np.random.Generator) -> list[tuple[int, int, list[int]]]:
    """``(start_frame, duration, movers)`` events; movers are 0-based object indices."""
    count, frames = options.objects, options.frames
    if options.motion == "static" or count == 0:
        return []
    first_rest = max(1, min(10, frames // 4))
    turns = 1 if options.simultaneous else count
    period = max(2, min(9, (frames - 1 - first_rest) // turns))
    duration = 1 if options.motion == "jump" else max(1, min(period - 1, round(0.6 * period)))
    events, start, turn = [], first_rest, 0
    while start + duration - 1 <= frames - 1:
        movers = list(range(count)) if options.simultaneous else [turn % count]
        events.append((start, duration, movers))
        step = period + (int(rng.integers(-1, 2)) if period >= 8 else 0)
        start += step
        turn += 1
    return events


def _plan_objects(
    options: SynthOptions, shapes: list[Shape], rng: np.random.Generator
) -> tuple[np.ndarray, list[list[int]]]:
    """Per-frame object poses ``(K, N, 4, 4)`` and the frames where each pose changes."""
    count, frames = len(shapes), options.frames
    radii = [_footprint_radius(shape) for shape in shapes]
    heights = [TABLE_TOP + shape.size[2] / 2 for shape in shapes]

    # Initial layout: non-overlapping footprints on the table top.
    states: list[np.ndarray] = []  # (x, y, yaw)
    for k in range(count):
        for _ in range(5000):
            limit_x = TABLE_SIZE[0] / 2 - TABLE_MARGIN - radii[k]
            limit_y = TABLE_SIZE[1] / 2 - TABLE_MARGIN - radii[k]
            x, y = rng.uniform(-limit_x, limit_x), rng.uniform(-limit_y, limit_y)
            if all(math.hypot(x - s[0], y - s[1]) >= radii[k] + radii[j] + OBJECT_GAP for j, s in enumerate(states)):
                break
        else:  # pragma: no cover - sizes are scaled so that this does not happen
            raise RuntimeError("could not place the objects on the table")
        states.append(np.array([x, y, rng.uniform(-math.pi, math.pi)]))

    # trajectory[k, f] = (x, y, yaw) of object k at frame f.
    trajectory = np.zeros((count, frames, 3))
    for k in range(count):
        trajectory[k, :] = states[k]
    smooth = options.motion == "smooth"
    low, high = (0.08, 0.25) if smooth else (0.05, 0.20)
    for start, duration, movers in _motion_schedule(options, rng):
        current = {k: trajectory[k, start - 1].copy() for k in range(count)}
        targets: dict[int, np.ndarray] = {}
        for k in movers:
            origin = current[k]
            for _ in range(500):
                distance = rng.uniform(low, high)
                direction = rng.uniform(-math.pi, math.pi)
                turn = math.radians(rng.uniform(10.0, 60.0)) * (1 if rng.random() < 0.5 else -1)
                candidate = origin + np.array([distance * math.cos(direction), distance * math.sin(direction), turn])
                if not _inside_table(candidate[0], candidate[1], radii[k]):
                    continue
                clear = True
                for j in range(count):
                    if j == k:
                        continue
                    other0 = current[j][:2]
                    other1 = targets[j][:2] if j in targets else other0
                    if smooth:
                        gap = _min_path_distance(origin[:2], candidate[:2], other0, other1)
                    else:
                        gap = float(np.linalg.norm(candidate[:2] - other1))
                    if gap < radii[k] + radii[j] + OBJECT_GAP:
                        clear = False
                        break
                if clear:
                    targets[k] = candidate
                    break
            else:
                # A crowded table: turn in place (the footprint circle stays where it is).
                logger.debug("object %d found no free place at frame %d and only turns", k + 1, start)
                targets[k] = origin + np.array([0.0, 0.0, math.radians(rng.uniform(10.0, 60.0))])
        for k, target in targets.items():
            origin = current[k]
            for i in range(duration):
                s = (i + 1) / duration
                eased = s * s * (3.0 - 2.0 * s)
                trajectory[k, start + i] = origin + eased * (target - origin)
            trajectory[k, start + duration :] = target

    poses = np.zeros((count, frames, 4, 4))
    moving: list[list[int]] = []
    for k in range(count):
        for f in range(frames):
            x, y, yaw = trajectory[k, f]
            poses[k, f] = _pose(x, y, heights[k], yaw)
        changed = np.any(np.abs(np.diff(trajectory[k], axis=0)) > 0.0, axis=1)
        moving.append([int(f) + 1 for f in np.flatnonzero(changed)])
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
    layout_rng, object_rng, motion_rng, camera_rng = (_rng(options.seed, _STREAM_PLAN, i) for i in range(4))
    static_shapes = _static_shapes(layout_rng)
    object_shapes = _object_shapes(object_rng, options.objects)
    object_poses, moving = _plan_objects(options, object_shapes, motion_rng)
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
        object_poses=object_poses.reshape(len(object_shapes), options.frames, 4, 4),
        static_shapes=static_shapes,
        object_shapes=object_shapes,
        light_direction=light / np.linalg.norm(light),
        moving_frames=moving,
    )


# --------------------------------------------------------------------------------------
# Textures

@dataclass(frozen=True)
class TextureStyle:
    """Parameters of :func:`make_texture` (hue/saturation/value ranges in [0, 1])."""

    hue: tuple[float, float]
    saturation: tuple[float, float]
    value: tuple[float, float]
    shapes_per_texel: float  # shape density
    radius: tuple[float, float]  # shape radius range in texels (log-uniform)
    contrast: float  # how far shape colours stray from the base colour (0..1)
    hue_spread: float  # hue range of the shapes around the base hue
    noise: float  # amplitude of the luminance noise


_STYLES = {
    "floor": TextureStyle((0.04, 0.12), (0.3, 0.55), (0.45, 0.65), 1 / 420, (2.0, 14.0), 0.45, 0.08, 0.22),
    "wall": TextureStyle((0.0, 1.0), (0.1, 0.3), (0.65, 0.85), 1 / 520, (2.0, 16.0), 0.45, 0.15, 0.16),
    "ceiling": TextureStyle((0.0, 1.0), (0.0, 0.12), (0.75, 0.88), 1 / 700, (2.0, 10.0), 0.3, 0.1, 0.12),
    "wood": TextureStyle((0.05, 0.1), (0.35, 0.65), (0.4, 0.65), 1 / 380, (2.0, 12.0), 0.45, 0.05, 0.25),
    "furniture": TextureStyle((0.0, 1.0), (0.25, 0.6), (0.5, 0.85), 1 / 360, (2.0, 14.0), 0.6, 0.2, 0.18),
    "object": TextureStyle((0.0, 1.0), (0.6, 0.95), (0.65, 0.95), 1 / 170, (2.5, 16.0), 1.0, 0.5, 0.15),
}


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV (each in [0, 1], hue wraps) to ``(N, 3)`` RGB in [0, 1]."""
    h = np.mod(np.asarray(h, dtype=float), 1.0) * 6.0
    s = np.clip(np.asarray(s, dtype=float), 0.0, 1.0)
    v = np.clip(np.asarray(v, dtype=float), 0.0, 1.0)
    channel = np.stack([np.mod(5.0 + h, 6.0), np.mod(3.0 + h, 6.0), np.mod(1.0 + h, 6.0)], axis=-1)
    ramp = np.clip(np.minimum(channel, 4.0 - channel), 0.0, 1.0)
    return v[..., None] * (1.0 - s[..., None] * ramp)


def _noise(rng: np.random.Generator, height: int, width: int, cell: float) -> np.ndarray:
    """Smooth value noise, about unit variance, with features ``cell`` texels apart."""
    grid = rng.standard_normal((max(2, math.ceil(height / cell) + 1), max(2, math.ceil(width / cell) + 1)))
    return cv2.resize(grid.astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)


_ALPHABET = "ABCDEFGHKMNPRSTUVWXYZ2345789&#%@"


def make_texture(rng: np.random.Generator, height: int, width: int, style: str) -> np.ndarray:
    """A procedural ``(height, width, 3)`` uint8 RGB texture: two-colour blotches and
    multi-scale noise under a few hundred random shapes, lines and letters."""
    look = _STYLES[style]
    base_hue = rng.uniform(*look.hue)
    base = _hsv_to_rgb(
        np.array([base_hue, base_hue + rng.uniform(-0.1, 0.1)]),
        rng.uniform(*look.saturation, 2),
        rng.uniform(*look.value, 2) * np.array([1.0, rng.uniform(0.7, 1.0)]),
    )
    blend = np.clip(0.5 + 0.6 * _noise(rng, height, width, 64.0), 0.0, 1.0)[:, :, None]
    image = base[0] * (1.0 - blend) + base[1] * blend
    luminance = look.noise * (0.6 * _noise(rng, height, width, 24.0) + 0.35 * _noise(rng, height, width, 8.0))
    image = image * (1.0 + luminance[:, :, None])
    image = np.ascontiguousarray((np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8))

    count = int(height * width * look.shapes_per_texel) + 3
    kinds = rng.integers(0, 7, count)
    centres = rng.uniform((0, 0), (width, height), (count, 2))
    radii = np.exp(rng.uniform(math.log(look.radius[0]), math.log(look.radius[1]), count))
    angles = rng.uniform(0.0, math.pi, count)
    aspects = rng.uniform(0.3, 1.0, count)
    thickness = rng.integers(1, 4, count)
    letters = rng.integers(0, len(_ALPHABET), count)
    vertices = rng.uniform(-1.0, 1.0, (count, 3, 2))
    # Shape colours: around the base colour, darker or lighter by up to ``contrast``.
    base_value = float(base.max(axis=1).mean())
    lighter = rng.random(count) < 0.5
    values = np.where(
        lighter,
        base_value + rng.uniform(0.3, 1.0, count) * look.contrast * (1.0 - base_value),
        base_value - rng.uniform(0.4, 1.0, count) * look.contrast * base_value,
    )
    colours = _hsv_to_rgb(
        base_hue + rng.uniform(-look.hue_spread, look.hue_spread, count),
        rng.uniform(look.saturation[0], min(1.0, look.saturation[1] + 0.2), count),
        values,
    ) * 255.0
    for i in range(count):
        colour = (float(colours[i, 0]), float(colours[i, 1]), float(colours[i, 2]))
        cx, cy, r = float(centres[i, 0]), float(centres[i, 1]), float(radii[i])
        centre = (int(cx), int(cy))
        kind = kinds[i]
        if kind == 0:
            cv2.circle(image, centre, int(r), colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.circle(image, centre, int(r), colour, int(thickness[i]), cv2.LINE_AA)
        elif kind == 2:
            box = cv2.boxPoints(((cx, cy), (2 * r, 2 * r * aspects[i]), math.degrees(angles[i])))
            cv2.fillPoly(image, [np.round(box).astype(np.int32)], colour, cv2.LINE_AA)
        elif kind == 3:
            dx, dy = 2.5 * r * math.cos(angles[i]), 2.5 * r * math.sin(angles[i])
            ends = (int(cx - dx), int(cy - dy)), (int(cx + dx), int(cy + dy))
            cv2.line(image, *ends, colour, int(thickness[i]), cv2.LINE_AA)
        elif kind == 4:
            cv2.fillPoly(image, [np.round(vertices[i] * r * 1.5 + (cx, cy)).astype(np.int32)], colour, cv2.LINE_AA)
        elif kind == 5:
            axes = (int(r), max(1, int(r * aspects[i])))
            cv2.ellipse(image, centre, axes, math.degrees(angles[i]), 0, 360, colour, -1, cv2.LINE_AA)
        else:
            origin = (int(cx - r), int(cy + r))
            scale = max(0.3, r / 10.0)
            font = cv2.FONT_HERSHEY_SIMPLEX
            cv2.putText(image, _ALPHABET[letters[i]], origin, font, scale, colour, int(thickness[i]), cv2.LINE_AA)
    return cv2.GaussianBlur(image, (0, 0), 0.6)


def _half_size(tile: np.ndarray) -> np.ndarray:
    """The next mip level of a texture tile (area average, at least 2x2)."""
    size = (max(2, math.ceil(tile.shape[1] / 2)), max(2, math.ceil(tile.shape[0] / 2)))
    return cv2.resize(tile, size, interpolation=cv2.INTER_AREA)


# The texture of face (axis a, sign) of a shape is indexed by the two other local axes.
_FACE_AXES = ((1, 2), (0, 2), (0, 1))


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
        intrinsics = plan.intrinsics
        u, v = np.meshgrid(np.arange(intrinsics.width, dtype=float), np.arange(intrinsics.height, dtype=float))
        # Camera-frame directions with z = 1, so the ray parameter t_hit is the depth z.
        self._directions = np.stack(
            [(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)], axis=-1
        ).reshape(-1, 3)

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
                tile_rng = _rng(seed, _STREAM_TEXTURE, shape.texture_key, face)
                tiles.append(make_texture(tile_rng, height, width, shape.style))
        self._levels = []
        for level in range(MIP_LEVELS):
            if level:
                tiles = [_half_size(tile) for tile in tiles]
            widths = np.array([tile.shape[1] for tile in tiles], dtype=np.int64)
            heights = np.array([tile.shape[0] for tile in tiles], dtype=np.int64)
            offsets = np.concatenate([[0], np.cumsum(widths * heights)[:-1]]).astype(np.int64)
            flat = np.concatenate([tile.reshape(-1, 3) for tile in tiles]) if tiles else np.zeros((1, 3), np.uint8)
            self._levels.append((flat, offsets, widths, heights))

    def _cast(self, index: int) -> dict:
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        for vertices, triangles in self._static_world:
            scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
        for k in range(len(self.plan.object_shapes)):
            vertices, triangles = self._meshes[len(self.plan.static_shapes) + k]
            pose = self.plan.object_poses[k, index]
            world = (vertices @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
            scene.add_triangles(o3d.core.Tensor(world), o3d.core.Tensor(triangles.astype(np.uint32)))
        pose = self.plan.camera_poses[index]
        directions = self._directions @ pose[:3, :3].T
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = pose[:3, 3]
        rays[:, 3:] = directions
        result = scene.cast_rays(o3d.core.Tensor(rays))
        return {
            "t_hit": result["t_hit"].numpy().astype(np.float64),
            "geometry_ids": result["geometry_ids"].numpy().astype(np.int64),
            "normals": result["primitive_normals"].numpy().astype(np.float64),
            "directions": directions,
            "origin": pose[:3, 3],
        }

    def render(self, index: int, depth_noise: bool | None = None, dropout: float | None = None) -> RenderedFrame:
        """Render frame ``index``; ``depth_noise`` and ``dropout`` default to the plan's options."""
        options = self.plan.options
        depth_noise = options.depth_noise if depth_noise is None else depth_noise
        dropout = options.dropout if dropout is None else dropout
        height, width = options.height, options.width
        cast = self._cast(index)
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
        depth_clean = depth_clean.reshape(height, width)
        depth = self._sensor_depth(index, depth_clean, grazing.reshape(height, width), depth_noise, dropout)
        return RenderedFrame(color_image, depth, depth_clean, labels.reshape(height, width))

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

    def _sensor_depth(
        self, index: int, depth_clean: np.ndarray, grazing: np.ndarray, depth_noise: bool, dropout: float
    ) -> np.ndarray:
        """Kinect-like depth: axial noise, out-of-range, grazing, edge and random dropouts."""
        seed = self.plan.options.seed
        depth = depth_clean.copy()
        valid = (depth_clean >= MIN_RANGE) & (depth_clean <= MAX_RANGE) & ~grazing
        if depth_noise:
            noise = _rng(seed, _STREAM_FRAME, index, 0).standard_normal(depth.shape)
            depth = depth + noise * KINECT_SIGMA_Z_COEFFICIENT * depth_clean**2
        if dropout > 0.0:
            valid &= _rng(seed, _STREAM_FRAME, index, 1).random(depth.shape) >= dropout
            # Thin bands along strong depth discontinuities go missing now and then.
            far = np.where(depth_clean > 0, depth_clean, MAX_RANGE * 2).astype(np.float32)
            kernel = np.ones((3, 3), np.uint8)
            jump = cv2.dilate(far, kernel) - cv2.erode(far, kernel)
            edges = jump > np.maximum(0.05, 0.04 * far)
            drop = _rng(seed, _STREAM_FRAME, index, 2).random(depth.shape) < EDGE_DROP_PROBABILITY
            valid &= ~(edges & drop)
        return np.where(valid, depth, 0.0)


def encode_depth(depth: np.ndarray) -> np.ndarray:
    """Metres to the 16-bit PNG values (5000 per metre, 0 = invalid)."""
    return np.clip(np.round(np.asarray(depth) * DEPTH_SCALE), 0, 65535).astype(np.uint16)


# --------------------------------------------------------------------------------------
# Output


def _is_generated(path: Path, root: Path) -> bool:
    relative = path.relative_to(root)
    if len(relative.parts) == 1:
        return relative.name in GENERATED_FILES
    if len(relative.parts) == 2 and relative.parts[0] in ("rgb", "depth", "labels"):
        return bool(_GENERATED_IMAGE.match(relative.name))
    if len(relative.parts) == 2 and relative.parts[0] == "objects":
        return bool(_GENERATED_OBJECT.match(relative.name))
    return False


def check_output_folder(out_dir: Path, overwrite: bool) -> None:
    """Raise :class:`OutputError` when :func:`generate_sequence` could not write into
    ``out_dir`` (a file, or a folder with files and no ``overwrite``); changes nothing."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir} is a file; give a folder for the synthetic sequence")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise OutputError(f"{out_dir} is not empty; pass --overwrite to replace it or choose another folder")


def _prepare_output(out_dir: Path, overwrite: bool) -> None:
    check_output_folder(out_dir, overwrite)
    if out_dir.is_dir() and any(out_dir.iterdir()):
        removed = 0
        for path in sorted(out_dir.rglob("*"), reverse=True):
            if path.is_file() and _is_generated(path, out_dir):
                path.unlink()
                removed += 1
        for name in GENERATED_FOLDERS:
            folder = out_dir / name
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        logger.info("%s: removed %d files of a previous synthetic sequence", out_dir, removed)
        if any(out_dir.iterdir()):
            logger.info("%s: keeping files that jsr synth did not write", out_dir)
    try:
        for name in GENERATED_FOLDERS:
            (out_dir / name).mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OutputError(f"cannot create {out_dir}: {error.strerror}; choose a writable folder") from None


def _write_image(path: Path, image: np.ndarray, params: tuple[int, ...] = ()) -> None:
    with atomic_path(path) as temporary:
        if not cv2.imwrite(str(temporary), image, list(params)):
            raise OutputError(f"cannot write {path}; check the free disk space and permissions")


def _image_list_text(kind: str, names: list[str], folder: str, suffix: str, options: SynthOptions) -> str:
    lines = [
        f"# {kind} images",
        f"# synthetic sequence by jsr synth (seed {options.seed})",
        "# timestamp filename",
    ]
    lines += [f"{name} {folder}/{name}.{suffix}" for name in names]
    return "\n".join(lines) + "\n"


def generate_sequence(
    out_dir: Path,
    options: SynthOptions,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Write the sequence of ``options`` to ``out_dir``; returns a JSON-ready summary dict.

    Raises :class:`InputError` for invalid options and :class:`OutputError` when
    ``out_dir`` is not empty (unless ``overwrite``: then only files this generator writes
    are removed first) or cannot be written.
    """
    from jsr import __version__

    started = time.perf_counter()
    options = validate_options(options)
    out_dir = Path(out_dir)
    _prepare_output(out_dir, overwrite)
    plan = build_scene_plan(options)
    renderer = SynthRenderer(plan)
    suffix = options.image_format
    colour_params = (cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY) if suffix == "jpg" else (cv2.IMWRITE_PNG_COMPRESSION, 6)
    png_params = (cv2.IMWRITE_PNG_COMPRESSION, 6)

    write_camera_yaml(out_dir / "camera.yaml", plan.intrinsics)
    metadata = {
        "generator": "jsr synth",
        "version": __version__,
        "options": asdict(options),
        "world_frame": "room frame, z up, floor at z = 0, table top at z = %.2f" % TABLE_TOP,
        "labels": "0 static scene, k object k",
        "objects": [
            {
                "id": k + 1,
                "shape": shape.kind,
                "size": [round(float(s), 6) for s in shape.size],
                "first_motion_frame": plan.first_motion_frames[k],
                "moving_frames": plan.moving_frames[k],
            }
            for k, shape in enumerate(plan.object_shapes)
        ],
    }
    import yaml

    atomic_write_text(out_dir / "synth.yaml", yaml.safe_dump(metadata, sort_keys=False))

    for index, name in enumerate(plan.names):
        frame = renderer.render(index)
        _write_image(out_dir / "rgb" / f"{name}.{suffix}", frame.color[:, :, ::-1], colour_params)
        _write_image(out_dir / "depth" / f"{name}.png", encode_depth(frame.depth), png_params)
        _write_image(out_dir / "labels" / f"{name}.png", frame.labels, png_params)
        if progress is not None:
            progress(index + 1, options.frames)

    header = f"synthetic sequence by jsr synth (seed {options.seed})"
    camera_header = header + "\ncamera-to-world T_w_c"
    write_tum_trajectory(out_dir / "groundtruth.txt", plan.timestamps, plan.camera_poses, camera_header)
    for k in range(options.objects):
        write_tum_trajectory(
            out_dir / "objects" / f"object_{k + 1}.txt",
            plan.timestamps,
            plan.object_poses[k],
            header + f"\nobject {k + 1}: object-to-world T_w_o, origin at the object centre",
        )
    # The lists come last: a sequence is only readable once every frame is on disk.
    atomic_write_text(out_dir / "depth.txt", _image_list_text("depth", plan.names, "depth", "png", options))
    atomic_write_text(out_dir / "rgb.txt", _image_list_text("colour", plan.names, "rgb", suffix, options))

    seconds = time.perf_counter() - started
    logger.info("%s: %d synthetic frames written in %.1f s", out_dir, options.frames, seconds)
    return {
        "out_dir": str(out_dir),
        "frames": options.frames,
        "objects": options.objects,
        "motion": options.motion,
        "simultaneous": options.simultaneous,
        "width": options.width,
        "height": options.height,
        "seed": options.seed,
        "image_format": suffix,
        "first_motion_frame": plan.first_motion_frames,
        "moving_frames": plan.moving_frames,
        "seconds": round(seconds, 3),
        "seconds_per_frame": round(seconds / options.frames, 4),
    }
