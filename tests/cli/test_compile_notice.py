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
