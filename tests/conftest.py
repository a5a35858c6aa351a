"""Shared test fixtures: where the real datasets live, and deterministic RNGs."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from stemmap.datasets import find_datasets_dir

DATASETS = find_datasets_dir(Path(__file__).resolve().parent)

# Tests load benchmark scripts by path (importlib); those import their shared helper modules
# (benchmarks/_*.py) by name, as Python allows when a script runs from its own folder.
# Appended, so a benchmark's name never shadows a test helper or an installed module.
_BENCHMARKS = str(Path(__file__).resolve().parents[1] / "benchmarks")
if _BENCHMARKS not in sys.path:
    sys.path.append(_BENCHMARKS)


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """Path to ../shared/datasets; the test is skipped (loudly) if it is absent."""
    if DATASETS is None or not DATASETS.is_dir():
        if os.environ.get("CI"):
            pytest.fail("../shared/datasets is missing in CI; real-data tests cannot run.")
        pytest.skip("../shared/datasets not found (set STEMMAP_DATASETS)")
    return DATASETS


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
