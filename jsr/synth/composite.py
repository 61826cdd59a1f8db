"""Composites: rendered textured rigid objects in a real RGB-D sequence, by depth test.

:func:`generate_composite` takes frames of a real TUM-layout sequence with ground-truth camera
poses (:mod:`jsr.synth.background`), finds a horizontal surface the objects rest on
(:mod:`jsr.synth.support`), plans their motion on it with jsr synth's schedules
(:mod:`jsr.synth.motion`: jumps, smooth moves, one at a time or simultaneous), and renders them
with jsr synth's ray caster and textures (:mod:`jsr.synth.render`) through the background's
camera (lens distortion included). In every frame an object pixel replaces the real one where
the object is nearer than the real surface, or where the real depth is missing and no real
surface close by is nearer; the object's depth gets the synthetic sensor model (axial noise,
random, grazing and edge dropouts; edge dropouts also take the real pixels along the object's
outline), its colour a light optical blur that also softens its outline. Depth and labels are rendered from the camera at the depth image's timestamp, colour
from the camera at the colour image's timestamp (they differ on real sensors).

The folder is written as ``jsr synth`` writes its own sequences (and as ``kitchen_box120`` is)::

    OUT/rgb/<colour stem>.<jpg|png>   OUT/depth/<depth stem>.png (16 bit, the background's scale)
    OUT/labels/<colour stem>.png      0 real scene, k object k
    OUT/rgb.txt, OUT/depth.txt        the background's timestamps
    OUT/groundtruth.txt               T_w_c at each colour timestamp (the background's ground truth)
    OUT/objects/object_<k>.txt        T_w_o at each colour timestamp, origin at the object centre
    OUT/camera.yaml, OUT/synth.yaml   the background's intrinsics; options, seed, version, frames, surface

The world is the background's ground-truth world.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import yaml

from jsr.errors import OutputError
from jsr.geometry import make_transform, rotation_about_axis
from jsr.io.atomic import atomic_write_text
from jsr.io.camera import write_camera_yaml
from jsr.io.trajectory import write_tum_trajectory
from jsr.synth.background import Background, open_background
from jsr.synth.motion import first_rest_frames, plan_object_motion
from jsr.synth.options import CompositeOptions, validate_composite_options
from jsr.synth.randomness import STREAM_COMPOSITE, seeded_rng
from jsr.synth.render import SynthRenderer, sensor_depth_model
from jsr.synth.scene import ScenePlan, footprint_radius, object_shapes
from jsr.synth.support import BackgroundViews, SurfaceGrid, SurfaceRegion, analyse_background, choose_surface
from jsr.synth.write import (
    check_output_folder,
    encode_depth,
    image_list_text,
    object_records,
    prepare_output,
    write_image,
)

logger = logging.getLogger(__name__)

COMPOSITE_TEXTURE_KEYS = 2000  # object k's textures: key 2000 + k (jsr synth's own scenes use 1000 + k)
HOLE_FILL_RADIUS = 2  # px at 640 wide: a pixel without real depth is hidden by real depth this close
MIN_IN_VIEW_PIXELS = 100  # pixels at 640 wide for synth.yaml to count a motion as seen
OPTICAL_BLUR_SIGMA = 0.7  # px at 640 wide: Gaussian blur of the rendered object's colour (Kinect-like optics)
SAME_POSE_MM = 0.2  # colour and depth cameras closer than this (and 0.01 degrees): one rendering
LIGHT_IN_SURFACE_FRAME = np.array([0.35, -0.5, 0.8])  # light direction, as in jsr synth's room


@dataclass
class CompositeFrame:
    """One composited frame: ``color`` ``(H, W, 3)`` uint8 RGB, ``depth`` ``(H, W)`` uint16 in
    the background's depth units, ``labels`` ``(H, W)`` uint8 (0 real scene, k object k)."""

    color: np.ndarray
    depth: np.ndarray
    labels: np.ndarray


@dataclass
class CompositePlan:
    """Everything of a composite but the pixels: the background, the surface the objects rest
    on, and a :class:`ScenePlan` holding the objects (shapes, per-frame ``T_w_o``) and the camera
    at each depth timestamp (``camera_poses``)."""

    options: CompositeOptions
    background: Background
    surface: SurfaceGrid
    surface_frames: int  # frames in which a free place on the surface is in view
    scene: ScenePlan


def build_composite_plan(options: CompositeOptions) -> CompositePlan:
    """Open the background, find the supporting surface and plan the objects' motion."""
    options = validate_composite_options(options)
    background = open_background(options.background, options.start, options.frames)
    intrinsics = background.intrinsics
    synth_options = options.synth_options(intrinsics.width, intrinsics.height, background.colour_format)
    shapes_rng, motion_rng, surface_rng = (seeded_rng(options.seed, STREAM_COMPOSITE, i) for i in range(3))
    shapes = object_shapes(shapes_rng, options.objects, COMPOSITE_TEXTURE_KEYS)
    radii = [footprint_radius(shape) for shape in shapes]
    half_heights = [shape.size[2] / 2.0 for shape in shapes]
    views, surfaces = analyse_background(background)
    moves = options.motion != "static" and options.objects > 0
    first_rest = range(first_rest_frames(synth_options) if moves else options.frames)
    surface, surface_frames = choose_surface(views, surfaces, max(radii, default=0.1), first_rest, surface_rng)
    logger.info(
        "%s: objects rest on a surface of %.2f m2 free, normal %s, in view in %d of %d frames",
        background.root, surface.area, np.round(surface.T_w_s[:3, 2], 3), surface_frames, len(background),
    )
    region = SurfaceRegion(surface, views, radii, half_heights)
    trajectory, moving = plan_object_motion(synth_options, radii, region, motion_rng, options.period)
    object_poses = np.zeros((len(shapes), options.frames, 4, 4))
    for k, shape in enumerate(shapes):
        for f in range(options.frames):
            x, y, yaw = trajectory[k, f]
            on_surface = make_transform(rotation_about_axis(np.array([0.0, 0.0, 1.0]), yaw), (x, y, half_heights[k]))
            object_poses[k, f] = surface.T_w_s @ on_surface
    light = surface.T_w_s[:3, :3] @ LIGHT_IN_SURFACE_FRAME
    scene = ScenePlan(
        options=synth_options,
        intrinsics=intrinsics,
        timestamps=background.colour_timestamps,
        names=[frame.name for frame in background.frames],
        camera_poses=background.depth_poses,
        object_poses=object_poses,
        static_shapes=[],
        object_shapes=shapes,
        light_direction=light / np.linalg.norm(light),
        moving_frames=moving,
    )
    _log_visibility(views, scene)
    return CompositePlan(options, background, surface, surface_frames, scene)


def _log_visibility(views: BackgroundViews, scene: ScenePlan) -> None:
    for k, shape in enumerate(scene.object_shapes):
        centres = scene.object_poses[k, :, :3, 3]
        seen = sum(bool(views.visible(centres[f : f + 1], f)[0]) for f in range(len(centres)))
        logger.info("object %d (%s): centre in view in %d of %d frames", k + 1, shape.kind, seen, len(centres))


class Compositor:
    """Composites the objects of a :class:`CompositePlan` into its background, frame by frame."""

    def __init__(self, plan: CompositePlan):
        self.plan = plan
        self.renderer = SynthRenderer(plan.scene)
        width = plan.background.intrinsics.width
        self._hole_kernel = np.ones((2 * max(1, round(HOLE_FILL_RADIUS * width / 640)) + 1,) * 2, np.uint8)
        self._blur_sigma = OPTICAL_BLUR_SIGMA * width / 640
        self._outline_kernel = np.ones((2 * max(1, math.ceil(2 * self._blur_sigma)) + 1,) * 2, np.uint8)

    def occluding_depth(self, real: np.ndarray) -> np.ndarray:
        """``(H, W)`` float64: the real depth an object must be nearer than; a pixel without
        depth takes the nearest real depth within ``HOLE_FILL_RADIUS`` (a dropout on a real
        surface still hides what is behind it), inf where there is none."""
        far = np.where(real > 0, real, np.inf).astype(np.float32)
        return np.where(real > 0, real, cv2.erode(far, self._hole_kernel)).astype(np.float64)

    def composite(self, index: int) -> CompositeFrame:
        """Frame ``index`` of the composite."""
        plan, background = self.plan, self.plan.background
        options = plan.options
        real_raw = background.depth_raw(index)
        real = real_raw.astype(np.float64) / background.intrinsics.depth_scale
        occluder = self.occluding_depth(real)

        seen = self.renderer.render_exact(index, background.depth_poses[index])
        wins = (seen.labels > 0) & (seen.depth < occluder)
        labels = np.where(wins, seen.labels, 0).astype(np.uint8)
        # The sensor model sees the object where it wins and the real scene elsewhere, so that
        # edge dropouts follow the outline between them.
        exact = np.where(wins, seen.depth, real)
        sensor = sensor_depth_model(
            exact, wins & seen.grazing, options.seed, index, options.depth_noise, options.dropout
        )
        object_depth = sensor.image()
        outline = cv2.dilate(wins.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~wins
        depth = real_raw.copy()
        depth[wins] = encode_depth(object_depth[wins], background.intrinsics.depth_scale)
        depth[outline & sensor.edge_dropped] = 0

        colour = background.colour(index)
        if _same_pose(background.colour_poses[index], background.depth_poses[index]):
            shown, colour_wins = seen, wins
        else:
            shown = self.renderer.render_exact(index, background.colour_poses[index])
            colour_wins = (shown.labels > 0) & (shown.depth < occluder)
        colour[colour_wins] = shown.color[colour_wins]
        if np.any(colour_wins):
            # A real camera's optics blur: the rendered object, sharp to the pixel, gets a light
            # blur, and so does its outline with the real pixels around it (anti-aliasing).
            around = cv2.dilate(colour_wins.astype(np.uint8), self._outline_kernel).astype(bool)
            blurred = cv2.GaussianBlur(colour, (0, 0), self._blur_sigma)
            colour[around] = blurred[around]
        return CompositeFrame(colour, depth, labels)


def _same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    relative = np.linalg.solve(a, b)
    angle = math.degrees(math.acos(float(np.clip((np.trace(relative[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
    return np.linalg.norm(relative[:3, 3]) * 1000.0 < SAME_POSE_MM and angle < 0.01


def check_composite_output(out_dir: Path, options: CompositeOptions, overwrite: bool) -> None:
    """Raise :class:`OutputError` when :func:`generate_composite` could not write ``out_dir``:
    as :func:`jsr.synth.write.check_output_folder`, and never into its own background."""
    out_dir = Path(out_dir)
    background = Path(options.background)
    if out_dir.resolve() == background.resolve() or out_dir.resolve().is_relative_to(background.resolve()):
        raise OutputError(
            f"{out_dir} is inside the background {background}, whose images it could replace; choose a folder outside it"
        )
    check_output_folder(out_dir, overwrite)


def generate_composite(
    out_dir: Path,
    options: CompositeOptions,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Write the composite of ``options`` to ``out_dir``; returns a JSON-ready summary dict.

    Raises :class:`InputError` for invalid options or an unusable background and
    :class:`OutputError` when ``out_dir`` is not empty (unless ``overwrite``: then only files
    jsr synth writes are removed first) or cannot be written.
    """
    from jsr import __version__

    started = time.perf_counter()
    options = validate_composite_options(options)
    out_dir = Path(out_dir)
    check_composite_output(out_dir, options, overwrite)
    plan = build_composite_plan(options)  # before touching the folder: a bad background changes nothing
    prepare_output(out_dir, overwrite)
    background, scene = plan.background, plan.scene
    suffix = scene.options.image_format
    compositor = Compositor(plan)

    write_camera_yaml(out_dir / "camera.yaml", background.intrinsics)
    depth_names = []
    labelled = np.zeros((options.objects, len(background)), dtype=np.int64)  # pixels of object k per frame
    for index, frame in enumerate(background.frames):
        result = compositor.composite(index)
        labelled[:, index] = np.bincount(result.labels.ravel(), minlength=options.objects + 1)[1 : options.objects + 1]
        write_image(out_dir / "rgb" / f"{frame.name}.{suffix}", result.color[:, :, ::-1], suffix)
        depth_names.append(frame.depth_path.stem)
        write_image(out_dir / "depth" / f"{frame.depth_path.stem}.png", result.depth, "png")
        write_image(out_dir / "labels" / f"{frame.name}.png", result.labels, "png")
        if progress is not None:
            progress(index + 1, len(background))

    metadata = _metadata(plan, __version__, labelled)
    for record in metadata["objects"]:
        if record["moving_frames"] and record["moving_frames"][0] not in record["moving_frames_in_view"]:
            logger.warning(
                "%s: object %d is out of view when it first moves (frame %d); another --start may show it",
                out_dir, record["id"], record["moving_frames"][0],
            )
    atomic_write_text(out_dir / "synth.yaml", yaml.safe_dump(metadata, sort_keys=False))
    header = f"composite by jsr synth --background {background.root} (seed {options.seed})"
    write_tum_trajectory(
        out_dir / "groundtruth.txt", scene.timestamps, background.colour_poses,
        header + "\ncamera-to-world T_w_c at the colour timestamps (the background's ground truth, interpolated)",
    )
    for k in range(options.objects):
        write_tum_trajectory(
            out_dir / "objects" / f"object_{k + 1}.txt",
            scene.timestamps,
            scene.object_poses[k],
            header + f"\nobject {k + 1}: object-to-world T_w_o, origin at the object centre",
        )
    # The lists come last: a sequence is only readable once every frame is on disk.
    depth_times = [f"{frame.depth_timestamp:.6f}" for frame in background.frames]
    atomic_write_text(out_dir / "depth.txt", image_list_text("depth", depth_times, depth_names, "depth", "png", header))
    colour_times = [f"{frame.timestamp:.6f}" for frame in background.frames]
    atomic_write_text(out_dir / "rgb.txt", image_list_text("colour", colour_times, scene.names, "rgb", suffix, header))

    seconds = time.perf_counter() - started
    logger.info("%s: %d composite frames written in %.1f s", out_dir, options.frames, seconds)
    return {
        "out_dir": str(out_dir),
        "background": str(background.root),
        "start": options.start,
        "frames": options.frames,
        "objects": options.objects,
        "motion": options.motion,
        "simultaneous": options.simultaneous,
        "width": background.intrinsics.width,
        "height": background.intrinsics.height,
        "seed": options.seed,
        "image_format": suffix,
        "first_motion_frame": scene.first_motion_frames,
        "moving_frames": scene.moving_frames,
        "surface_area_m2": round(plan.surface.area, 3),
        "frames_in_view": [item["frames_in_view"] for item in metadata["objects"]],
        "seconds": round(seconds, 3),
        "seconds_per_frame": round(seconds / options.frames, 4),
    }


def _metadata(plan: CompositePlan, version: str, labelled: np.ndarray) -> dict:
    """What ``synth.yaml`` records; ``labelled`` ``(K, N)``: pixels labelled object k in frame n."""
    background, scene, surface = plan.background, plan.scene, plan.surface
    options = asdict(plan.options)
    pixel_scale = (background.intrinsics.width / 640) ** 2
    return {
        "generator": "jsr synth --background",
        "version": version,
        "options": options,
        "background": {
            "path": str(background.root),
            "frames_in_background": background.total_frames,
            "first_frame": background.start,
            "frames": len(background),
            "first_colour": background.frames[0].name,
            "last_colour": background.frames[-1].name,
        },
        "world_frame": "the background's ground-truth world",
        "timing": "depth and labels rendered from the camera at each depth timestamp, colour from the camera at "
        "each colour timestamp (both interpolated in the background's ground truth); groundtruth.txt and "
        "objects/ are at the colour timestamps",
        "labels": "0 real scene, k object k (where the object is nearer than the real depth)",
        "surface": {
            "T_w_s": [[round(float(v), 6) for v in row] for row in surface.T_w_s],
            "normal_up": [round(float(v), 6) for v in surface.T_w_s[:3, 2]],
            "free_area_m2": round(surface.area, 4),
            "frames_with_a_visible_free_place": plan.surface_frames,
        },
        "objects": [
            {
                **record,
                "frames_in_view": int(np.count_nonzero(labelled[k])),
                "median_pixels_in_view": int(np.median(labelled[k][labelled[k] > 0])) if labelled[k].any() else 0,
                # Motions a camera could see: the object in view before and after (a composite's
                # camera may look away while an object moves).
                "moving_frames_in_view": [
                    frame for frame in record["moving_frames"]
                    if min(labelled[k, frame - 1], labelled[k, frame]) >= MIN_IN_VIEW_PIXELS * pixel_scale
                ],
            }
            for k, record in enumerate(object_records(scene))
        ],
    }

