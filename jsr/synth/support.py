"""Where composited objects stand in a real background: a horizontal supporting surface (floor,
table, counter) found in the background's depth, and the places on it that are free and seen.

Gravity is not given. It is estimated from the surface normals seen in the background, in the
ground-truth world: starting from the cameras' mean "up" (a hand-held camera is held roughly
upright), the normals within a shrinking cone are averaged; floors and table tops dominate that
cone. Points whose normal is within ``HORIZONTAL_DEGREES`` of up are grouped by height; each
well-populated height is a plane, fitted to its points. On a grid of ``CELL`` metres in the
plane, a cell is *supported* where the plane's points fall (and no ray was seen passing through
the plane there), *blocked* where something stands above the plane lower than
``OBSTACLE_TOP`` (a chair leg, a wall, a mug), and *free* when supported and not blocked. An
object of footprint radius r may stand where the free cells reach r around it.

A place is *visible* in a frame when the object's centre there projects inside the image (a
margin kept), lies within ``VIEW_RANGE`` of the camera, and the real depth at that pixel is not
nearer than it (not hidden). The surface is drawn among those on which a free place is visible
in nearly as many frames as on the best one. :class:`SurfaceRegion` is that surface as a :class:`jsr.synth.motion.SupportRegion`
for the motion planner: initial places and jump targets are drawn among free places weighted by
how much of the coming rest they are visible in; smooth moves must keep the whole footprint on
free cells along their path.

Frames: ``T_w_s`` maps the surface frame (origin on the plane, z along its normal, "up") to the
world of the background's ground truth.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from jsr.errors import InputError
from jsr.geometry import KINECT_SIGMA_Z_COEFFICIENT, invert_transform, make_transform, transform_points
from jsr.synth.background import Background
from jsr.synth.motion import random_turn
from jsr.synth.render import camera_rays, field_of_view

logger = logging.getLogger(__name__)

ANALYSIS_STEP = 4  # px between analysed pixels at 640 wide (scaled with the width)
SMOOTHING_WINDOW = 7  # px, depth averaged before normals (noise of real depth)
MAX_ANALYSED_FRAMES = 40  # frames sampled evenly over the selection to find surfaces
ANALYSIS_RANGE = (0.4, 4.0)  # m: depth used to find surfaces (farther real depth is too noisy)
GRAVITY_CONES = (40.0, 25.0, 15.0, 10.0)  # degrees: cone of normals averaged into "up", shrinking
HORIZONTAL_DEGREES = 12.0  # a point whose normal is this close to up lies on a horizontal surface
HEIGHT_BIN = 0.01  # m, histogram of horizontal points' heights
MIN_PLANE_POINTS = 400  # horizontal points at one height to make a candidate surface
PLANE_BAND = 0.03  # m, a point this close to a plane (plus 2 sigma of its depth) belongs to it
CELL = 0.02  # m, grid cell on a surface
OBSTACLE_TOP = 0.40  # m above the surface: higher things (a table over the floor) do not block it
OBSTACLE_FLOOR = 0.025  # m above the surface before a point counts as an obstacle (plus 3 sigma)
MIN_CELL_POINTS = 2  # points of the plane in a cell for it to count as supported
EDGE_MARGIN = 0.01  # m kept between a footprint and the end of the free cells
VIEW_RANGE = (0.6, 3.2)  # m: camera to object centre where a place counts as visible (good real depth)
IMAGE_MARGIN = 0.02  # share of the image width kept between a visible object and the image border
OCCLUSION_TOLERANCE = 0.05  # m: real depth this much nearer than the object's centre hides it
MIN_VISIBLE_SHARE = 0.6  # a jump target or the end of a smooth move is visible in this share of its rest
JUMP_DISTANCE = (0.05, 0.6)  # m: preferred jump lengths (a hand moving the object to another spot)
SMOOTH_DISTANCE = (0.08, 0.25)  # m: smooth moves, as in jsr synth's scenes
VISIBILITY_HEIGHT = 0.1  # m above a surface: the reference centre when surfaces are compared
MIN_VISIBLE_FRAME_SHARE = 0.3  # below this share of frames seeing the chosen surface, a warning
GOOD_SURFACE_SHARE = 0.8  # surfaces seen in this share of the frames the best one is seen in are candidates


@dataclass
class SurfaceGrid:
    """A horizontal surface of the background: its frame, grid and free places.

    ``free`` ``(Gy, Gx)`` bool, cell ``(i, j)`` centred at surface coordinates
    ``origin + (j + 0.5, i + 0.5) * CELL``; ``clearance`` ``(Gy, Gx)`` metres from a cell centre
    to the nearest cell that is not free.
    """

    T_w_s: np.ndarray
    origin: np.ndarray  # (2,) surface coordinates of the grid's corner
    free: np.ndarray
    clearance: np.ndarray
    points: int  # points of the background on the plane

    @property
    def area(self) -> float:
        return float(np.count_nonzero(self.free)) * CELL * CELL

    def cell_centres(self) -> np.ndarray:
        """``(Gy, Gx, 2)`` surface coordinates of the cell centres."""
        rows, cols = np.indices(self.free.shape)
        return np.stack([cols + 0.5, rows + 0.5], axis=-1) * CELL + self.origin

    def clearance_at(self, xy: np.ndarray) -> np.ndarray:
        """Clearance (m) at ``(N, 2)`` surface points; 0 outside the grid."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        cols = np.floor((xy[:, 0] - self.origin[0]) / CELL).astype(int)
        rows = np.floor((xy[:, 1] - self.origin[1]) / CELL).astype(int)
        inside = (rows >= 0) & (rows < self.free.shape[0]) & (cols >= 0) & (cols < self.free.shape[1])
        result = np.zeros(len(xy))
        result[inside] = self.clearance[rows[inside], cols[inside]]
        return result

    def to_world(self, xy: np.ndarray, height: float) -> np.ndarray:
        """``(N, 3)`` world points ``height`` above surface points ``(N, 2)``."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        local = np.column_stack([xy, np.full(len(xy), height)])
        return transform_points(self.T_w_s, local)


@dataclass
class BackgroundViews:
    """What every selected frame of the background sees, coarsely: the camera (depth time) and
    a ``(F, h, w)`` depth image reduced by ``ANALYSIS_STEP`` (the nearest depth of each block),
    to tell whether a place is in view and not hidden."""

    background: Background
    step: int
    near_depth: np.ndarray  # (F, h, w) float32 metres, inf where no depth
    T_c_w: np.ndarray = field(init=False)  # (F, 4, 4)
    _field: tuple[float, float, float, float] = field(init=False)  # normalised x, y bounds of the image

    def __post_init__(self):
        self.T_c_w = invert_transform(self.background.depth_poses)
        self._field = field_of_view(self.background.intrinsics)

    def visible(self, points_w: np.ndarray, frame: int, radius: float = 0.0) -> np.ndarray:
        """``(N,)`` bool: whether objects of ``radius`` (m) centred at world points ``(N, 3)`` are
        within the image and their centres not hidden in ``frame``."""
        intrinsics = self.background.intrinsics
        camera = transform_points(self.T_c_w[frame], points_w)
        z = camera[:, 2]
        result = (z >= VIEW_RANGE[0]) & (z <= VIEW_RANGE[1])
        x_min, x_max, y_min, y_max = self._field
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = camera[:, 0] / z, camera[:, 1] / z
        result &= (x >= x_min) & (x <= x_max) & (y >= y_min) & (y <= y_max)
        if not np.any(result):
            return result
        pixels, _ = cv2.projectPoints(
            camera[result].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intrinsics.matrix,
            intrinsics.distortion_coefficients,
        )
        pixels = pixels.reshape(-1, 2)
        margin = IMAGE_MARGIN * intrinsics.width + intrinsics.fx * radius / z[result]
        inside = (
            (pixels[:, 0] >= margin) & (pixels[:, 0] <= intrinsics.width - 1 - margin)
            & (pixels[:, 1] >= margin) & (pixels[:, 1] <= intrinsics.height - 1 - margin)
        )
        rows = np.clip((pixels[:, 1] / self.step).astype(int), 0, self.near_depth.shape[1] - 1)
        cols = np.clip((pixels[:, 0] / self.step).astype(int), 0, self.near_depth.shape[2] - 1)
        real = self.near_depth[frame, rows, cols]
        hidden = real < z[result] - OCCLUSION_TOLERANCE
        result[np.flatnonzero(result)] = inside & ~hidden
        return result

    def visible_share(self, points_w: np.ndarray, frames: range, radius: float = 0.0) -> np.ndarray:
        """``(N,)`` share of ``frames`` in which objects of ``radius`` at world points are visible."""
        frames = [f for f in frames if 0 <= f < len(self.background)]
        if not frames:
            return np.zeros(len(points_w))
        return np.mean([self.visible(points_w, f, radius) for f in frames], axis=0)


def analyse_background(background: Background) -> tuple[BackgroundViews, list[SurfaceGrid]]:
    """The coarse views of every frame and the horizontal surfaces of the background
    (largest first), in the ground-truth world. Raises :class:`InputError` when no surface
    is found."""
    intrinsics = background.intrinsics
    step = max(1, round(ANALYSIS_STEP * intrinsics.width / 640))
    rays = camera_rays(intrinsics).reshape(intrinsics.height, intrinsics.width, 3)
    count = len(background)
    sampled = set(np.unique(np.linspace(0, count - 1, min(count, MAX_ANALYSED_FRAMES)).round().astype(int)))
    near = []
    samples = []
    for index in range(count):
        depth = background.depth(index)
        near.append(_near_depth(depth, step))
        if index in sampled:
            samples.append(_frame_samples(depth, rays, step, background.depth_poses[index], index))
    views = BackgroundViews(background, step, np.stack(near))
    points = np.concatenate([s[0] for s in samples])
    normals = np.concatenate([s[1] for s in samples])
    ranges = np.concatenate([s[2] for s in samples])
    frame_of = np.concatenate([s[3] for s in samples])
    cameras = background.depth_poses[frame_of, :3, 3]
    if len(points) == 0:
        raise InputError(f"background {background.root}: no usable depth in the selected frames")
    up = _gravity(normals, background.depth_poses)
    surfaces = [
        surface
        for plane in _horizontal_planes(points, normals, ranges, up)
        if (surface := _surface_grid(plane, points, ranges, cameras)) is not None
    ]
    if not surfaces:
        raise InputError(
            f"background {background.root}: no horizontal surface (floor, table) is seen in frames "
            f"{background.start}..{background.start + count - 1}; choose other frames with --start"
        )
    return views, sorted(surfaces, key=lambda s: -s.area)


def choose_surface(
    views: BackgroundViews,
    surfaces: list[SurfaceGrid],
    radius: float,
    first_rest: range,
    rng: np.random.Generator,
) -> tuple[SurfaceGrid, int]:
    """A surface, and in how many frames a free place on it is visible: one on which a free place for a footprint of ``radius`` is visible in many frames:
    drawn with ``rng`` among those seen in at least ``GOOD_SURFACE_SHARE`` of the frames the best
    one is seen in (floor or table: seeds differ), preferring those seen during ``first_rest``
    (the frames before the first motion: a motion is seen only if the object was).
    Raises :class:`InputError` when none has room."""
    frames = range(len(views.background))
    seen = np.zeros((len(surfaces), len(frames)), dtype=bool)  # a free place of surface i in view in frame f
    for i, surface in enumerate(surfaces):
        roomy = surface.clearance >= radius + EDGE_MARGIN
        centres = surface.to_world(surface.cell_centres()[roomy], VISIBILITY_HEIGHT)
        if len(centres):
            seen[i] = [bool(np.any(views.visible(centres, f, radius))) for f in frames]
        logger.debug(
            "surface at %s (normal %s): %.2f m2 free, a place visible in %d of %d frames",
            np.round(surface.T_w_s[:3, 3], 3), np.round(surface.T_w_s[:3, 2], 3), surface.area,
            np.count_nonzero(seen[i]), len(frames),
        )
    visible_frames = seen.sum(axis=1)
    seen_first = seen[:, list(first_rest)].mean(axis=1) if len(first_rest) else np.ones(len(surfaces))
    best = int(visible_frames.max(initial=0))
    if best == 0:
        raise InputError(
            f"background {views.background.root}: no horizontal surface seen in the selected frames has room "
            f"for an object {2 * radius:.2f} m across; choose other frames (--start) or fewer objects"
        )
    good = [i for i in range(len(surfaces)) if visible_frames[i] >= GOOD_SURFACE_SHARE * best]
    good = [i for i in good if seen_first[i] >= MIN_VISIBLE_SHARE] or good
    chosen = good[int(rng.integers(len(good)))]
    if visible_frames[chosen] < MIN_VISIBLE_FRAME_SHARE * len(frames):
        logger.warning(
            "%s: the supporting surface is in view in only %d of %d frames",
            views.background.root, visible_frames[chosen], len(frames),
        )
    return surfaces[chosen], int(visible_frames[chosen])


def _near_depth(depth: np.ndarray, step: int) -> np.ndarray:
    """The nearest valid depth of each ``step`` x ``step`` block, inf where none."""
    height, width = (depth.shape[0] // step) * step, (depth.shape[1] // step) * step
    blocks = np.where(depth > 0, depth, np.inf)[:height, :width].astype(np.float32)
    return blocks.reshape(height // step, step, width // step, step).min(axis=(1, 3))


def _frame_samples(
    depth: np.ndarray, rays: np.ndarray, step: int, T_w_c: np.ndarray, index: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """World points ``(N, 3)``, unit normals ``(N, 3)`` (facing the camera), camera depth ``(N,)``
    and the frame index ``(N,)`` of every ``step``-th pixel of smoothed depth with a reliable normal."""
    valid = (depth > 0).astype(np.float32)
    window = (SMOOTHING_WINDOW, SMOOTHING_WINDOW)
    total = cv2.boxFilter(depth.astype(np.float32), -1, window, normalize=False)
    support = cv2.boxFilter(valid, -1, window, normalize=False)
    smoothed = np.where(support >= 0.6 * SMOOTHING_WINDOW**2, total / np.maximum(support, 1.0), 0.0)
    points = rays * smoothed[:, :, None]
    # Normals by central differences 2 steps wide: on the grid, neighbours are one step apart.
    grid = points[::step, ::step]
    z = grid[:, :, 2]
    centre = grid[1:-1, 1:-1]
    dx = grid[1:-1, 2:] - grid[1:-1, :-2]
    dy = grid[2:, 1:-1] - grid[:-2, 1:-1]
    normals = np.cross(dx, dy)
    length = np.linalg.norm(normals, axis=2)
    zc = z[1:-1, 1:-1]
    neighbours = np.stack([z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]])
    # A neighbour far off in depth: a discontinuity, not a surface.
    smooth = np.all((neighbours > 0) & (np.abs(neighbours - zc) < 0.1 * zc), axis=0)
    keep = smooth & (zc >= ANALYSIS_RANGE[0]) & (zc <= ANALYSIS_RANGE[1]) & (length > 0)
    normals = normals[keep] / length[keep][:, None]
    centre = centre[keep]
    normals *= -np.sign(np.einsum("ij,ij->i", normals, centre))[:, None]
    world_points = transform_points(T_w_c, centre)
    world_normals = normals @ T_w_c[:3, :3].T
    return world_points, world_normals, zc[keep], np.full(len(centre), index)


def _gravity(normals: np.ndarray, T_w_c: np.ndarray) -> np.ndarray:
    """``(3,)`` unit "up" in the world: the mean of the normals within a shrinking cone around
    the cameras' mean up (image rows run down: up is the camera's -y)."""
    up = -T_w_c[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    for cone in GRAVITY_CONES:
        near = normals @ up > math.cos(math.radians(cone))
        if np.count_nonzero(near) < MIN_PLANE_POINTS:
            break
        up = normals[near].sum(axis=0)
        up /= np.linalg.norm(up)
    return up


def _horizontal_planes(
    points: np.ndarray, normals: np.ndarray, ranges: np.ndarray, up: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(normal, point on plane)`` of the horizontal planes: peaks of the heights of points
    whose normal is near ``up``, each refitted to its points."""
    horizontal = normals @ up > math.cos(math.radians(HORIZONTAL_DEGREES))
    heights = points[horizontal] @ up
    if len(heights) < MIN_PLANE_POINTS:
        return []
    edges = np.arange(heights.min(), heights.max() + 2 * HEIGHT_BIN, HEIGHT_BIN)
    histogram, edges = np.histogram(heights, bins=edges)
    # Mass within +-2 bins of each bin: a plane spreads over a few centimetres (noise).
    mass = np.convolve(histogram, np.ones(5))[2:-2]
    planes = []
    taken = np.zeros(len(mass), dtype=bool)
    for peak in np.argsort(mass)[::-1]:
        if mass[peak] < MIN_PLANE_POINTS:
            break
        if taken[max(0, peak - 5) : peak + 6].any():
            continue
        taken[peak] = True  # the strongest peaks first: a peak beside a stronger one is its flank
        height = 0.5 * (edges[peak] + edges[peak + 1])
        band = PLANE_BAND + 2.0 * KINECT_SIGMA_Z_COEFFICIENT * ranges[horizontal] ** 2
        members = points[horizontal][np.abs(heights - height) < band]
        member_ranges = ranges[horizontal][np.abs(heights - height) < band]
        normal, point = up, up * height
        for _ in range(3):  # least squares plane, then the points near it again
            if len(members) < MIN_PLANE_POINTS:
                break
            point = members.mean(axis=0)
            _, _, vt = np.linalg.svd(members - point, full_matrices=False)
            normal = vt[2] if vt[2] @ up > 0 else -vt[2]
            band = PLANE_BAND + 2.0 * KINECT_SIGMA_Z_COEFFICIENT * member_ranges**2
            near = np.abs((members - point) @ normal) < band
            members, member_ranges = members[near], member_ranges[near]
        if len(members) < MIN_PLANE_POINTS or normal @ up <= math.cos(math.radians(HORIZONTAL_DEGREES)):
            continue
        # Two peaks of one broad plane (noise, ground-truth drift) converge on the same plane.
        if all(abs((point - other_point) @ normal) >= 2.0 * PLANE_BAND for _, other_point, _ in planes):
            planes.append((normal, point, len(members)))
    return [(normal, point) for normal, point, _ in sorted(planes, key=lambda plane: -plane[2])]


def _surface_frame(normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """``T_w_s``: z along ``normal``, origin at ``point``, x and y any orthonormal pair."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    x_axis = np.cross(helper, normal)
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(normal, x_axis)
    return make_transform(np.column_stack([x_axis, y_axis, normal]), point)


def _surface_grid(
    plane: tuple[np.ndarray, np.ndarray], points: np.ndarray, ranges: np.ndarray, cameras: np.ndarray
) -> SurfaceGrid | None:
    """The grid of free cells of one plane, from all sampled points (``cameras`` ``(N, 3)``:
    the position of the camera that saw each point)."""
    normal, point = plane
    T_w_s = _surface_frame(normal, point)
    T_s_w = invert_transform(T_w_s)
    local = transform_points(T_s_w, points)
    sigma = KINECT_SIGMA_Z_COEFFICIENT * ranges**2
    on_plane = np.abs(local[:, 2]) < PLANE_BAND + 2.0 * sigma
    if np.count_nonzero(on_plane) < MIN_PLANE_POINTS:
        return None
    low, high = np.percentile(local[on_plane, :2], [0.5, 99.5], axis=0)
    origin = low - 2 * CELL
    shape = (int(math.ceil((high[1] - low[1]) / CELL)) + 4, int(math.ceil((high[0] - low[0]) / CELL)) + 4)

    def counts(xy: np.ndarray) -> np.ndarray:
        cols = np.floor((xy[:, 0] - origin[0]) / CELL).astype(int)
        rows = np.floor((xy[:, 1] - origin[1]) / CELL).astype(int)
        inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
        flat = rows[inside] * shape[1] + cols[inside]
        return np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape)

    surface = counts(local[on_plane, :2])
    above = (local[:, 2] > OBSTACLE_FLOOR + 3.0 * sigma) & (local[:, 2] < OBSTACLE_TOP)
    obstacles = counts(local[above, :2])
    # A point seen below the plane: its ray passed through the plane, where there is no surface.
    camera_local = transform_points(T_s_w, cameras)
    below = (local[:, 2] < -(PLANE_BAND + 2.0 * sigma)) & (camera_local[:, 2] > 0)
    fraction = camera_local[below, 2] / (camera_local[below, 2] - local[below, 2])
    crossings = camera_local[below, :2] + fraction[:, None] * (local[below, :2] - camera_local[below, :2])
    seen_through = counts(crossings)

    supported = (surface >= MIN_CELL_POINTS) & (surface >= 2 * seen_through)
    kernel = np.ones((3, 3), np.uint8)
    supported = cv2.morphologyEx(supported.astype(np.uint8), cv2.MORPH_CLOSE, kernel).astype(bool)
    blocked = cv2.dilate((obstacles >= MIN_CELL_POINTS).astype(np.uint8), kernel).astype(bool)
    free = supported & ~blocked
    padded = np.pad(free.astype(np.uint8), 1)  # the grid's border is not free
    distance = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    clearance = np.maximum(distance - 0.5, 0.0) * CELL
    return SurfaceGrid(T_w_s, origin, free, clearance, int(np.count_nonzero(on_plane)))


class SurfaceRegion:
    """A :class:`SurfaceGrid` of a background as the motion planner's support region, for
    objects of footprint radii ``radii`` and half heights ``half_heights`` (metres)."""

    def __init__(self, surface: SurfaceGrid, views: BackgroundViews, radii: list[float], half_heights: list[float]):
        self.surface = surface
        self.views = views
        self.radii = radii
        self.half_heights = half_heights
        self._centres = surface.cell_centres().reshape(-1, 2)
        self._clearance = surface.clearance.reshape(-1)
        self._shares: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}

    def _places(self, k: int, frames: range) -> tuple[np.ndarray, np.ndarray]:
        """Free cell centres ``(M, 2)`` where object ``k`` fits, and the share of ``frames``
        each is visible in (memoised: the planner asks again for every attempt)."""
        key = (k, frames.start, frames.stop)
        if key not in self._shares:
            fits = self._clearance >= self.radii[k] + EDGE_MARGIN
            centres = self._centres[fits]
            world = self.surface.to_world(centres, self.half_heights[k])
            self._shares[key] = (centres, self.views.visible_share(world, frames, self.radii[k]))
        return self._shares[key]

    def _draw(self, rng: np.random.Generator, centres: np.ndarray, weights: np.ndarray) -> np.ndarray:
        if len(centres) == 0 or weights.sum() <= 0:
            raise InputError("no free place on the supporting surface for an object")
        index = rng.choice(len(centres), p=weights / weights.sum())
        # Anywhere in the cell, so that places do not line up on the grid.
        return centres[index] + rng.uniform(-0.5, 0.5, 2) * CELL

    def _visible_weights(self, shares: np.ndarray) -> np.ndarray:
        """Weights of places: fully seen places first; if none is seen enough, any seen one."""
        weights = np.where(shares >= MIN_VISIBLE_SHARE, shares**2, 0.0)
        return weights if weights.sum() > 0 else shares**2

    def initial_position(self, rng: np.random.Generator, k: int, frames: range) -> np.ndarray:
        centres, shares = self._places(k, frames)
        weights = self._visible_weights(shares)
        if weights.sum() <= 0:  # not seen during the first rest: anywhere on the surface
            weights = np.ones(len(centres))
        return self._draw(rng, centres, weights)

    def propose_move(
        self, rng: np.random.Generator, k: int, origin: np.ndarray, smooth: bool, frames: range
    ) -> np.ndarray:
        if smooth:
            distance = rng.uniform(*SMOOTH_DISTANCE)
            direction = rng.uniform(-math.pi, math.pi)
            step = np.array([distance * math.cos(direction), distance * math.sin(direction)])
            return np.append(origin[:2] + step, origin[2] + random_turn(rng))
        centres, shares = self._places(k, frames)
        distance = np.linalg.norm(centres - origin[:2], axis=1)
        weights = self._visible_weights(shares) * (distance >= JUMP_DISTANCE[0])
        preferred = weights * (distance <= JUMP_DISTANCE[1])
        weights = preferred if preferred.sum() > 0 else weights
        if weights.sum() <= 0:
            return origin.copy()  # nowhere to go: allows_move refuses, the planner turns it in place
        return np.append(self._draw(rng, centres, weights), origin[2] + random_turn(rng))

    def allows_move(self, k: int, origin: np.ndarray, target: np.ndarray, smooth: bool, frames: range) -> bool:
        radius = self.radii[k] + EDGE_MARGIN
        if np.linalg.norm(target[:2] - origin[:2]) < 1e-9:
            return False
        if not smooth:
            return bool(self.surface.clearance_at(target[:2])[0] >= radius)
        # The whole footprint stays on free cells along the path (the surface need not be convex).
        samples = max(2, int(math.ceil(np.linalg.norm(target[:2] - origin[:2]) / (0.5 * CELL))) + 1)
        path = origin[:2] + np.linspace(0.0, 1.0, samples)[:, None] * (target[:2] - origin[:2])
        if np.any(self.surface.clearance_at(path) < radius):
            return False
        world = self.surface.to_world(target[:2], self.half_heights[k])
        return bool(self.views.visible_share(world, frames, self.radii[k])[0] >= MIN_VISIBLE_SHARE)
