"""``stemmap detect --footprint`` runs the ``stemmap`` preset of grid 80 (issue 11, Dec 5;
docs/algorithms/scan-detection.md, "Grid 80 is the `stemmap` preset"), with and without
``--rejected``: the real-geometry benchmark's lidR scans (0.5 deg nearest-return, no noise,
its 20 vantage points) written as a scan file give, through the command line, exactly the
detections of the API detector the benchmark runs."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from tests.scan.test_stub_runs import GRID_67
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.maps import write_observations_csv
from stemmap.io.scans import write_scans_npz
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

runner = CliRunner()


def _lidr_scans(datasets_dir: Path):
    """The benchmark's lidR scans at 0.5 deg nearest-return without noise (seed 11 + index)."""
    from _real_scanning import scene_scans, vantage_points
    from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch

    i = list(SLICES).index("lidr_dbh")
    sl = load_slice(datasets_dir, "lidr_dbh")
    rng = np.random.default_rng(11 + i)
    vp = vantage_points(sl, 20, rng)
    ranges, _ = scene_scans(sl, vp, "nearest", 0.5, "none", 11 + i)
    return noisy_batch(ranges, 0.5, 0.0, rng)


def _api_csv(path: Path, batch, **over) -> str:
    cfg = DetectorConfig.preset("stemmap", beam_footprint_deg=0.5, **over)
    write_observations_csv(path, ScanTrunkDetector(cfg).detect_batch(batch))
    return path.read_text()


def test_detect_with_a_footprint_runs_grid_80_with_and_without_rejected(
    datasets_dir: Path, tmp_path: Path
):
    batch = _lidr_scans(datasets_dir)
    src = tmp_path / "lidr.npz"
    write_scans_npz(src, batch)
    outs = {}
    for name, extra in (("plain", []), ("rejected", ["--rejected", str(tmp_path / "rej.csv")])):
        out = tmp_path / f"{name}.csv"
        args = ["detect", str(src), "--out", str(out), "--footprint", "0.5", "-q", *extra]
        res = runner.invoke(app, args)
        assert res.exit_code == 0, res.output
        outs[name] = out.read_text()
    api = _api_csv(tmp_path / "api.csv", batch)
    assert outs["plain"] == api
    assert outs["rejected"] == api  # the numpy pass that records the rejections
    # the preset before the flip (grid 67) reads lidR's junction views otherwise
    assert _api_csv(tmp_path / "g67.csv", batch, **GRID_67) != api
    with (tmp_path / "rej.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert rows and all(r["reason"] for r in rows)
