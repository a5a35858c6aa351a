"""An honest zip bomb -- an NPZ whose arrays are announced consistently and really are huge
once decompressed -- is refused before numpy allocates it, by the read budget
(``stemmap.io._budget``: half the available memory, ``STEMMAP_MAX_READ_GB`` to change it).

Before, only damage was caught (an announced size the member cannot hold); a 20 MB NPZ of
deflated zeros holding 20 GB of ``ranges`` passed every check and numpy allocated 20 GB.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
from numpy.lib import format as npy_format
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import ConfigError, InputError
from stemmap.io import _budget, read_scans
from stemmap.io._budget import BUDGET_ENV, BUDGET_FLOOR_BYTES, read_budget

ROWS, BEAMS = 4000, 361  # 11.6 MB of float64 ranges, ~12 kB deflated


def _bomb(path: Path, rows: int = ROWS, method: int = zipfile.ZIP_DEFLATED) -> Path:
    """A valid scan NPZ whose ranges are all 5.0 m: tiny on disk, ``rows`` x 361 in memory.

    Written member by member in chunks, as a real bomb would be (nothing of the announced
    size is ever held in memory by the test)."""
    with zipfile.ZipFile(path, "w", compression=method) as zf:
        for name, value in (("angle_min", -math.pi / 2), ("angle_increment", math.pi / 360)):
            with zf.open(f"{name}.npy", "w") as fh:
                npy_format.write_array(fh, np.array(value))
        with zf.open("time.npy", "w") as fh:
            npy_format.write_array(fh, np.arange(rows) * 0.025)
        with zf.open("ranges.npy", "w", force_zip64=True) as fh:
            npy_format.write_array_header_1_0(
                fh, {"descr": "<f8", "fortran_order": False, "shape": (rows, BEAMS)}
            )
            row = np.full(BEAMS, 5.0).tobytes()
            for _ in range(rows):
                fh.write(row)
    return path


def test_honest_bomb_over_the_budget_is_refused_naming_file_size_and_limit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bomb = _bomb(tmp_path / "bomb.npz")
    assert bomb.stat().st_size < 100_000  # consistent headers: no damage to detect
    monkeypatch.setenv(BUDGET_ENV, "0.005")  # 5 MB
    with pytest.raises(InputError) as info:
        read_scans(bomb)
    msg = str(info.value)
    assert "bomb.npz" in msg
    assert "11.6 MB when decompressed" in msg and "'ranges'" in msg and "(4000, 361)" in msg
    assert "read limit of 5 MB" in msg and f"{BUDGET_ENV}=0.1" in msg  # 11.6 MB + 10 %, GB


@pytest.mark.parametrize("method", [zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
def test_bzip2_and_lzma_members_expand_past_deflates_ratio_and_still_load(
    tmp_path: Path, method: int
) -> None:
    # before: every compressed member was bounded by deflate's 1032:1, so a genuine bzip2 NPZ
    # of a constant array (~1e5:1) was refused as "damaged"; the budget bounds these now
    p = _bomb(tmp_path / "b.npz", rows=20_000, method=method)
    assert p.stat().st_size * 1032 < 20_000 * BEAMS * 8
    batch = read_scans(p)
    assert batch.ranges.shape == (20_000, BEAMS) and np.all(batch.ranges == 5.0)


def test_the_same_file_loads_within_the_default_budget(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv(BUDGET_ENV, raising=False)
    batch = read_scans(_bomb(tmp_path / "bomb.npz"))
    assert batch.ranges.shape == (ROWS, BEAMS) and float(batch.ranges.max()) == 5.0


def test_zero_turns_the_limit_off(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(_budget, "available_memory", lambda: 1000)
    monkeypatch.setenv(BUDGET_ENV, "0")
    assert read_budget()[0] == math.inf
    monkeypatch.setenv(BUDGET_ENV, "lots")
    with pytest.raises(ConfigError, match="not a number of gigabytes"):
        read_budget()


def test_default_is_half_the_available_memory_with_a_floor(monkeypatch) -> None:
    monkeypatch.delenv(BUDGET_ENV, raising=False)
    monkeypatch.setattr(_budget, "available_memory", lambda: 16 * 10**9)
    budget, why = read_budget()
    assert budget == 8e9 and "50% of the 16 GB" in why
    monkeypatch.setattr(_budget, "available_memory", lambda: 100 * 10**6)
    assert read_budget()[0] == BUDGET_FLOOR_BYTES  # a busy machine still reads ordinary files


def test_available_memory_is_plausible() -> None:
    avail = _budget.available_memory()
    assert avail is not None and 10**7 < avail < 10**15


def test_cli_refuses_with_one_error_line_and_writes_nothing(tmp_path: Path, monkeypatch) -> None:
    bomb = _bomb(tmp_path / "bomb.npz")
    monkeypatch.setattr(_budget, "available_memory", lambda: 8 * 10**6)  # budget = floor
    monkeypatch.setattr(_budget, "BUDGET_FLOOR_BYTES", 4 * 10**6)
    out = tmp_path / "d.csv"
    res = CliRunner().invoke(app, ["detect", str(bomb), "-o", str(out), "-q"])
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())
    assert "error: scan NPZ" in text and "read limit of 4 MB" in text
    assert "50% of the 8 MB of memory available now" in text
    assert not out.exists()


def test_whole_cloud_read_of_a_laz_announcing_billions_is_refused_first(
    tmp_path: Path,
) -> None:
    # read_las (map / odometry frames, library use) concatenates every chunk: a LAZ header
    # announcing 2e10 points asked laspy for them chunk by chunk and failed only after the
    # first chunk; the budget refuses from the header (xyz + 4 fields, twice: 2.24 TB)
    from hostile_inputs import las_announcing  # benchmarks/ (tests/conftest.py)
    from stemmap.io.clouds import read_las

    p = las_announcing(tmp_path / "c.laz", 2 * 10**10)
    with pytest.raises(InputError, match=r"announces 20,000,000,000 points, ~2\.24 TB"):
        read_las(p)


_ROOM_PROBE = """
import json, mmap, resource, sys
from stemmap.io import _budget

def mapped():
    return _budget._mapped_bytes()

limit = mapped() + (3 << 30)  # 3 GiB above what the process has mapped now
resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
before = (_budget._address_space_room(), mapped())
block = mmap.mmap(-1, 1 << 30)  # 1 GiB mapped, never touched: no RSS, but address space
after = (_budget._address_space_room(), mapped())
avail = _budget.available_memory()
print(json.dumps({"limit": limit, "before": before, "after": after, "avail": avail}))
"""


def test_address_space_room_is_the_limit_less_what_is_mapped() -> None:
    """Under ``ulimit -v`` (RLIMIT_AS) the room is the limit less the process's mapped size
    (VmSize), not the limit: before, a process already holding 1 GiB of address space under a
    4 GiB limit was told 4 GiB were available. Run in a child: RLIMIT_AS would bind pytest."""
    import json
    import os
    import subprocess
    import sys

    src = str(Path(_budget.__file__).parents[2])
    env = dict(os.environ, PYTHONPATH=src)
    res = subprocess.run(
        [sys.executable, "-c", _ROOM_PROBE], env=env, capture_output=True, text=True, check=True
    )
    got = json.loads(res.stdout)
    limit, (room0, mapped0), (room1, mapped1) = got["limit"], got["before"], got["after"]
    slack = 64 << 20  # reading /proc and building tuples may map a new malloc arena or two
    assert abs(room0 - (limit - mapped0)) <= slack
    assert abs(room0 - (3 << 30)) <= slack
    # mapping 1 GiB shrinks the room by 1 GiB (the old code kept returning `limit`)
    assert abs((room0 - room1) - (1 << 30)) <= slack
    assert abs((mapped1 - mapped0) - (1 << 30)) <= slack
    assert got["avail"] <= room1 + slack  # the least of the sources


def test_address_space_room_is_floored_at_zero(monkeypatch) -> None:
    import resource

    monkeypatch.setattr(resource, "getrlimit", lambda _r: (1 << 20, resource.RLIM_INFINITY))
    monkeypatch.setattr(_budget, "_mapped_bytes", lambda: 1 << 30)
    assert _budget._address_space_room() == 0
    monkeypatch.setattr(_budget, "_mapped_bytes", lambda: None)  # /proc unreadable: the limit
    assert _budget._address_space_room() == 1 << 20
    monkeypatch.setattr(resource, "getrlimit", lambda _r: (resource.RLIM_INFINITY,) * 2)
    assert _budget._address_space_room() is None
