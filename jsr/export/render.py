"""Previews of a results folder as PNGs (:func:`render_results`), after the paper's Figure 6.

Written into ``RESULTS/plots/`` (or ``out_dir``)::

    static_view_<k>.png     the static mesh from viewpoint k of a few chosen along the camera
                            trajectory (k = 1..views), with the camera path
    scene_frame_<n>.png     the static mesh with every object model placed at its pose in frame n,
                            each object in its own tint (Figure 6 A), with the camera path and the
                            camera of frame n
    object_<K>.png          object K's model alone, from two of the directions its keyframes saw
                            it from (Figure 6 D)

Inputs read from the results folder: ``summary.json`` (intrinsics), ``landmarks.csv`` (frame
index -> timestamp), ``camera.tum`` (``T_w_c``), ``static/mesh.ply`` (world frame),
``objects/object_K/mesh.ply`` (object frame), ``trajectory.tum`` (``T_w_o``) and
``keyframes.tum`` (``T_o_c``). Meshes are drawn by :mod:`jsr.export.raster` on the CPU.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from jsr.errors import InputError
from jsr.export.colours import STATIC_COLOUR, object_colour, rgb
from jsr.export.raster import MeshLayer, Rendering, View, draw_path, render_meshes
from jsr.geometry import transform_points
from jsr.io.atomic import atomic_write_bytes
from jsr.io.trajectory import read_tum_trajectory
from jsr.io.writers import read_csv, read_geometry_ply

logger = logging.getLogger(__name__)

STATIC_LABEL = 1
"""Label of the static mesh's pixels in a :class:`~jsr.export.raster.Rendering`; object K has ``1 + K``."""

TINT_SHARE = 0.6
"""How much of an object's colour in the scene view is its tint (the rest its own texture)."""

SET_BACK = 0.5
"""A preview camera stands this share of its distance to what it looks at further back than the
recorded camera, so the view shows the surroundings of what the camera saw."""

RAISE_DEGREES = 15.0
"""... and this much higher, looking down on the scene."""

ZOOM_OUT = 0.8
"""Focal length of a preview relative to the sequence camera's (at the same image width)."""

OBJECT_VIEW_MIN_DEGREES = 30.0
"""Two keyframe directions closer than this show the same side: the second object view then
turns the first by ``OBJECT_VIEW_TURN_DEGREES`` about the up direction instead."""
OBJECT_VIEW_TURN_DEGREES = 60.0

BACKGROUND = (255, 255, 255)
PATH_COLOUR = (40, 40, 40)
_OBJECT_FOLDER = re.compile(r"^object_(\d+)$")


@dataclass
class ObjectModel:
    """Object K's mesh (object frame), ``T_w_o`` where it was tracked and ``T_o_c`` of its keyframes."""

    object_id: int
    layer: MeshLayer
    timestamps: np.ndarray
    poses: np.ndarray
    keyframe_poses: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """Centre of the mesh's bounding box, object frame ``(3,)``."""
        vertices = self.layer.vertices
        return 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))

    def pose_at(self, timestamp: float) -> np.ndarray | None:
        """``T_w_o`` in the last tracked frame at or before ``timestamp`` (where the map last
        saw the object), or None when it was first tracked later."""
        earlier = np.flatnonzero(self.timestamps <= timestamp + 1e-6)
        return self.poses[earlier[-1]] if len(earlier) else None


def mesh_layer(path: Path, label: int, cull_back_faces: bool = True) -> MeshLayer:
    """A :class:`MeshLayer` of a PLY mesh (vertex colours grey when it has none)."""
    mesh = read_geometry_ply(path)
    triangles = np.asarray(getattr(mesh, "triangles", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        raise InputError(f"{path} holds no triangles; re-run jsr reconstruct to write the mesh again")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    colors = np.asarray(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors() else np.full(
        (len(vertices), 3), 0.7)
    return MeshLayer(vertices, triangles, colors, label=label, cull_back_faces=cull_back_faces).with_normals()


def _frame_timestamps(results_dir: Path) -> dict[int, float]:
    rows = read_csv(results_dir / "landmarks.csv") if (results_dir / "landmarks.csv").is_file() else []
    try:
        return {int(row["frame"]): float(row["timestamp"]) for row in rows}
    except (KeyError, ValueError):
        raise InputError(f"{results_dir / 'landmarks.csv'} is not a jsr landmarks.csv; re-run jsr reconstruct") from None


def _run_status(results_dir: Path) -> str | None:
    try:
        return json.loads((results_dir / "summary.json").read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        return None


def _intrinsics(results_dir: Path) -> dict:
    path = results_dir / "summary.json"
    try:
        intrinsics = json.loads(path.read_text())["input"]["intrinsics"]
        return {key: float(intrinsics[key]) for key in ("fx", "fy", "cx", "cy", "width", "height")}
    except FileNotFoundError:
        raise InputError(f"{results_dir} has no summary.json; is it a results folder of 'jsr reconstruct'?") from None
    except (ValueError, KeyError, TypeError):
        raise InputError(f"{path} has no readable input.intrinsics; re-run jsr reconstruct") from None


def load_objects(results_dir: Path) -> list[ObjectModel]:
    """The objects of a results folder that have a mesh and were tracked, by id."""
    folder = results_dir / "objects"
    models = []
    for path in sorted(folder.iterdir(), key=lambda p: p.name) if folder.is_dir() else []:
        found = _OBJECT_FOLDER.match(path.name)
        if not found:
            continue
        object_id = int(found.group(1))
        if not (path / "mesh.ply").is_file() or not (path / "trajectory.tum").is_file():
            logger.warning("%s: no mesh.ply or trajectory.tum; object %d is not drawn", path, object_id)
            continue
        timestamps, poses = read_tum_trajectory(path / "trajectory.tum")
        if len(poses) == 0:
            logger.warning("object %d was never tracked; it is not drawn", object_id)
            continue
        keyframes = read_tum_trajectory(path / "keyframes.tum")[1] if (path / "keyframes.tum").is_file() else \
            np.zeros((0, 4, 4))
        # An object model is a shell open on the sides its keyframes never saw; seen from such a
        # side, its inside still shows where and how large the object is: back faces are kept.
        models.append(ObjectModel(object_id, mesh_layer(path / "mesh.ply", 1 + object_id, cull_back_faces=False),
                                  timestamps, poses, keyframes))
    return sorted(models, key=lambda model: model.object_id)


# ------------------------------------------------------------------------------------------
# Viewpoints


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_w_c`` of a camera at ``eye`` looking at ``target`` with ``up`` (world) upwards in the
    image (camera y points down, z forward)."""
    forward = np.asarray(target, dtype=float) - np.asarray(eye, dtype=float)
    forward /= max(np.linalg.norm(forward), 1e-12)
    down = -(np.asarray(up, dtype=float) - np.dot(up, forward) * forward)
    if np.linalg.norm(down) < 1e-9:  # looking straight along up: any perpendicular will do
        down = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0.0, 1.0, 0.0])
    down /= np.linalg.norm(down)
    right = np.cross(down, forward)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def _rotation_about(axis: np.ndarray, degrees: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / max(np.linalg.norm(axis), 1e-12) * math.radians(degrees)).as_matrix()


def spread_along_trajectory(poses: np.ndarray, count: int, metres_per_radian: float = 1.0) -> list[int]:
    """Indices of ``count`` poses of ``(N, 4, 4)`` ``T_w_c`` spread evenly along the trajectory,
    its length counting both the camera's travel (metres) and its turns (radians, at
    ``metres_per_radian``): a camera that mostly turns on the spot still gets distinct views."""
    if len(poses) == 0:
        return []
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    cosine = np.einsum("ij,ij->i", poses[:-1, :3, 2], poses[1:, :3, 2])
    step = step + metres_per_radian * np.arccos(np.clip(cosine, -1.0, 1.0))
    along = np.concatenate([[0.0], np.cumsum(step)])
    if along[-1] <= 0:
        return [len(poses) // 2]
    wanted = (np.arange(count) + 0.5) / count * along[-1]
    chosen = np.argmin(np.abs(along[None, :] - wanted[:, None]), axis=1)  # the pose nearest each mark
    return sorted(set(int(i) for i in chosen))


def _median_depth(layer: MeshLayer, view: View) -> float | None:
    """Median depth of the mesh vertices that ``view`` sees (in its image, in front of it)."""
    vertices = layer.vertices[:: max(1, len(layer.vertices) // 20000)]
    pixels, depth = view.project(vertices)
    seen = (depth > 0.1) & (pixels[:, 0] >= 0) & (pixels[:, 0] < view.width) & (pixels[:, 1] >= 0) & (
        pixels[:, 1] < view.height)
    return float(np.median(depth[seen])) if np.count_nonzero(seen) >= 10 else None


def preview_view(T_w_c: np.ndarray, target: np.ndarray, intrinsics: dict, width: int) -> View:
    """A camera set back from ``T_w_c`` (by ``SET_BACK`` of its distance to ``target``) and
    raised (``RAISE_DEGREES``), looking at ``target`` with the recorded camera's up direction,
    at ``width`` pixels and the sequence's aspect ratio, zoomed out by ``ZOOM_OUT``."""
    eye = T_w_c[:3, 3]
    up = -T_w_c[:3, 1]
    offset = eye - target
    distance = max(np.linalg.norm(offset), 0.3)
    raised = _rotation_about(np.cross(offset, up), -RAISE_DEGREES) @ (offset / max(np.linalg.norm(offset), 1e-12))
    if np.dot(raised, up) < np.dot(offset, up) / distance:  # the sign of the cross product: go up, not down
        raised = _rotation_about(np.cross(offset, up), RAISE_DEGREES) @ (offset / max(np.linalg.norm(offset), 1e-12))
    new_eye = target + raised * distance * (1.0 + SET_BACK)
    return _view_of_size(look_at(new_eye, target, up), intrinsics, width, ZOOM_OUT)


def _view_of_size(T_w_c: np.ndarray, intrinsics: dict, width: int, zoom: float) -> View:
    scale = width / intrinsics["width"]
    height = int(round(intrinsics["height"] * scale))
    focal = 0.5 * (intrinsics["fx"] + intrinsics["fy"]) * scale * zoom
    return View(width, height, focal, focal, (width - 1) / 2.0, (height - 1) / 2.0, T_w_c)


def recorded_view(T_w_c: np.ndarray, intrinsics: dict) -> View:
    """The sequence camera itself at ``T_w_c``."""
    return View(int(intrinsics["width"]), int(intrinsics["height"]), intrinsics["fx"], intrinsics["fy"],
                intrinsics["cx"], intrinsics["cy"], T_w_c)


# ------------------------------------------------------------------------------------------
# Images


def _caption(image: np.ndarray, text: str) -> np.ndarray:
    """``text`` on a white band at the top left (the mesh behind it may carry text of its own)."""
    image = np.ascontiguousarray(image)
    (text_width, text_height), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
    cv2.rectangle(image, (0, 0), (text_width + 20, text_height + baseline + 16), BACKGROUND, -1)
    cv2.putText(image, text, (10, 8 + text_height), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (20, 20, 20), 1, cv2.LINE_AA)
    return image


def _label(image: np.ndarray, text: str, pixel: np.ndarray, colour: tuple[int, int, int]) -> None:
    u, v = int(round(pixel[0])), int(round(pixel[1]))
    if not (0 <= u < image.shape[1] and 0 <= v < image.shape[0]):
        return
    cv2.putText(image, text, (u + 8, v - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 4, cv2.LINE_AA)
    cv2.putText(image, text, (u + 8, v - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.55, colour, 1, cv2.LINE_AA)


def write_png(path: Path, rgb_image: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` uint8 RGB image as PNG, atomically."""
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(rgb_image[:, :, ::-1]))
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise RuntimeError(f"could not encode {path}")
    atomic_write_bytes(Path(path), encoded.tobytes())
    return Path(path)


def tinted(layer: MeshLayer, colour: tuple[int, int, int], share: float = TINT_SHARE) -> MeshLayer:
    """``layer`` with its colours blended towards ``colour`` (0-255) by ``share``."""
    tint = np.asarray(colour, dtype=np.float64) / 255.0
    return MeshLayer(layer.vertices, layer.triangles, (1.0 - share) * layer.colors + share * tint, layer.label,
                     layer.cull_back_faces, layer.normals)


def placed(layer: MeshLayer, T_w_o: np.ndarray) -> MeshLayer:
    """``layer`` (object frame) moved into the world by ``T_w_o``."""
    return MeshLayer(transform_points(T_w_o, layer.vertices), layer.triangles, layer.colors, layer.label,
                     layer.cull_back_faces, layer.normals @ T_w_o[:3, :3].T)


def render_scene(static: MeshLayer, objects: list[ObjectModel], timestamp: float, view: View,
                 supersample: int = 2) -> tuple[Rendering, list[int]]:
    """The static mesh with every object that had been tracked by ``timestamp`` placed at its
    pose then (:meth:`ObjectModel.pose_at`), each tinted in its colour. Returns the rendering
    (labels: ``STATIC_LABEL`` static, ``1 + K`` object K) and the ids of the objects placed."""
    layers, shown = [static], []
    for model in objects:
        pose = model.pose_at(timestamp)
        if pose is None:
            continue
        layers.append(placed(tinted(model.layer, rgb(object_colour(model.object_id))), pose))
        shown.append(model.object_id)
    return render_meshes(layers, view, BACKGROUND, supersample), shown


def object_views(model: ObjectModel, size: int, intrinsics: dict) -> list[View]:
    """Two views of ``model`` in its own frame, from the directions of its keyframes: the one
    that faces the most of the model's surface, then the best of those at least
    ``OBJECT_VIEW_MIN_DEGREES`` from it (when there is none, the first turned by
    ``OBJECT_VIEW_TURN_DEGREES`` about the up direction); at a distance that fits the model
    into ``size x size`` pixels."""
    centre = model.centre
    vertices = model.layer.vertices
    radius = float(np.percentile(np.linalg.norm(vertices - centre, axis=1), 98)) or 0.1
    keyframes = model.keyframe_poses if len(model.keyframe_poses) else np.eye(4)[None]
    directions = keyframes[:, :3, 3] - centre
    directions /= np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    corners = vertices[model.layer.triangles]
    area_normals = 0.5 * np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    facing_area = np.clip(area_normals @ directions.T, 0.0, None).sum(axis=0)  # per direction, occlusion ignored
    best = int(np.argmax(facing_area))
    up = -keyframes[best, :3, 1]
    apart = np.degrees(np.arccos(np.clip(directions @ directions[best], -1.0, 1.0))) >= OBJECT_VIEW_MIN_DEGREES
    if np.any(apart):
        second = directions[int(np.argmax(np.where(apart, facing_area, -np.inf)))]
    else:
        second = _rotation_about(up, OBJECT_VIEW_TURN_DEGREES) @ directions[best]
    focal = 0.5 * (intrinsics["fx"] + intrinsics["fy"]) * size / intrinsics["width"] * 2.0
    distance = 1.2 * radius * focal / (0.5 * size)
    return [View(size, size, focal, focal, (size - 1) / 2.0, (size - 1) / 2.0,
                 look_at(centre + direction * distance, centre, up)) for direction in (directions[best], second)]


def render_results(
    results_dir: Path,
    out_dir: Path | None = None,
    frame: int | None = None,
    views: int = 3,
    width: int = 800,
    supersample: int = 2,
) -> dict:
    """Write the previews of a results folder (see the module docstring); returns
    ``{"files": [paths], "frame": n, "objects_placed": [ids], "seconds": s}``.

    ``frame`` (index into the processed frames; default the last) is the frame whose object
    poses the scene view shows; ``views`` how many static views; ``width`` the image width
    in pixels (height from the sequence's aspect ratio; object views are ``width / 2``
    square, two side by side).
    """
    started = time.perf_counter()
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise InputError(f"results folder {results_dir} does not exist")
    if views < 1 or width < 64 or supersample < 1:
        raise InputError("give --views >= 1 and --width >= 64")
    out_dir = Path(out_dir) if out_dir is not None else results_dir / "plots"
    intrinsics = _intrinsics(results_dir)
    if not (results_dir / "static" / "mesh.ply").is_file():
        if _run_status(results_dir) == "complete":
            raise InputError(f"{results_dir} has no static/mesh.ply: its keyframes fused into an empty model (too "
                             "few keyframes or too little valid depth); there is nothing to draw")
        raise InputError(f"{results_dir} has no static/mesh.ply: the meshes are written at the end of a complete run "
                         "(re-run jsr reconstruct to the end)")
    static = mesh_layer(results_dir / "static" / "mesh.ply", STATIC_LABEL)
    camera_timestamps, camera_poses = read_tum_trajectory(results_dir / "camera.tum")
    if len(camera_poses) == 0:
        raise InputError(f"{results_dir / 'camera.tum'} holds no poses: no frame was tracked")
    frames = _frame_timestamps(results_dir)
    frame = max(frames) if frame is None and frames else frame
    if frame is None or frame not in frames:
        span = f"0 to {max(frames)}" if frames else "none"
        raise InputError(f"frame {frame} was not processed in {results_dir} (frames: {span})")
    timestamp = frames[frame]
    objects = load_objects(results_dir)
    written = []

    for number, index in enumerate(spread_along_trajectory(camera_poses, views), start=1):
        pose = camera_poses[index]
        depth = _median_depth(static, recorded_view(pose, intrinsics)) or 1.5
        view = preview_view(pose, pose[:3, 3] + pose[:3, 2] * depth, intrinsics, width)
        rendering = render_meshes([static], view, BACKGROUND, supersample)
        draw_path(rendering, camera_poses[:, :3, 3], PATH_COLOUR)
        frame_number = _frame_of(frames, camera_timestamps[index])
        written.append(write_png(out_dir / f"static_view_{number}.png",
                                 _caption(rendering.color, f"static map, view {number} (camera of frame "
                                                           f"{frame_number})")))

    earlier = np.flatnonzero(camera_timestamps <= timestamp + 1e-6)
    pose = camera_poses[earlier[-1] if len(earlier) else 0]
    placed_centres = [transform_points(m.pose_at(timestamp), m.centre[None])[0] for m in objects
                      if m.pose_at(timestamp) is not None]
    if placed_centres:
        target = np.mean(placed_centres, axis=0)
    else:
        target = pose[:3, 3] + pose[:3, 2] * (_median_depth(static, recorded_view(pose, intrinsics)) or 1.5)
    view = preview_view(pose, target, intrinsics, width)
    rendering, shown = render_scene(static, objects, timestamp, view, supersample)
    draw_path(rendering, camera_poses[:, :3, 3], PATH_COLOUR)
    image = rendering.color
    camera_pixel, camera_depth = view.project(pose[:3, 3][None])
    if camera_depth[0] > 0:
        cv2.circle(image, tuple(int(round(c)) for c in camera_pixel[0]), 6, rgb(STATIC_COLOUR), -1, cv2.LINE_AA)
        _label(image, f"camera, frame {frame}", camera_pixel[0], rgb(STATIC_COLOUR))
    for model in objects:
        if model.object_id in shown:
            centre = transform_points(model.pose_at(timestamp), model.centre[None])
            _label(image, f"object {model.object_id}", view.project(centre)[0][0], rgb(object_colour(model.object_id)))
    written.append(write_png(out_dir / f"scene_frame_{frame}.png",
                             _caption(image, f"static map and {len(shown)} object(s) at frame {frame}")))

    size = max(64, width // 2)
    for model in objects:
        tiles = [render_meshes([model.layer], object_view, BACKGROUND, supersample).color
                 for object_view in object_views(model, size, intrinsics)]
        image = _caption(np.concatenate(tiles, axis=1), f"object {model.object_id}: two views of its model")
        cv2.line(image, (size, 0), (size, size - 1), (200, 200, 200), 1)
        written.append(write_png(out_dir / f"object_{model.object_id}.png", image))
    seconds = time.perf_counter() - started
    logger.info("rendered %d images of %s in %.1f s", len(written), results_dir, seconds)
    return {"files": [str(path) for path in written], "frame": frame, "objects_placed": shown, "seconds": seconds}


def _frame_of(frames: dict[int, float], timestamp: float) -> int:
    """The processed frame whose timestamp is nearest ``timestamp``."""
    numbers = np.array(sorted(frames))
    times = np.array([frames[n] for n in numbers])
    return int(numbers[int(np.argmin(np.abs(times - timestamp)))]) if len(numbers) else 0
