"""Per-scan state spilled to a temporary file (stemmap.slam._spill)."""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.slam._spill import SpilledRows, SpillFile

_ROW = np.dtype([("frame", np.int64), ("value", np.float64)])


def test_spill_file_round_trips_chunks_of_any_dtype_and_shape(rng):
    """Every chunk reads back the arrays written, in any order; the file exists only once
    something was written and is gone after close."""
    f = SpillFile()
    assert len(f) == 0 and f.nbytes == 0 and f._file is None
    chunks = [
        (rng.integers(0, 9, 5), rng.normal(size=(3, 4))),
        (np.zeros(0, dtype=np.int32), rng.normal(size=(2, 2, 2)).astype(np.float32)),
        (np.arange(7, dtype=np.int64)[::2],),  # not contiguous
    ]
    assert [f.append(c) for c in chunks] == [0, 1, 2]
    assert f.nbytes == sum(np.ascontiguousarray(a).nbytes for c in chunks for a in c)
    for i in (2, 0, 1):
        got = f.read(i)
        assert len(got) == len(chunks[i])
        for g, w in zip(got, chunks[i], strict=True):
            assert g.dtype == w.dtype and g.shape == w.shape
            np.testing.assert_array_equal(g, w)
    f.close()
    with pytest.raises(ValueError, match="closed"):
        f.read(0)
    with pytest.raises(ValueError, match="closed"):
        f.append(chunks[0])


@pytest.mark.parametrize("resident_rows", [1 << 16, 7, 1])
def test_spilled_rows_keep_every_row_in_order_within_the_bound(rng, resident_rows):
    """Appends of 0-5 rows (scalars broadcast): every row comes back in order and in reverse,
    whatever the bound; the resident buffer never holds more than ``resident_rows`` (or one
    append) and the rest is in the file."""
    t = SpilledRows(_ROW, resident_rows=resident_rows, capacity=2)
    want_f, want_v = [], []
    for k in range(200):
        m = int(rng.integers(0, 6))
        v = rng.normal(size=m)
        t.append(frame=k, value=v)
        want_f += [k] * m
        want_v += v.tolist()
        assert t._n <= max(resident_rows, 5)
    assert len(t) == len(want_f)
    rows = np.concatenate(list(t.chunks()))
    np.testing.assert_array_equal(rows["frame"], want_f)
    np.testing.assert_array_equal(rows["value"], want_v)
    back = np.concatenate(list(t.chunks(reverse=True)))
    np.testing.assert_array_equal(back, rows[::-1])
    assert (t.spilled > 0) == (resident_rows < len(want_f))
    assert t.resident_nbytes <= max(resident_rows, 5) * _ROW.itemsize
    t.close()
    with pytest.raises(ValueError, match="resident_rows"):
        SpilledRows(_ROW, resident_rows=0)


def test_spilled_rows_resident_memory_stops_growing():
    """The same resident bytes after 20,000 rows as after 2,000 (a 512-row bound)."""
    t = SpilledRows(_ROW, resident_rows=512)
    sizes = []
    for k in range(20_000):
        t.append(frame=k, value=float(k))
        if k + 1 in (2_000, 20_000):
            sizes.append(t.resident_nbytes)
    assert sizes[0] == sizes[1] == 512 * _ROW.itemsize
    assert t.spilled >= 20_000 - 512
    assert sum(c.shape[0] for c in t.chunks()) == 20_000


def test_spilled_rows_read_by_range_and_by_column(rng):
    """``rows(lo, hi)`` and a column's slices give the rows appended, across the spilled
    chunks and the resident buffer, in any order of reads."""
    t = SpilledRows(_ROW, resident_rows=5, capacity=2)
    vals = rng.normal(size=23)
    for lo in range(0, 23, 3):
        t.append(frame=np.arange(lo, min(lo + 3, 23)), value=vals[lo : lo + 3])
    assert t.spilled > 10
    col = t.column("value")
    assert len(col) == 23
    for lo, hi in ((0, 23), (4, 17), (20, 23), (9, 10), (0, 0), (16, 4)):
        np.testing.assert_array_equal(t.rows(lo, hi)["frame"], np.arange(lo, max(lo, hi)))
        np.testing.assert_array_equal(col[lo:hi], vals[lo:hi])
    with pytest.raises(IndexError):
        col[::2]
