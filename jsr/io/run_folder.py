"""The output folder of a run: refuse to clobber results, clear them only when asked."""

from __future__ import annotations

import shutil
from pathlib import Path

from jsr.errors import OutputError

# Files and folders that jsr writes into a results folder; only these are ever removed.
RESULT_ENTRIES = (
    "config.yaml",
    "summary.json",
    "camera.tum",
    "landmarks.csv",
    "timings.csv",
    "metrics.json",
    "scene.ply",
    "static",
    "objects",
    "masks",
    "plots",
)
RESULT_MARKERS = ("config.yaml", "summary.json")


def is_results_folder(path: Path) -> bool:
    """True if ``path`` looks like a folder written by ``jsr reconstruct``."""
    return any((Path(path) / marker).exists() for marker in RESULT_MARKERS)


def prepare_output_folder(path: Path, overwrite: bool = False) -> Path:
    """Create ``path`` for new results.

    An existing empty folder is used as is. A folder holding earlier jsr results is
    refused unless ``overwrite``, in which case only the entries jsr writes are removed.
    A non-empty folder that is not a jsr results folder is always refused: jsr never
    deletes files it did not write.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"output path {path} is a file; give a folder")
    if path.is_dir() and any(path.iterdir()):
        if not is_results_folder(path):
            raise OutputError(f"output folder {path} is not empty and holds no jsr results; choose a new or empty folder")
        if not overwrite:
            raise OutputError(f"output folder {path} already holds results; pass --overwrite or choose another folder")
        for name in RESULT_ENTRIES:
            entry = path / name
            if entry.is_dir():
                shutil.rmtree(entry)
            elif entry.exists():
                entry.unlink()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OutputError(f"cannot create output folder {path}: {error.strerror}") from None
    return path
