"""``stemmap detect --sigma-from-scan`` (issue 11): the scan's own range-noise estimate."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app

runner = CliRunner()


def _noisy_scans(tmp_path: Path) -> Path:
    from stemmap.io.scans import write_scans_npz
    from stemmap.sim.forest import random_stand
    from stemmap.sim.scanner import ScannerModel, simulate_scans

    stand = random_stand(40, (20.0, 20.0), dbh_mean=0.3, dbh_std=0.08, rng=3)
    # 3 cm of range noise: three times the 1 cm the stemmap preset assumes
    model = ScannerModel(angle_increment=math.radians(0.5), range_noise=0.03, range_max=30.0)
    poses = np.column_stack([np.linspace(-8, 8, 12), np.full(12, -9.5), np.full(12, math.pi / 2)])
    poses[:, :2] += 10.0
    scans, _, _ = simulate_scans(stand, poses, model, rng=5)
    p = tmp_path / "scans.npz"
    write_scans_npz(p, scans)
    return p


def _rows(path: Path) -> int:
    return sum(1 for _ in path.open()) - 1


def test_sigma_from_scan_option(tmp_path: Path) -> None:
    src = _noisy_scans(tmp_path)
    off, on = tmp_path / "off.csv", tmp_path / "on.csv"
    r_off = runner.invoke(
        app, ["detect", str(src), "--out", str(off), "-q", "--no-sigma-from-scan"]
    )
    r_on = runner.invoke(app, ["detect", str(src), "--out", str(on), "-q", "--sigma-from-scan"])
    assert r_off.exit_code == 0, r_off.output
    assert r_on.exit_code == 0, r_on.output
    # with 3 cm noise the 1 cm RMS test rejects noisy trunk arcs; the scan's own estimate
    # (~3 cm) lets them through: strictly more detections on the same scans
    assert _rows(on) > _rows(off) > 0
    doc = json.loads((tmp_path / "on.csv.run.json").read_text())
    assert doc["parameters"]["sigma_from_scan"] is True


def test_sigma_from_scan_help() -> None:
    res = runner.invoke(app, ["detect", "--help"], env={"COLUMNS": "200"})
    assert "--sigma-from-scan" in res.output and "--no-sigma-from-scan" in res.output
