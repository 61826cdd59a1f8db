"""One sequence of a batch, as a task that runs on a Dask worker (:func:`run_entry`).

The task runs :func:`jsr.pipeline.run.run_reconstruction` into ``OUT/<name>`` exactly as
``jsr reconstruct`` does (same config, same seed, so the same files), then, when the sequence
has ground truth, evaluates the results as ``jsr evaluate`` does (figures only: no
``metrics.json`` is added to the folder). It never raises: whatever happens becomes the
``status`` and ``error`` of the row it returns, so one failing sequence does not stop the
others. A run whose results are already there and complete with the same settings is skipped.
"""

from __future__ import annotations

import json
import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from jsr.batch.manifest import BatchEntry
from jsr.errors import JsrError

logger = logging.getLogger(__name__)

STOP_CHECK_SECONDS = 1.0
"""How often a running task asks the scheduler whether the batch was stopped (one round trip)."""

MAX_WARNINGS = 20
"""Warnings of a task kept in its row (the first ones, without repeats)."""


class _WarningCollector(logging.Handler):
    """Keeps the warnings jsr logs during a task for its row, instead of the worker's stderr
    (which, on a local cluster, is the user's terminal, in the middle of the progress bar)."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if message not in self.messages and len(self.messages) < MAX_WARNINGS:
            self.messages.append(message)


@contextmanager
def _warnings_collected():
    """Within the block, warnings of the ``jsr`` loggers go to the collector it yields only."""
    library_logger = logging.getLogger("jsr")
    collector = _WarningCollector()
    saved = list(library_logger.handlers), library_logger.propagate, library_logger.level
    library_logger.handlers[:] = [collector]
    library_logger.propagate = False
    library_logger.setLevel(min(library_logger.getEffectiveLevel(), logging.WARNING))
    try:
        yield collector
    finally:
        library_logger.handlers[:], library_logger.propagate = saved[0], saved[1]
        library_logger.setLevel(saved[2])


@dataclass(frozen=True)
class BatchSettings:
    """What applies to every entry: a config file and overrides (the entry's own ``set`` comes
    after them), ``save_masks`` and ``render`` as the options of ``jsr reconstruct``, and
    ``force`` to redo runs that are complete."""

    config_file: Path | None = None
    overrides: tuple[str, ...] = ()
    save_masks: bool = False
    render: bool = False
    force: bool = False


class BatchStopped(KeyboardInterrupt):
    """The batch was stopped (Ctrl-C on the client): the run writes the frames done and stops."""


class StopSignal:
    """The Dask event ``name`` that the client sets to stop the batch, seen from a task.
    :meth:`check` is an ``on_frame`` callback: it raises :class:`BatchStopped` once the event is
    set, asking the scheduler at most every ``STOP_CHECK_SECONDS``."""

    def __init__(self, name: str):
        from distributed import Event

        self.event = Event(name)
        self.last_check = time.monotonic()

    def is_set(self) -> bool:
        return self.event.is_set()

    def check(self, _report=None) -> None:
        now = time.monotonic()
        if now - self.last_check >= STOP_CHECK_SECONDS:
            self.last_check = now
            if self.event.is_set():
                raise BatchStopped("the batch was stopped")


def up_to_date(results: Path, sequence, config, save_masks: bool, render: bool = False) -> tuple[bool, str]:
    """Whether ``results`` holds a complete run of ``sequence`` (an opened
    :class:`~jsr.io.dataset.RGBDSequence`) with ``config``; and if not, why."""
    from jsr.config import config_to_yaml
    from jsr.io.writers import read_csv

    try:
        summary = json.loads((results / "summary.json").read_text())
        config_text = (results / "config.yaml").read_text()
    except (OSError, ValueError):
        return False, "no results yet"
    if summary.get("status") != "complete":
        return False, f"the earlier run is {summary.get('status')}"
    selection = summary.get("input") or {}
    if config_text != config_to_yaml(config):
        return False, "the config differs"
    if (selection.get("sequence") != str(sequence.root) or selection.get("frames_selected") != len(sequence)
            or selection.get("intrinsics") != sequence.intrinsics.to_dict()):
        return False, "the sequence, its frames or its intrinsics differ"
    try:
        first = read_csv(results / "landmarks.csv")[0]
        if float(first["timestamp"]) != float(sequence.entries[0].timestamp):
            return False, "the first frame differs"
    except (OSError, IndexError, KeyError, ValueError):
        return False, "no readable landmarks.csv"
    if save_masks and not (results / "masks").is_dir():
        return False, "the earlier run saved no masks"
    if render and not (results / "plots" / "static_view_1.png").is_file():
        return False, "the earlier run rendered no previews"
    return True, "complete with the same settings"


def _run_figures(summary: dict) -> dict:
    return {
        "frames": summary.get("frames_processed"),
        "frames_tracked": summary.get("frames_tracked"),
        "fps": summary.get("fps"),
        "seconds": summary.get("seconds"),
        "object_maps": len(summary.get("objects") or []),
    }


def evaluation_figures(metrics: dict) -> dict:
    """The figures of a batch row from :func:`jsr.evaluate.run.evaluate_run`'s metrics: camera
    ATE RMSE, and per true object the matched map's pose error and tracked share (the worst
    over the objects in the flat columns), mask precision and recall."""
    camera = metrics.get("camera") or {}
    figures = {"ate_rmse_cm": _scaled((camera.get("ate") or {}).get("rmse"), 100.0)}
    objects = metrics.get("objects")
    if objects is not None:
        matches = objects.get("matches") or []
        figures.update(
            objects_true=len(objects.get("true") or []),
            objects_matched=len(matches),
            object_t_rmse_cm_max=_worst(matches, "translation_rmse_cm", max),
            object_r_rmse_deg_max=_worst(matches, "rotation_rmse_deg", max),
            tracked_share_min=_worst(matches, "tracked_share", min),
            object_matches=[{key: match.get(key) for key in (
                "estimated_id", "true_id", "frames", "translation_rmse_cm", "rotation_rmse_deg", "tracked_share",
                "further_maps")} for match in matches],
        )
    masks = metrics.get("masks")
    if masks:
        figures.update(mask_precision=masks.get("precision"), mask_recall=masks.get("recall"))
    return figures


def _scaled(value, factor: float):
    return None if value is None else value * factor


def _worst(matches: list[dict], key: str, pick):
    values = [match[key] for match in matches if match.get(key) is not None]
    return pick(values) if values else None


def run_entry(entry: BatchEntry, out_dir: Path, settings: BatchSettings, stop_event: str | None = None) -> dict:
    """Reconstruct ``entry`` into ``out_dir / entry.name`` (or skip it when its results are up
    to date) and return its row: ``name, sequence, results, status`` (``complete``,
    ``skipped``, ``failed`` or ``interrupted``), ``error``, the run's figures and, with ground
    truth, the evaluation's, and the ``warnings`` jsr logged meanwhile. ``stop_event`` names a
    Dask event that stops the run when set."""
    with _warnings_collected() as collector:
        row = _run_entry(entry, out_dir, settings, stop_event)
    row["warnings"] = collector.messages
    return row


def _run_entry(entry: BatchEntry, out_dir: Path, settings: BatchSettings, stop_event: str | None) -> dict:
    from jsr.config import load_config
    from jsr.io.dataset import check_first_frame
    from jsr.io.run_folder import prepare_output_folder
    from jsr.pipeline.run import open_configured_sequence, run_reconstruction

    results = Path(out_dir) / entry.name
    row = {"name": entry.name, "sequence": str(entry.sequence), "results": str(results), "status": "failed",
           "error": ""}
    stop = StopSignal(stop_event) if stop_event is not None else None
    if stop is not None and stop.is_set():  # the batch stopped while this task waited for a worker
        return {**row, "status": "not started", "error": "the batch was stopped"}
    try:
        config = load_config(settings.config_file, [*settings.overrides, *entry.overrides])
        sequence = open_configured_sequence(entry.sequence, config, preset=entry.preset, start=entry.start,
                                            max_frames=entry.max_frames)
        check_first_frame(sequence)
        done, why = (False, "--force") if settings.force else up_to_date(results, sequence, config,
                                                                         settings.save_masks, settings.render)
        if done:
            logger.info("%s: skipped (%s)", entry.name, why)
            summary = json.loads((results / "summary.json").read_text())
            row["status"] = "skipped"
        else:
            logger.info("%s: reconstructing (%s)", entry.name, why)
            prepare_output_folder(results, overwrite=True)
            summary = run_reconstruction(sequence, config, results, on_frame=None if stop is None else stop.check,
                                         save_masks=settings.save_masks)
            row["status"] = "complete"
            if settings.render:
                row.update(_render(results))
        row.update(_run_figures(summary))
        if (Path(entry.sequence) / "groundtruth.txt").is_file():
            row.update(_evaluation(results, entry.sequence))
    except KeyboardInterrupt:  # BatchStopped: the run wrote the frames done
        row["status"], row["error"] = "interrupted", "the batch was stopped"
        row.update(_figures_on_disk(results))
    except JsrError as error:
        row["error"] = str(error)
    except Exception as error:  # a bug: recorded, and the batch goes on
        logger.debug("%s: traceback", entry.name, exc_info=True)
        row["error"] = f"internal error ({type(error).__name__}: {error})"
    return row


def _render(results: Path) -> dict:
    from jsr.export.render import render_results

    try:
        render_results(results)
        return {}
    except JsrError as error:  # the run stands; it has no previews (e.g. no mesh: nothing was fused)
        return {"render_error": str(error)}


def _evaluation(results: Path, sequence: Path) -> dict:
    from jsr.evaluate.run import evaluate_run

    try:
        return evaluation_figures(evaluate_run(results, sequence))
    except JsrError as error:  # the run stands; its figures could not be measured
        return {"evaluation_error": str(error)}


def _figures_on_disk(results: Path) -> dict:
    try:
        return _run_figures(json.loads((results / "summary.json").read_text()))
    except (OSError, ValueError):
        return {}
