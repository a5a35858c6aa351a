"""The leaf kernels compile without numba's reference counting (stemmap._leaf_jit): the flag
exists in this numba, the hot kernels carry it, and a leaf kernel runs as an ordinary one."""

from __future__ import annotations

import numpy as np

from stemmap import _leaf_jit
from stemmap.scan import _fast_segments, _fit_geometric, _fit_lm


def test_numba_has_the_flag():
    # without it the kernels compile as ordinary njit ones: same results, ~1.6x slower
    assert _leaf_jit.HAS_NRT_FLAG


def test_hot_kernels_are_leaves():
    for kernel in (_fit_lm._cost_and_normal, _fit_lm.levenberg_marquardt, _fit_geometric._fit_one):
        assert kernel.targetoptions.get("_nrt") is False, kernel
    # allocating kernels called from leaves state the runtime explicitly
    for kernel in (_fit_geometric._reject_largest, _fast_segments._geometric_cov):
        assert kernel.targetoptions.get("_nrt") is True, kernel


def test_leaf_kernel_reads_views_and_nrt_callee_allocates():
    @_leaf_jit.nrt_njit()
    def total_sorted(x):  # pragma: no cover - numba
        return np.sort(x)[-1] + 0.0

    @_leaf_jit.leaf_njit()
    def leaf(x, lo, hi):  # pragma: no cover - numba
        v = x[lo:hi]  # a view: no reference counted
        s = 0.0
        for i in range(v.shape[0]):
            s += v[i]
        return s + total_sorted(v)

    x = np.arange(10.0)
    assert leaf(x, 2, 6) == 2.0 + 3.0 + 4.0 + 5.0 + 5.0
