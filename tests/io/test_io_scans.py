"""Scan files: NPZ / CSV round trips, damaged frames skipped, unreadable files rejected."""

from __future__ import annotations

import doctest
import logging
import math
import types
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import stemmap.io.scans as scans_mod
from stemmap.errors import InputError
from stemmap.io import (
    SkippedFrame,
    iter_scans,
    read_scans,
    read_scans_indexed,
    stack_scans,
    write_scans_csv,
    write_scans_npz,
)
from stemmap.types import LaserScan, ScanBatch


def _batch(rng: np.random.Generator, s: int = 20, n: int = 181) -> ScanBatch:
    r = rng.uniform(0.2, 25.0, size=(s, n))
    r[rng.random((s, n)) < 0.1] = np.nan  # no return
    r[rng.random((s, n)) < 0.02] = np.inf  # max-range reading
    return ScanBatch(
        r,
        100.0 + 0.025 * np.arange(s),
        -math.pi / 2,
        math.radians(1.0),
        range_min=0.05,
        range_max=30.0,
        frame="front_laser",
    )


def _same(a: ScanBatch, b: ScanBatch) -> None:
    # exact: both formats store float64 losslessly (NaN and inf included)
    np.testing.assert_array_equal(a.ranges, b.ranges)
    np.testing.assert_array_equal(a.times, b.times)
    assert (a.angle_min, a.angle_increment) == (b.angle_min, b.angle_increment)
    assert (a.range_min, a.range_max, a.frame) == (b.range_min, b.range_max, b.frame)


@pytest.mark.parametrize(("writer", "ext"), [(write_scans_npz, ".npz"), (write_scans_csv, ".csv")])
def test_round_trip_is_exact(
    tmp_path: Path, rng: np.random.Generator, writer: object, ext: str
) -> None:
    b = _batch(rng)
    p = tmp_path / f"scans{ext}"
    writer(p, b)  # type: ignore[operator]
    skipped: list[SkippedFrame] = []
    _same(b, read_scans(p, skipped=skipped))
    assert skipped == []
    lazy = list(iter_scans(p))
    assert len(lazy) == len(b)
    np.testing.assert_array_equal(lazy[3].ranges, b.ranges[3])
    assert lazy[3].time == b.times[3]


def test_uncompressed_npz_and_infinite_range_max(tmp_path: Path) -> None:
    b = ScanBatch(np.ones((2, 4)), np.array([0.0, 1.0]), 0.0, 0.1)  # range_max = inf
    for compress in (True, False):
        p = tmp_path / f"s{compress}.npz"
        write_scans_npz(p, b, compress=compress)
        _same(b, read_scans(p))
    write_scans_csv(tmp_path / "s.csv", b)
    assert read_scans(tmp_path / "s.csv").range_max == math.inf


def test_npz_written_by_hand_with_minimal_fields(tmp_path: Path) -> None:
    p = tmp_path / "hand.npz"
    np.savez(
        p,
        ranges=np.full((3, 5), 4, dtype=np.int32),  # integer millimetres? no: metres, promoted
        times=np.array([0.0, 0.1, 0.2], dtype=np.float32),  # 'times' accepted as alias
        angle_min=-0.5,
        angle_increment=0.25,
    )
    b = read_scans(p)
    assert b.ranges.dtype == np.float64 and b.n_beams == 5 and len(b) == 3
    assert b.range_min == 0.0 and b.range_max == math.inf and b.frame == "laser"


def test_iter_scans_is_lazy(tmp_path: Path, rng: np.random.Generator) -> None:
    b = _batch(rng, s=50)
    p = tmp_path / "long.csv"
    write_scans_csv(p, b)
    it = iter_scans(p)
    assert isinstance(it, types.GeneratorType)
    first = next(it)
    assert isinstance(first, LaserScan) and first.time == b.times[0]
    it.close()


# ---------------------------------------------------------------- damaged frames: skipped


def test_csv_truncated_row_and_bad_value_are_skipped(
    tmp_path: Path, rng: np.random.Generator, caplog: pytest.LogCaptureFixture
) -> None:
    b = _batch(rng, s=6, n=10)
    p = tmp_path / "s.csv"
    write_scans_csv(p, b)
    lines = p.read_text().splitlines()
    # lines[0] comment, [1] header, [2..7] scans 0..5
    lines[3] = lines[3].rsplit(",", 3)[0]  # scan 1: truncated (3 beams missing)
    lines[5] = lines[5].replace(",", ",abc,", 1).rsplit(",", 1)[0]  # scan 3: non-number
    lines[6] = "nan" + lines[6][lines[6].index(",") :]  # scan 4: NaN time -> invalid
    p.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][: len(lines[-1]) // 2])  # scan 5 cut
    skipped: list[SkippedFrame] = []
    with caplog.at_level(logging.WARNING):
        got = read_scans(p, skipped=skipped)
    assert [s.frame_index for s in skipped] == [1, 3, 4, 5]
    assert "truncated" in skipped[0].reason and "line 4" in skipped[0].reason
    np.testing.assert_array_equal(got.times, b.times[[0, 2]])
    np.testing.assert_array_equal(got.ranges, b.ranges[[0, 2]])
    assert sum("skipping scan" in r.message for r in caplog.records) == 4
    assert read_scans_indexed(p)[1].tolist() == [0, 2]


def test_csv_empty_fields_are_no_return(tmp_path: Path) -> None:
    p = tmp_path / "s.csv"
    p.write_text(
        "time,angle_min,angle_increment,range_min,range_max,r0,r1,r2\n0.5,0,0.1,,,1.5,,3\n"
    )
    b = read_scans(p)
    assert b.range_min == 0.0 and b.range_max == math.inf
    np.testing.assert_array_equal(b.ranges, [[1.5, np.nan, 3.0]])


def test_npz_nan_time_frame_is_skipped(tmp_path: Path) -> None:
    p = tmp_path / "s.npz"
    t = np.array([0.0, np.nan, 0.2])
    np.savez(p, ranges=np.ones((3, 4)), time=t, angle_min=0.0, angle_increment=0.1)
    skipped: list[SkippedFrame] = []
    b = read_scans(p, skipped=skipped)
    assert len(b) == 2 and [s.frame_index for s in skipped] == [1]
    assert [i for i, _ in scans_mod._indexed(p, None, None)] == [0, 2]
    assert read_scans_indexed(p)[1].tolist() == [0, 2]


def test_stack_scans_keeps_dominant_geometry(caplog: pytest.LogCaptureFixture) -> None:
    def scan(t: float, n: int, amin: float = -1.0) -> LaserScan:
        return LaserScan(np.full(n, 2.0), amin, 0.01, time=t, range_max=20.0)

    scans = [scan(0, 100), scan(1, 90), scan(2, 100), scan(3, 100, amin=-1.2), scan(4, 100)]
    skipped: list[SkippedFrame] = []
    with caplog.at_level(logging.WARNING):
        b = stack_scans(scans, skipped=skipped, indices=[10, 11, 12, 13, 14], source="x.bag")
    np.testing.assert_array_equal(b.times, [0, 2, 4])
    assert [s.frame_index for s in skipped] == [11, 13]
    assert "90 beams" in skipped[0].reason and "differs" in skipped[0].reason
    assert any(
        "mixes beam geometries" in r.message and "x.bag" in r.message for r in caplog.records
    )


def test_stack_scans_narrower_range_window_masks_out_of_window_returns() -> None:
    a = LaserScan(np.array([0.5, 5.0, 25.0]), 0.0, 0.1, time=0, range_min=0.1, range_max=30.0)
    b = LaserScan(np.array([0.5, 5.0, 25.0]), 0.0, 0.1, time=1, range_min=1.0, range_max=20.0)
    batch = stack_scans([a, b])
    assert (batch.range_min, batch.range_max) == (0.1, 30.0)
    np.testing.assert_array_equal(batch.ranges, [[0.5, 5.0, 25.0], [np.nan, 5.0, np.nan]])
    # every return valid in the batch was valid for its own sensor window
    assert batch.ranges[1][np.isfinite(batch.ranges[1])].tolist() == [5.0]


# ---------------------------------------------------------------- unreadable files: InputError


def test_missing_file_and_unknown_format(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        read_scans(tmp_path / "nope.npz")
    with pytest.raises(InputError, match="does not exist"):
        read_scans(tmp_path / "nope.csv")
    (tmp_path / "x.json").write_text("{}")
    with pytest.raises(InputError, match="cannot tell the scan format"):
        read_scans(tmp_path / "x.json")


def test_truncated_npz(tmp_path: Path, rng: np.random.Generator) -> None:
    p = tmp_path / "s.npz"
    write_scans_npz(p, _batch(rng), compress=False)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"s\.npz.*truncated"):
        read_scans(p)


@pytest.mark.parametrize("compress", [True, False])
def test_corrupted_npz_bytes(tmp_path: Path, rng: np.random.Generator, compress: bool) -> None:
    p = tmp_path / "s.npz"
    write_scans_npz(p, _batch(rng), compress=compress)
    data = bytearray(p.read_bytes())
    i = len(data) // 2
    data[i : i + 64] = bytes(64)  # a damaged disk block in the middle of 'ranges'
    p.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"field 'ranges' cannot be read \(Bad CRC-32"):
        read_scans(p)


def test_npz_with_object_array_is_refused_without_unpickling(tmp_path: Path) -> None:
    p = tmp_path / "evil.npz"
    np.savez(
        p,
        ranges=np.array([[1.0, "x"]], dtype=object),
        time=np.zeros(1),
        angle_min=0.0,
        angle_increment=0.1,
    )
    with pytest.raises(InputError, match=r"'ranges'.*no pickle"):
        read_scans(p)


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"time": np.zeros(2), "angle_min": 0.0, "angle_increment": 0.1}, "lacks field.*ranges"),
        ({"ranges": np.ones((2, 3)), "angle_min": 0.0, "angle_increment": 0.1}, "lacks.*time"),
        (
            {"ranges": np.ones(3), "time": np.zeros(1), "angle_min": 0.0, "angle_increment": 0.1},
            r"shape \(S, N\)",
        ),
        (
            {"ranges": np.ones((2, 3)), "time": np.zeros(3), "angle_min": 0, "angle_increment": 1},
            r"'time' must have shape \(2,\)",
        ),
        (
            {"ranges": np.array([["a", "b"]]), "time": [0.0], "angle_min": 0, "angle_increment": 1},
            "dtype <U1",
        ),
        (
            {"ranges": np.ones((1, 3)), "time": [0.0], "angle_min": [0, 1], "angle_increment": 1},
            "'angle_min' must be a scalar",
        ),
        (
            {"ranges": np.ones((1, 3)), "time": [0.0], "angle_min": 0, "angle_increment": 0.0},
            "angle_increment must be non-zero",
        ),
        (
            {"ranges": np.ones((2, 3)), "time": [np.nan] * 2, "angle_min": 0, "angle_increment": 1},
            "no scan",
        ),
    ],
)
def test_malformed_npz(tmp_path: Path, fields: dict[str, object], match: str) -> None:
    p = tmp_path / "bad.npz"
    np.savez(p, **fields)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=match):
        read_scans(p)


def test_npy_and_garbage_files(tmp_path: Path) -> None:
    p = tmp_path / "single.npz"
    with p.open("wb") as fh:
        np.save(fh, np.ones((2, 3)))
    with pytest.raises(InputError, match="single array"):
        read_scans(p)
    q = tmp_path / "garbage.npz"
    q.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match="cannot be read"):
        read_scans(q)
    z = tmp_path / "nokeys.npz"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("readme.txt", "hello")
    with pytest.raises(InputError, match="lacks field"):
        read_scans(z)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "empty"),
        ("# only a comment\n\n", "empty"),
        ("time,x,y\n1,2,3\n", "header must start with"),
        ("time,angle_min,angle_increment,range_min,range_max\n1,0,0.1,0,10\n", "header must"),
        (
            "time,angle_min,angle_increment,range_min,range_max,r0\n1,0,0.1,0,10,1,2\n",
            "no usable laser scan.*1 damaged",
        ),
    ],
)
def test_malformed_csv(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        read_scans(p)


def test_binary_csv(tmp_path: Path) -> None:
    p = tmp_path / "bin.csv"
    p.write_bytes(b"\xff\xfe\x00\x81binary")
    with pytest.raises(InputError, match="not UTF-8"):
        read_scans(p)


def test_docstring_examples_run() -> None:
    res = doctest.testmod(scans_mod, optionflags=doctest.ELLIPSIS)
    assert res.failed == 0 and res.attempted > 0


@settings(max_examples=30, deadline=None)
@given(
    arrays(
        np.float64,
        st.tuples(st.integers(1, 4), st.integers(1, 6)),
        elements=st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True),
    ),
    st.floats(-math.pi, math.pi),
    st.floats(1e-6, 0.1),
)
def test_csv_and_npz_round_trip_any_float(
    tmp_path_factory: pytest.TempPathFactory, r: np.ndarray, amin: float, inc: float
) -> None:
    b = ScanBatch(r, np.arange(r.shape[0]) * 0.1, amin, inc)
    d = tmp_path_factory.mktemp("rt")
    write_scans_csv(d / "s.csv", b)
    write_scans_npz(d / "s.npz", b)
    for name in ("s.csv", "s.npz"):
        # range_unit="m": any float is declared metres (without it, a median return beyond
        # 500 m is refused as millimetres, io.conventions.check_scan_ranges)
        got = read_scans(d / name, range_unit="m")
        # exact: negative zero, subnormals, +-inf and NaN all survive
        np.testing.assert_array_equal(got.ranges, b.ranges)
        num = ~np.isnan(b.ranges)
        np.testing.assert_array_equal(np.signbit(got.ranges[num]), np.signbit(b.ranges[num]))
        assert (got.angle_min, got.angle_increment) == (amin, inc)
