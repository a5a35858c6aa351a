"""``StemConfig.ladder_by``: the single-tree ladder may also take a smaller stem fitted below
the kept stem's RMS when its DBH error with the section term is smaller and the two DBHs agree
within ``ladder_agree_z`` standard deviations of their difference (docs/algorithms/cloud.md
"The single-tree ladder by its error"). The stem values below are those traced on the real
cells (``benchmarks/cloud_single_tree_trace.py``)."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import pytest

from cloud_robustness import TRANSFORMS, Context, write_las
from stemmap.cloud._ladder import _single_tree_stem, _stem_weight
from stemmap.cloud.config import StemConfig
from stemmap.cloud.reference import stem_references
from stemmap.cloud.stems import detect_stems_file
from stemmap.errors import ConfigError
from stemmap.io.clouds import read_cloud

Stem = tuple[tuple[float, ...], str]


def _stem(dbh: float, n: int, rms: float) -> Stem:
    # (x, y, dbh, n_points, quality, arc, rms, n_slices, taper, dbh_std, cxx, cxy, cyy, h)
    return ((0.0, 0.0, dbh, n, 1.0, 230.0, rms, 4, 0.0, 0.001, 0.0, 0.0, 0.0, 1.3), "bh")


def _ladder(at_tol: float, stem: Stem) -> Callable[[bool, float, float], Stem | None]:
    """A ladder whose only stem is ``stem``, on the band's slices at tolerance ``at_tol``."""

    def refit(thin: bool, first: float, tol: float) -> Stem | None:
        return stem if not thin and math.isclose(tol, at_tol) else None

    return refit


def _errors(table: dict[int, float]) -> Callable[[Stem], float]:
    return lambda s: table[id(s)]


def test_default_and_validation() -> None:
    assert StemConfig().ladder_by == "tolerance"
    assert StemConfig().ladder_agree_z == 2.0
    assert StemConfig(ladder_by="error").ladder_by == "error"
    with pytest.raises(ConfigError, match="ladder_by"):
        StemConfig(ladder_by="support")
    with pytest.raises(ConfigError, match="ladder_agree_z"):
        StemConfig(ladder_agree_z=0.0)


# treels spruce with 1 cm noise, seed 0: the kept stem is a line through 0.9 / 1.1 / 1.9 m
# (25.25 cm, RMS 13.3 mm, DBH sd with the section term 2.61 cm); the ladder's 6 mm rung holds
# four slices, one at 1.3 m (23.67 cm, sd 0.52 cm) with more support
SPRUCE_TOL0 = 0.024
SPRUCE_KEPT = _stem(0.2525, 300, 0.0133)
SPRUCE_RUNG = _stem(0.2367, 180, 0.0060)


def test_a_better_measurement_of_the_same_surface_is_taken() -> None:
    assert _stem_weight(SPRUCE_RUNG[0]) > _stem_weight(SPRUCE_KEPT[0])
    refit = _ladder(SPRUCE_TOL0 / 4, SPRUCE_RUNG)
    # by tolerance: fitted at 6 mm, below the kept stem's 13.3 mm RMS -- no fair comparison
    assert _single_tree_stem(SPRUCE_KEPT, refit, SPRUCE_TOL0, False) is SPRUCE_KEPT
    errors = _errors({id(SPRUCE_KEPT): 0.0261, id(SPRUCE_RUNG): 0.0052})
    got = _single_tree_stem(SPRUCE_KEPT, refit, SPRUCE_TOL0, False, error=errors)
    assert got is SPRUCE_RUNG


def test_a_larger_error_is_not_taken() -> None:
    refit = _ladder(SPRUCE_TOL0 / 4, SPRUCE_RUNG)
    errors = _errors({id(SPRUCE_KEPT): 0.0052, id(SPRUCE_RUNG): 0.0261})
    got = _single_tree_stem(SPRUCE_KEPT, refit, SPRUCE_TOL0, False, error=errors)
    assert got is SPRUCE_KEPT


def test_a_circle_carved_from_rough_bark_is_refused() -> None:
    # aRchi Tree_1 at 20 %, seed 0: the kept stem 53.58 cm (found at RMS 18.2 mm, sd 1.50 cm);
    # the 14.6 mm rung carves a 40.36 cm circle of five slices out of its bark, a consistent
    # inner surface: its error (1.18 cm) is the smaller and its support the larger, but it
    # lies 13.2 cm from the kept stem, 7 sd of the difference
    tol0 = 0.0585
    kept = _stem(0.5358, 150, 0.0163)
    carved = _stem(0.4036, 60, 0.0063)
    assert _stem_weight(carved[0]) > _stem_weight(kept[0])
    errors = _errors({id(kept): 0.0150, id(carved): 0.0118})
    refit = _ladder(tol0 / 4, carved)
    got = _single_tree_stem(kept, refit, tol0, False, 0.0182, errors)
    assert got is kept
    # the agreement is what refuses it: with a bound wide enough to hold 13 cm it would win
    assert _single_tree_stem(kept, refit, tol0, False, 0.0182, errors, agree_z=8.0) is carved


@pytest.mark.slow
def test_noisy_spruce_within_its_ring(datasets_dir: Path, tmp_path: Path) -> None:
    """treels spruce with 1 cm Gaussian noise per axis (``cloud_robustness`` ``noise_1cm``,
    seed 0, through its LAS file): by tolerance the DBH is 1.88 cm off the shipped cloud's
    ring (the line across the whorls at 1.3 and 1.5 m), by error 0.29 cm. Bounds: the
    issue's 1.5 cm on both sides."""
    path = datasets_dir / "treels/spruce.laz"
    xyz = read_cloud(path).xyz
    (ref,) = stem_references(xyz, detect_stems_file(path, StemConfig()))
    assert ref is not None and ref.full
    prep = TRANSFORMS["noise_1cm"](Context(xyz, None, 0))
    assert prep is not None
    f = tmp_path / "cloud.las"
    write_las(f, prep.xyz, prep.scale, prep.offset_round)
    by_tol = detect_stems_file(f, StemConfig())
    by_err = detect_stems_file(f, StemConfig(ladder_by="error"))
    assert len(by_tol) == len(by_err) == 1
    assert abs(by_tol.diameter[0] - ref.diameter) > 0.015
    assert abs(by_err.diameter[0] - ref.diameter) < 0.015


@pytest.mark.slow
def test_tree_1_thinned_keeps_its_bark(datasets_dir: Path, tmp_path: Path) -> None:
    """aRchi Tree_1 (54 cm, rough bark) thinned to 20 %, seed 0, through the benchmark's LAS
    file: the ladder's 40.4 cm carved circle has the smaller DBH error but is refused by the
    agreement; the DBH stays within the benchmark's 1.5 cm of the shipped tree's."""
    path = datasets_dir / "archi/Tree_1_point_cloud.las"
    xyz = read_cloud(path).xyz
    shipped = detect_stems_file(path, StemConfig())
    prep = TRANSFORMS["subsample_20"](Context(xyz, None, 0))
    assert prep is not None
    f = tmp_path / "cloud.las"
    write_las(f, prep.xyz, prep.scale, prep.offset_round)
    got = detect_stems_file(f, StemConfig(ladder_by="error"))
    assert len(shipped) == len(got) == 1
    assert abs(got.diameter[0] - shipped.diameter[0]) < 0.015
