"""Agglomerative hierarchical clustering of planar blocks into planes.

Step 3 of the plane extraction of :mod:`jsr.pipeline.planes` (after Feng, Taguchi and
Kamat, ICRA 2014): the graph of adjacent planar blocks (moment sums ``(B, 11)``, see
:mod:`jsr.pipeline.plane_fitting`) is merged cheapest pair first under one merge rule
(:class:`_MergeRule`: normals agree within their noise, the merged fit stays within the
depth noise). The lower levels of the hierarchy, where merges are independent, are computed
in vectorised rounds (mutually best pairs, and stars of blocks around them); a binary heap
then finishes the hierarchy sequentially, with lazy re-evaluation of pairs whose clusters
changed after they were queued.
"""

from __future__ import annotations

import heapq
import logging
import math
import operator

import numpy as np

from jsr.config import PlanesConfig
from jsr.pipeline.plane_fitting import (
    MIN_GAP_TO_NOISE,
    N_MOMENTS,
    fit_scalar,
    fit_stack,
    normal_variance,
    smallest_eigenvalues,
)

logger = logging.getLogger(__name__)

# Merge test: the residual increase per point of the smaller cluster stays below this many T^2.
_INCREASE_FACTOR = 4.0


class _MergeRule:
    """The merge test of two clusters and its cost (shared by the batch and heap stages).

    Two clusters may merge if the angle between their normals is below
    ``max(merge_angle, angle_noise_sigmas * sqrt(var_a + var_b))`` (the normal variances of
    :func:`normal_variance`: small far blocks have noisy normals, large planes precise ones)
    and the merged fit MSE is below ``T^2 = merge_rmse_sigmas^2 * c^2 * E[Z^4]``. The cost
    is the ratio of the two, so merges are ranked relative to the noise at their depths.
    Besides (not in Feng et al.): the increase of the summed squared residuals caused by the
    merge, per point of the smaller cluster, must stay below ``(2 T)^2``. Far away (where
    ``T`` reaches several centimetres) the merged RMSE of a large wall and a small parallel
    surface 15 cm in front of it (book backs, a cabinet door) can pass, while the smaller
    cluster's points are clearly off the wall's plane. (The factor 2 leaves room for the
    low-frequency warping of real depth sensors, about 1 cm at 1-2 m.)
    """

    def __init__(self, cfg: PlanesConfig, coefficient: float):
        self.min_angle = math.radians(cfg.merge_angle_degrees)
        self.angle_sigmas = cfg.angle_noise_sigmas
        self.merge_factor = cfg.merge_rmse_sigmas**2 * coefficient**2
        self.coefficient2 = coefficient**2
        self.max_angle = math.radians(89.0)
        self.correlation = float(cfg.block_size)

    def costs(
        self,
        moments: np.ndarray,
        normals: np.ndarray,
        normal_var: np.ndarray,
        mse: np.ndarray,
        first: np.ndarray,
        second: np.ndarray,
    ) -> np.ndarray:
        """Merge costs of cluster pairs ``(first[i], second[i])``; inf where not allowed."""
        angle_limit = np.clip(
            self.angle_sigmas * np.sqrt(normal_var[first] + normal_var[second]), self.min_angle, self.max_angle
        )
        dots = np.abs(np.einsum("ij,ij->i", normals[first], normals[second]))
        merged = moments[first] + moments[second]
        merged_mse = smallest_eigenvalues(merged)
        limit = self.merge_factor * merged[:, 10] / np.maximum(merged[:, 0], 1.0)
        costs = merged_mse / limit
        # Residual increase, per point of the smaller cluster (a parallel plane a few noise
        # sigmas away fails this while the merged RMSE can still pass).
        n_first, n_second = moments[first, 0], moments[second, 0]
        increase = merged[:, 0] * merged_mse - n_first * mse[first] - n_second * mse[second]
        costs[increase > _INCREASE_FACTOR * limit * np.minimum(n_first, n_second)] = np.inf
        costs[dots < np.cos(angle_limit)] = np.inf
        costs[~(costs < 1.0)] = np.inf
        return costs

    def cost(
        self, ma: list[float], mb: list[float], na: tuple, nb: tuple, va: float, vb: float, ea: float, eb: float
    ) -> float:
        """Scalar version of :meth:`costs` for the heap loop."""
        angle_limit = self.angle_sigmas * math.sqrt(va + vb)
        if angle_limit < self.min_angle:
            angle_limit = self.min_angle
        elif angle_limit > self.max_angle:
            angle_limit = self.max_angle
        if abs(na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]) < math.cos(angle_limit):
            return math.inf
        merged = list(map(operator.add, ma, mb))
        mse, _, z4 = fit_scalar(merged, False)
        limit = self.merge_factor * z4
        if not limit > 0.0 or mse >= limit:
            return math.inf
        if merged[0] * mse - ma[0] * ea - mb[0] * eb > _INCREASE_FACTOR * limit * min(ma[0], mb[0]):
            return math.inf
        return mse / limit


def _unique_cluster_pairs(owner: np.ndarray, block_pairs: np.ndarray, count: int) -> np.ndarray:
    """Distinct pairs ``(a < b)`` of different clusters adjacent through ``block_pairs``."""
    a = owner[block_pairs[:, 0]]
    b = owner[block_pairs[:, 1]]
    different = a != b
    low = np.minimum(a[different], b[different])
    high = np.maximum(a[different], b[different])
    codes = np.sort(low * count + high)
    if len(codes):
        codes = codes[np.concatenate([[True], codes[1:] != codes[:-1]])]
    return np.column_stack([codes // count, codes % count])


def _batch_merge_rounds(
    moments: np.ndarray,
    normals: np.ndarray,
    normal_var: np.ndarray,
    mse: np.ndarray,
    block_pairs: np.ndarray,
    rule: _MergeRule,
    coefficient: float,
    max_rounds: int = 12,
    min_fraction: float = 0.15,
) -> tuple[np.ndarray, ...]:
    """Lower levels of the hierarchy, vectorised over all clusters at once.

    Every cluster points to its cheapest allowed neighbour. A mutually best pair would also
    be merged by the sequential algorithm before either joins another cluster, so all such
    pairs merge in one numpy step; the larger cluster of the pair is the centre. Clusters
    whose cheapest neighbour is a centre (or its partner) join that centre in the same step
    (the star merges a growing plane makes block by block in the sequential algorithm), if
    the fit of the whole group still passes the merge test; otherwise only the pair merges.
    Rounds repeat until one merges fewer than ``min_fraction`` of the clusters; the heap stage
    then finishes the hierarchy.

    ``moments``, ``normals``, ``normal_var``, ``mse`` describe the initial clusters (planar
    blocks), ``block_pairs`` their adjacency. Returns ``(owner (B,) cluster of each initial
    cluster, moments, normals, normal_var, mse, pairs (P, 2), costs (P,))`` for the clusters
    after the rounds, with their allowed pairs and merge costs.
    """
    count = len(moments)
    owner = np.arange(count)
    index = np.arange(count)
    moments = moments.copy()
    normals = normals.copy()
    normal_var = normal_var.copy()
    mse = mse.copy()
    finished = False
    for round_number in range(max_rounds + 1):
        pairs = _unique_cluster_pairs(owner, block_pairs, count)
        costs = rule.costs(moments, normals, normal_var, mse, pairs[:, 0], pairs[:, 1])
        allowed = np.isfinite(costs)
        pairs, costs = pairs[allowed], costs[allowed]
        if len(pairs) == 0 or finished or round_number == max_rounds:
            break
        # Cheapest allowed neighbour of every cluster.
        ends = np.concatenate([pairs[:, 0], pairs[:, 1]])
        others = np.concatenate([pairs[:, 1], pairs[:, 0]])
        both_costs = np.concatenate([costs, costs])
        cheapest = np.full(count, np.inf)
        np.minimum.at(cheapest, ends, both_costs)
        is_best = both_costs == cheapest[ends]
        target = np.full(count, -1, dtype=np.int64)
        target[ends[is_best]] = others[is_best]
        has_target = target >= 0
        safe_target = np.where(has_target, target, index)
        mutual = has_target & (safe_target[safe_target] == index)
        size = moments[:, 0]
        larger = (size > size[safe_target]) | ((size == size[safe_target]) & (index < safe_target))
        centre = mutual & larger
        partner = mutual & ~larger
        group = index.copy()
        group[partner] = safe_target[partner]
        joiner = has_target & ~mutual
        to_centre = joiner & centre[safe_target]
        to_partner = joiner & partner[safe_target]
        group[to_centre] = safe_target[to_centre]
        group[to_partner] = safe_target[safe_target[to_partner]]
        live = np.flatnonzero(np.bincount(owner, minlength=count))
        # Whole-group test of the stars; a failing star keeps only its pair merge.
        grouped = _group_sums(moments, live, group[live], count)
        stars = np.unique(group[live[joiner[live] & (group[live] != live)]])
        if len(stars):
            merged = grouped[stars]
            star_cost = smallest_eigenvalues(merged) / (rule.merge_factor * merged[:, 10] / np.maximum(merged[:, 0], 1.0))
            failed = np.zeros(count, dtype=bool)
            failed[stars[~(star_cost < 1.0)]] = True
            revert = joiner & failed[group]
            if revert.any():
                group[revert] = index[revert]
                grouped = _group_sums(moments, live, group[live], count)
        moved = live[group[live] != live]
        if len(moved) == 0:
            break
        finished = len(moved) < min_fraction * len(live)
        logger.debug("round %d: %d clusters, %d pairs, %d merged", round_number, len(live), len(pairs), len(moved))
        centres = np.unique(group[moved])
        moments[centres] = grouped[centres]
        centre_normals, _, _, eigenvalues = fit_stack(moments[centres])
        normals[centres] = centre_normals
        normal_var[centres] = normal_variance(moments[centres], eigenvalues, coefficient, rule.correlation)
        mse[centres] = eigenvalues[:, 0]
        owner = group[owner]
    return owner, moments, normals, normal_var, mse, pairs, costs


def _group_sums(moments: np.ndarray, members: np.ndarray, groups: np.ndarray, count: int) -> np.ndarray:
    """``(count, 11)`` moment sums of ``members`` added up by their ``groups`` id."""
    sums = np.zeros((count, N_MOMENTS))
    for channel in range(N_MOMENTS):
        sums[:, channel] = np.bincount(groups, weights=moments[members, channel], minlength=count)
    return sums


def _heap_merge(
    moments: np.ndarray,
    normals: np.ndarray,
    normal_var: np.ndarray,
    mse: np.ndarray,
    pairs: np.ndarray,
    costs: np.ndarray,
    rule: _MergeRule,
    coefficient: float,
) -> np.ndarray:
    """Sequential agglomerative clustering with a binary heap; returns the root of every cluster.

    The heap holds ``(cost, a, b, version_a, version_b)``; the cheapest pair is merged. A
    popped pair whose clusters changed since it was queued (or that now belong to other
    clusters) is re-evaluated on the current clusters, once per pair and version, and queued
    again if still allowed. Merging adds moment sums: the merged fit is O(1).
    """
    count = len(moments)
    parent = list(range(count))
    version = [0] * count
    involved = np.unique(pairs).tolist()
    cluster_moments: list[list[float] | None] = [None] * count
    cluster_normal: list[tuple | None] = [None] * count
    cluster_var = [0.0] * count
    cluster_mse = [0.0] * count
    for index, row, normal, variance, error in zip(
        involved,
        moments[involved].tolist(),
        normals[involved].tolist(),
        normal_var[involved].tolist(),
        mse[involved].tolist(),
    ):
        cluster_moments[index] = row
        cluster_normal[index] = normal
        cluster_var[index] = variance
        cluster_mse[index] = error
    zeros = [0] * len(pairs)
    heap = list(zip(costs.tolist(), pairs[:, 0].tolist(), pairs[:, 1].tolist(), zeros, zeros))
    heapq.heapify(heap)
    evaluated: dict[tuple[int, int], tuple[int, int]] = {}
    heappop, heappush = heapq.heappop, heapq.heappush
    coefficient2 = coefficient * coefficient
    add = operator.add
    cost_of = rule.cost
    correlation = rule.correlation

    def find(node: int) -> int:
        while parent[node] != node:
            parent[node] = parent[parent[node]]
            node = parent[node]
        return node

    merges = reevaluations = 0
    while heap:
        _, a, b, va, vb = heappop(heap)
        ra = find(a)
        rb = find(b)
        if ra == rb:
            continue
        if ra == a and rb == b and version[a] == va and version[b] == vb:
            ma, mb = cluster_moments[a], cluster_moments[b]
            if mb[0] > ma[0]:  # the larger cluster keeps its id
                a, b, ma, mb = b, a, mb, ma
            merged = list(map(add, ma, mb))
            mse, lam_mid, z4, nx, ny, nz = fit_scalar(merged, True)
            noise = mse if mse > coefficient2 * z4 else coefficient2 * z4
            parent[b] = a
            cluster_moments[a] = merged
            cluster_moments[b] = None
            cluster_normal[a] = (nx, ny, nz)
            cluster_mse[a] = mse
            gap = lam_mid - mse
            if gap > MIN_GAP_TO_NOISE * noise:
                cluster_var[a] = noise * correlation / (merged[0] * gap)
            else:
                cluster_var[a] = math.inf
            version[a] += 1
            merges += 1
            continue
        key = (ra, rb) if ra < rb else (rb, ra)
        current = (version[key[0]], version[key[1]])
        if evaluated.get(key) == current:
            continue
        evaluated[key] = current
        reevaluations += 1
        cost = cost_of(
            cluster_moments[ra],
            cluster_moments[rb],
            cluster_normal[ra],
            cluster_normal[rb],
            cluster_var[ra],
            cluster_var[rb],
            cluster_mse[ra],
            cluster_mse[rb],
        )
        if cost < 1.0:
            heappush(heap, (cost, ra, rb, version[ra], version[rb]))
    logger.debug("plane clustering heap: %d clusters, %d merges, %d re-evaluations", len(involved), merges, reevaluations)
    roots = np.array(parent, dtype=np.int64)
    while True:
        next_roots = roots[roots]
        if np.array_equal(next_roots, roots):
            return roots
        roots = next_roots


def cluster_blocks(
    moments: np.ndarray,
    planar: np.ndarray,
    grid_shape: tuple[int, int],
    cfg: PlanesConfig,
    coefficient: float,
    max_heap_passes: int = 4,
) -> np.ndarray:
    """Agglomerative hierarchical clustering of the planar blocks of a ``grid_shape`` grid.

    ``moments``: ``(B, 11)`` moment sums per block; ``planar``: ``(B,)`` bool. Returns the
    cluster id (a block index) of every block, -1 for non-planar blocks.
    """
    hb, wb = grid_shape
    rule = _MergeRule(cfg, coefficient)
    labels = np.full(hb * wb, -1, dtype=np.int64)
    planar_index = np.flatnonzero(planar)
    if len(planar_index) == 0:
        return labels
    compact = np.full(hb * wb, -1, dtype=np.int64)
    compact[planar_index] = np.arange(len(planar_index))
    grid = np.arange(hb * wb).reshape(hb, wb)
    block_pairs = np.concatenate(
        [
            np.column_stack([grid[:, :-1].ravel(), grid[:, 1:].ravel()]),
            np.column_stack([grid[:-1, :].ravel(), grid[1:, :].ravel()]),
        ]
    )
    block_pairs = compact[block_pairs]
    block_pairs = block_pairs[(block_pairs[:, 0] >= 0) & (block_pairs[:, 1] >= 0)]
    block_moments = moments[planar_index]
    normals, _, _, eigenvalues = fit_stack(block_moments)
    normal_var = normal_variance(block_moments, eigenvalues, coefficient, rule.correlation)
    owner, cluster_moments, cluster_normals, cluster_var, cluster_mse, pairs, costs = _batch_merge_rounds(
        block_moments, normals, normal_var, eigenvalues[:, 0], block_pairs, rule, coefficient
    )
    # The heap drops a pair that fails the merge test; the pair may pass later, once one of
    # its clusters has grown (its normal is then better determined). A final vectorised check
    # of all adjacent clusters catches those; the heap runs again until none is left.
    count = len(block_moments)
    for _ in range(max_heap_passes):
        if len(pairs) == 0:
            break
        roots = _heap_merge(cluster_moments, cluster_normals, cluster_var, cluster_mse, pairs, costs, rule, coefficient)
        owner = roots[owner]
        live = np.flatnonzero(np.bincount(owner, minlength=count))
        cluster_moments = _group_sums(block_moments, np.arange(count), owner, count)
        fitted_normals, _, _, eigenvalues = fit_stack(cluster_moments[live])
        cluster_normals[live] = fitted_normals
        cluster_var[live] = normal_variance(cluster_moments[live], eigenvalues, coefficient, rule.correlation)
        cluster_mse[live] = eigenvalues[:, 0]
        pairs = _unique_cluster_pairs(owner, block_pairs, count)
        costs = rule.costs(cluster_moments, cluster_normals, cluster_var, cluster_mse, pairs[:, 0], pairs[:, 1])
        allowed = np.isfinite(costs)
        pairs, costs = pairs[allowed], costs[allowed]
    labels[planar_index] = planar_index[owner]
    return labels
