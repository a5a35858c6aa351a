"""The first-run compile notice asks only about the kernels the run will compile: the scan
kernels and the chosen SLAM back-end's own (an iSAM2 demo never compiles FastSLAM's kernels, so
asking about those announced a "first run" on every run)."""

from __future__ import annotations

from pathlib import Path

import pytest

from stemmap.cli._summary import announce_compile


def _fake_cache(root: Path, folder: str, stem: str) -> None:
    d = root / f"{folder}_0123abcd"
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{stem}.kernel-10.py311.nbi").write_bytes(b"")


@pytest.fixture
def cache_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    return tmp_path


def test_empty_cache_names_scan_and_the_backend_kernels(cache_dir: Path, capsys) -> None:
    announce_compile("scan", backend="isam2")
    err = " ".join(capsys.readouterr().err.split())
    assert "first run" in err
    for name in ("_detect_fast", "_fit_geometric", "_isam2_track"):
        assert name in err
    assert "_fastslam_kernel" not in err and "_association_kernel" not in err


def test_cached_backend_is_silent_whatever_the_other_backends(cache_dir: Path, capsys) -> None:
    _fake_cache(cache_dir, "scan", "_detect_fast")
    _fake_cache(cache_dir, "scan", "_fit_geometric")
    _fake_cache(cache_dir, "slam", "_isam2_track")
    announce_compile("scan", backend="isam2")
    assert capsys.readouterr().err == ""
    announce_compile("scan", backend="fastslam")
    err = " ".join(capsys.readouterr().err.split())
    assert "_fastslam_kernel" in err and "_isam2_track" not in err


def test_detect_and_stems_announce_their_first_run(cache_dir: Path, tmp_path: Path) -> None:
    # the user audit (docs/cli.md): the first `stemmap detect` compiled for minutes (3.5 min
    # wall on the loaded machine) and the first `stemmap stems` for 80 s with no sign of life;
    # `map` and `demo` already said so
    import numpy as np
    from typer.testing import CliRunner

    from stemmap.cli import app
    from stemmap.io.scans import write_scans_npz
    from stemmap.types import ScanBatch

    src = tmp_path / "scans.npz"
    a = np.linspace(-1.5, 1.5, 181)
    write_scans_npz(
        src, ScanBatch(np.full((2, a.size), 8.0), np.arange(2) * 0.1, -1.5, a[1] - a[0])
    )
    res = CliRunner().invoke(app, ["detect", str(src), "--out", str(tmp_path / "d.csv")])
    assert res.exit_code == 0, res.output
    assert "first run" in res.output and "_detect_fast" in res.output
    res = CliRunner().invoke(app, ["detect", str(src), "--out", str(tmp_path / "e.csv"), "-q"])
    assert res.exit_code == 0 and "first run" not in res.output
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, np.random.default_rng(0).uniform(0, 5, (200, 3)))
    res = CliRunner().invoke(app, ["stems", str(cloud), "--out", str(tmp_path / "s.csv")])
    assert res.exit_code == 0, res.output
    assert "first run" in res.output and "_grid_kernel" in " ".join(res.output.split())


_ODO = ["--odometry", "{d}/good_odo.csv"]
_BAD_INPUTS = {
    "truncated PLY": ["stems", "{d}/bad.ply", "--out", "{d}/s.csv"],
    "bad --origin": ["stems", "{d}/c.xyz", "--out", "{d}/s.csv", "--origin", "1,2,3,4"],
    "--imu-topic on an NPZ": ["detect", "{d}/s.npz", "--out", "{d}/d.csv", "--imu-topic", "/i"],
    "odometry CSV lacking a column": [
        "map", "{d}/s.npz", "--odometry", "{d}/o.csv", "--out", "{d}/m",
    ],
    "bad --sensor-offset": ["map", "{d}/s.npz", *_ODO, "--sensor-offset", "x", "--out", "{d}/m"],
    "missing --gnss file": ["map", "{d}/s.npz", *_ODO, "--gnss", "{d}/no.csv", "--out", "{d}/m"],
    "odometry not covering the scans": [
        "map", "{d}/s.npz", "--odometry", "{d}/short_odo.csv", "--out", "{d}/m",
    ],
    # (Dec 5) the prior map was read after the scans' detection had compiled and run
    "missing --prior-map": ["map", "{d}/s.npz", *_ODO, "--prior-map", "{d}/nomap", "--out",
                            "{d}/m"],
    "damaged --prior-map": ["map", "{d}/s.npz", *_ODO, "--prior-map", "{d}/bad_map", "--out",
                            "{d}/m"],
    "--prior-type graph without graph.npz": [
        "map", "{d}/s.npz", *_ODO, "--prior-map", "{d}/map", "--prior-type", "graph", "--out",
        "{d}/m",
    ],
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(_BAD_INPUTS))
def test_bad_input_is_reported_before_the_first_run_notice(
    cache_dir: Path, tmp_path: Path, case: str
) -> None:
    # the user walk (Dec 4): "first run: compiling numba kernels ..." was printed, and for a
    # scans file the detector compiled, before an input or option error that needed no kernel
    import numpy as np
    from typer.testing import CliRunner

    from stemmap.cli import app

    d = tmp_path / "in"
    d.mkdir()
    (d / "bad.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nend_header\n1\n"
    )
    np.savetxt(d / "c.xyz", np.random.default_rng(0).uniform(0, 5, (50, 3)))
    np.savez(
        d / "s.npz",
        ranges=np.full((3, 10), 5.0),
        time=np.arange(3.0),
        angle_min=0.0,
        angle_increment=0.01,
    )
    (d / "o.csv").write_text("time_s,speed\n0,1\n")
    (d / "good_odo.csv").write_text("time_s,speed,yaw_rate\n0,1,0\n1,1,0\n2,1,0\n3,1,0\n")
    (d / "short_odo.csv").write_text("time_s,speed,yaw_rate\n10,1,0\n11,1,0\n")
    for name, rows in (("map", "0,1.0,2.0,0.3\n"), ("bad_map", "0,1.0,x,0.3\n")):
        (d / name).mkdir()
        (d / name / "trees.csv").write_text("id,x,y,diameter\n" + rows)
    argv = [a.format(d=d) for a in _BAD_INPUTS[case]]
    res = CliRunner().invoke(app, argv)
    assert res.exit_code == 2, res.output
    assert "error:" in res.output
    assert "first run" not in res.output
