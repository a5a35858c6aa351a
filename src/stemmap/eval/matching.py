"""One-to-one matching of detections to ground truth (Hungarian assignment with a distance gate)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from stemmap.errors import InputError

__all__ = ["Matching", "match_points"]


@dataclass(frozen=True, eq=False)
class Matching:
    """Result of :func:`match_points`.

    ``pairs`` is (M, 2) int: (detection index, truth index); ``distances`` (M,) metres.
    ``unmatched_detections`` / ``unmatched_truth`` hold the remaining indices.
    """

    pairs: np.ndarray
    distances: np.ndarray
    unmatched_detections: np.ndarray
    unmatched_truth: np.ndarray

    @property
    def n_matched(self) -> int:
        return int(self.pairs.shape[0])


def match_points(detections: ArrayLike, truth: ArrayLike, gate: float) -> Matching:
    """Minimum-total-distance one-to-one matching of (N, 2) detections to (M, 2) truth.

    Pairs farther apart than ``gate`` (metres) are never matched.
    """
    d = np.asarray(detections, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(truth, dtype=np.float64).reshape(-1, 2)
    if not gate > 0:
        raise InputError(f"gate must be > 0 m, got {gate}.")
    if d.shape[0] == 0 or t.shape[0] == 0:
        return Matching(
            np.zeros((0, 2), dtype=np.int64),
            np.zeros(0),
            np.arange(d.shape[0]),
            np.arange(t.shape[0]),
        )
    cost = cdist(d, t)
    big = 1e6 + cost.max()
    rows, cols = linear_sum_assignment(np.where(cost <= gate, cost, big))
    ok = cost[rows, cols] <= gate
    rows, cols = rows[ok], cols[ok]
    return Matching(
        np.column_stack((rows, cols)).astype(np.int64),
        cost[rows, cols],
        np.setdiff1d(np.arange(d.shape[0]), rows),
        np.setdiff1d(np.arange(t.shape[0]), cols),
    )
