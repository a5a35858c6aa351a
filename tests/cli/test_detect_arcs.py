"""``stemmap detect --arcs/--no-arcs`` (issue 11, fourteenth and fifteenth rounds): the
largest-consistent-arc re-fit from the command line, on in the stemmap preset since the
fifteenth round."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from tests.scan.test_arcs import TRUNK, _scan
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.scans import write_scans_npz
from stemmap.scan.config import ARC_OPTIONS
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

runner = CliRunner()


def _diameters(path: Path) -> list[float]:
    with path.open(newline="") as fh:
        return [float(row["diameter"]) for row in csv.DictReader(fh)]


def test_arcs_measure_a_trunk_on_its_own_arc(tmp_path: Path) -> None:
    # a 30 cm trunk at 5 m with a 6 cm stub touching its silhouette edge: without the arcs
    # the fit takes the stub in and reads the trunk > 6 cm too wide
    batch = _scan([TRUNK, (5.02, 0.19, 0.03)])
    src = tmp_path / "scan.npz"
    write_scans_npz(src, batch)
    off, on, dflt = tmp_path / "off.csv", tmp_path / "on.csv", tmp_path / "default.csv"
    for dst, flags in ((off, ["--no-arcs"]), (on, ["--arcs"]), (dflt, [])):
        res = runner.invoke(app, ["detect", str(src), "--out", str(dst), "-q", *flags])
        assert res.exit_code == 0, res.output
    (d_off,), (d_on,), (d_default,) = _diameters(off), _diameters(on), _diameters(dflt)
    assert d_off > 2 * TRUNK[2] + 0.06
    # noise-free 0.5 deg beams: the arc's fit is within the ~2 mm the beams leave at the edge
    assert abs(d_on - 2 * TRUNK[2]) < 0.006
    assert d_default == d_on  # on in the stemmap preset since the fifteenth round
    # the option is exactly the documented setting of the Python API, the preset's
    api = ScanTrunkDetector(
        DetectorConfig.preset(
            "zheng2012",
            arc_refit=True,
            arc_sigmas=2.0,
            arc_replace=3.0,
            arc_tangent_sigmas=3.0,
            arc_chi2=True,
            arc_short_steps=True,
        )
    ).config
    assert DetectorConfig.preset("zheng2012", **ARC_OPTIONS) == api
    preset = DetectorConfig.preset("stemmap")
    assert all(getattr(preset, k) == v for k, v in ARC_OPTIONS.items())
    assert json.loads((tmp_path / "on.csv.run.json").read_text())["parameters"]["arcs"] is True
    assert json.loads((tmp_path / "off.csv.run.json").read_text())["parameters"]["arcs"] is False


def test_arcs_help_names_the_trade_off() -> None:
    res = runner.invoke(app, ["detect", "--help"], env={"COLUMNS": "200"})
    assert "--no-arcs" in res.output and "lobed rocks" in res.output
