"""Shared fixtures. Real-data tests use ``shared_data`` and skip cleanly when ../shared/data is absent."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def _shared_data_dir() -> Path | None:
    env = os.environ.get("LRSLAM_SHARED_DATA")
    for cand in ([Path(env)] if env else []) + [REPO.parent / "shared" / "data"]:
        if cand.is_dir():
            return cand
    return None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to ../shared/data (or $LRSLAM_SHARED_DATA); skips the test when absent."""
    d = _shared_data_dir()
    if d is None:
        pytest.skip("../shared/data not present")
    return d


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def tiny_batch(tmp_path_factory) -> dict:
    """A finished tiny batch (tests/batch_fixtures.py): 9 jobs, 3 of them failing."""
    from batch_fixtures import finished_batch

    return finished_batch(tmp_path_factory.mktemp("batch"))
