"""Shared test fixtures: the location of ../shared/data and a skip-with-message when it is absent."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

DATA_DIR = Path(os.environ.get("TRISPLAT_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def shared_data(name: str) -> Path:
    """Path of ../shared/data/<name>; skips the test with a clear message when it is not there."""
    p = DATA_DIR / name
    if not p.exists():
        pytest.skip(f"shared test data {p} is absent (set TRISPLAT_SHARED_DATA or put ../shared/data beside the repo)")
    return p


@pytest.fixture
def data_dir():
    return shared_data("")
