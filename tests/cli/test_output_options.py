"""A refused output names the command-line option that gave its path (io._cli_context.PathNames):
``--rejected 'a.npz' is the same file as the input SCANS 'a.npz'``, not ``--out`` for every
output, nor a bare path. One place (run_products) words it for every command."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.products import OutputError, run_products

runner = CliRunner()


def _error(argv: list[object]) -> str:
    res = runner.invoke(app, [str(a) for a in argv])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, res.output
    return lines[0].removeprefix("error: ")


@pytest.fixture
def scans(tmp_path: Path) -> Path:
    from stemmap.io.scans import write_scans_npz
    from stemmap.types import ScanBatch

    a = np.linspace(-1.5, 1.5, 181)
    p = tmp_path / "scans.npz"
    write_scans_npz(p, ScanBatch(np.full((2, a.size), 8.0), np.arange(2) * 0.1, a[0], a[1] - a[0]))
    return p


def test_second_output_on_the_input_names_its_own_option(scans, tmp_path):
    # before: "--out 'scans.npz' is the input ..." although --out was o.csv
    msg = _error(["detect", scans, "--out", tmp_path / "o.csv", "--rejected", scans])
    assert msg.startswith(f"--rejected {str(scans)!r} is the same file as the input SCANS ")
    assert scans.read_bytes()[:2] == b"PK"  # untouched


def test_two_outputs_on_one_file_name_both_options(scans, tmp_path):
    o = tmp_path / "o.csv"
    msg = _error(["detect", scans, "--out", o, "--rejected", o])
    assert f"given twice, as --out {str(o)!r} and --rejected {str(o)!r}" in msg
    other = tmp_path / "sub" / ".." / "o.csv"  # another spelling of the same file
    msg = _error(["detect", scans, "--out", o, "--rejected", other])
    assert f"--out {str(o)!r} and --rejected {str(other)!r}" in msg


def test_output_on_the_manifest_names_the_option_and_the_manifest_owner(scans, tmp_path):
    o = tmp_path / "o.csv"
    m = tmp_path / "o.csv.run.json"
    msg = _error(["detect", scans, "--out", o, "--rejected", m])
    assert msg.startswith(f"--rejected {str(m)!r} is where the run's manifest goes")
    assert f"the manifest of --out {str(o)!r}" in msg


def test_a_derived_product_is_an_output_not_an_option(tmp_path):
    # sim scans writes run_poses.csv beside --out: --trees-out on it names the option once
    out = tmp_path / "run.npz"
    poses = tmp_path / "run_poses.csv"
    msg = _error(["sim", "scans", "--out", out, "--trees-out", poses, "-q"])
    assert f"as --trees-out {str(poses)!r} and output {str(poses)!r}" in msg


def test_input_given_by_an_option_is_named_by_it(tmp_path):
    # fuse: --out on the --calibration file
    for n in ("scan.npz", "frame.png", "calib.json"):
        (tmp_path / n).write_text("x")
    calib = tmp_path / "calib.json"
    argv = ["fuse", "--scan", tmp_path / "scan.npz", "--image", tmp_path / "frame.png"]
    msg = _error([*argv, "--calibration", calib, "--out", calib])
    assert msg.startswith(
        f"--out {str(calib)!r} is the same file as the input --calibration {str(calib)!r}"
    )


def test_stems_png_on_the_cloud(tmp_path):
    cloud = tmp_path / "c.xyz"
    cloud.write_text("0 0 0\n")
    msg = _error(["stems", cloud, "--out", tmp_path / "s.csv", "--png", cloud])
    assert msg.startswith(f"--png {str(cloud)!r} is the same file as the input CLOUDS ")


def test_folder_commands_name_out(tmp_path, scans):
    f = tmp_path / "a_file"
    f.write_text("keep")
    assert _error(["demo", "--out", f]).startswith(f"--out {str(f)!r} is a file, but must be")
    msg = _error(["map", scans, "-o", tmp_path])
    assert msg.startswith(f"--out {str(tmp_path)!r} is a folder that contains the input INPUT ")


def test_blocked_folder_names_the_option(scans, tmp_path):
    (tmp_path / "blk").write_text("a file")
    r = tmp_path / "blk" / "r.csv"
    msg = _error(["detect", scans, "--out", tmp_path / "o.csv", "--rejected", r])
    assert msg.startswith(f"cannot write --rejected {str(r)!r}: ")


def test_odometry_camera_output_is_checked_too(tmp_path):
    # camera-only odometry wrote its CSV directly (no refusal, no staging, no manifest)
    cam = tmp_path / "frames"
    cam.mkdir()
    (cam / "camera.json").write_text("{}")
    msg = _error(["odometry", "--camera", cam, "--out", cam / "camera.json"])
    assert msg.startswith(f"--out {str(cam / 'camera.json')!r} is a file of the input folder ")
    assert "--camera" in msg and (cam / "camera.json").read_text() == "{}"


def test_outside_a_command_the_messages_say_output_and_input(tmp_path):
    p = tmp_path / "in.csv"
    p.write_text("x")
    with pytest.raises(OutputError) as err, run_products("t", inputs=[p], outputs=[p]):
        pass
    assert str(err.value).startswith(f"output {str(p)!r} is the same file as the input {str(p)!r}")
