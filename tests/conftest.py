"""Shared test fixtures.

Tests marked ``real`` use the RGB-D sequences in ``../shared/data`` (beside the repository)
and are skipped when that folder is absent.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def pytest_collection_modifyitems(config, items):
    if SHARED_DATA.is_dir():
        return
    skip_real = pytest.mark.skip(reason=f"real sequences not found at {SHARED_DATA}")
    for item in items:
        if "real" in item.keywords:
            item.add_marker(skip_real)


@pytest.fixture(autouse=True)
def library_logging_restored():
    """The CLI configures the ``jsr`` logger (its own handler, a level, no propagation) when a
    test runs a command; each test gets it back as it was, so ``caplog`` sees library logs."""
    library_logger = logging.getLogger("jsr")
    state = list(library_logger.handlers), library_logger.level, library_logger.propagate
    yield
    library_logger.handlers[:] = state[0]
    library_logger.setLevel(state[1])
    library_logger.propagate = state[2]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder of the shared real sequences (tests using it are marked ``real``)."""
    return SHARED_DATA


SYNTH_SEQUENCE_OPTIONS = dict(frames=16, objects=1, motion="jump", width=160, height=120, seed=0)
"""Options of the ``synth_sequence`` fixture (for :class:`jsr.synth.options.SynthOptions`)."""


@pytest.fixture(scope="session")
def synth_sequence(tmp_path_factory) -> Path:
    """A small synthetic TUM-layout sequence (160x120, 16 frames, one jumping object, seed 0),
    written once per test session by :func:`jsr.synth.write.generate_sequence`. Do not modify it."""
    from jsr.synth.options import SynthOptions
    from jsr.synth.write import generate_sequence

    root = tmp_path_factory.mktemp("synth") / "sequence"
    generate_sequence(root, SynthOptions(**SYNTH_SEQUENCE_OPTIONS))
    return root
