"""Tests of ``stemmap._memory``: the rate-limited heap trim (issue 13, soak)."""

from __future__ import annotations

import ctypes
import sys
import time

import numpy as np
import pytest

import stemmap._memory as memory
from stemmap._memory import HeapTrimmer, malloc_trim


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_trimmer_calls_at_most_once_per_interval() -> None:
    clock, calls = _Clock(), []
    trimmer = HeapTrimmer(10.0, clock=clock, trim=lambda: calls.append(clock.t) or True)
    done = []
    for _ in range(1000):  # a progress callback every 0.25 s for 250 s
        clock.t += 0.25
        done.append(trimmer())
    # 250 s at one trim per >= 10 s: 25 trims, 10 s apart, the first 10 s after construction
    assert trimmer.n_trims == len(calls) == sum(done) == 25
    assert np.allclose(np.diff(calls), 10.0)
    assert calls[0] == pytest.approx(110.0)


def test_trimmer_irregular_calls_keep_the_least_interval() -> None:
    clock, calls = _Clock(), []
    trimmer = HeapTrimmer(5.0, clock=clock, trim=lambda: calls.append(clock.t) or True)
    rng = np.random.default_rng(3)
    for dt in rng.exponential(2.0, 500):
        clock.t += float(dt)
        trimmer()
    assert len(calls) >= 2
    assert np.all(np.diff(calls) >= 5.0)
    # never more than one trim per interval of the run's length
    assert len(calls) <= (clock.t - 100.0) / 5.0


def test_trimmer_zero_interval_trims_every_call_and_bad_interval_is_refused() -> None:
    calls = []
    trimmer = HeapTrimmer(0.0, clock=_Clock(), trim=lambda: calls.append(1) or True)
    assert [trimmer() for _ in range(3)] == [True, True, True]
    assert len(calls) == 3
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="min_interval_s"):
            HeapTrimmer(bad)


def test_malloc_trim_is_a_no_op_where_unsupported(monkeypatch: pytest.MonkeyPatch) -> None:
    memory._libc_trim.cache_clear()
    monkeypatch.setattr(sys, "platform", "darwin")
    try:
        assert memory._libc_trim() is None
        assert malloc_trim() is False
    finally:
        memory._libc_trim.cache_clear()


def test_malloc_trim_without_the_symbol_is_a_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    class NoTrim:  # a C library without malloc_trim (musl)
        def __init__(self, name: object) -> None:
            pass

    memory._libc_trim.cache_clear()
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setattr(ctypes, "CDLL", NoTrim)
    try:
        assert malloc_trim() is False
    finally:
        memory._libc_trim.cache_clear()


@pytest.mark.skipif(memory._libc_trim() is None, reason="needs glibc's malloc_trim")
def test_malloc_trim_on_glibc_returns_freed_pages() -> None:
    # many small blocks (below the mmap threshold: they live in the arena), every other one
    # freed: the free chunks sit below in-use ones, so only malloc_trim can release them
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    blocks = [libc.malloc(64 * 1024) for _ in range(400)]
    try:
        for b in blocks[::2]:
            libc.free(b)
        assert malloc_trim() is True
    finally:
        for b in blocks[1::2]:
            libc.free(b)


def test_trimmers_on_the_process_clock_share_their_interval() -> None:
    """A back-end that trims its own loop (``Isam2Slam``) inside ``stemmap map``'s progress
    callback, which trims too: together no more often than one of them alone."""
    calls: list[str] = []
    outer = HeapTrimmer(0.05, trim=lambda: calls.append("outer") or True)
    inner = HeapTrimmer(0.05, trim=lambda: calls.append("inner") or True)
    t0 = time.process_time()
    while time.process_time() - t0 < 0.06:  # burn CPU past one interval
        pass
    assert inner() is True
    assert outer() is False  # the inner trim just now counts for both
    t0 = time.process_time()
    while time.process_time() - t0 < 0.06:
        pass
    assert outer() is True
    assert inner() is False
    assert calls == ["inner", "outer"]
