"""Text inputs (CSV tables, XYZ clouds, scan CSV, GeoJSON) are measured before they are read:
a line over 1 MB, or a parse estimated above the read budget, is refused by name.

Before, the readers read the whole file and split it: one 300 MB line of ``1 `` in an XYZ
file made 150 M Python strings (7.3 GB peak, then "out of memory" under an 8 GB limit:
``benchmarks/hostile_inputs.py``), and a table of short lines takes ~200 B of Python objects
per line (1 M lines of ``0,0,0``: 6 MB on disk, 210 MB to parse).
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.io import _budget
from stemmap.io._budget import BUDGET_ENV, text_stats


@pytest.mark.parametrize("block", [1, 2, 3, 4, 7, 1 << 24])
def test_text_stats_across_block_boundaries(tmp_path: Path, monkeypatch, block: int) -> None:
    monkeypatch.setattr(_budget, "_BLOCK", block)
    p = tmp_path / "t.txt"
    for content, expect in [
        (b"", (0, 0, 0, 0)),
        (b"a", (1, 1, 1, 1)),
        (b"ab\ncde\nf", (8, 3, 3, 2)),
        (b"abc\n\n\nabcdefg\nx\n", (16, 5, 7, 4)),
        (b"x" * 10, (10, 1, 10, 1)),
        (b"\n\n\nxyz", (6, 4, 3, 4)),
    ]:
        p.write_bytes(content)
        st = text_stats(p)
        assert (st.size, st.lines, st.longest, st.longest_line) == expect, content


def _odometry(tmp_path: Path, body: bytes) -> Path:
    p = tmp_path / "o.csv"
    p.write_bytes(b"time_s,speed,yaw_rate\n" + body)
    return p


def test_one_enormous_line_in_a_csv_is_refused_without_splitting_it(tmp_path: Path) -> None:
    from stemmap.cli._map_inputs import read_odometry_csv

    p = _odometry(tmp_path, b"0,0,0\n" + b"1," * 4_000_000 + b"\n")  # line 3: 8 MB
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match=r"o\.csv' line 3 is 8 MB long"):
            read_odometry_csv(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # before: the text, its lines and 4 M field strings (> 200 MB); now one read block
    # (Python allocates the 16 MB asked for, then shrinks it) and its newline search
    assert peak < 48e6


def test_many_short_lines_over_the_budget_are_refused(tmp_path: Path, monkeypatch) -> None:
    from stemmap.cli._map_inputs import read_odometry_csv

    p = _odometry(tmp_path, b"0,0,0\n" * 1_000_000)
    monkeypatch.setenv(BUDGET_ENV, "0.1")  # 100 MB: the parse needs ~218 MB
    with pytest.raises(InputError) as info:
        read_odometry_csv(p)
    msg = str(info.value)
    assert "6 MB in 1,000,001 lines needs ~218 MB to parse" in msg
    assert f"{BUDGET_ENV}=0.3" in msg
    monkeypatch.setenv(BUDGET_ENV, "0.3")
    read_odometry_csv(p)  # reads within a budget that fits


def test_xyz_with_one_enormous_line(tmp_path: Path) -> None:
    from stemmap.io.clouds import read_xyz

    p = tmp_path / "c.xyz"
    p.write_bytes(b"1 " * 2_000_000)
    with pytest.raises(InputError, match=r"point file .*c\.xyz' line 1 is 4 MB long"):
        read_xyz(p)


def test_xyz_with_thousands_of_columns(tmp_path: Path) -> None:
    from stemmap.io.clouds import read_xyz

    p = tmp_path / "c.xyz"
    np.savetxt(p, np.ones((3, 1000)))
    with pytest.raises(InputError, match=r"has 1,000 columns on its first line"):
        read_xyz(p)
    np.savetxt(p, np.ones((3, 7)))
    assert read_xyz(p).xyz.shape == (3, 3)


def test_scan_csv_with_one_enormous_line(tmp_path: Path) -> None:
    from stemmap.io.scans import read_scans

    p = tmp_path / "s.csv"
    p.write_bytes(b"time_s,angle_min,angle_increment,range_min,range_max,r0\n" + b"5," * 10**6)
    with pytest.raises(InputError, match=r"scan CSV .* line 2 is 2 MB long"):
        read_scans(p)


def test_geojson_over_the_budget(tmp_path: Path, monkeypatch) -> None:
    from stemmap.io.maps import read_trees_geojson, write_trees_geojson
    from stemmap.types import StemMap, Tree

    p = tmp_path / "t.geojson"
    write_trees_geojson(p, StemMap(tuple(Tree(k, k, -k, 0.3) for k in range(2000))))
    size = p.stat().st_size
    monkeypatch.setenv(BUDGET_ENV, str(20 * size / 1e9))  # json.loads needs ~25 B per byte
    with pytest.raises(InputError, match=r"trees GeoJSON .* needs ~"):
        read_trees_geojson(p)
    monkeypatch.delenv(BUDGET_ENV)
    assert len(read_trees_geojson(p)) == 2000


def test_a_scan_csv_streams_past_a_budget_that_stops_holding_it(tmp_path: Path, monkeypatch):
    """read_scans holds every scan, so the whole parse is budgeted; iter_scans (what
    `stemmap odometry` streams) holds one line at a time, so only the line length is."""
    from stemmap.io.scans import iter_scans, read_scans

    p = tmp_path / "s.csv"
    rows = "".join(f"{0.1 * k:.1f},-1.0,0.5,0.05,30.0,4.0,4.1,4.2\n" for k in range(2000))
    p.write_text("time,angle_min,angle_increment,range_min,range_max,r0,r1,r2\n" + rows)
    # 1 MB: below the ~1.2 MB a held parse is estimated at (3 B per byte + 500 B per line)
    monkeypatch.setenv(BUDGET_ENV, "0.001")
    with pytest.raises(InputError, match=r"scan CSV .* needs ~"):
        read_scans(p)
    assert sum(1 for _ in iter_scans(p)) == 2000
