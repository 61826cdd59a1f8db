"""Asynchronous bundle adjustment beside tracking: :class:`BundleScheduler`.

Asynchrony (:class:`BundleScheduler`): the problem is gathered (copied) from the live map in the
caller's thread, solved in a worker thread, and applied at the next ``apply_finished`` call,
which waits for the job if needed. The output therefore never depends on thread timing, and the
synchronous mode (same code, solved in the caller's thread) gives bit-identical maps.
"""

from __future__ import annotations

import logging
import weakref
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from jsr.config import BundleAdjustmentConfig, NoiseConfig
from jsr.pipeline.bundle import BundleProblem
from jsr.pipeline.bundle_solution import BundleResult, BundleSolution, apply_solution
from jsr.pipeline.maps import Map, ObjectMap

logger = logging.getLogger(__name__)


class BundleScheduler:
    """Runs bundle adjustment of each map every ``every_keyframes`` keyframes, off the caller's
    thread, with results that do not depend on timing.

    * :meth:`maybe_start` (after a keyframe was added): if due, copies the window into a
      :class:`BundleProblem` now and submits the solve to a single worker thread.
    * :meth:`apply_finished` applies the job of that map at the next call after it was started,
      waiting for it if needed (``wait=True``, the deterministic mode). With ``wait=False`` it
      applies only a job that is already done -- timing-dependent, for callers that prefer that.
    * :meth:`finish` waits and applies; :meth:`shutdown` stops the worker.
    * The sensor's noise (:mod:`~jsr.pipeline.bundle_noise`): each run of the static map
      starts from the components its last applied run estimated (``noise_components``) and
      estimates them again; object maps' runs use them as they are.

    With ``config.asynchronous`` false the solve runs inside :meth:`maybe_start` but is still
    applied at the next :meth:`apply_finished`, so both modes give identical maps. A map with a
    job in flight gets its result applied (waiting) before a new job is started.
    """

    def __init__(self, config: BundleAdjustmentConfig, noise: NoiseConfig, intrinsics_matrix: np.ndarray):
        self.config = config
        self.noise = noise
        self.intrinsics_matrix = np.asarray(intrinsics_matrix, dtype=float).copy()
        self.results: list[BundleResult] = []
        self._executor: ThreadPoolExecutor | None = None
        self._pending: weakref.WeakKeyDictionary[Map, Future] = weakref.WeakKeyDictionary()
        self._started_at: weakref.WeakKeyDictionary[Map, int] = weakref.WeakKeyDictionary()
        # the sensor's noise components (bundle_noise) as the static map's last applied run
        # estimated them; None until then
        self.noise_components: np.ndarray | None = None

    def pending(self, map: Map) -> bool:
        """True if a job of ``map`` was started and not applied yet."""
        return map in self._pending

    def maybe_start(self, map: Map, window: int | None = None) -> bool:
        """Start a run on a snapshot of ``map`` if ``every_keyframes`` keyframes were added since
        the last start; returns True if one was started."""
        config = self.config
        if not config.enabled:
            return False
        count = len(map.keyframes)
        if count - self._started_at.get(map, 0) < config.every_keyframes:
            return False
        if map in self._pending:
            self.apply_finished(map, wait=True)
        self._started_at[map] = count
        problem = BundleProblem.from_map(map, config, self.noise, self.intrinsics_matrix, window)
        if problem is None:
            return False
        arguments = (config, self.noise_components, self._estimates(map))
        if config.asynchronous:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jsr-bundle")
            future = self._executor.submit(problem.solve, *arguments)
        else:
            future = Future()
            try:
                future.set_result(problem.solve(*arguments))
            except Exception as error:  # raised at apply time, as in the asynchronous mode
                future.set_exception(error)
        self._pending[map] = future
        logger.debug("%s: bundle adjustment started at %d keyframes (%s)", map.name, count,
                     "asynchronous" if config.asynchronous else "synchronous")
        return True

    def apply_finished(self, map: Map, wait: bool = True) -> BundleResult | None:
        """Apply the started job of ``map`` (waiting for it if ``wait``); returns its result, or
        None if there was none (or, with ``wait=False``, it is still running)."""
        future = self._pending.get(map)
        if future is None or (not wait and not future.done()):
            return None
        del self._pending[map]
        return self._apply(map, future.result())  # re-raises an error of the worker

    def _apply(self, map: Map, solution: BundleSolution) -> BundleResult:
        """Write ``solution`` into ``map``, keep the noise a static-map run estimated, and
        record the result."""
        apply_solution(map, solution)
        if solution.result.success and self._estimates(map):
            self.noise_components = solution.result.noise_components
        self.results.append(solution.result)
        return solution.result

    def finish(self, map: Map) -> BundleResult | None:
        """Wait for and apply the job of ``map``, if any."""
        return self.apply_finished(map, wait=True)

    def run_global(self, map: Map) -> BundleResult | None:
        """Solve all of ``map``'s keyframes at once (the first held fixed), in the caller's
        thread, and apply the result; None if bundle adjustment is off or there is nothing
        to optimise. Windowed runs correct each window against the fixed keyframes before it,
        so the drift they leave behind stays; one run over the whole map spreads it. It
        starts from (and, for the static map, re-estimates) the sensor's noise."""
        if not self.config.enabled:
            return None
        self.finish(map)
        problem = BundleProblem.from_map(map, self.config, self.noise, self.intrinsics_matrix,
                                         window=len(map.keyframes))
        if problem is None:
            return None
        result = self._apply(map, problem.solve(self.config, self.noise_components, self._estimates(map)))
        logger.info("%s: bundle adjustment over all %d keyframes: cost %.4g -> %.4g in %.1f s",
                    map.name, len(map.keyframes), result.initial_cost, result.final_cost, result.seconds)
        return result

    def _estimates(self, map: Map) -> bool:
        """Whether runs of ``map`` estimate the sensor's noise components: those of the static
        map, with ``estimate_noise``. An object map's windows hold a few hundred observations
        of one object (on a composite, a rendered one whose depth has no noise at all); its
        runs use the static map's estimate, from the same sensor."""
        return self.config.estimate_noise and not isinstance(map, ObjectMap)

    def shutdown(self) -> None:
        """Stop the worker; jobs not applied yet are discarded (call :meth:`finish` first to keep them)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        self._pending = weakref.WeakKeyDictionary()

    def __enter__(self) -> "BundleScheduler":
        return self

    def __exit__(self, *exc_info) -> None:
        self.shutdown()
