"""Every real cloud in ../shared/datasets yields its stems (issue 11), with DBH against the
cloud's own breast-height ring and tree height against the cloud's top (issue 14).

Numbers per dataset: ``python benchmarks/cloud_real.py`` (docs/algorithms/cloud.md, "Real
clouds"); the rings are the benchmark's fixed references (benchmarks/_cloud_refs.py: seeded
from a committed file, not from the detection under test). Tolerances: 1.5 cm of the ring
reference for single trees (the issue's target; the references' own RMS is 0.3-2.1 cm), 1 cm
DBH RMSE over a plot's full rings, 0.5 m of height.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from _cloud_refs import CLOUDS, fixed_references, load_seeds, reference_of_each
from stemmap.cloud.result import BASE_SLICE, CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems_file
from stemmap.io.clouds import read_cloud

pytestmark = pytest.mark.slow


def _run(path: Path) -> tuple[np.ndarray, CloudStems, list[float], list[float]]:
    xyz = read_cloud(path).xyz
    det = detect_stems_file(path, replace(StemConfig(), estimate_height=True))
    key = next(k for k, v in CLOUDS.items() if path.as_posix().endswith(v))
    refs = fixed_references(xyz, load_seeds()[key])
    errs, full = [], []
    for i, hit in enumerate(reference_of_each(refs, det.xy)):
        if hit is not None:
            ref = hit[1]
            errs.append(float(det.diameter[i] - ref.diameter))
            if ref.full:
                full.append(errs[-1])
    return xyz, det, errs, full


def _height_ok(xyz: np.ndarray, det: CloudStems) -> None:
    for i in range(len(det)):
        near = np.hypot(*(xyz[:, :2] - det.xy[i]).T) <= 1.0
        base = det.z[i] - det.dbh_height[i]
        assert abs(det.height[i] - (xyz[near, 2].max() - base)) < 0.5


@pytest.mark.parametrize(
    ("rel", "base"),
    [
        ("treels/spruce.laz", "ground"),  # branches to the ground: found no stem before
        ("treels/pine.laz", "ground"),
        ("archi/Tree_1_point_cloud.las", "lowest stem points"),  # no ground in the cloud
        ("archi/Tree_2_point_cloud.las", "lowest stem points"),
    ],
)
def test_single_trees(datasets_dir: Path, rel: str, base: str) -> None:
    xyz, det, errs, _ = _run(datasets_dir / rel)
    assert len(det) == 1
    assert det.base == base
    assert len(errs) == 1 and abs(errs[0]) < 0.015
    assert np.isfinite(det.diameter_std[0]) and det.diameter_std[0] < 0.01
    _height_ok(xyz, det)


def test_lidr_slice(datasets_dir: Path) -> None:
    _, det, _, full = _run(datasets_dir / "lidr_dbh" / "dbh.laz")
    assert len(det) == 1 and det.base == BASE_SLICE
    assert len(full) == 1 and abs(full[0]) < 0.015


def test_pine_plot(datasets_dir: Path) -> None:
    xyz, det, _, full = _run(datasets_dir / "treels" / "pine_plot.laz")
    # 16 trunks pass through 1.3 m (the 1.3 m slice, docs/algorithms/cloud.md; the other
    # blobs in it are shrubs and debris below 1.5 m, and a 1.7 m sapling at (1.09, 9.68) m
    # with no return at 1.30-1.50 m: "pine_plot's 17th stem", no stem since the
    # continues-above test)
    assert len(det) == 16
    assert len(full) >= 8
    assert float(np.sqrt(np.mean(np.square(full)))) <= 0.01
    _height_ok(xyz, det)


def test_fortls_slice(datasets_dir: Path) -> None:
    _, det, _, full = _run(datasets_dir / "fortls_slice" / "diameters.laz")
    # 20 trunks of 10001 points each (200,020 points): all seen as full rings
    assert len(det) == 20 and len(full) == 20
    assert float(np.sqrt(np.mean(np.square(full)))) <= 0.01
