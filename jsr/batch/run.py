"""Many sequences at once on Dask (:func:`run_batch`): one task per manifest entry.

The tasks run on a local cluster of worker processes (``workers``, one thread each: two
reconstructions never share an interpreter, and each keeps the threads of its own front-end
and bundle adjustment) or on an existing scheduler (``scheduler``, an address such as
``tcp://host:8786``; its workers need jsr installed and must see the sequence and output
folders at the same paths).

Written into ``OUT`` as each task finishes (atomically)::

    OUT/<name>/                 the results folder of entry <name>, as 'jsr reconstruct' writes it
    OUT/batch_summary.csv       one row per entry: name, sequence, status, frames, fps, figures, error
    OUT/batch_summary.json      the same with the batch's settings and per-object figures

A row's ``status`` is ``complete``, ``skipped`` (complete earlier with the same settings),
``failed`` (with its ``error``), ``interrupted`` (stopped while running: its folder holds the
frames done), ``not started`` (the batch stopped first) or, while the batch runs, ``pending``.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import uuid
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Callable

from jsr import __version__
from jsr.batch.manifest import BatchEntry
from jsr.batch.task import BatchSettings, run_entry
from jsr.errors import InputError, OutputError
from jsr.io.writers import write_csv, write_json

logger = logging.getLogger(__name__)

SUMMARY_COLUMNS = ("name", "sequence", "status", "frames", "frames_tracked", "fps", "seconds", "object_maps",
                   "ate_rmse_cm", "objects_true", "objects_matched", "object_t_rmse_cm_max", "object_r_rmse_deg_max",
                   "tracked_share_min", "mask_precision", "mask_recall", "error", "results")
STOP_GRACE_SECONDS = 60.0
"""After Ctrl-C, how long running tasks get to write the frames they have done and stop."""


def default_workers(entries: int) -> int:
    """Worker processes of a local cluster: one per two cores (a reconstruction keeps about two
    threads busy: its front-end's and its bundle adjustment's), at least one, at most one per entry."""
    return max(1, min(entries, (os.cpu_count() or 2) // 2))


class BatchSummary:
    """The rows of a batch by entry, written to ``batch_summary.csv`` and ``.json`` on every change."""

    def __init__(self, out_dir: Path, entries: list[BatchEntry], settings: BatchSettings, cluster: str):
        self.out_dir = Path(out_dir)
        self.header = {"version": __version__, "out": str(self.out_dir), "cluster": cluster,
                       "settings": {key: (str(value) if isinstance(value, Path) else value)
                                    for key, value in asdict(settings).items()}}
        self.status = "running"
        self.rows = {entry.name: {"name": entry.name, "sequence": str(entry.sequence), "status": "pending",
                                  "error": "", "results": str(self.out_dir / entry.name)} for entry in entries}

    def record(self, row: dict) -> None:
        self.rows[row["name"]] = row
        self.write()

    def counts(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for row in self.rows.values():
            counts[row["status"]] = counts.get(row["status"], 0) + 1
        return counts

    def as_dict(self) -> dict:
        return {**self.header, "status": self.status, "counts": self.counts(), "sequences": list(self.rows.values())}

    def write(self) -> None:
        write_json(self.out_dir / "batch_summary.json", self.as_dict())
        write_csv(self.out_dir / "batch_summary.csv", SUMMARY_COLUMNS,
                  ([_cell(row.get(column)) for column in SUMMARY_COLUMNS] for row in self.rows.values()))


def _cell(value):
    return "" if value is None else value


@contextmanager
def _sigint_ignored_by_children():
    """Worker processes started within the block ignore SIGINT (a child keeps an ignored
    signal ignored): Ctrl-C in a terminal reaches the whole process group, and it is the
    client's to decide what stops (the running tasks write the frames they have done)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _client(workers: int | None, scheduler: str | None, entries: int):
    """A Dask client and the local cluster it owns (None with ``scheduler``)."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            return Client(scheduler, timeout="20s"), None
        except (OSError, TimeoutError, ValueError) as error:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {error}") from None
    workers = workers or default_workers(entries)
    # A task whose worker died is not retried: it is recorded as failed, as any other failure.
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), _sigint_ignored_by_children():
        # ":0": any free port for the scheduler's HTTP server, so batches side by side do not collide
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                               memory_limit=0, silence_logs=logging.CRITICAL)
    return Client(cluster), cluster


def run_batch(
    entries: list[BatchEntry],
    out_dir: Path,
    settings: BatchSettings = BatchSettings(),
    workers: int | None = None,
    scheduler: str | None = None,
    on_result: Callable[[dict], None] | None = None,
) -> dict:
    """Run every entry as a Dask task into ``out_dir / name``; returns the batch summary (also
    written, see the module docstring). ``on_result(row)`` is called as each task finishes.
    KeyboardInterrupt (Ctrl-C, SIGTERM in the CLI) stops the batch: running tasks are told to
    stop and get ``STOP_GRACE_SECONDS`` to write the frames they have done; the summary says
    which were interrupted and which did not start; the workers are shut down; then the
    KeyboardInterrupt is raised again."""
    from distributed import as_completed

    out_dir = Path(out_dir).absolute()  # workers elsewhere (--scheduler) write to the same place
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"output path {out_dir} is a file; give a folder")
    if workers is not None and scheduler is not None:
        raise InputError("give --workers (a local cluster) or --scheduler (an existing one), not both")
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OutputError(f"cannot create output folder {out_dir}: {error.strerror}") from None
    summary = BatchSummary(out_dir, entries, settings, scheduler or f"local, {workers or default_workers(len(entries))} "
                           "worker process(es)")
    summary.write()
    try:
        client, cluster = _client(workers, scheduler, len(entries))
    except KeyboardInterrupt:  # before any task ran
        summary.status = "interrupted"
        for row in summary.rows.values():
            row.update(status="not started", error="the batch was stopped")
        summary.write()
        raise
    stop_name = f"jsr-batch-stop-{uuid.uuid4().hex}"
    futures = {}
    try:
        for entry in entries:
            future = client.submit(run_entry, entry, out_dir, settings, stop_name, pure=False,
                                   key=f"jsr-{entry.name}-{uuid.uuid4().hex[:8]}")
            futures[future] = entry
        for future in as_completed(list(futures)):
            row = _row_of(future, futures[future])
            summary.record(row)
            if on_result is not None:
                on_result(row)
        summary.status = "complete"
    except KeyboardInterrupt:
        summary.status = "interrupted"
        _stop(client, stop_name, futures, summary, on_result)
        raise
    finally:
        summary.write()
        client.close()
        if cluster is not None:
            cluster.close()
    return summary.as_dict()


def _row_of(future, entry: BatchEntry) -> dict:
    """The row a finished task returned, or a failed row when the task itself broke (its worker died)."""
    try:
        return future.result()
    except Exception as error:
        return {"name": entry.name, "sequence": str(entry.sequence), "status": "failed",
                "error": f"the task did not finish ({type(error).__name__}: {error})"}


def _stop(client, stop_name: str, futures: dict, summary: BatchSummary, on_result) -> None:
    """Tell running tasks to stop, collect what they return within the grace period, cancel the rest."""
    from distributed import Event, wait

    open_futures = [future for future in futures if summary.rows[futures[future].name]["status"] == "pending"]
    logger.warning("stopping: %d sequence(s) not finished; running ones write the frames they have done",
                   len(open_futures))
    try:
        Event(stop_name, client=client).set()
        wait([f for f in open_futures if f.status == "pending"], timeout=STOP_GRACE_SECONDS)
    except KeyboardInterrupt:  # a second Ctrl-C: stop waiting
        logger.warning("not waiting for the running sequences any longer")
    except Exception:  # the grace period ran out
        logger.debug("stop grace period over", exc_info=True)
    for future in open_futures:
        entry = futures[future]
        if future.status in ("finished", "error"):
            row = _row_of(future, entry)
        else:
            future.cancel()
            row = {"name": entry.name, "sequence": str(entry.sequence), "results": str(summary.out_dir / entry.name),
                   "status": "interrupted" if _started(summary.out_dir / entry.name) else "not started",
                   "error": "the batch was stopped"}
        summary.rows[entry.name] = row
        if on_result is not None and row["status"] != "not started":
            on_result(row)


def _started(results: Path) -> bool:
    """Whether a task began writing ``results`` in this batch (its summary says it is not complete)."""
    import json

    try:
        return json.loads((results / "summary.json").read_text()).get("status") in ("running", "interrupted")
    except (OSError, ValueError):
        return False
