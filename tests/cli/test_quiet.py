"""One ``-q/--quiet`` on every command that prints progress or a summary (cli._common.QuietFlag):
the same option, help and behaviour -- products written as without it, nothing on stdout, no
progress bar or first-run notice, errors still printed, ``--json`` still printed."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app

runner = CliRunner()


def _scans(d: Path) -> Path:
    """Three scans with one 0.3 m trunk 3 m ahead (something to detect and summarise)."""
    from stemmap.io.scans import write_scans_npz
    from stemmap.types import ScanBatch

    a = np.linspace(-1.5, 1.5, 361)
    # range to a circle of radius 0.15 m centred 3 m along the x axis, else 12 m
    b = 3.0 * np.sin(a)
    hit = np.abs(b) < 0.15
    r = np.where(hit, 3.0 * np.cos(a) - np.sqrt(np.clip(0.15**2 - b**2, 0, None)), 12.0)
    p = d / "scans.npz"
    write_scans_npz(p, ScanBatch(np.tile(r, (3, 1)), np.arange(3) * 0.1, a[0], a[1] - a[0]))
    return p


def _cloud(d: Path) -> Path:
    """Two vertical 0.3 m cylinders on a flat ground (an .xyz cloud for ``stems``)."""
    g = np.random.default_rng(0)
    ground = np.c_[g.uniform(-5, 5, (4000, 2)), g.normal(0, 0.01, 4000)]
    stems = []
    for cx, cy in ((-2.0, 0.0), (2.0, 1.0)):
        t, z = g.uniform(0, 2 * np.pi, 3000), g.uniform(0.2, 3.0, 3000)
        stems.append(np.c_[cx + 0.15 * np.cos(t), cy + 0.15 * np.sin(t), z])
    p = d / "cloud.xyz"
    np.savetxt(p, np.vstack([ground, *stems]), fmt="%.4f")
    return p


#: command -> (argv builder, product written, has --json)
CASES: dict[str, tuple[Any, str, bool]] = {
    "detect": (lambda s, c, o: ["detect", s, "--out", o / "d.csv"], "d.csv", False),
    "odometry": (lambda s, c, o: ["odometry", s, "--out", o / "t.csv"], "t.csv", False),
    "stems": (lambda s, c, o: ["stems", c, "--out", o / "s.csv"], "s.csv", True),
    "map": (
        lambda s, c, o: ["map", "--sim", "--sim-trees", "10", "--sim-size", "20", "--out", o / "m"],
        "m/trees.csv",
        True,
    ),
    "demo": (
        lambda s, c, o: ["demo", "--n-trees", "5", "--out", o / "demo"],
        "demo/trees.csv",
        True,
    ),
    "io convert-scans": (
        lambda s, c, o: ["io", "convert-scans", s, "--out", o / "c.csv"],
        "c.csv",
        False,
    ),
    "sim scans": (
        lambda s, c, o: ["sim", "scans", "--out", o / "r.npz", "--n-scans", "20"],
        "r.npz",
        False,
    ),
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("quiet_inputs")
    return _scans(d), _cloud(d)


def _run(argv: list[Any]) -> Any:
    return runner.invoke(app, [str(a) for a in argv])


@pytest.mark.parametrize("name", sorted(CASES))
def test_quiet_silences_stdout_and_keeps_the_products(name, inputs, tmp_path):
    build, product, has_json = CASES[name]
    scans, cloud = inputs
    loud = _run(build(scans, cloud, tmp_path / "loud"))
    assert loud.exit_code == 0, loud.output
    assert loud.stdout.strip(), "without -q the command prints its summary"
    quiet = _run([*build(scans, cloud, tmp_path / "quiet"), "-q"])
    assert quiet.exit_code == 0, quiet.output
    assert quiet.stdout == ""
    # no progress bar, first-run notice or summary on stderr either (warnings may remain)
    assert "first run" not in quiet.stderr and "it/s" not in quiet.stderr
    assert (tmp_path / "quiet" / product).exists()
    if name == "detect":  # the same product, byte for byte
        a, b = (tmp_path / d / product for d in ("loud", "quiet"))
        assert a.read_text() == b.read_text()
    if has_json:
        js = _run([*build(scans, cloud, tmp_path / "json"), "--quiet", "--json"])
        assert js.exit_code == 0, js.output
        doc = json.loads(js.stdout)
        assert "summary" in doc and doc["files"]


def test_sim_score_quiet_prints_nothing_and_writes_the_same_metrics(tmp_path):
    """``sim score`` (no --json object on stdout: its --json is a file): -q prints no
    summary, and the metrics file is byte for byte the one written without it."""
    run, stems = tmp_path / "run.npz", tmp_path / "stems.csv"
    sim = _run(["sim", "scans", "--out", run, "--n-scans", "20", "-q"])
    assert sim.exit_code == 0, sim.output
    det = _run(["detect", run, "--out", stems, "-q"])
    assert det.exit_code == 0, det.output
    loud = _run(["sim", "score", stems, "--run", run, "--json", tmp_path / "loud.json"])
    assert loud.exit_code == 0, loud.output
    assert "precision" in loud.stdout  # the summary, without -q
    for flag in ("-q", "--quiet"):
        quiet = _run(["sim", "score", stems, "--run", run, "--json", tmp_path / "q.json", flag])
        assert quiet.exit_code == 0, quiet.output
        assert quiet.stdout == "" and quiet.stderr == ""
        assert (tmp_path / "q.json").read_bytes() == (tmp_path / "loud.json").read_bytes()
    # errors are still printed: a detections file that does not exist
    bad = _run(["sim", "score", tmp_path / "missing.csv", "--run", run, "-q"])
    assert bad.exit_code == 2
    assert bad.stdout == "" and bad.stderr.startswith("error:")


def test_quiet_still_prints_errors(tmp_path):
    res = _run(["detect", tmp_path / "missing.npz", "--out", tmp_path / "d.csv", "-q"])
    assert res.exit_code == 2
    assert res.stdout == "" and res.stderr.startswith("error:")


def _commands(cmd: Any, path: tuple[str, ...] = ()) -> Any:
    for name, sub in getattr(cmd, "commands", {}).items():
        yield from _commands(sub, (*path, name))
    if not getattr(cmd, "commands", None):
        yield " ".join(path), cmd


def test_one_quiet_option_everywhere():
    import typer.main

    from stemmap.cli._common import QuietFlag

    expected = QuietFlag.__metadata__[0].help
    with_quiet = {}
    for name, cmd in _commands(typer.main.get_command(app)):
        for p in cmd.params:
            if p.name == "quiet":
                with_quiet[name] = p
    # every command of the brief, and the sim / io ones that had their own
    assert {"detect", "odometry", "stems", "map", "demo", "io convert-scans", "sim scans",
            "sim score", "sim munjer"} <= set(with_quiet)  # fmt: skip
    for name, p in with_quiet.items():
        assert sorted(p.opts) == ["--quiet", "-q"], name
        assert p.help == expected, name
