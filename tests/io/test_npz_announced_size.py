"""NPZ members whose .npy header announces more data than the file holds are refused by name.

numpy allocates an array at its announced shape before reading it, so a damaged 1 kB file
announcing (10**6, 10**6) floats ended every NPZ reader in "out of memory: the input is too
large for this machine" -- pointing at the machine, not at the file.
"""

from __future__ import annotations

import io
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
from numpy.lib import format as npy_format
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import InputError
from stemmap.io import read_scans, write_scans_npz
from stemmap.io._util import check_npz_sizes
from stemmap.io.frames import read_frames_npz
from stemmap.types import ScanBatch

HUGE = (10**6, 10**6)


def _npy(arr: np.ndarray) -> bytes:
    bio = io.BytesIO()
    np.save(bio, arr)
    return bio.getvalue()


def _announce(src: Path, dst: Path, member: str, shape: tuple[int, ...] = HUGE) -> None:
    """Copy the NPZ ``src`` to ``dst`` with ``member``'s header announcing ``shape``."""
    with zipfile.ZipFile(src) as zi, zipfile.ZipFile(dst, "w") as zo:
        for info in zi.infolist():
            data = zi.read(info.filename)
            if info.filename == member:
                bio = io.BytesIO(data)
                npy_format.read_magic(bio)
                _, _, dtype = npy_format.read_array_header_1_0(bio)
                head = io.BytesIO()
                npy_format.write_array_header_1_0(
                    head,
                    {
                        "descr": npy_format.dtype_to_descr(dtype),
                        "fortran_order": False,
                        "shape": shape,
                    },
                )
                data = head.getvalue() + bio.read()
            zo.writestr(info, data)


def _scans(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    b = ScanBatch(rng.uniform(1, 20, (6, 91)), np.arange(6) * 0.1, -math.pi / 2, math.pi / 90)
    p = tmp_path / "scans.npz"
    write_scans_npz(p, b)
    return p


def test_scan_npz_announcing_terabytes_names_the_field(tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    _announce(_scans(tmp_path), bad, "ranges.npy")
    with pytest.raises(InputError, match=r"field 'ranges' announces shape \(1000000, 1000000\)"):
        read_scans(bad)


def test_cli_says_damaged_not_out_of_memory(tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    _announce(_scans(tmp_path), bad, "ranges.npy")
    res = CliRunner().invoke(app, ["detect", str(bad), "-o", str(tmp_path / "d.csv"), "-q"])
    assert res.exit_code == 2
    assert "out of memory" not in res.output
    assert "damaged or truncated" in res.output and "bad.npz" in res.output
    assert not (tmp_path / "d.csv").exists()


def test_frames_bundle_announcing_terabytes(tmp_path: Path) -> None:
    good = tmp_path / "drive.npz"
    pts = np.zeros((4, 3), np.float32)
    np.savez_compressed(good, times=np.array([0.0, 0.1]), points=pts, frame_ptr=np.array([0, 2, 4]))
    read_frames_npz(good)  # the intact bundle reads
    bad = tmp_path / "bad.npz"
    _announce(good, bad, "points.npy")
    with pytest.raises(InputError, match=r"frames bundle .*field 'points' announces"):
        read_frames_npz(bad)


def test_honest_members_pass_stored_and_compressed(tmp_path: Path) -> None:
    """Real files pass: the bound is the member's own sizes, not a guess."""
    arrays = {"a": np.zeros((300, 400)), "b": np.arange(7), "c": np.array("text"), "d": np.zeros(0)}
    for save in (np.savez, np.savez_compressed):
        p = tmp_path / f"{save.__name__}.npz"
        save(p, **arrays)  # type: ignore[operator]
        with np.load(p) as z:
            check_npz_sizes(z, p, "test NPZ")


def test_deflate_ratio_bounds_a_lying_uncompressed_size(tmp_path: Path) -> None:
    """A member whose zip entry also lies about its size is still bounded by its compressed size."""
    p = tmp_path / "lie.npz"
    head = io.BytesIO()
    npy_format.write_array_header_1_0(
        head, {"descr": "<f8", "fortran_order": False, "shape": (10**9,)}
    )
    with zipfile.ZipFile(p, "w", compression=zipfile.ZIP_DEFLATED) as zo:
        zo.writestr("x.npy", head.getvalue() + b"\0" * 800)
    raw = bytearray(p.read_bytes())
    # the central directory's uncompressed size (offset 24 of the entry) claims 8 GB
    cd = raw.rfind(b"PK\x01\x02")
    raw[cd + 24 : cd + 28] = (0xFFFFFFF0).to_bytes(4, "little")
    p.write_bytes(bytes(raw))
    with (
        np.load(p) as z,
        pytest.raises(InputError, match=r"field 'x' announces shape \(1000000000,\)"),
    ):
        check_npz_sizes(z, p, "test NPZ")
