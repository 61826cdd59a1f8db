"""VLAD appearance descriptors of segments (Jegou et al., TPAMI 2012), for the segment-based
registration of Caccamo et al. 2017, Section 2.2.2.

A :class:`VladVocabulary` is a set of ``K`` visual words (k-means centres of SIFT
descriptors). The VLAD of a set of descriptors is, per word, the sum of the residuals
``x - c`` of the descriptors whose nearest word is ``c``, concatenated into a ``K * 128``
vector and normalised. A :class:`SegmentIndex` holds the VLADs of the segments of the object
maps and returns the most similar ones by cosine similarity.

Everything is vectorised numpy; training is seeded by an explicit ``numpy.random.Generator``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Hashable

import numpy as np
from scipy.sparse import csr_matrix

logger = logging.getLogger(__name__)

DESCRIPTOR_DIM = 128
NORMALIZATIONS = ("power", "intra")
_CHUNK_ROWS = 16384  # rows per block when computing descriptor-to-centre distances


def _as_descriptors(descriptors: np.ndarray, name: str = "descriptors") -> np.ndarray:
    array = np.asarray(descriptors)
    if array.ndim != 2 or array.shape[1] != DESCRIPTOR_DIM:
        raise ValueError(f"{name} must have shape (N, {DESCRIPTOR_DIM}), got {array.shape}")
    return array.astype(np.float32, copy=False)


def nearest_centres(descriptors: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index ``(N,)`` and squared distance ``(N,)`` of the nearest centre of every descriptor.

    Ties go to the lowest centre index. Distances are computed in float64 by blocks of rows.
    """
    x = np.asarray(descriptors, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64)
    count = len(x)
    index = np.zeros(count, dtype=np.int64)
    distance = np.zeros(count, dtype=np.float64)
    if count == 0 or len(c) == 0:
        return index, distance
    c_sq = np.einsum("ij,ij->i", c, c)
    for start in range(0, count, _CHUNK_ROWS):
        block = x[start : start + _CHUNK_ROWS]
        d2 = np.einsum("ij,ij->i", block, block)[:, None] - 2.0 * block @ c.T + c_sq[None, :]
        best = np.argmin(d2, axis=1)
        index[start : start + len(block)] = best
        distance[start : start + len(block)] = np.maximum(d2[np.arange(len(block)), best], 0.0)
    return index, distance


def kmeans_plusplus(data: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """``(k, D)`` initial centres by k-means++ seeding (Arthur and Vassilvitskii 2007)."""
    x = np.asarray(data, dtype=np.float64)
    count = len(x)
    centres = np.empty((k, x.shape[1]), dtype=np.float64)
    first = int(rng.integers(count))
    centres[0] = x[first]
    closest = np.einsum("ij,ij->i", x - centres[0], x - centres[0])
    for i in range(1, k):
        total = closest.sum()
        if total <= 0.0:  # all points coincide with chosen centres: pick uniformly
            pick = int(rng.integers(count))
        else:
            pick = int(np.searchsorted(np.cumsum(closest), rng.random() * total, side="right"))
            pick = min(pick, count - 1)
        centres[i] = x[pick]
        diff = x - centres[i]
        closest = np.minimum(closest, np.einsum("ij,ij->i", diff, diff))
    return centres


def kmeans(
    data: np.ndarray,
    k: int,
    rng: np.random.Generator,
    iterations: int = 30,
    tolerance: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's k-means with k-means++ seeding; returns ``(centres (k, D), labels (N,))``.

    Deterministic for a given ``rng`` state. A centre left without points is moved to the
    point farthest from its current centre. Stops after ``iterations`` rounds, when no label
    changes, or when the largest centre shift falls below ``tolerance`` (relative to the data
    scale).
    """
    x = np.asarray(data, dtype=np.float64)
    if len(x) < k:
        raise ValueError(f"k-means needs at least k={k} points, got {len(x)}")
    centres = kmeans_plusplus(x, k, rng)
    labels, distance = nearest_centres(x, centres)
    scale = max(float(np.abs(x).max()), 1e-12)
    for iteration in range(iterations):
        counts = np.bincount(labels, minlength=k)
        membership = csr_matrix((np.ones(len(x)), (labels, np.arange(len(x)))), shape=(k, len(x)))
        sums = np.asarray(membership @ x)
        new_centres = centres.copy()
        filled = counts > 0
        new_centres[filled] = sums[filled] / counts[filled, None]
        empty = np.flatnonzero(~filled)
        if len(empty):
            # Re-seed empty clusters at the points worst served by the current centres.
            farthest = np.argsort(-distance, kind="stable")[: len(empty)]
            new_centres[empty] = x[farthest]
        shift = float(np.abs(new_centres - centres).max())
        centres = new_centres
        new_labels, distance = nearest_centres(x, centres)
        converged = np.array_equal(new_labels, labels) or shift <= tolerance * scale
        labels = new_labels
        if converged:
            logger.debug("k-means converged after %d iterations", iteration + 1)
            break
    return centres, labels


@dataclass
class VladVocabulary:
    """Visual words for VLAD; ``centres`` is ``(K, 128)`` float32.

    ``normalization``: ``"power"`` (signed square root of every component, Jegou et al. 2012)
    or ``"intra"`` (L2 normalisation of every word's residual block, Arandjelovic and
    Zisserman 2013); either is followed by a global L2 normalisation.
    """

    centres: np.ndarray
    normalization: str = "power"

    def __post_init__(self) -> None:
        self.centres = _as_descriptors(self.centres, "centres")
        if len(self.centres) == 0:
            raise ValueError("a vocabulary needs at least one centre")
        if self.normalization not in NORMALIZATIONS:
            raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {self.normalization!r}")

    @property
    def size(self) -> int:
        """Number of visual words ``K``."""
        return len(self.centres)

    @property
    def dimension(self) -> int:
        """Length of a VLAD vector, ``K * 128``."""
        return self.size * DESCRIPTOR_DIM

    @classmethod
    def train(
        cls,
        descriptors: np.ndarray,
        size: int,
        rng: np.random.Generator,
        iterations: int = 30,
        normalization: str = "power",
    ) -> "VladVocabulary":
        """k-means (k-means++ seeding, Lloyd iterations) of ``descriptors`` ``(N, 128)``.

        With fewer distinct descriptors than ``size`` the vocabulary gets one word per
        distinct descriptor (logged as a warning). Deterministic for a given ``rng`` state.
        """
        data = _as_descriptors(descriptors)
        if size < 1:
            raise ValueError(f"vocabulary size must be positive, got {size}")
        if len(data) == 0:
            raise ValueError("cannot train a vocabulary without descriptors")
        distinct = len(np.unique(data, axis=0)) if len(data) <= 4 * size else len(data)
        k = min(size, distinct)
        if k < size:
            logger.warning("only %d distinct descriptors: vocabulary of %d words instead of %d", distinct, k, size)
        centres, _ = kmeans(data, k, rng, iterations=iterations)
        return cls(centres=centres.astype(np.float32), normalization=normalization)

    @classmethod
    def train_on_sample(cls, descriptors: np.ndarray, settings, rng: np.random.Generator) -> "VladVocabulary":
        """:meth:`train` with the ``vlad`` section of the config (``settings``: size,
        iterations, normalisation) on at most ``settings.training_descriptors`` of
        ``descriptors`` ``(N, 128)``, drawn with ``rng``."""
        if len(descriptors) > settings.training_descriptors:
            descriptors = descriptors[np.sort(rng.choice(len(descriptors), settings.training_descriptors, replace=False))]
        return cls.train(descriptors, settings.vocabulary_size, rng, settings.kmeans_iterations, settings.normalization)

    def assign(self, descriptors: np.ndarray) -> np.ndarray:
        """``(M,)`` index of the nearest word of every descriptor."""
        return nearest_centres(_as_descriptors(descriptors), self.centres)[0]

    def encode(self, descriptors: np.ndarray) -> np.ndarray:
        """``(K * 128,)`` float32 VLAD of ``descriptors`` ``(M, 128)``; zeros when ``M == 0``."""
        data = _as_descriptors(descriptors)
        return self.encode_groups(data, [np.arange(len(data))])[0]

    def encode_groups(self, descriptors: np.ndarray, groups: list[np.ndarray]) -> np.ndarray:
        """``(G, K * 128)`` float32 VLADs of several subsets of ``descriptors``.

        ``groups``: ``G`` index arrays into ``descriptors`` (e.g. ``Segments.point_indices``);
        descriptors are assigned to words once. An empty group gives a zero row.
        """
        data = _as_descriptors(descriptors)
        k = self.size
        out = np.zeros((len(groups), k * DESCRIPTOR_DIM), dtype=np.float32)
        if len(groups) == 0 or len(data) == 0:
            return out
        groups = [np.asarray(g, dtype=np.int64).ravel() for g in groups]
        lengths = np.array([len(g) for g in groups], dtype=np.int64)
        if lengths.sum() == 0:
            return out
        members = np.concatenate(groups)
        group_of = np.repeat(np.arange(len(groups)), lengths)
        words = self.assign(data)
        residuals = data[members].astype(np.float64) - self.centres[words[members]].astype(np.float64)
        # Sum residuals per (group, word) cell: sort by cell, then reduce contiguous runs.
        cell = group_of * k + words[members]
        order = np.argsort(cell, kind="stable")
        cell_sorted = cell[order]
        starts = np.flatnonzero(np.r_[True, cell_sorted[1:] != cell_sorted[:-1]])
        sums = np.add.reduceat(residuals[order], starts, axis=0)
        vlad = np.zeros((len(groups) * k, DESCRIPTOR_DIM), dtype=np.float64)
        vlad[cell_sorted[starts]] = sums
        vlad = vlad.reshape(len(groups), k, DESCRIPTOR_DIM)
        if self.normalization == "intra":
            block_norm = np.linalg.norm(vlad, axis=2, keepdims=True)
            vlad = np.divide(vlad, block_norm, out=np.zeros_like(vlad), where=block_norm > 0)
        vlad = vlad.reshape(len(groups), k * DESCRIPTOR_DIM)
        if self.normalization == "power":
            vlad = np.sign(vlad) * np.sqrt(np.abs(vlad))
        norm = np.linalg.norm(vlad, axis=1, keepdims=True)
        vlad = np.divide(vlad, norm, out=np.zeros_like(vlad), where=norm > 0)
        out[:] = vlad
        return out


@dataclass
class _Entry:
    object_map_id: int
    segment_key: Hashable


@dataclass
class SegmentIndex:
    """VLADs of object-map segments, searched by cosine similarity.

    ``add(object_map_id, segment_key, vlad)`` stores one segment (``segment_key`` is any
    hashable the caller uses to find the segment again, e.g. ``(keyframe_id, segment)``);
    adding the same ``(object_map_id, segment_key)`` again replaces its VLAD.
    """

    _entries: list[_Entry] = field(default_factory=list, repr=False)
    _vectors: list[np.ndarray] = field(default_factory=list, repr=False)
    _position: dict[tuple[int, Hashable], int] = field(default_factory=dict, repr=False)
    _matrix: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self._entries)

    def add(self, object_map_id: int, segment_key: Hashable, vlad: np.ndarray) -> None:
        vector = np.asarray(vlad, dtype=np.float32).ravel()
        if self._vectors and len(vector) != len(self._vectors[0]):
            raise ValueError(f"VLAD length {len(vector)} differs from the index's {len(self._vectors[0])}")
        norm = float(np.linalg.norm(vector))
        vector = vector / norm if norm > 0 else np.zeros_like(vector)
        key = (object_map_id, segment_key)
        if key in self._position:
            self._vectors[self._position[key]] = vector
        else:
            self._position[key] = len(self._entries)
            self._entries.append(_Entry(object_map_id, segment_key))
            self._vectors.append(vector)
        self._matrix = None

    def remove_map(self, object_map_id: int) -> None:
        """Forget every segment of one object map."""
        keep = [i for i, e in enumerate(self._entries) if e.object_map_id != object_map_id]
        self._entries = [self._entries[i] for i in keep]
        self._vectors = [self._vectors[i] for i in keep]
        self._position = {(e.object_map_id, e.segment_key): i for i, e in enumerate(self._entries)}
        self._matrix = None

    def object_map_ids(self) -> list[int]:
        """Object maps with at least one segment, ascending."""
        return sorted({e.object_map_id for e in self._entries})

    def query(
        self, vlad: np.ndarray, top_k: int, object_map_id: int | None = None
    ) -> list[tuple[Hashable, float]]:
        """The ``top_k`` most similar segments as ``(segment_key, cosine similarity)``, best
        first; restricted to one object map when ``object_map_id`` is given. Ties go to the
        segment added first. A zero query is similar to nothing (similarity 0 everywhere).
        """
        if top_k <= 0 or not self._entries:
            return []
        if self._matrix is None:
            self._matrix = np.stack(self._vectors)
        query = np.asarray(vlad, dtype=np.float32).ravel()
        if len(query) != self._matrix.shape[1]:
            raise ValueError(f"query length {len(query)} differs from the index's {self._matrix.shape[1]}")
        norm = float(np.linalg.norm(query))
        query = query / norm if norm > 0 else query
        similarity = (self._matrix.astype(np.float64) @ query.astype(np.float64))
        candidates = np.arange(len(self._entries))
        if object_map_id is not None:
            owners = np.array([e.object_map_id for e in self._entries])
            candidates = candidates[owners == object_map_id]
        # Best first; ties by insertion order (lexsort's last key is the primary one).
        order = candidates[np.lexsort((candidates, -similarity[candidates]))][:top_k]
        return [(self._entries[i].segment_key, float(similarity[i])) for i in order]
