"""Where the rigid objects of a sequence rest and how they move: the motion schedule and the
planner of per-frame object positions on a support surface.

The planner works in the frame of a support surface (z along its normal, the objects stand on
``z = 0``): an object's state is ``(x, y, yaw)``. What the surface allows is asked of a
:class:`SupportRegion`: the synthetic table top (:class:`TableTop`) or a surface found in a real
background (:mod:`jsr.synth.support`). The planner keeps footprints apart (a vertical cylinder
around each object, ``OBJECT_GAP`` between them, along the whole path of a smooth move).
"""

from __future__ import annotations

import logging
import math
from typing import Protocol

import numpy as np

from jsr.synth.options import SynthOptions

logger = logging.getLogger(__name__)

OBJECT_GAP = 0.03  # metres between the footprint circles of two objects
FIRST_REST_FRAMES = 10  # frames before the first motion (at most a quarter of the sequence)
SYNTH_PERIOD = 9  # frames between the starts of two motions in jsr synth's own scenes
SMOOTH_SHARE = 0.6  # share of the period a smooth motion takes
PLACEMENT_ATTEMPTS = 5000
MOVE_ATTEMPTS = 500
TURN_DEGREES = (10.0, 60.0)  # a move turns the object about its vertical axis by this much, either way


class SupportRegion(Protocol):
    """Where objects may stand, in the surface frame (metres). ``k`` is the 0-based object
    index, ``frames`` the frames the object will rest at the new place (visibility)."""

    def initial_position(self, rng: np.random.Generator, k: int, frames: range) -> np.ndarray:
        """A ``(2,)`` candidate ``(x, y)`` for object ``k`` before any motion."""

    def propose_move(
        self, rng: np.random.Generator, k: int, origin: np.ndarray, smooth: bool, frames: range
    ) -> np.ndarray:
        """A ``(3,)`` candidate ``(x, y, yaw)`` for object ``k`` now at ``origin`` ``(x, y, yaw)``."""

    def allows_move(self, k: int, origin: np.ndarray, target: np.ndarray, smooth: bool, frames: range) -> bool:
        """Whether object ``k`` may go from ``origin`` to ``target`` (``(2,)`` or more, x y first)."""


def random_turn(rng: np.random.Generator) -> float:
    """A turn about the vertical axis, radians: 10 to 60 degrees either way."""
    return math.radians(rng.uniform(*TURN_DEGREES)) * (1 if rng.random() < 0.5 else -1)


class TableTop:
    """The synthetic scene's table top: a rectangle ``size`` (x, y) centred on the origin,
    ``margin`` kept free along its edges; objects of footprint radii ``radii``."""

    def __init__(self, size: tuple[float, float], margin: float, radii: list[float]):
        self.half = np.asarray(size, dtype=float) / 2.0 - margin
        self.radii = radii

    def initial_position(self, rng: np.random.Generator, k: int, frames: range) -> np.ndarray:
        limit_x, limit_y = self.half - self.radii[k]
        return np.array([rng.uniform(-limit_x, limit_x), rng.uniform(-limit_y, limit_y)])

    def propose_move(
        self, rng: np.random.Generator, k: int, origin: np.ndarray, smooth: bool, frames: range
    ) -> np.ndarray:
        low, high = (0.08, 0.25) if smooth else (0.05, 0.20)
        distance = rng.uniform(low, high)
        direction = rng.uniform(-math.pi, math.pi)
        turn = random_turn(rng)
        return origin + np.array([distance * math.cos(direction), distance * math.sin(direction), turn])

    def allows_move(self, k: int, origin: np.ndarray, target: np.ndarray, smooth: bool, frames: range) -> bool:
        # The rectangle is convex: a path between two places inside it stays inside.
        return bool(np.all(np.abs(target[:2]) + self.radii[k] <= self.half))


def min_path_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> float:
    """Smallest distance between two points moving linearly (same timing) from *0 to *1."""
    start = a0 - b0
    velocity = (a1 - a0) - (b1 - b0)
    speed2 = float(velocity @ velocity)
    s = 0.0 if speed2 < 1e-18 else float(np.clip(-(start @ velocity) / speed2, 0.0, 1.0))
    return float(np.linalg.norm(start + s * velocity))


def first_rest_frames(options: SynthOptions) -> int:
    """How many frames the objects rest before the first motion (no randomness)."""
    return max(1, min(FIRST_REST_FRAMES, options.frames // 4))


def motion_schedule(
    options: SynthOptions, rng: np.random.Generator, period: int = SYNTH_PERIOD
) -> list[tuple[int, int, list[int]]]:
    """``(start_frame, duration, movers)`` events; movers are 0-based object indices.

    A first rest, then one motion every ``period`` frames (jittered by a frame from 8 on),
    moving the objects in turn (all at once with ``simultaneous``); a jump takes one frame, a
    smooth motion 60% of the period.
    """
    count, frames = options.objects, options.frames
    if options.motion == "static" or count == 0:
        return []
    first_rest = first_rest_frames(options)
    turns = 1 if options.simultaneous else count
    period = max(2, min(period, (frames - 1 - first_rest) // turns))
    duration = 1 if options.motion == "jump" else max(1, min(period - 1, round(SMOOTH_SHARE * period)))
    events, start, turn = [], first_rest, 0
    while start + duration - 1 <= frames - 1:
        movers = list(range(count)) if options.simultaneous else [turn % count]
        events.append((start, duration, movers))
        step = period + (int(rng.integers(-1, 2)) if period >= 8 else 0)
        start += step
        turn += 1
    return events


def plan_object_motion(
    options: SynthOptions,
    radii: list[float],
    region: SupportRegion,
    rng: np.random.Generator,
    period: int = SYNTH_PERIOD,
) -> tuple[np.ndarray, list[list[int]]]:
    """Per-frame ``(x, y, yaw)`` of every object in the surface frame, ``(K, N, 3)``, and the
    frames where each object's state differs from the previous frame's.

    ``radii`` are the footprint radii (a vertical cylinder containing the object at any yaw).
    An object that finds no free place for a motion turns where it stands.
    """
    count, frames = len(radii), options.frames
    moves = options.motion != "static" and count > 0
    first_rest = range(0, first_rest_frames(options) if moves else frames)

    # Initial layout: footprints apart. (Drawn before the schedule: the synthetic scenes of
    # earlier versions drew in this order, and the same seed keeps giving the same files.)
    states: list[np.ndarray] = []  # (x, y, yaw)
    for k in range(count):
        for _ in range(PLACEMENT_ATTEMPTS):
            x, y = region.initial_position(rng, k, first_rest)
            if all(math.hypot(x - s[0], y - s[1]) >= radii[k] + radii[j] + OBJECT_GAP for j, s in enumerate(states)):
                break
        else:
            raise RuntimeError("could not place the objects apart on their support surface")
        states.append(np.array([x, y, rng.uniform(-math.pi, math.pi)]))

    schedule = motion_schedule(options, rng, period)
    starts = [start for start, _, _ in schedule]

    def resting_frames(frame: int) -> range:
        """The frames from ``frame`` up to the next motion (or the end)."""
        later = [start for start in starts if start > frame]
        return range(frame, later[0] if later else frames)

    # trajectory[k, f] = (x, y, yaw) of object k at frame f.
    trajectory = np.zeros((count, frames, 3))
    for k in range(count):
        trajectory[k, :] = states[k]
    smooth = options.motion == "smooth"
    for start, duration, movers in schedule:
        current = {k: trajectory[k, start - 1].copy() for k in range(count)}
        rest = resting_frames(start + duration - 1)
        targets: dict[int, np.ndarray] = {}
        for k in movers:
            origin = current[k]
            for _ in range(MOVE_ATTEMPTS):
                candidate = region.propose_move(rng, k, origin, smooth, rest)
                if not region.allows_move(k, origin, candidate, smooth, rest):
                    continue
                clear = True
                for j in range(count):
                    if j == k:
                        continue
                    other0 = current[j][:2]
                    other1 = targets[j][:2] if j in targets else other0
                    if smooth:
                        gap = min_path_distance(origin[:2], candidate[:2], other0, other1)
                    else:
                        gap = float(np.linalg.norm(candidate[:2] - other1))
                    if gap < radii[k] + radii[j] + OBJECT_GAP:
                        clear = False
                        break
                if clear:
                    targets[k] = candidate
                    break
            else:
                # A crowded surface: turn in place (the footprint circle stays where it is).
                logger.debug("object %d found no free place at frame %d and only turns", k + 1, start)
                targets[k] = origin + np.array([0.0, 0.0, math.radians(rng.uniform(*TURN_DEGREES))])
        for k, target in targets.items():
            origin = current[k]
            for i in range(duration - 1):
                s = (i + 1) / duration
                eased = s * s * (3.0 - 2.0 * s)
                trajectory[k, start + i] = origin + eased * (target - origin)
            # The target itself on the motion's last frame (origin + (target - origin) can miss it
            # by a rounding step, which made the next frame look like a motion too).
            trajectory[k, start + duration - 1 :] = target

    moving = []
    for k in range(count):
        changed = np.any(np.abs(np.diff(trajectory[k], axis=0)) > 0.0, axis=1)
        moving.append([int(f) + 1 for f in np.flatnonzero(changed)])
    return trajectory, moving
