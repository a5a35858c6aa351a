"""Every numeric option is validated: a usage error (exit 2) naming the option and its range."""

from __future__ import annotations

import math

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._validate import bounded, range_text

runner = CliRunner()

CASES = [
    (["demo", "--n-trees", "0"], "--n-trees", "whole number >= 1"),
    (["demo", "--seed", "-1"], "--seed", ">= 0"),
    (["sim", "scans", "--out", "x.npz", "--n-trees", "0"], "--n-trees", ">= 1"),
    (["sim", "scans", "--out", "x.npz", "--speed", "0"], "--speed", "finite number > 0"),
    (["sim", "scans", "--out", "x.npz", "--rate-hz", "0"], "--rate-hz", "> 0"),
    (["sim", "scans", "--out", "x.npz", "--rate-hz", "inf"], "--rate-hz", "finite number"),
    (["sim", "scans", "--out", "x.npz", "--seed", "-1"], "--seed", ">= 0"),
    (["sim", "scans", "--out", "x.npz", "--size", "nan"], "--size", "> 4"),
    (["sim", "scans", "--out", "x.npz", "--n-scans", "1"], "--n-scans", ">= 2"),
    (["map", "--sim", "--sim-size", "-10"], "--sim-size", "> 4"),
    (["map", "--sim", "--sim-size", "nan"], "--sim-size", "finite number > 4"),
    (["map", "--sim", "--sim-trees", "0"], "--sim-trees", ">= 1"),
    (["map", "--sim", "--seed", "-1"], "--seed", ">= 0"),
    (["map", "--sim", "--t-end", "-5"], "--t-end", "> 0"),
    (["detect", "s.npz", "--out", "o.csv", "--sigma", "0"], "--sigma", "> 0"),
    (["detect", "s.npz", "--out", "o.csv", "--footprint", "nan"], "--footprint", "[0, 180)"),
    (["harvest-sim", "--bearing", "nan"], "--bearing", "[-180, 180]"),
    (["harvest-sim", "--max-cycles", "-3"], "--max-cycles", ">= 1"),
    (["harvest-sim", "--trees", "-1"], "--trees", ">= 1"),
    (["harvest-sim", "--seed", "-1"], "--seed", ">= 0"),
    (["harvest-sim", "--target", "bearing"], "--bearing", "DEGREES"),
    (["harvest-sim", "--target", "index"], "--index", ">= 0"),
    (["stems", "c.xyz", "--read-points", "0"], "--read-points", ">= 1"),
    (["stems", "c.xyz", "--chunk-size", "0"], "--chunk-size", "> 0"),
    (["stems", "c.xyz", "--buffer", "-1"], "--buffer", ">= 0"),
    (["stems", "c.xyz", "--workers", "0"], "--workers", ">= 1"),
    (["calibrate", "p.csv", "--out", "c.json", "--threshold-px", "0"], "--threshold-px", "> 0"),
    (["calibrate", "p.csv", "--out", "c.json", "--fx", "-1"], "--fx", "> 0"),
    (["calibrate", "p.csv", "--out", "c.json", "--width", "0"], "--width", ">= 1"),
    (
        [
            "fuse",
            "--scan",
            "s",
            "--image",
            "i",
            "--calibration",
            "c",
            "--out",
            "o",
            "--scan-index",
            "-1",
        ],
        "--scan-index",
        ">= 0",
    ),
    (["sim", "score", "d.csv", "--run", "r.npz", "--gate", "0"], "--gate", "> 0"),
    (["sim", "score", "d.csv", "--run", "r.npz", "--min-returns", "0"], "--min-returns", ">= 1"),
]


@pytest.mark.parametrize(("argv", "option", "valid"), CASES, ids=[" ".join(c[0]) for c in CASES])
def test_bad_option_is_a_usage_error(tmp_path, monkeypatch, argv, option, valid):
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(app, argv)
    assert res.exit_code == 2, res.output
    errs = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(errs) == 1, res.output  # one unwrapped line, no rich panel
    assert option in errs[0] and valid in errs[0], errs[0]
    assert "Traceback" not in res.output and "╭" not in res.output
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_bounded_accepts_the_range_and_none():
    cb = bounded("--x", gt=0, le=1)
    assert cb(None) is None and cb(1) == 1 and cb(0.5) == 0.5
    for bad in (0, 1.5, math.nan, math.inf):
        with pytest.raises(typer.BadParameter, match="must be"):
            cb(bad)
    assert bounded("--y", finite=False)(math.inf) == math.inf
    assert range_text(ge=0, lt=180) == "a finite number in [0, 180)"
    assert range_text(ge=1, integer=True) == "a whole number >= 1"


def test_angle_increment_damage_is_refused(tmp_path):
    for inc, expected in ((0.0, "non-zero"), (1.0, "spans")):
        p = tmp_path / f"inc{inc}.npz"
        np.savez(
            p,
            ranges=np.full((2, 181), 3.0),
            time=np.arange(2.0),
            angle_min=-1.5,
            angle_increment=inc,
        )
        res = runner.invoke(app, ["detect", str(p), "--out", str(tmp_path / "o.csv")])
        assert res.exit_code == 2
        assert expected in res.output and "angle_increment" in res.output


def test_misleading_messages_fixed(tmp_path):
    txt = tmp_path / "scans.npz"
    txt.write_text("time,angle_min\n0,1\n")
    res = runner.invoke(app, ["detect", str(txt), "--out", str(tmp_path / "o.csv")])
    assert res.exit_code == 2 and "pickle" not in res.output
    assert "not an NPZ (zip) archive" in res.output and "CSV named .npz" in res.output
    folder = tmp_path / "frame.png"
    folder.mkdir()
    for argv in (
        ["segment", str(folder), "--out", str(tmp_path / "m.png")],
        ["calibrate", str(folder), "--out", str(tmp_path / "c.json")],
    ):
        res = runner.invoke(app, argv)
        assert res.exit_code == 2 and "does not exist" not in res.output, res.output
        assert "not a regular file" in res.output or "is a folder" in res.output
