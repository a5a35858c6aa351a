"""The radius at breast height from the slices about it (``StemConfig.dbh_from``;
docs/algorithms/cloud.md "Breast-height DBH, stage by stage").

A root flare widens the lowest slices of the 0.8-2.0 m band and fades by about breast height:
the profile is convex and the Theil-Sen line through every kept slice passes above the stem
at 1.3 m (treels pine_plot: +0.40 cm over its ten full rings). ``"median"`` takes the median of
the slice holding the measurement height and its neighbours, ``"slice"`` that slice alone.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stemmap.cloud.bhradius import near_median_radius
from stemmap.cloud.config import StemConfig
from stemmap.cloud.dbhsd import MEDIAN_FACTOR
from stemmap.cloud.slicestem import _SliceFits, _stem_at
from stemmap.cloud.stems import detect_stems_file
from stemmap.errors import ConfigError

H = np.array([0.9, 1.1, 1.3, 1.5, 1.7, 1.9])
#: a flared profile (radii, m): 1.5 cm wider at 0.9 m, 1 cm at 1.1 m, straight from 1.3 m up
#: (the shape of treels pine_plot's stems, e.g. ring 10: 27.2 / 27.4 / 25.3 / 25.0 / 25.3 /
#: 25.0 cm in diameter)
FLARED = [0.140, 0.135, 0.125, 0.1245, 0.124, 0.1235]


def _fits(radii: list[float], centers: np.ndarray | None = None) -> _SliceFits:
    ns = len(radii)
    cov = np.zeros((1, ns, 3, 3))
    cov[0, :] = np.diag([1e-6, 1e-6, 4e-6])
    cen = np.tile([1.0, 2.0], (1, ns, 1)).astype(float) if centers is None else centers[None]
    return _SliceFits(
        passed=np.ones((1, ns), dtype=bool),
        fitted=np.ones((1, ns), dtype=bool),
        centers=cen,
        radii=np.array([radii], dtype=float),
        rms=np.full((1, ns), 0.005),
        arcs=np.full((1, ns), 320.0),
        n_in=np.full((1, ns), 40, dtype=np.int64),
        weights=np.full((1, ns), 40 / 0.005**2),
        cov=cov,
        present=np.array([ns]),
    )


def test_the_line_through_a_flared_profile_is_above_the_stem() -> None:
    """The line at 1.3 m is above the 12.5 cm slice there; the median of the 1.1 / 1.3 /
    1.5 m slices is that slice's radius (the flare at 1.1 m is outvoted), the slice mode the
    slice's own; a vertical stem, so no lean correction."""
    fits, m, hh = _fits(FLARED), np.ones(6, dtype=bool), H - 1.3
    line = _stem_at(fits, 0, m, hh, StemConfig(dbh_from="line"))
    assert line is not None
    assert line[0] > 0.127  # 0.2 cm or more of radius above the slice at breast height
    near = near_median_radius(fits.radii[0], fits.centers[0], fits.cov[0, :, 2, 2], hh, 0.2)
    assert near is not None
    assert near[0] == pytest.approx(0.125, abs=1e-12)
    # the variance of the median of three slices along the line's slope (1.65 cm of radius
    # per m: 3.3 mm steps against 2 mm of fit noise): above the iid median's (1.346 / 3 of one
    # slice's variance), below one slice's own (a steep taper makes the median the middle
    # slice); exact values: tests/cloud/test_dbh_sd.py
    assert MEDIAN_FACTOR[3] / 3 * 4e-6 < near[1] < 4e-6
    at = _stem_at(fits, 0, m, hh, StemConfig(), at_slice=True)
    assert at is not None and at[0] == pytest.approx(0.125, abs=1e-12)


def test_a_leaning_stem_keeps_the_lean_correction() -> None:
    """Centres moving 0.2 m per m of height (11.3 degrees): the median is lean-corrected by
    2 cos / (1 + cos), as the line is."""
    cen = np.column_stack((1.0 + 0.2 * (H - 1.3), np.full(6, 2.0)))
    fits, hh = _fits(FLARED, cen), H - 1.3
    near = near_median_radius(fits.radii[0], fits.centers[0], fits.cov[0, :, 2, 2], hh, 0.2)
    assert near is not None
    cos_t = 1 / math.sqrt(1 + 0.2**2)
    assert near[0] == pytest.approx(0.125 * 2 * cos_t / (1 + cos_t), rel=1e-9)


def test_fewer_than_three_slices_about_the_height_keep_the_line() -> None:
    """Kept slices at 0.9 / 1.3 / 1.7 / 1.9 m: only one within 0.2 m of 1.3 m -- None (the
    caller keeps the line)."""
    keep = np.array([True, False, True, False, True, True])
    fits = _fits(FLARED)
    r, cen, var = fits.radii[0, keep], fits.centers[0, keep], fits.cov[0, keep, 2, 2]
    assert near_median_radius(r, cen, var, H[keep] - 1.3, 0.2) is None


def test_config_refuses_an_unknown_value() -> None:
    with pytest.raises(ConfigError, match="dbh_from"):
        StemConfig(dbh_from="spline")
    assert StemConfig().dbh_from == "median"  # default since Dec 6 (docs/algorithms.md)


@pytest.mark.slow
def test_pine_plot_full_rings(datasets_dir: Path) -> None:
    """treels pine_plot.laz as shipped (cloud_real.py's run): the same stems with every value;
    against the ten full rings the line has a bias of +0.39 cm and RMSE 0.75 cm, the median
    below 0.1 cm bias and 0.35 cm RMSE (measured -0.03 / 0.26)."""
    from cloud_real import CLOUDS, run_one

    path = str(datasets_dir / CLOUDS["treels_pine_plot"])
    line = run_one(path, "treels_pine_plot", {"dbh_from": "line"})
    med = run_one(path, "treels_pine_plot", {"dbh_from": "median"})
    assert med["n_stems"] == line["n_stems"] and med["full_ring_stems"] == 10
    assert line["dbh_bias_vs_full_rings_cm"] > 0.3 and line["dbh_rmse_vs_full_rings_cm"] > 0.7
    assert abs(med["dbh_bias_vs_full_rings_cm"]) < 0.1
    assert med["dbh_rmse_vs_full_rings_cm"] < 0.35


def _cells(key: str, name: str, seed: int, cfgs: list[StemConfig]) -> list[dict[str, Any]]:
    """cloud_robustness's rows of cloud ``key`` under transform ``name`` (seed) per config."""
    from cloud_real import CLOUDS
    from cloud_robustness import run_baseline, score_run, transformed_files

    bl = run_baseline(key, datasets_dir_of() / CLOUDS[key])
    with tempfile.TemporaryDirectory() as td:
        rows = [
            [score_run(nm, bl, detect_stems_file(f, c), prep) for c in cfgs]
            for nm, prep, f in transformed_files(bl, [name], Path(td), seed)
        ]
    assert len(rows) == 1
    return rows[0]


def datasets_dir_of() -> Path:
    from stemmap.datasets import find_datasets_dir

    root = find_datasets_dir()
    assert root is not None
    return root


@pytest.mark.slow
def test_spruce_cells_the_median_passes(datasets_dir: Path) -> None:
    """The two cells of cloud_loo.py where the values differ in passing (Dec 6): treels
    spruce at 20 % (seed 1) and with 1 cm noise (seed 3) -- the line 3.06 / 2.09 cm off the
    ring, the median 0.28 / 0.98 cm (the issue's single-tree target: 1.5 cm)."""
    line, med = StemConfig(dbh_from="line"), StemConfig(dbh_from="median")
    rows = [
        _cells("treels_spruce", "subsample_20", 1, [line, med]),
        _cells("treels_spruce", "noise_1cm", 3, [line, med]),
    ]
    for r_line, r_med in rows:
        assert r_line["matched"] == r_med["matched"] == 1
        assert abs(r_line["dbh_vs_ring_rmse_cm"]) > 1.5
        assert abs(r_med["dbh_vs_ring_rmse_cm"]) <= 1.5
