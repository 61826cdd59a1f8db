"""A z-buffer triangle rasteriser in numpy: meshes seen by a pinhole camera, on the CPU.

Why our own: the previews of ``jsr render`` must come out on a machine with no display and no
GPU, from a plain ``pip install``. Open3D's ``OffscreenRenderer`` (0.20) needs Vulkan there
(the Debian packages ``libvulkan1`` and ``mesa-vulkan-drivers``) and took 9-13 s per 800x600
view of a 670k-triangle room on lavapipe; pyrender needs EGL or OSMesa system libraries and
pins a 2014 PyOpenGL. This one needs numpy and OpenCV only, gives the same bytes on every
machine (which the tests rely on), and returns per pixel which mesh was seen.

Conventions: camera frame x right, y down, z forward (OpenCV); ``T_w_c`` (4x4 float64) maps
camera to world coordinates; pixel ``(u, v)`` has its centre at integer coordinates. Meshes
whose surfaces face their outside along the triangle winding (as marching cubes on a TSDF
makes them: normals toward the free space the camera saw) can be drawn with back faces
culled, so a wall seen from behind is see-through: a virtual camera set back behind the
scanned room still sees into it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

NEAR_PLANE = 0.05
"""Triangles with a vertex nearer than this (metres, along z) are left out rather than clipped:
the previews look at the scene from set-back viewpoints, where such triangles are rare."""

FRAGMENT_BUDGET = 1 << 21
"""Candidate pixels tested per chunk of triangles: bounds the memory of one chunk (~100 MB)."""

AMBIENT = 0.35
"""Share of the light that reaches a surface whatever its orientation (the rest is a head light)."""


@dataclass
class View:
    """A virtual pinhole camera: ``width x height`` pixels, focal lengths and principal point in
    pixels, ``T_w_c`` (4x4 float64) its pose in the world."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    T_w_c: np.ndarray

    def scaled(self, factor: int) -> "View":
        """The same camera with ``factor`` times the pixels in each direction (pixel centres kept)."""
        return View(self.width * factor, self.height * factor, self.fx * factor, self.fy * factor,
                    (self.cx + 0.5) * factor - 0.5, (self.cy + 0.5) * factor - 0.5, self.T_w_c)

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(N, 3)`` world points -> ``(N, 2)`` pixels ``(u, v)`` and ``(N,)`` depths z (metres)."""
        points = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        in_camera = (points - self.T_w_c[:3, 3]) @ self.T_w_c[:3, :3]
        z = in_camera[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = np.stack([self.fx * in_camera[:, 0] / z + self.cx, self.fy * in_camera[:, 1] / z + self.cy], 1)
        return pixels, z


@dataclass
class MeshLayer:
    """One mesh to draw: ``vertices`` ``(N, 3)`` float64 in the world frame, ``triangles``
    ``(T, 3)`` int vertex indices, ``colors`` ``(N, 3)`` float in [0, 1], and the ``label`` its
    pixels get in :attr:`Rendering.labels` (> 0)."""

    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray
    label: int = 1
    cull_back_faces: bool = True
    normals: np.ndarray | None = None
    """``(N, 3)`` vertex normals (world frame); computed from the triangles when None."""

    def with_normals(self) -> "MeshLayer":
        """This layer with its vertex normals computed (to reuse across views)."""
        if self.normals is None:
            self.normals = vertex_normals(self.vertices, np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3))
        return self


@dataclass
class Rendering:
    """What a view saw: ``color`` ``(H, W, 3)`` uint8 RGB, ``depth`` ``(H, W)`` float32 metres
    along z (inf where nothing), ``labels`` ``(H, W)`` int32 (the :class:`MeshLayer` label seen,
    0 where nothing)."""

    color: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    view: View = field(repr=False, default=None)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(N, 3)`` unit normals: the area-weighted mean of the normals of the triangles around
    each vertex (winding order gives the side)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    corners = vertices[triangles]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # length = 2 * area
    corner_vertex = triangles.ravel()
    normals = np.stack([np.bincount(corner_vertex, weights=np.repeat(face[:, k], 3), minlength=len(vertices))
                        for k in range(3)], axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.maximum(length, 1e-12)


class _Buffers:
    """The z-buffer of one render: per pixel the nearest depth, the triangle and its
    perspective-correct barycentric weights."""

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        self.depth = np.full(width * height, np.inf)
        self.triangle = np.full(width * height, -1, dtype=np.int64)
        self.weights = np.zeros((width * height, 3))

    def merge(self, pixel: np.ndarray, depth: np.ndarray, triangle: np.ndarray, weights: np.ndarray) -> None:
        """Keep, per pixel, the nearest of these fragments if it is nearer than what is there.
        Ties keep the earlier fragment (stable sort), so the result depends on the input only."""
        order = np.lexsort((depth, pixel))
        pixel, depth = pixel[order], depth[order]
        first = np.ones(len(pixel), dtype=bool)
        first[1:] = pixel[1:] != pixel[:-1]
        chosen = order[first]
        pixel, depth = pixel[first], depth[first]
        nearer = depth < self.depth[pixel]
        pixel, chosen = pixel[nearer], chosen[nearer]
        self.depth[pixel] = depth[nearer]
        self.triangle[pixel] = triangle[chosen]
        self.weights[pixel] = weights[chosen]


def _rasterise(buffers: _Buffers, pixels: np.ndarray, depths: np.ndarray, triangles: np.ndarray) -> None:
    """Fill ``buffers`` with the triangles ``(T, 3)`` whose vertices project to ``pixels``
    ``(N, 2)`` at ``depths`` ``(N,)``. A pixel is covered when its centre is inside the
    triangle or on its edge (shared edges are covered twice; the z-test picks one)."""
    width, height = buffers.width, buffers.height
    corners = pixels[triangles]  # (T, 3, 2)
    low = np.ceil(corners.min(axis=1)).astype(np.int64)
    high = np.floor(corners.max(axis=1)).astype(np.int64)
    low = np.maximum(low, 0)
    high = np.minimum(high, [width - 1, height - 1])
    span = high - low + 1  # (T, 2): box of candidate pixel centres
    area = ((corners[:, 1, 0] - corners[:, 0, 0]) * (corners[:, 2, 1] - corners[:, 0, 1])
            - (corners[:, 1, 1] - corners[:, 0, 1]) * (corners[:, 2, 0] - corners[:, 0, 0]))
    keep = np.flatnonzero((span > 0).all(axis=1) & (np.abs(area) > 1e-12))
    # Chunks of triangles of similar box size, so the candidate grid of a chunk wastes little.
    keep = keep[np.argsort(np.maximum(span[keep, 0], span[keep, 1]), kind="stable")]
    start = 0
    while start < len(keep):
        side = int(np.max(span[keep[start], :]))
        count = max(1, FRAGMENT_BUDGET // max(1, side * side))
        # the chunk's largest box sets its grid: grow the chunk while the budget allows
        stop = min(len(keep), start + count)
        chunk = keep[start:stop]
        box_w, box_h = int(span[chunk, 0].max()), int(span[chunk, 1].max())
        while len(chunk) * box_w * box_h > FRAGMENT_BUDGET and len(chunk) > 1:
            chunk = chunk[: max(1, len(chunk) // 2)]
            box_w, box_h = int(span[chunk, 0].max()), int(span[chunk, 1].max())
        _rasterise_chunk(buffers, chunk, corners, depths[triangles], area, low, span, box_w, box_h)
        start += len(chunk)


def _rasterise_chunk(buffers, chunk, corners, corner_depths, area, low, span, box_w, box_h) -> None:
    offset_x, offset_y = np.meshgrid(np.arange(box_w), np.arange(box_h))
    offset_x, offset_y = offset_x.ravel(), offset_y.ravel()
    inside_box = (offset_x[None, :] < span[chunk, 0:1]) & (offset_y[None, :] < span[chunk, 1:2])
    rows, columns = np.nonzero(inside_box)
    triangle = chunk[rows]
    x = (low[triangle, 0] + offset_x[columns]).astype(np.float64)
    y = (low[triangle, 1] + offset_y[columns]).astype(np.float64)
    a, b, c = corners[triangle, 0], corners[triangle, 1], corners[triangle, 2]
    # Edge functions: each is twice the signed area of (edge, pixel); divided by the
    # triangle's they are its barycentric coordinates in the image.
    w_a = ((c[:, 0] - b[:, 0]) * (y - b[:, 1]) - (c[:, 1] - b[:, 1]) * (x - b[:, 0])) / area[triangle]
    w_b = ((a[:, 0] - c[:, 0]) * (y - c[:, 1]) - (a[:, 1] - c[:, 1]) * (x - c[:, 0])) / area[triangle]
    w_c = 1.0 - w_a - w_b
    inside = (w_a >= 0) & (w_b >= 0) & (w_c >= 0)
    if not np.any(inside):
        return
    triangle, x, y = triangle[inside], x[inside], y[inside]
    screen = np.stack([w_a[inside], w_b[inside], w_c[inside]], axis=1)
    # Perspective-correct: 1/z is linear in the image, and so are the weights divided by z.
    over_z = screen / corner_depths[triangle]
    inverse_depth = over_z.sum(axis=1)
    weights = over_z / inverse_depth[:, None]
    pixel = y.astype(np.int64) * buffers.width + x.astype(np.int64)
    buffers.merge(pixel, 1.0 / inverse_depth, triangle, weights)


def render_meshes(layers: list[MeshLayer], view: View, background=(255, 255, 255), supersample: int = 2) -> Rendering:
    """Draw ``layers`` as seen by ``view``: vertex colours lit by a light at the camera.

    ``supersample`` draws at that many times the resolution in each direction and averages
    down (anti-aliasing); labels and depth are those at the centre of each pixel's block.
    """
    fine = view.scaled(supersample)
    vertex_offset = 0
    all_vertices, all_triangles, all_colors, all_normals, triangle_labels = [], [], [], [], []
    for layer in layers:
        vertices = np.asarray(layer.vertices, dtype=np.float64).reshape(-1, 3)
        triangles = np.asarray(layer.triangles, dtype=np.int64).reshape(-1, 3)
        if len(vertices) == 0 or len(triangles) == 0:
            continue
        in_camera = (vertices - fine.T_w_c[:3, 3]) @ fine.T_w_c[:3, :3]
        corners = in_camera[triangles]
        keep = (corners[:, :, 2] > NEAR_PLANE).all(axis=1)
        if layer.cull_back_faces:
            normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            keep &= np.einsum("ij,ij->i", normal, corners.mean(axis=1)) < 0  # faces the camera at the origin
        triangles = triangles[keep]
        all_vertices.append(in_camera)
        all_triangles.append(triangles + vertex_offset)
        all_colors.append(np.clip(np.asarray(layer.colors, dtype=np.float64).reshape(-1, 3), 0.0, 1.0))
        all_normals.append(layer.with_normals().normals @ fine.T_w_c[:3, :3])
        triangle_labels.append(np.full(len(triangles), layer.label, dtype=np.int32))
        vertex_offset += len(vertices)
    buffers = _Buffers(fine.width, fine.height)
    if all_triangles:
        vertices = np.concatenate(all_vertices)
        triangles = np.concatenate(all_triangles)
        depths = vertices[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = np.stack([fine.fx * vertices[:, 0] / depths + fine.cx,
                               fine.fy * vertices[:, 1] / depths + fine.cy], axis=1)
        _rasterise(buffers, pixels, depths, triangles)
    hit = buffers.triangle >= 0
    image = np.empty((fine.width * fine.height, 3))
    image[:] = np.asarray(background, dtype=np.float64) / 255.0
    labels = np.zeros(fine.width * fine.height, dtype=np.int32)
    if np.any(hit):
        triangles = np.concatenate(all_triangles)
        corners = triangles[buffers.triangle[hit]]  # (P, 3) vertex indices
        weights = buffers.weights[hit][:, :, None]
        colors = (np.concatenate(all_colors)[corners] * weights).sum(axis=1)
        normals = (np.concatenate(all_normals)[corners] * weights).sum(axis=1)
        vertices = np.concatenate(all_vertices)
        points = (vertices[corners] * weights).sum(axis=1)
        facing = np.abs(np.einsum("ij,ij->i", normals, points)) / np.maximum(
            np.linalg.norm(normals, axis=1) * np.linalg.norm(points, axis=1), 1e-12)
        image[hit] = colors * (AMBIENT + (1.0 - AMBIENT) * facing)[:, None]
        labels[hit] = np.concatenate(triangle_labels)[buffers.triangle[hit]]
    image = (image.reshape(fine.height, fine.width, 3) * 255.0).astype(np.float32)
    centre = supersample // 2
    color = cv2.resize(image, (view.width, view.height), interpolation=cv2.INTER_AREA) if supersample > 1 else image
    return Rendering(
        color=np.clip(np.rint(color), 0, 255).astype(np.uint8),
        depth=buffers.depth.reshape(fine.height, fine.width)[centre::supersample, centre::supersample]
        .astype(np.float32).copy(),
        labels=labels.reshape(fine.height, fine.width)[centre::supersample, centre::supersample].copy(),
        view=view,
    )


def draw_path(rendering: Rendering, points_world: np.ndarray, color, thickness: int = 2,
              occlusion_margin: float = 0.05) -> None:
    """Draw the polyline through ``(N, 3)`` world points onto ``rendering.color`` (in place)
    where the rendered surfaces do not hide it (by more than ``occlusion_margin`` metres)."""
    view = rendering.view
    points = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    if len(points) < 2:
        return
    # Dense samples, about one per pixel along the path, each tested against the z-buffer.
    pixels, _ = view.project(points)
    step = np.linalg.norm(np.diff(np.nan_to_num(pixels, nan=0.0, posinf=0.0, neginf=0.0), axis=0), axis=1)
    samples = []
    for k in range(len(points) - 1):
        count = int(np.clip(step[k], 1, 200))
        t = np.linspace(0.0, 1.0, count, endpoint=False)[:, None]
        samples.append(points[k] * (1 - t) + points[k + 1] * t)
    samples.append(points[-1:])
    samples = np.concatenate(samples)
    pixels, depth = view.project(samples)
    u, v = np.rint(pixels[:, 0]), np.rint(pixels[:, 1])
    on_image = (depth > NEAR_PLANE) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
    visible = np.zeros(len(samples), dtype=bool)
    index = np.flatnonzero(on_image)
    visible[index] = depth[index] <= rendering.depth[v[index].astype(int), u[index].astype(int)] + occlusion_margin
    image = np.ascontiguousarray(rendering.color)
    for k in range(len(samples) - 1):
        if visible[k] and visible[k + 1]:
            cv2.line(image, (int(u[k]), int(v[k])), (int(u[k + 1]), int(v[k + 1])), tuple(int(c) for c in color),
                     thickness, cv2.LINE_AA)
    rendering.color = image
