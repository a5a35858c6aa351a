"""``stemmap detect --step-split`` (issue 11, Dec 5): the leave-one-dataset-out choice of the
step split, reachable from the command line."""

from __future__ import annotations

import json
from pathlib import Path

from tests.scan.test_step_split import BEHIND, STEM, _stem_and_neighbour
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.scans import write_scans_npz

runner = CliRunner()


def test_step_split_finds_the_stem_with_a_branch_behind_it(tmp_path: Path) -> None:
    # a 20 cm stem whose segment runs on into a branch behind its silhouette edge (the TreeLS
    # plot's scan 6 steps): one 7-return candidate that fails the RMS test without the split
    src = tmp_path / "scan.npz"
    write_scans_npz(src, _stem_and_neighbour(BEHIND))
    off, on, default = tmp_path / "off.csv", tmp_path / "on.csv", tmp_path / "default.csv"
    r_off = runner.invoke(app, ["detect", str(src), "--out", str(off), "-q", "--no-step-split"])
    r_on = runner.invoke(app, ["detect", str(src), "--out", str(on), "-q", "--step-split"])
    # the stemmap preset's default since Dec 5: the same as --step-split
    r_def = runner.invoke(app, ["detect", str(src), "--out", str(default), "-q"])
    assert r_off.exit_code == 0, r_off.output
    assert r_on.exit_code == 0, r_on.output
    assert r_def.exit_code == 0, r_def.output
    assert len(off.read_text().splitlines()) == 1  # header only
    assert default.read_text() == on.read_text()
    off_doc = json.loads((tmp_path / "off.csv.run.json").read_text())
    assert off_doc["parameters"]["step_split"] is False
    rows = on.read_text().splitlines()
    assert len(rows) == 2
    head = rows[0].split(",")
    row = dict(zip(head, rows[1].split(","), strict=True))
    # noise-free, 4 returns over ~60 deg of the stem: within 2 cm of its diameter
    assert abs(float(row["diameter"]) - 2 * STEM[2]) < 0.02
    doc = json.loads((tmp_path / "on.csv.run.json").read_text())
    assert doc["parameters"]["step_split"] is True
