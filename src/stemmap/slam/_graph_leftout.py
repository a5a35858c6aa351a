"""The measurements of the keyframes left out of the iSAM2 graph, in bounded memory (ours).

In localisation mode (:mod:`stemmap.slam._graph_revisits`) nearly every keyframe of a revisit
stays out of the graph (the 10x Victoria Park soak of ``benchmarks/soak.py``: 12,984 of
14,498), and its window's measurements are kept for two uses only: the tracker's localisation
on the map at the next restart (the last few keyframes) and the localisation of every
left-out run on the final map after the batch step (:func:`~stemmap.slam._graph_revisits.
localise_skipped`, run by run in keyframe order). The store therefore holds the recent
keyframes in flat arrays and writes older ones to an anonymous temporary file in chunks,
read back chunk by chunk (sequentially) at the end: resident memory is bounded by
``resident_rows`` measurements whatever the drive length, and the results are the same bytes
as an all-in-memory store. On the 10x soak the in-memory store grew by ~0.47 MB per pass
(11,900 measurements of 40 bytes) with capacity doublings of 1.3, 2.6 and 5.2 MB
(docs/reliability.md "Soak", "Where the growth per pass goes"); a drive of one Victoria Park
pass (5,000 measurements) never touches the file.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from stemmap.slam._spill import SpillFile
from stemmap.types import FloatArray

__all__ = ["LeftOutMeasurements"]


class LeftOutMeasurements:
    """The window measurements of the keyframes left out of the graph: a read-only mapping
    ``keyframe -> (trees, bearing, range, sigmas (m, 2))``, filled in increasing keyframe order.

    Resident: flat arrays of the most recent keyframes, 16 bytes per keyframe and 40 per
    measurement (grown geometrically up to ``resident_rows`` measurements). When a keyframe
    would take the resident measurements past ``resident_rows`` (or the resident keyframes
    past ``resident_rows // 4``: transit keyframes have none), every resident keyframe but
    the last ``keep_recent`` (the tracker's localisation reads the last few) is appended to a
    temporary file (:class:`stemmap.slam._spill.SpillFile`: unnamed, removed when closed) as
    one chunk; only the chunk's first and last keyframe and its place in the file stay in
    memory. Reads of spilled keyframes load their whole chunk, cached one at a
    time, so reading in keyframe order reads the file once. ``resident_rows`` bounds the
    memory (~40 bytes each; default 65,536: ~2.6 MB); a keyframe with more measurements than
    that is held whole.
    """

    def __init__(
        self, capacity: int = 256, *, resident_rows: int = 1 << 16, keep_recent: int = 16
    ) -> None:
        if resident_rows < 1 or keep_recent < 0:
            raise ValueError(
                f"resident_rows must be >= 1 and keep_recent >= 0, got {resident_rows} and "
                f"{keep_recent}"
            )
        capacity = max(int(capacity), 1)
        self.resident_rows = int(resident_rows)
        self.keep_recent = int(keep_recent)
        # keyframes without measurements (transit) take no rows: bounded by count as well
        self._max_kf = max(self.resident_rows // 4, self.keep_recent + 1)
        self._kf = np.zeros(capacity, dtype=np.int64)
        self._ptr = np.zeros(capacity + 1, dtype=np.int64)
        rows = min(4 * capacity, self.resident_rows)
        self._tree = np.zeros(rows, dtype=np.int64)
        self._val = np.zeros((rows, 4))  # bearing, range, sigma_b, sigma_r
        self._n = 0  # resident keyframes
        self._n_spilled = 0  # keyframes in the file
        # per chunk in the file (same index): first keyframe, last keyframe
        self._chunks: list[tuple[int, int]] = []
        self._file = SpillFile("stemmap-leftout-")
        self._cached: tuple[int, Any] | None = None  # (chunk, (kf, ptr, tree, val))
        self._alias: np.ndarray | None = None
        self._last = -1  # the last keyframe added (order check)
        self._closed = False

    # -- writing -----------------------------------------------------------------------------
    def add(
        self, k: int, trees: np.ndarray, brg: FloatArray, rng: FloatArray, sig: FloatArray
    ) -> None:
        """Keyframe ``k`` (larger than every one added before) with its ``m`` measurements."""
        m = int(trees.shape[0])
        if self._closed:
            raise ValueError("the store is closed")
        if len(self) and k <= self._last:
            raise ValueError(f"keyframes are added in increasing order: {k} after {self._last}")
        full = int(self._ptr[self._n]) + m > self.resident_rows or self._n >= self._max_kf
        if full and self._n > self.keep_recent:
            self._spill(self._n - self.keep_recent)
        n = self._n
        if n == self._kf.shape[0]:
            self._kf = np.concatenate((self._kf, np.zeros(n, dtype=np.int64)))
            self._ptr = np.concatenate((self._ptr, np.zeros(n, dtype=np.int64)))
        a = int(self._ptr[n])
        if a + m > self._tree.shape[0]:
            cap = max(a + m, min(2 * self._tree.shape[0], self.resident_rows))
            grow = cap - self._tree.shape[0]
            self._tree = np.concatenate((self._tree, np.zeros(grow, dtype=np.int64)))
            self._val = np.concatenate((self._val, np.zeros((grow, 4))))
        self._tree[a : a + m] = trees
        self._val[a : a + m, 0] = brg
        self._val[a : a + m, 1] = rng
        self._val[a : a + m, 2:] = sig
        self._kf[n] = k
        self._ptr[n + 1] = a + m
        self._n = n + 1
        self._last = int(k)

    def _spill(self, q: int) -> None:
        """The oldest ``q`` resident keyframes to the file (one chunk); the rest move up."""
        b = int(self._ptr[q])
        self._file.append((self._kf[:q], self._ptr[: q + 1], self._tree[:b], self._val[:b]))
        self._chunks.append((int(self._kf[0]), int(self._kf[q - 1])))
        self._n_spilled += q
        n, e = self._n, int(self._ptr[self._n])
        self._kf[: n - q] = self._kf[q:n]
        self._ptr[: n - q + 1] = self._ptr[q : n + 1] - b
        self._tree[: e - b] = self._tree[b:e]
        self._val[: e - b] = self._val[b:e]
        self._n = n - q

    def close(self) -> None:
        """Remove the spill file; the store keeps its length (a count for the back-end's
        statistics) but can no longer be read or added to."""
        self._file.close()
        self._cached = None
        self._closed = True

    def __enter__(self) -> LeftOutMeasurements:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- reading -----------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n + self._n_spilled

    @property
    def resident_nbytes(self) -> int:
        """Bytes of the arrays held in memory (the bound ``resident_rows`` applies to)."""
        return sum(a.nbytes for a in (self._kf, self._ptr, self._tree, self._val))

    @property
    def spilled(self) -> int:
        """Keyframes written to the temporary file."""
        return self._n_spilled

    def _chunk(self, c: int) -> Any:
        """Chunk ``c`` as ``(kf, ptr, tree, val)`` arrays (read once, cached one at a time)."""
        if self._cached is not None and self._cached[0] == c:
            return self._cached[1]
        data = self._file.read(c)
        self._cached = (c, data)
        return data

    def _find(self, k: int) -> tuple[Any, int] | None:
        """``((kf, ptr, tree, val), index)`` of keyframe ``k``, None when it is not stored."""
        if self._closed:
            raise ValueError("the store is closed")
        if self._n and k >= self._kf[0]:
            data: Any = (self._kf[: self._n], self._ptr, self._tree, self._val)
        else:
            firsts = [ch[0] for ch in self._chunks]
            c = int(np.searchsorted(firsts, k, side="right")) - 1
            if c < 0 or k > self._chunks[c][1]:
                return None
            data = self._chunk(c)
        kf = data[0]
        i = int(np.searchsorted(kf, k))
        return (data, i) if i < kf.shape[0] and kf[i] == k else None

    def __contains__(self, k: object) -> bool:
        return isinstance(k, (int, np.integer)) and self._find(int(k)) is not None

    def __getitem__(self, k: int) -> tuple[np.ndarray, FloatArray, FloatArray, FloatArray]:
        hit = self._find(int(k))
        if hit is None:
            raise KeyError(k)
        (_, ptr, tree, val), i = hit
        a, b = int(ptr[i]), int(ptr[i + 1])
        v = val[a:b]
        t = tree[a:b] if self._alias is None else self._alias[tree[a:b]]
        return t, v[:, 0], v[:, 1], v[:, 2:]

    def __iter__(self) -> Iterator[int]:
        if self._closed:
            raise ValueError("the store is closed")
        for c in range(len(self._chunks)):
            yield from self._chunk(c)[0].tolist()
        yield from self._kf[: self._n].tolist()

    def remap_trees(self, alias: np.ndarray) -> None:
        """Point every measurement at ``alias[tree]`` (the representatives of merged trees);
        applied on reading (spilled chunks are not rewritten), composed over calls."""
        alias = np.asarray(alias, dtype=np.int64)
        self._alias = alias.copy() if self._alias is None else alias[self._alias]
