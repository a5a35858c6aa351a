"""``stemmap detect --fit-noise-floor`` (issue 11, Dec 5): the preset's fit weighted by the
measured noise, reachable from the command line; it acts only with ``--footprint``."""

from __future__ import annotations

import json
import math
from pathlib import Path

from tests.scan.test_edge_protrusion import STEP
from tests.scan.test_stub_runs import _scan
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.scans import write_scans_npz

runner = CliRunner()


def _detect(tmp_path: Path, src: Path, name: str, *args: str) -> tuple[str, dict]:
    out = tmp_path / f"{name}.csv"
    res = runner.invoke(app, ["detect", str(src), "--out", str(out), "-q", *args])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / f"{name}.csv.run.json").read_text())
    return out.read_text(), doc["parameters"]


def test_fit_noise_floor_is_the_default_with_a_footprint_and_inert_without(tmp_path: Path):
    # a clean 30 cm disc at 4 m whose edge beam falls just off the outline (the view the
    # tests' 1 cm sigma reads 1.4 cm thin: tests/scan/test_fit_noise_default.py)
    batch, _, _ = _scan(4.0, 0.3 + math.radians(STEP) * 5.3 / 12, 0.0)
    src = tmp_path / "scan.npz"
    write_scans_npz(src, batch)
    fp = ("--footprint", str(STEP))
    default, p_def = _detect(tmp_path, src, "default", *fp)
    on, _ = _detect(tmp_path, src, "on", *fp, "--fit-noise-floor", "0.003")
    off, p_off = _detect(tmp_path, src, "off", *fp, "--fit-noise-floor", "0")
    assert p_def["fit_noise_floor"] is None  # not given: the preset's
    assert p_off["fit_noise_floor"] == 0.0
    assert default == on  # the preset's 3 mm
    assert default != off  # the diameter moves (measured -1.40 -> -0.58 cm)
    # an averaging scanner (no --footprint): the option does nothing
    avg, _ = _detect(tmp_path, src, "avg")
    avg_off, _ = _detect(tmp_path, src, "avg_off", "--fit-noise-floor", "0")
    assert avg == avg_off


def test_a_negative_fit_noise_floor_is_refused(tmp_path: Path):
    batch, _, _ = _scan(4.0, 0.3, 0.0)
    src = tmp_path / "scan.npz"
    write_scans_npz(src, batch)
    out = tmp_path / "x.csv"
    res = runner.invoke(app, ["detect", str(src), "--out", str(out), "--fit-noise-floor", "-1"])
    assert res.exit_code == 2
    assert not out.exists()
