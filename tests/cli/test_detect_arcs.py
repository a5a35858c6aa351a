"""``stemmap detect --arcs`` (issue 11, fourteenth round): the largest-consistent-arc re-fit
from the command line, the setting leave-one-dataset-out scores best on the real slices."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from tests.scan.test_arcs import TRUNK, _scan
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.scans import write_scans_npz
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

runner = CliRunner()


def _diameters(path: Path) -> list[float]:
    with path.open(newline="") as fh:
        return [float(row["diameter"]) for row in csv.DictReader(fh)]


def test_arcs_measure_a_trunk_on_its_own_arc(tmp_path: Path) -> None:
    # a 30 cm trunk at 5 m with a 6 cm stub touching its silhouette edge: the default's fit
    # takes the stub in and reads the trunk > 6 cm too wide
    batch = _scan([TRUNK, (5.02, 0.19, 0.03)])
    src = tmp_path / "scan.npz"
    write_scans_npz(src, batch)
    off, on = tmp_path / "off.csv", tmp_path / "on.csv"
    r_off = runner.invoke(app, ["detect", str(src), "--out", str(off), "-q"])
    r_on = runner.invoke(app, ["detect", str(src), "--out", str(on), "-q", "--arcs"])
    assert r_off.exit_code == 0, r_off.output
    assert r_on.exit_code == 0, r_on.output
    (d_off,), (d_on,) = _diameters(off), _diameters(on)
    assert d_off > 2 * TRUNK[2] + 0.06
    # noise-free 0.5 deg beams: the arc's fit is within the ~2 mm the beams leave at the edge
    assert abs(d_on - 2 * TRUNK[2]) < 0.006
    # the option is exactly the documented setting of the Python API
    api = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", arc_refit=True, arc_sigmas=2.0, arc_replace=3.0)
    ).detect_batch(batch)
    assert abs(2 * api.radii[0] - d_on) < 1e-6
    doc = json.loads((tmp_path / "on.csv.run.json").read_text())
    assert doc["parameters"]["arcs"] is True


def test_arcs_help_names_the_trade_off() -> None:
    res = runner.invoke(app, ["detect", "--help"], env={"COLUMNS": "200"})
    assert "--arcs" in res.output and "rock faces" in res.output
