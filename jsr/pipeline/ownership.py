"""Pixel ownership: which map every pixel of a frame went to (the ``masks/`` images, the dense
models' fusion masks), and the pixel boxes where the front-end looks closer (objects and
candidate moving regions).
"""

from __future__ import annotations

import cv2
import numpy as np

from jsr.pipeline.measurements import FrameMeasurements
from jsr.pipeline.maps import ObjectMap
from jsr.pipeline.state import DYNAMIC, FrameAssignment, SceneState

OWNERSHIP_FILL_RADIUS = 3  # px at 640 wide: pixels in no segment (no depth) take the owner of most labelled neighbours


def ownership_image(measurements: FrameMeasurements, assignment: FrameAssignment,
                    dynamic: list[int] | tuple = ()) -> np.ndarray:
    """``(H, W)`` uint8: 0 static, K for the pixels of the segments and features of object (or
    candidate) K, DYNAMIC for the segments ``dynamic`` that no map owns."""
    labels = measurements.segments.label_image
    image = np.zeros(labels.shape, dtype=np.uint8)
    segment_owner = assignment.segment_owner.copy()
    if len(dynamic):
        dynamic = np.asarray(dynamic, dtype=np.int64)
        segment_owner[dynamic[segment_owner[dynamic] == 0]] = DYNAMIC
    if not np.any(segment_owner > 0) and not np.any(assignment.point_owner > 0):
        return image
    owner_of_label = np.append(segment_owner, 0).astype(np.uint8)  # label -1 -> static
    image = owner_of_label[np.where(labels >= 0, labels, len(assignment.segment_owner))]
    if assignment.not_object_pixels is not None:
        image[assignment.not_object_pixels] = 0
    image = fill_unlabelled(image, labels < 0, max(1, round(OWNERSHIP_FILL_RADIUS * labels.shape[1] / 640)))
    object_points = np.flatnonzero(assignment.point_owner > 0)
    if len(object_points):
        height, width = labels.shape
        pixels = np.round(measurements.points.pixels[object_points]).astype(int)
        u, v = np.clip(pixels[:, 0], 0, width - 1), np.clip(pixels[:, 1], 0, height - 1)
        image[v, u] = assignment.point_owner[object_points].astype(np.uint8)
    return image


def published_mask(ownership: np.ndarray, object_maps: list[ObjectMap]) -> np.ndarray:
    """The ownership image ``(H, W)`` uint8 as ``masks/`` shows it: the pixels of candidates
    not yet confirmed are DYNAMIC (moving, not modelled yet), as are non-rigid regions."""
    candidates = [m.object_id for m in object_maps if not m.confirmed]
    if not candidates:
        return ownership
    return np.where(np.isin(ownership, candidates), np.uint8(DYNAMIC), ownership).astype(np.uint8)


def pixel_box(pixels: np.ndarray) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (end exclusive) bounding the True pixels of ``(H, W)`` bool."""
    rows, cols = np.nonzero(pixels)
    return int(cols.min()), int(rows.min()), int(cols.max()) + 1, int(rows.max()) + 1


def fill_unlabelled(ownership: np.ndarray, unlabelled: np.ndarray, radius: int) -> np.ndarray:
    """``ownership`` ``(H, W)`` uint8 with every ``unlabelled`` pixel (no segment: no depth,
    mostly) given to the object owning more than half of the labelled pixels within ``radius``
    (0 otherwise): depth dropouts inside an object's faces belong to it."""
    if not unlabelled.any() or not ownership.any():
        return ownership
    size = (2 * radius + 1, 2 * radius + 1)
    labelled = (~unlabelled).astype(np.float32)
    labelled_count = cv2.boxFilter(labelled, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    filled = ownership.copy()
    for object_id in np.unique(ownership[~unlabelled & (ownership > 0)]):
        mine = ((ownership == object_id) & ~unlabelled).astype(np.float32)
        count = cv2.boxFilter(mine, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
        filled[unlabelled & (count > 0.5 * labelled_count)] = object_id
    return filled


def detail_boxes(state: SceneState, frame_index: int) -> list[tuple[int, int, int, int]]:
    """Pixel boxes ``(x0, y0, x1, y1)`` of the objects in the previous frame's ownership
    image, and of the moving regions of the last ``CANDIDATE_DETAIL_FRAMES`` frames that
    had too few 3D points to start a map, grown by ``features.object_detail_margin`` of
    their size on every side: where the front-end adds the finest-scale keypoints (small
    objects carry few otherwise)."""
    # expired candidates go even with the detail pass off, so the list cannot grow
    memory = state.memory
    memory.candidate_boxes = [(box, until) for box, until in memory.candidate_boxes if until >= frame_index]
    features = state.config.features
    if not (state.config.objects.enabled and features.object_detail):
        return []
    regions = [box for box, _ in memory.candidate_boxes]
    mask = memory.previous_mask
    if mask is not None and mask.any():
        for object_id in np.unique(mask[(mask > 0) & (mask != DYNAMIC)]):
            regions.append(pixel_box(mask == object_id))
    if not regions:
        return []
    width, height = state.intrinsics.width, state.intrinsics.height
    boxes = []
    for x0, y0, x1, y1 in regions:
        grow_x = int(round(features.object_detail_margin * (x1 - x0)))
        grow_y = int(round(features.object_detail_margin * (y1 - y0)))
        boxes.append((max(0, x0 - grow_x), max(0, y0 - grow_y), min(width, x1 + grow_x), min(height, y1 + grow_y)))
    return boxes
