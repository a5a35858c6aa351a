"""``stemmap detect --noise-batch`` (issue 11, Dec 4): sparse scans share their batch's
range-noise estimate."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app

runner = CliRunner()


def _sparse_noisy_scans(tmp_path: Path) -> tuple[Path, np.ndarray]:
    """A walk past four 30-44 cm trunks in the open, 0.5 deg, 3 cm of range noise: each scan
    sees a few trunks with 6-20 returns, too few continuous triples for its own estimate."""
    from stemmap.io.scans import write_scans_npz
    from stemmap.sim.forest import Stand
    from stemmap.sim.scanner import ScannerModel, simulate_scans

    stand = Stand(
        np.array([[3.0, 4.0], [7.0, 6.5], [11.0, 3.5], [15.0, 6.0]]),
        np.array([0.30, 0.36, 0.40, 0.44]),
    )
    model = ScannerModel(angle_increment=math.radians(0.5), range_noise=0.03, range_max=30.0)
    poses = np.column_stack([np.linspace(0, 18, 30), np.zeros(30), np.full(30, math.pi / 2)])
    scans, _, _ = simulate_scans(stand, poses, model, rng=7)
    p = tmp_path / "scans.npz"
    write_scans_npz(p, scans)
    return p, scans.ranges


def _rows(path: Path) -> int:
    return sum(1 for _ in path.open()) - 1


def test_noise_batch_option(tmp_path: Path) -> None:
    from stemmap.scan.plausibility import scan_noise

    src, ranges = _sparse_noisy_scans(tmp_path)
    r = np.where(np.isfinite(ranges) & (ranges < 30.0), ranges, np.nan)
    assert np.mean(scan_noise(r, 0.2) == 0.0) > 0.8  # most scans: no estimate of their own
    off, on = tmp_path / "off.csv", tmp_path / "on.csv"
    r_off = runner.invoke(app, ["detect", str(src), "--out", str(off), "-q"])
    r_on = runner.invoke(app, ["detect", str(src), "--out", str(on), "-q", "--noise-batch", "2"])
    assert r_off.exit_code == 0, r_off.output
    assert r_on.exit_code == 0, r_on.output
    # the configured 1 cm rejects most noisy arcs; the batch's ~3 cm lets them through
    assert _rows(on) > _rows(off)
    doc = json.loads((tmp_path / "on.csv.run.json").read_text())
    assert doc["parameters"]["noise_batch"] == 2.0


def test_noise_batch_refuses_a_factor_below_one(tmp_path: Path) -> None:
    src, _ = _sparse_noisy_scans(tmp_path)
    res = runner.invoke(
        app, ["detect", str(src), "--out", str(tmp_path / "x.csv"), "--noise-batch", "0.5"]
    )
    assert res.exit_code != 0
    assert "--noise-batch" in res.output


def test_noise_batch_scale_option(tmp_path: Path) -> None:
    # --noise-batch-scale biweight (batch_noise_scale, Dec 5): the batch's estimate by the
    # biweight; with --noise-batch the noisy arcs pass as with the MAD's (both read ~3 cm)
    src, _ = _sparse_noisy_scans(tmp_path)
    off, on = tmp_path / "off.csv", tmp_path / "on.csv"
    r_off = runner.invoke(app, ["detect", str(src), "--out", str(off), "-q"])
    args = ["detect", str(src), "--out", str(on), "-q", "--noise-batch", "2"]
    r_on = runner.invoke(app, [*args, "--noise-batch-scale", "biweight"])
    assert r_off.exit_code == 0, r_off.output
    assert r_on.exit_code == 0, r_on.output
    assert _rows(on) > _rows(off)
    doc = json.loads((tmp_path / "on.csv.run.json").read_text())
    assert doc["parameters"]["noise_batch_scale"] == "biweight"
    bad = runner.invoke(app, [*args, "--noise-batch-scale", "std"])
    assert bad.exit_code != 0
