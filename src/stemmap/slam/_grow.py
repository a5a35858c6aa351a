"""Growable arrays for the online mapper's per-scan and per-tree bookkeeping (ours).

:class:`_Grow` keeps a NumPy buffer and a fill count so the numba front-end
(:func:`~stemmap.slam._isam2_track.track_keyframe`) reads contiguous arrays while scans and
trees are appended one at a time: capacity doubles when full (amortised O(1) append).
"""

from __future__ import annotations

from typing import Any

import numpy as np


class _Grow:
    """A growable float/int array with amortised O(1) append along axis 0."""

    def __init__(self, shape: tuple[int, ...], dtype: Any = np.float64, fill: float = 0.0):
        self.a = np.full((256, *shape), fill, dtype=dtype)
        self.n = 0
        self.fill = fill

    def room(self, extra: int) -> None:
        need = self.n + extra
        if need > self.a.shape[0]:
            b = np.full(
                (max(need, 2 * self.a.shape[0]), *self.a.shape[1:]), self.fill, self.a.dtype
            )
            b[: self.n] = self.a[: self.n]
            self.a = b

    def append(self, v: Any) -> None:
        self.room(1)
        self.a[self.n] = v
        self.n += 1

    def extend(self, v: Any) -> None:
        v = np.asarray(v)
        self.room(v.shape[0])
        self.a[self.n : self.n + v.shape[0]] = v
        self.n += v.shape[0]
