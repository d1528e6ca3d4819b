"""Shared fixtures: where the real data of ../shared lives, skipping with a reason when absent."""

from __future__ import annotations

from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = PROJECT_ROOT.parent / "shared" / "data"
SHARED_DOCS = PROJECT_ROOT.parent / "shared" / "docs"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real calibration files and stereo pairs; tests using them skip when ../shared is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it lives beside the project in ../shared/data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def reference_docs() -> Path:
    """State-dict key lists of the authors' and PSMNet's checkpoints."""
    ref = SHARED_DOCS / "reference"
    if not ref.is_dir():
        pytest.skip(f"reference folder {ref} is absent (it lives beside the project in ../shared/docs)")
    return ref
