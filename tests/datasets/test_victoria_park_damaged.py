"""Victoria Park with a truncated inputs.dat is refused, never silently mapped (issue 13)."""

from __future__ import annotations

import shutil

import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.datasets.victoria_park import load_victoria_park
from stemmap.errors import InputError


@pytest.fixture
def truncated(datasets_dir, tmp_path):
    """A copy of Victoria Park whose inputs.dat stops at t = 7 s (../shared is never touched)."""
    src = datasets_dir / "victoria_park"
    dst = tmp_path / "vp"
    dst.mkdir()
    for n in ("measurements.dat", "gps.dat"):
        shutil.copyfile(src / n, dst / n)
    lines = (src / "inputs.dat").read_text().splitlines(keepends=True)
    (dst / "inputs.dat").write_text("".join(ln for ln in lines if float(ln.split()[0]) <= 7.0))
    return dst


def test_truncated_odometry_is_refused_with_the_common_span(truncated):
    vp = load_victoria_park(truncated)
    with pytest.raises(InputError) as ei:
        vp.problem()
    msg = str(ei.value)
    assert "inputs.dat" in msg and "measurements.dat" in msg and "truncated" in msg
    assert "--t-end 7.0" in msg
    # the common span maps: the scans up to 7 s are covered by the odometry
    p = vp.slice(0.0, 7.0).problem()
    assert p.frames.times[-1] <= 7.0


def test_the_intact_run_passes_the_span_check(datasets_dir):
    load_victoria_park(datasets_dir / "victoria_park").check_time_spans()


def test_map_cli_refuses_the_truncated_run(truncated, tmp_path):
    res = CliRunner().invoke(
        app,
        [
            *("map", "--dataset", "victoria-park", "--data", str(truncated), "--backend", "ekf"),
            *("--out", str(tmp_path / "m"), "--no-progress"),
        ],
    )
    assert res.exit_code == 2
    errs = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(errs) == 1 and "inputs.dat" in errs[0] and "--t-end" in errs[0]
    assert not (tmp_path / "m").exists()
