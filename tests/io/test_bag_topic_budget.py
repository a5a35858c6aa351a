"""``read_scans`` (``detect``, ``map``) holds a bag's whole LaserScan topic and then its
stack, ~4 x the topic's float32 ranges; the per-chunk checks (``io._bag_budget``) bound one
chunk, not the topic. The scans' bytes are now summed as they are read and the read is
refused (ReadLimitError, an InputError) once they and their stack pass the read budget."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io import read_scans
from stemmap.io._budget import BUDGET_ENV, ReadLimitError
from stemmap.io.bag_write import write_scans_bag
from stemmap.types import ScanBatch

N_SCANS, BEAMS = 120, 10_000  # 9.6 MB of float64 ranges, 4.8 MB of float32 in the bag


def _bag(path: Path, ros: int = 1, **kw: object) -> Path:
    a = np.linspace(-math.pi / 2, math.pi / 2, BEAMS)
    ranges = np.full((N_SCANS, BEAMS), 5.0)
    batch = ScanBatch(ranges, np.arange(N_SCANS) * 0.025, a[0], a[1] - a[0])
    return write_scans_bag(path, batch, ros=ros, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("name", "kw"),
    [("b.bag", {"ros": 1, "compression": "bz2"}), ("m", {"ros": 2, "storage": "mcap"})],
)
def test_a_topic_past_the_budget_is_refused_part_way(tmp_path: Path, monkeypatch, name, kw):
    bag = _bag(tmp_path / name, **kw)
    # 12 MB: one chunk passes its own check (7 x < 1 MB), the topic needs 2 x 9.6 MB
    monkeypatch.setenv(BUDGET_ENV, "0.012")
    with pytest.raises(ReadLimitError) as exc:
        read_scans(bag, topic="/scan")
    msg = str(exc.value)
    assert "topic '/scan'" in msg and f"{BUDGET_ENV} above " in msg and "read limit of 12 MB" in msg
    # refused once the scans and their stack pass 12 MB: 12e6 / (2 x 80 kB) = 75 scans,
    # not after reading all 120 (the bound on what is held)
    first = int(msg.split("its first ")[1].split(" scans")[0].replace(",", ""))
    assert first == math.floor(12e6 / (2 * 8 * BEAMS)) + 1 < N_SCANS


def test_a_topic_within_the_budget_reads_as_before(tmp_path: Path, monkeypatch) -> None:
    bag = _bag(tmp_path / "b.bag", ros=1, compression="lz4")
    monkeypatch.setenv(BUDGET_ENV, "0.02")  # 20 MB > 19.2 MB
    batch = read_scans(bag)
    assert batch.ranges.shape == (N_SCANS, BEAMS) and np.all(batch.ranges == 5.0)
    monkeypatch.setenv(BUDGET_ENV, "0")  # off
    assert read_scans(bag).ranges.shape == (N_SCANS, BEAMS)


def test_cli_refusal_is_one_error_line_and_no_output(tmp_path: Path, monkeypatch) -> None:
    bag = _bag(tmp_path / "b.bag", ros=1)
    monkeypatch.setenv(BUDGET_ENV, "0.012")
    out = tmp_path / "d.csv"
    res = CliRunner().invoke(app, ["detect", str(bag), "-o", str(out), "-q"])
    assert res.exit_code == 2, res.output
    errors = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "read limit" in res.output
    assert not out.exists()
