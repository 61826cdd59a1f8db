"""Shared test fixtures.

Tests marked ``real`` use the RGB-D sequences in ``../shared/data`` (beside the repository)
and are skipped when that folder is absent.
"""

from __future__ import annotations

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


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder of the shared real sequences (tests using it are marked ``real``)."""
    return SHARED_DATA
