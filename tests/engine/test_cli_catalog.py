"""When `stemmap stems` uses the engine, and its error paths (no cluster needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._catalog import EngineOptions, wants_engine


def test_engine_kicks_in_for_catalogs_and_options_only(
    stand_tiles: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    folder, _ = stand_tiles
    one = str(sorted(folder.glob("*.laz"))[0])
    none = EngineOptions()
    assert not wants_engine([one], none)  # a single file: in-process, as before
    assert wants_engine([one], EngineOptions(chunk_size=20.0))  # one big file in chunks
    assert wants_engine([one], EngineOptions(workers=2))
    assert wants_engine([one, one], none)
    assert wants_engine([str(folder)], none)
    assert wants_engine([str(folder / "*.laz")], none)
    lst = tmp_path / "tiles.txt"
    lst.write_text(one + "\n")
    assert wants_engine([str(lst)], none)
    xyz_text = tmp_path / "cloud.txt"  # an XYZ text cloud is not a list of tiles
    xyz_text.write_text("1.0 2.0 3.0\n4.0 5.0 6.0\n")
    assert not wants_engine([str(xyz_text)], none)
    bag = tmp_path / "run_bag"  # a ROS 2 bag folder stays a bag
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    assert not wants_engine([str(bag)], none)


def test_cli_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    res = CliRunner().invoke(app, ["stems", str(empty), "--out", str(tmp_path / "s.csv")])
    text = " ".join(res.output.split())  # rich wraps long lines
    assert res.exit_code == 2
    assert "holds no .las/.laz" in text
    assert "bag" not in text.lower()
    res = CliRunner().invoke(
        app, ["stems", str(tmp_path / "none_*.laz"), "--out", str(tmp_path / "s.csv")]
    )
    assert res.exit_code == 2 and "matches no file" in " ".join(res.output.split())
