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


def test_work_folder_of_other_files_is_refused_untouched(
    stand_tiles: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    """``--work`` on a folder of the user's: refused before any work, nothing deleted.

    A run removes ``<work>/stage`` when it is done and replaces ``<work>/manifest.jsonl``:
    ``--work ~/data`` (or the tile folder itself) deleted a ``stage`` folder of the user's.
    """
    folder, _ = stand_tiles
    mine = tmp_path / "mine"
    (mine / "stage").mkdir(parents=True)
    (mine / "stage" / "notes.txt").write_text("precious\n")
    (mine / "manifest.jsonl").write_text("my own list\n")
    for work in (mine, folder):
        res = CliRunner().invoke(
            app,
            ["stems", str(folder), "--out", str(tmp_path / "s.csv"), "--work", str(work), "-q"],
        )
        text = " ".join(res.output.split())
        assert res.exit_code == 2, text
        assert "is not a stemmap work folder" in text and str(work) in text
    assert (mine / "stage" / "notes.txt").read_text() == "precious\n"
    assert (mine / "manifest.jsonl").read_text() == "my own list\n"
    assert not (tmp_path / "s.csv").exists()


def test_work_folder_accepts_new_empty_and_earlier_runs(tmp_path: Path) -> None:
    from stemmap.engine.manifest import Manifest

    Manifest(tmp_path / "new").claim()
    (tmp_path / "empty").mkdir()
    Manifest(tmp_path / "empty").claim()
    old = tmp_path / "old"
    (old / "chunks").mkdir(parents=True)
    (old / "stage" / "x-1_y0ab").mkdir(parents=True)
    (old / "stage" / "pilot").mkdir()
    man = Manifest(old)
    man.append("x-1_y0ab", "done", {}, "p", seconds=1.0)
    man.claim()
    with man.path.open("a") as fh:  # a line torn by a kill after a complete first line
        fh.write('{"chunk": "x0_y0", "inp')
    man.claim()
    man.path.write_text('{"chunk": "x0_y0", "inp')  # the first line itself torn
    man.claim()
