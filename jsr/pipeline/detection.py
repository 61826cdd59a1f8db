"""Moving-object detection from segment outlier ratios (Caccamo et al. 2017, Section 2.1).

After a frame is registered against the static map, the point measurements matched to static
landmarks are either inliers (they move with the static scene) or outliers. A segment whose
matched features are mostly outliers moves differently from the static scene: it is a moving
region, and its features initialise a new object map. Segments of one object that touch in
the image are grouped so that they initialise a single object map.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from jsr.config import DetectionConfig
from jsr.pipeline.measurements import Segments

logger = logging.getLogger(__name__)

# one displaced landmark is a depth edge as often as motion: a segment joins a group with more
# (kitchen_box120 frame 20: two static segments with 1 each joined the box's group)
MIN_DISPLACED_PER_SEGMENT = 2


@dataclass
class SegmentOutlierStats:
    """Per segment (``S`` rows): matched point features, outliers among them, and their ratio
    (``outliers / matched``, 0.0 for a segment without matched features)."""

    matched: np.ndarray  # (S,) int64
    outliers: np.ndarray  # (S,) int64
    outlier_ratio: np.ndarray  # (S,) float64


def _mask(values: np.ndarray | None, count: int, name: str, default: bool) -> np.ndarray:
    if values is None:
        return np.full(count, default, dtype=bool)
    array = np.asarray(values, dtype=bool)
    if array.shape != (count,):
        raise ValueError(f"{name} must have shape ({count},), got {array.shape}")
    return array


def segment_outlier_stats(
    segments: Segments,
    matched: np.ndarray,
    inlier: np.ndarray,
    exclude: np.ndarray | None = None,
) -> SegmentOutlierStats:
    """Matched features and outlier ratio of every segment.

    ``matched``, ``inlier``, ``exclude``: ``(N,)`` bool over the frame's point measurements.
    A measurement counts when it is matched and not excluded; it is an outlier when it is
    not also an inlier (an inlier that was not matched is ignored).
    """
    count = len(np.asarray(matched))
    matched = _mask(matched, count, "matched", True)
    inlier = _mask(inlier, count, "inlier", False)
    exclude = _mask(exclude, count, "exclude", False)
    num_segments = len(segments)
    lengths = np.array([len(idx) for idx in segments.point_indices], dtype=np.int64)
    if len(lengths) != num_segments:
        raise ValueError(f"{len(lengths)} point index arrays for {num_segments} segments")
    if lengths.sum() == 0:
        zeros = np.zeros(num_segments, dtype=np.int64)
        return SegmentOutlierStats(zeros, zeros.copy(), np.zeros(num_segments))
    members = np.concatenate([np.asarray(idx, dtype=np.int64).ravel() for idx in segments.point_indices])
    owner = np.repeat(np.arange(num_segments), lengths)
    counted = matched[members] & ~exclude[members]
    outlier = counted & ~inlier[members]
    matched_counts = np.bincount(owner, weights=counted, minlength=num_segments).astype(np.int64)
    outlier_counts = np.bincount(owner, weights=outlier, minlength=num_segments).astype(np.int64)
    ratio = np.divide(
        outlier_counts, matched_counts, out=np.zeros(num_segments), where=matched_counts > 0
    )
    return SegmentOutlierStats(matched_counts, outlier_counts, ratio)


def chance_of_at_least(hits: np.ndarray, trials: np.ndarray, base_ratio: float) -> np.ndarray:
    """``(S,)`` probability of at least ``hits`` among ``trials`` if each were a hit at the
    frame's ``base_ratio`` only (binomial upper tail; the ratio clipped to [0.05, 0.95]): a
    segment's outliers among its matched features, or a group's displaced landmarks among
    those projecting into it. Small values mean far more than mismatches and noise explain."""
    from scipy.stats import binom

    ratio = float(np.clip(base_ratio, 0.05, 0.95))
    return binom.sf(np.asarray(hits) - 1, np.asarray(trials), ratio)


def _beyond_chance(stats: SegmentOutlierStats, matched: np.ndarray, inlier: np.ndarray,
                   exclude: np.ndarray | None, config: DetectionConfig) -> np.ndarray:
    """``(S,)`` bool: segments holding more outliers than the frame's overall outlier ratio
    makes likely (:func:`chance_of_at_least` below ``config.significance``; all True when
    that is 1), counting the matched measurements not in ``exclude``."""
    if config.significance >= 1.0:
        return np.ones(len(stats.matched), dtype=bool)
    counted = np.asarray(matched, dtype=bool) & ~_mask(exclude, len(np.asarray(matched)), "exclude", False)
    total = int(counted.sum())
    base = float((counted & ~np.asarray(inlier, dtype=bool)).sum()) / total if total else 0.0
    return chance_of_at_least(stats.outliers, stats.matched, base) < config.significance


def detect_moving_segments(
    segments: Segments,
    matched: np.ndarray,
    inlier: np.ndarray,
    config: DetectionConfig,
    exclude: np.ndarray | None = None,
) -> list[int]:
    """Segments (ascending) whose outlier ratio exceeds ``config.segment_outlier_ratio``
    (strictly) and that have at least ``config.min_segment_features`` matched features,
    ignoring the measurements in ``exclude`` (e.g. those already given to an object map).

    With ``config.significance`` below 1, a segment must also hold more outliers than the
    frame's overall outlier ratio makes likely (:func:`chance_of_at_least`): on real data a
    quarter of all static matches can be outliers, and a static segment with 4 outliers in 6
    matches is chance, not motion.
    """
    stats = segment_outlier_stats(segments, matched, inlier, exclude)
    moving = (stats.outlier_ratio > config.segment_outlier_ratio) & (
        stats.matched >= config.min_segment_features
    )
    if moving.any():
        moving &= _beyond_chance(stats, matched, inlier, exclude, config)
    ids = np.flatnonzero(moving).tolist()
    if ids:
        logger.debug(
            "moving segments %s (outlier ratios %s)", ids, np.round(stats.outlier_ratio[ids], 3).tolist()
        )
    return ids


def segment_adjacency_pairs(label_image: np.ndarray, max_gap_pixels: int = 0) -> np.ndarray:
    """``(E, 2)`` unique pairs ``(a, b)``, ``a < b``, of segment labels whose pixels are at most
    ``max_gap_pixels + 1`` apart along both image axes (8-neighbours for a gap of 0).
    Label -1 (no segment) is ignored."""
    labels = np.asarray(label_image)
    if labels.ndim != 2:
        raise ValueError(f"label image must be 2D, got shape {labels.shape}")
    if max_gap_pixels < 0:
        raise ValueError(f"max_gap_pixels must be >= 0, got {max_gap_pixels}")
    rows, cols = np.flatnonzero((labels >= 0).any(axis=1)), np.flatnonzero((labels >= 0).any(axis=0))
    if not len(rows):
        return np.zeros((0, 2), dtype=np.int64)
    labels = labels[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]  # (the pairs lie within the labels' box)
    height, width = labels.shape
    reach = max_gap_pixels + 1
    pairs = []
    # Half of the offsets in the (2 reach + 1)^2 window: the other half gives the same pairs.
    for dy in range(0, reach + 1):
        for dx in range(-reach, reach + 1):
            if dy == 0 and dx <= 0:
                continue
            if dy >= height or abs(dx) >= width:
                continue
            a = labels[: height - dy, max(0, -dx) : width - max(0, dx)]
            b = labels[dy:, max(0, dx) : width + min(0, dx)]
            keep = (a >= 0) & (b >= 0) & (a != b)
            if keep.any():
                pairs.append(np.stack([a[keep], b[keep]], axis=1))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    stacked = np.sort(np.concatenate(pairs).astype(np.int64), axis=1)
    # one code per pair: a 1-D unique is many times faster than np.unique(axis=0)
    count = int(stacked.max()) + 1
    codes = np.unique(stacked[:, 0] * count + stacked[:, 1])
    return np.stack([codes // count, codes % count], axis=1)


def merge_adjacent_moving_segments(
    segments: Segments, ids: list[int], max_gap_pixels: int = 0
) -> list[list[int]]:
    """Group the moving segments ``ids`` that touch in the image (directly, or across at
    most ``max_gap_pixels`` pixels of other labels), transitively, so that one object spread
    over several segments initialises one object map.

    Returns groups with ascending members, ordered by their smallest member; every id
    appears in exactly one group.
    """
    unique_ids = sorted({int(i) for i in ids})
    if not unique_ids:
        return []
    num_segments = len(segments)
    if unique_ids[0] < 0 or unique_ids[-1] >= num_segments:
        raise ValueError(f"segment ids {unique_ids} out of range for {num_segments} segments")
    # Keep only the moving segments in the label image, renumbered 0..M-1.
    relabel = np.full(num_segments + 1, -1, dtype=np.int64)  # last entry serves label -1
    relabel[unique_ids] = np.arange(len(unique_ids))
    labels = np.asarray(segments.label_image, dtype=np.int64)
    moving_labels = relabel[np.where((labels >= 0) & (labels < num_segments), labels, -1)]
    pairs = segment_adjacency_pairs(moving_labels, max_gap_pixels)
    count = len(unique_ids)
    graph = coo_matrix(
        (np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(count, count)
    )
    _, component = connected_components(graph, directed=False)
    groups: dict[int, list[int]] = {}
    for position, comp in enumerate(component):
        groups.setdefault(int(comp), []).append(unique_ids[position])
    return sorted(groups.values(), key=lambda group: group[0])


def displaced_landmark_groups(
    segments: Segments,
    displaced: np.ndarray,
    projecting: np.ndarray,
    little_static_support: np.ndarray,
    config: DetectionConfig,
) -> list[list[int]]:
    """Groups of touching segments that moved by their displaced static landmarks.

    All arrays are ``(S,)`` over the segments: ``displaced`` and ``projecting`` count the static
    landmarks (inliers in the previous frame) that project into each segment with depth and of
    those the ones whose surface is no longer there; ``little_static_support`` marks segments
    hardly shown static by their features.

    A segment is a candidate when it has displaced landmarks, at least
    ``config.displaced_share`` of those projecting into it, and little static support.
    Touching candidates (``config.merge_gap_pixels``) form a group: an object split over
    segments (a cylinder's lit and shaded sides) counts its landmarks together. A group moves
    when so many of its landmarks are displaced that the frame's own share of displaced
    landmarks (depth noise, blur, depth edges; :func:`chance_of_at_least`)
    makes that less likely than ``config.displaced_significance``: 5 of 5 in most frames, 10
    of 10 in a blurred one where a fifth of all landmarks are displaced.
    Returns the groups, each ascending, ordered by their smallest member.
    """
    displaced, projecting = np.asarray(displaced), np.asarray(projecting)
    candidates = (displaced >= MIN_DISPLACED_PER_SEGMENT) & (
        displaced >= config.displaced_share * projecting) & np.asarray(little_static_support, dtype=bool)
    frame_share = float(displaced.sum()) / max(int(projecting.sum()), 1)
    moving = []
    for group in merge_adjacent_moving_segments(segments, np.flatnonzero(candidates).tolist(),
                                                config.merge_gap_pixels):
        chance = chance_of_at_least(int(displaced[group].sum()), int(projecting[group].sum()), frame_share)
        if float(chance) < config.displaced_significance:
            moving.append(group)
    return moving
