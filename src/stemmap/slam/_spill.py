"""Per-scan state of a long drive in bounded memory: arrays spilled to a temporary file (ours).

A back-end that keeps something for every scan or every detection until the end of the run
(the EKF smoother's association log, the left-out keyframes' measurements of iSAM2's
localisation mode) grows linearly with the drive. These stores keep a bounded number of
recent rows in memory and append older ones as chunks to an anonymous temporary file
(:func:`tempfile.TemporaryFile`: unnamed, removed when closed or when the process ends), to be
read back chunk by chunk, in order or in reverse. The bytes read back are the bytes written,
so a result computed from them does not depend on where the chunks were cut.

* :class:`SpillFile`: the file: a chunk is a tuple of numpy arrays (any dtypes and shapes),
  written once, read back whole by its index; only each chunk's offset, dtypes and shapes
  stay in memory.
* :class:`SpilledRows`: an append-only table of fixed-size records (a structured dtype) with
  at most ``resident_rows`` in memory; :meth:`SpilledRows.chunks` yields every row in order
  (or in reverse), chunk by chunk.
  :meth:`SpilledRows.rows` reads a range of rows, :meth:`SpilledRows.column` one field by
  slices (:class:`SpilledColumn`).
* :class:`SpilledRanges`: a table whose row ranges are written in any order (a backward pass
  writes its blocks last first) and read back by row range.

Used by :class:`stemmap.slam._ekf_smooth.ObservationLog`, the EKF smoother's streamed solves
(:mod:`stemmap.slam._ekf_stream`) and :class:`stemmap.slam._graph_leftout.LeftOutMeasurements`
(docs/reliability.md "Soak").
"""

from __future__ import annotations

import bisect
import tempfile
import weakref
from collections.abc import Iterator, Sequence
from typing import IO

import numpy as np
from numpy.typing import DTypeLike

__all__ = ["SpillFile", "SpilledColumn", "SpilledRanges", "SpilledRows"]


class SpillFile:
    """Chunks of numpy arrays appended to an anonymous temporary file, read back by index.

    The file is opened on the first :meth:`append` (a run that never spills never creates
    one) and removed by :meth:`close` or when the object is collected. Per chunk, memory
    holds its byte offset and its arrays' dtypes and shapes.
    """

    def __init__(self, prefix: str = "stemmap-spill-") -> None:
        self.prefix = prefix
        self._file: IO[bytes] | None = None
        self._chunks: list[tuple[int, tuple[tuple[np.dtype, tuple[int, ...]], ...]]] = []
        self._end = 0  # bytes written
        self._closed = False

    def append(self, arrays: Sequence[np.ndarray]) -> int:
        """Write ``arrays`` as one chunk; returns its index (0, 1, ...)."""
        if self._closed:
            raise ValueError("the spill file is closed")
        if self._file is None:
            # (kept open across calls, closed by close() or when the owner is collected)
            self._file = tempfile.TemporaryFile(prefix=self.prefix)  # noqa: SIM115
            weakref.finalize(self, self._file.close)
        f = self._file
        f.seek(self._end)
        spec = []
        for arr in arrays:
            a = np.ascontiguousarray(arr)
            f.write(a.tobytes())
            spec.append((a.dtype, a.shape))
        self._chunks.append((self._end, tuple(spec)))
        self._end = f.tell()
        return len(self._chunks) - 1

    def read(self, c: int) -> tuple[np.ndarray, ...]:
        """Chunk ``c``'s arrays, as written (new arrays)."""
        if self._closed:
            raise ValueError("the spill file is closed")
        assert self._file is not None
        off, spec = self._chunks[c]
        self._file.seek(off)
        out = []
        for dt, shape in spec:
            count = int(np.prod(shape, dtype=np.int64))
            out.append(np.fromfile(self._file, dtype=dt, count=count).reshape(shape))
        return tuple(out)

    def __len__(self) -> int:
        return len(self._chunks)

    @property
    def nbytes(self) -> int:
        """Bytes written to the file."""
        return self._end

    def close(self) -> None:
        """Remove the file; nothing can be read or appended afterwards."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self._closed = True


class SpilledRows:
    """Append-only records of a structured ``dtype``, at most ``resident_rows`` in memory.

    Rows are appended in a preallocated buffer (grown geometrically from ``capacity`` up to
    ``resident_rows``); when an append would pass ``resident_rows``, the buffer's rows go to
    the :class:`SpillFile` as one chunk and the buffer starts empty again. An append longer
    than ``resident_rows`` is held whole (the bound is then that append). Reading
    (:meth:`chunks`) does not change the store.
    """

    def __init__(
        self, dtype: DTypeLike, *, resident_rows: int = 1 << 16, capacity: int = 1024,
        prefix: str = "stemmap-rows-",
    ) -> None:  # fmt: skip
        if resident_rows < 1:
            raise ValueError(f"resident_rows must be >= 1, got {resident_rows}")
        self.dtype = np.dtype(dtype)
        self.resident_rows = int(resident_rows)
        self._buf = np.zeros(max(1, min(int(capacity), self.resident_rows)), dtype=self.dtype)
        self._n = 0  # resident rows
        self._n_spilled = 0
        self._file = SpillFile(prefix)
        self._starts: list[int] = []  # first row of each spilled chunk
        self._last: tuple[int, np.ndarray] | None = None  # the chunk last read by rows()

    def append(self, **columns: np.ndarray | float | int) -> None:
        """Append ``k`` rows given as one array (or scalar, broadcast) per field; ``k`` is the
        arrays' length (1 when every field is a scalar; nothing when it is 0)."""
        lengths = {int(np.shape(v)[0]) for v in columns.values() if np.ndim(v) > 0}
        if len(lengths) > 1:
            raise ValueError(f"columns of different lengths: {sorted(lengths)}")
        k = lengths.pop() if lengths else 1
        if k == 0:
            return
        n = self._n
        if n + k > self.resident_rows and n:
            self._file.append((self._buf[:n],))
            self._starts.append(self._n_spilled)
            self._n_spilled += n
            n = self._n = 0
        if n + k > self._buf.shape[0]:
            cap = max(n + k, min(2 * self._buf.shape[0], self.resident_rows))
            grown = np.zeros(cap, dtype=self.dtype)
            grown[:n] = self._buf[:n]
            self._buf = grown
        rows = self._buf[n : n + k]
        for name, v in columns.items():
            rows[name] = v
        self._n = n + k

    def __len__(self) -> int:
        return self._n + self._n_spilled

    @property
    def spilled(self) -> int:
        """Rows written to the temporary file."""
        return self._n_spilled

    @property
    def resident_nbytes(self) -> int:
        """Bytes of the in-memory buffer (bounded by ``resident_rows`` records)."""
        return int(self._buf.nbytes)

    def chunks(self, *, reverse: bool = False) -> Iterator[np.ndarray]:
        """Every row, chunk by chunk (record arrays; the resident one is a view), first row
        first; ``reverse``: the chunks last first, each chunk's rows last first."""
        parts = [*range(len(self._file)), None]
        for c in reversed(parts) if reverse else parts:
            rows = self._buf[: self._n] if c is None else self._file.read(c)[0]
            if rows.shape[0]:
                yield rows[::-1] if reverse else rows

    def rows(self, lo: int, hi: int) -> np.ndarray:
        """Rows ``[lo, hi)`` (a new record array; one chunk is read per call that leaves the
        chunk read last, so reading the table in order reads each chunk once)."""
        parts = []
        while lo < hi:
            if lo >= self._n_spilled:
                parts.append(self._buf[lo - self._n_spilled : hi - self._n_spilled])
                break
            c = bisect.bisect(self._starts, lo) - 1
            if self._last is None or self._last[0] != c:
                self._last = (c, self._file.read(c)[0])
            chunk, c0 = self._last[1], self._starts[c]
            parts.append(chunk[lo - c0 : hi - c0])
            lo = c0 + chunk.shape[0]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=self.dtype)

    def column(self, name: str) -> SpilledColumn:
        """Field ``name`` as a read-only array-like (``len``, slices)."""
        return SpilledColumn(self, name)

    def close(self) -> None:
        """Remove the spill file (the resident rows stay readable; nothing more is spilled)."""
        self._last = None
        self._file.close()


class SpilledColumn:
    """One field of a :class:`SpilledRows` read by slices (``col[lo:hi]``, step 1)."""

    def __init__(self, rows: SpilledRows, name: str) -> None:
        self._rows, self._name = rows, name

    def __len__(self) -> int:
        return len(self._rows)

    def __getitem__(self, sl: slice) -> np.ndarray:
        lo, hi, step = sl.indices(len(self._rows))
        if step != 1:
            raise IndexError("SpilledColumn reads slices with step 1 only")
        return self._rows.rows(lo, max(lo, hi))[self._name]


class SpilledRanges:
    """Rows of a table written as blocks ``[lo, lo + len)`` in any order, read back by range.

    Each block is one :class:`SpillFile` chunk (a tuple of arrays with the rows on axis 0);
    memory holds the blocks' ranges and the last block read (sequential reads of a range at a
    time read each block once).
    """

    def __init__(self, prefix: str = "stemmap-ranges-") -> None:
        self._file = SpillFile(prefix)
        self._lo: list[int] = []
        self._hi: list[int] = []
        self._idx: list[int] = []
        self._last: tuple[int, tuple[np.ndarray, ...]] | None = None

    def put(self, lo: int, arrays: Sequence[np.ndarray]) -> None:
        """Write rows ``[lo, lo + len(arrays[0]))`` (ranges must not overlap)."""
        hi = lo + int(np.shape(arrays[0])[0])
        at = bisect.bisect(self._lo, lo)
        self._lo.insert(at, lo)
        self._hi.insert(at, hi)
        self._idx.insert(at, self._file.append(arrays))

    def get(self, lo: int, hi: int) -> tuple[np.ndarray, ...]:
        """Rows ``[lo, hi)`` of every array (copies; the range must have been written)."""
        parts: list[tuple[np.ndarray, ...]] = []
        at = bisect.bisect(self._lo, lo) - 1
        while lo < hi:
            b0, b1, c = self._lo[at], self._hi[at], self._idx[at]
            if not b0 <= lo < b1:
                raise KeyError(f"row {lo} was not written")
            if self._last is None or self._last[0] != c:
                self._last = (c, self._file.read(c))
            parts.append(tuple(a[lo - b0 : min(hi, b1) - b0] for a in self._last[1]))
            lo = min(hi, b1)
            at += 1
        if len(parts) == 1:
            return tuple(a.copy() for a in parts[0])
        return tuple(np.concatenate(cols) for cols in zip(*parts, strict=True))

    def close(self) -> None:
        """Remove the temporary file."""
        self._last = None
        self._file.close()
