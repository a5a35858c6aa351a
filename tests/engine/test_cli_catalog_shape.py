"""An empty (or nearly empty) tile-catalog run gets the single file's shape check.

Before (main at 88c3073) `stemmap stems TILES/` skipped the check for another up axis and
the empty-result evidence (`io.conventions.up_axis_hint`, `cli._stems_base.
empty_result_notes`): TreeLS pine written Y up and cut into tiles gave "no stems found: no
chunk found a stem" and nothing else, where the single file warns that the cloud lies on
its side. A catalog takes no --up-axis, so the warning says to turn the tiles instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app


def _y_up_tiles(src: Path, out: Path, size: float) -> Path:
    """``src`` turned Y up ((x, z, -y), as photogrammetry writes it), cut into LAS tiles."""
    import laspy

    las = laspy.read(src)
    p = np.column_stack((las.x, las.z, -np.asarray(las.y)))
    ij = np.floor((p[:, :2] - p[:, :2].min(axis=0)) / size).astype(np.int64)
    out.mkdir(parents=True)
    for key in np.unique(ij, axis=0):
        m = np.all(ij == key, axis=1)
        header = laspy.LasHeader(point_format=0, version="1.2")
        header.scales, header.offsets = np.full(3, 0.001), np.zeros(3)
        tile = laspy.LasData(header)
        tile.x, tile.y, tile.z = p[m, 0], p[m, 1], p[m, 2]
        tile.write(str(out / f"t_{key[0]}_{key[1]}.las"))
    return out


def test_lying_tree_in_tiles_is_warned(datasets_dir: Path, tmp_path: Path) -> None:
    """TreeLS spruce Y up in 10 m tiles: no stem, the lying-tree warning and the cloud's size.
    (TreeLS pine Y up, used before Dec 5, now gives one false 7.4 cm stem -- a horizontal
    branch standing vertical -- in tiles as in the single file, with the same warning:
    docs/algorithms/cloud.md "Point order", "A lying tree"; the single file is tested in
    tests/cli/test_stems_conventions.py, the tiles were checked by hand: 42 s in a test.)"""
    tiles = _y_up_tiles(datasets_dir / "treels" / "spruce.laz", tmp_path / "tiles", 10.0)
    res = CliRunner().invoke(
        app, ["stems", str(tiles), "-o", str(tmp_path / "s.csv"), "--workers", "1"]
    )
    text = " ".join(res.output.split())
    assert res.exit_code == 0, text
    assert "no stems found: no chunk found a stem (no cluster passed" in text
    assert "like a tree lying on its side" in text
    assert "A tile catalog takes no --up-axis" in text
    assert "read as metres with z up, the cloud is 2.5 x 16.9 m across and 2.5 m tall" in text
