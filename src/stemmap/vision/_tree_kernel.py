"""Compiled evaluation of gradient-boosted decision trees (numba; own module so that the cached
kernel is not invalidated by edits elsewhere).

Trees are stored flat: node ``k`` of the forest splits on ``feature[k]`` at ``threshold[k]``
(``x <= threshold`` goes to ``left[k]``, a NaN goes left when ``missing_left[k]``), leaves carry
``value[k]``; tree ``t`` starts at node ``roots[t]`` and child indices are global.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True)
def forest_raw_score(
    X: NDArray[np.float32],
    feature: NDArray[np.int32],
    threshold: NDArray[np.float64],
    left: NDArray[np.int32],
    right: NDArray[np.int32],
    missing_left: NDArray[np.uint8],
    is_leaf: NDArray[np.uint8],
    value: NDArray[np.float64],
    roots: NDArray[np.int64],
    baseline: float,
) -> NDArray[np.float64]:  # pragma: no cover - compiled
    """Sum of the leaf values reached by every row of X, plus the baseline (the raw score /
    log-odds of a binary gradient-boosting model)."""
    n = X.shape[0]
    out = np.full(n, baseline)
    for i in range(n):
        acc = 0.0
        for t in range(roots.shape[0]):
            k = roots[t]
            while not is_leaf[k]:
                x = X[i, feature[k]]
                if np.isnan(x):
                    k = left[k] if missing_left[k] else right[k]
                elif x <= threshold[k]:
                    k = left[k]
                else:
                    k = right[k]
            acc += value[k]
        out[i] += acc
    return out
