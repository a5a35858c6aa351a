"""``StemConfig.thin_remeasure_by``: the thin re-measure of a stem found on a thickened band
replaces the thick measurement when its DBH error (fit noise plus the kept slices' section
scatter) is smaller, not when more thin slices agree (docs/algorithms/cloud.md "Thinned
clouds: the re-measure by its error")."""

from __future__ import annotations

from pathlib import Path

import pytest

from cloud_robustness import TRANSFORMS, Context
from stemmap.cloud._ladder import _section_sd
from stemmap.cloud.config import StemConfig
from stemmap.cloud.stems import detect_stems
from stemmap.errors import ConfigError
from stemmap.io.clouds import read_cloud


def _row(std: float) -> tuple[float, ...]:
    # (x, y, dbh, n_points, quality, arc, rms, n_slices, taper, dbh_std, cxx, cxy, cyy, h)
    return (0.0, 0.0, 0.5, 100, 1.0, 230.0, 0.01, 4, 0.0, std, 0.0, 0.0, 0.0, 1.3)


def test_the_rule_is_a_choice_of_two() -> None:
    # "error" since Dec 6: chosen in 6 of 7 folds of the cloud LOO, held out never worse
    assert StemConfig().thin_remeasure_by == "error"
    assert StemConfig(thin_remeasure_by="slices").thin_remeasure_by == "slices"
    with pytest.raises(ConfigError, match="thin_remeasure_by"):
        StemConfig(thin_remeasure_by="count")


def test_the_error_is_read_at_the_model_weight_of_the_section_term() -> None:
    # whatever the configured weight (0: the stated std is the fit noise alone), the choice
    # reads the std with the section term at k = 1; no stem is an infinite error
    seen: list[float] = []

    def measure(cfg: StemConfig) -> tuple[tuple[float, ...], str]:
        seen.append(cfg.dbh_sd_scatter)
        return _row(0.02 + cfg.dbh_sd_scatter), "breast height"

    assert _section_sd(measure, StemConfig(dbh_sd_scatter=0.0)) == pytest.approx(1.02)
    assert seen == [1.0]
    assert _section_sd(lambda cfg: None, StemConfig()) == float("inf")


@pytest.mark.slow
def test_the_weight_never_changes_a_dbh(datasets_dir: Path) -> None:
    # the premise of the comparison: the section term changes the stated std, never the
    # DBH (aRchi Tree_1 at 20 %, seed 0: a thickened band, thin re-measure and ladder)
    xyz = read_cloud(datasets_dir / "archi/Tree_1_point_cloud.las").xyz
    prep = TRANSFORMS["subsample_20"](Context(xyz, None, 0))
    assert prep is not None
    k0 = detect_stems(prep.xyz, StemConfig(dbh_sd_scatter=0.0))
    k1 = detect_stems(prep.xyz, StemConfig(dbh_sd_scatter=1.0))
    assert len(k0) == len(k1) == 1
    assert k0.diameter[0] == k1.diameter[0]
    assert k1.diameter_std[0] > k0.diameter_std[0]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2])
def test_tree_1_thinned_keeps_the_better_measurement(datasets_dir: Path, seed: int) -> None:
    """aRchi Tree_1 (54 cm, 3-4 cm out of round) thinned to 20 % (the benchmark's draws, in
    memory). Seed 0: the three 0.4 m slices fit 26.9 / 28.0 / 26.7 cm (53.6 cm DBH); the thin
    re-measure passes four 0.2 m slices, one of them on the section's small side (22.2 cm at
    1.7 m), and by the count rule replaces the thick stem (52.0 cm). Its error with the
    section scatter is several times the thick one's, and by the error the thick stem
    stays, within the benchmark's 1.5 cm of the shipped tree's DBH."""
    xyz = read_cloud(datasets_dir / "archi/Tree_1_point_cloud.las").xyz
    shipped = detect_stems(xyz, StemConfig())
    assert len(shipped) == 1
    prep = TRANSFORMS["subsample_20"](Context(xyz, None, seed))
    assert prep is not None
    by_count = detect_stems(prep.xyz, StemConfig(thin_remeasure_by="slices"))
    by_error = detect_stems(prep.xyz, StemConfig(thin_remeasure_by="error"))
    assert len(by_count) == len(by_error) == 1
    assert abs(by_count.diameter[0] - shipped.diameter[0]) > 0.015
    assert abs(by_error.diameter[0] - shipped.diameter[0]) < 0.015
