"""Property-based fuzzing of every file reader (hypothesis; bounded for CI, issue 13).

Property: a reader given a mutated valid file returns data or raises a StemmapError (the CLI's
one-line ``error:``), never another exception. ``benchmarks/fuzz.py`` runs the long campaign
(>= 100,000 inputs); here each reader gets a few dozen shrinkable mutation lists, ~20-40 s CPU
in total (the image target goes through ``stemmap segment`` and gets fewer examples).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stemmap.io.fuzzing import MUTATION_KINDS, TARGETS, check_input, mutate, write_seeds

_SEEDS: dict[str, bytes] = {}


def _seed(name: str) -> bytes:
    if name not in _SEEDS:
        with tempfile.TemporaryDirectory() as d:
            _SEEDS.update(write_seeds(Path(d), [name]))
    return _SEEDS[name]


ops_strategy = st.lists(
    st.tuples(
        st.integers(0, len(MUTATION_KINDS) - 1),
        st.floats(0.0, 1.0, exclude_max=True),
        st.integers(0, (1 << 16) - 1),
    ),
    min_size=1,
    max_size=4,
)

FAST = [n for n in TARGETS if not n.startswith("image_")]


@pytest.mark.parametrize("name", FAST)
def test_seed_file_reads(name):
    assert check_input(name, _seed(name)) is None


@pytest.mark.parametrize("name", FAST)
@settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(ops=ops_strategy)
def test_reader_never_raises_a_raw_exception(name, ops):
    logging.disable(logging.CRITICAL)
    try:
        tb = check_input(name, mutate(_seed(name), ops))
    finally:
        logging.disable(logging.NOTSET)
    assert tb is None, f"{name} with mutations {ops}:\n{tb}"


@pytest.mark.parametrize("name", ["image_png", "image_jpg"])
@settings(max_examples=5, deadline=None, derandomize=True)
@given(ops=ops_strategy)
def test_segment_on_damaged_images(name, ops):
    tb = check_input(name, mutate(_seed(name), ops))
    assert tb is None, f"{name} with mutations {ops}:\n{tb}"
