"""Pixel precision and recall of estimated object masks against label images."""

from __future__ import annotations

from typing import Iterable

import numpy as np

from jsr.evaluate.stats import ratio


def _empty_counts() -> dict[str, int]:
    return {"true_positive": 0, "predicted": 0, "actual": 0}


def _counts_to_metrics(counts: dict[str, int]) -> dict:
    true_positive, predicted, actual = counts["true_positive"], counts["predicted"], counts["actual"]
    union = predicted + actual - true_positive
    return {
        "precision": ratio(true_positive, predicted),
        "recall": ratio(true_positive, actual),
        "iou": ratio(true_positive, union),
        "true_positive_pixels": int(true_positive),
        "predicted_pixels": int(predicted),
        "actual_pixels": int(actual),
    }


def _accumulate(counts: dict[str, int], predicted: np.ndarray, actual: np.ndarray) -> None:
    counts["true_positive"] += int(np.count_nonzero(predicted & actual))
    counts["predicted"] += int(np.count_nonzero(predicted))
    counts["actual"] += int(np.count_nonzero(actual))


def mask_precision_recall(
    mask_pairs: Iterable[tuple[np.ndarray, np.ndarray]], matches: Iterable[tuple[int, int]] = ()
) -> dict:
    """Pixel precision/recall of estimated masks against label images.

    ``mask_pairs`` yields ``(mask, label)`` integer images of the same shape (0 static, else an
    object id). Overall: "object" pixels ``mask != 0`` against ``label != 0``. For each
    ``(estimated K, true k)`` in ``matches``: ``mask == K`` against ``label == k``. Counts are
    summed over all frames before dividing (pixel-level, not a mean of per-frame scores).
    Returns ``{"frames", "precision", "recall", "iou", ..._pixels, "pairs": [...]}``; a ratio
    with a zero denominator is ``None``.
    """
    matches = [(int(estimated), int(true)) for estimated, true in matches]
    overall = _empty_counts()
    per_pair = {pair: _empty_counts() for pair in matches}
    frames = 0
    for mask, label in mask_pairs:
        mask, label = np.asarray(mask), np.asarray(label)
        if mask.shape != label.shape:
            raise ValueError(f"mask shape {mask.shape} differs from label shape {label.shape}")
        frames += 1
        _accumulate(overall, mask != 0, label != 0)
        for (estimated, true), counts in per_pair.items():
            _accumulate(counts, mask == estimated, label == true)
    result = {"frames": frames, **_counts_to_metrics(overall), "pairs": []}
    for (estimated, true), counts in per_pair.items():
        result["pairs"].append({"estimated_id": estimated, "true_id": true, **_counts_to_metrics(counts)})
    return result
