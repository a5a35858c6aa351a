"""treels pine_plot.laz randomly subsampled (benchmarks/cloud_robustness.py ``subsample_50``,
``subsample_20``, ``subsample_10``, seed 0; docs/algorithms/cloud.md "Plots at lower density
(Dec 4)"). A sparse band is cut into 3 slices of 0.4 m (from a 90th-percentile spacing of
75 mm on); two rules that did not follow the slices are pinned here:

* the pooled band fit asked for ``min_slices + 1`` = 4 slices with inliers, which 3 slices
  cannot give (:func:`stemmap.cloud.pooled._pooled_slices_needed`): at 10 % it lost 5 stems
  whose cylinders fit at 5-8 mm RMS;
* stems found on the thick slices are measured again on the thin ones
  (:func:`stemmap.cloud.slicestem._thin_slice_stem`): the thick lowest slice takes in the root
  flare and pulled DBH up.

References: the full-ring fits of the cloud as shipped (:func:`stemmap.cloud.reference.
stem_references`, 10 of its 16 stems -- 17 before the continues-above test; RMSE 0.75 cm
there), as the benchmark.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloud_robustness import TRANSFORMS, Context, _match
from stemmap.cloud import pooled
from stemmap.cloud.reference import stem_references
from stemmap.cloud.result import CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems
from stemmap.io.clouds import read_cloud


def _score(
    base: CloudStems, full: np.ndarray, ref_d: np.ndarray, det: CloudStems
) -> tuple[int, float]:
    """Baseline stems matched (the benchmark's gate) and DBH RMSE (m) over the full rings."""
    pairs = _match(base.xy, base.diameter, det.xy)
    err = np.array([det.diameter[j] - ref_d[i] for i, j in pairs if full[i]])
    return len(pairs), float(np.sqrt(np.mean(err**2)))


@pytest.fixture(scope="module")
def plot(datasets_dir: Path) -> tuple[np.ndarray, CloudStems, np.ndarray, np.ndarray]:
    xyz = read_cloud(datasets_dir / "treels/pine_plot.laz").xyz
    base = detect_stems(xyz, StemConfig())
    refs = stem_references(xyz, base)
    full = np.array([r is not None and r.full for r in refs])
    ref_d = np.array([r.diameter if r is not None else np.nan for r in refs])
    assert len(base) == 16 and full.sum() == 10  # 17 before the continues-above test
    return xyz, base, full, ref_d


def _run(plot: tuple, transform: str, cfg: StemConfig | None = None) -> tuple[int, float]:
    xyz, base, full, ref_d = plot
    prep = TRANSFORMS[transform](Context(xyz, None))
    assert prep is not None
    return _score(base, full, ref_d, detect_stems(prep.xyz, cfg or StemConfig()))


@pytest.mark.slow
def test_tenth_density_plot_keeps_its_pooled_stems(
    plot: tuple, monkeypatch: pytest.MonkeyPatch
) -> None:
    """10 %: 13 of the 16 stems (before: 8 of 17); 12 leaves one stem of margin, and the rule
    before the fix (4 slices with inliers out of 3) is back at 8."""
    n, _ = _run(plot, "subsample_10")
    assert n >= 12
    monkeypatch.setattr(pooled, "_pooled_slices_needed", lambda cfg, ns: cfg.min_slices + 1)
    # and without density_slice_points (on since Dec 6: it keeps two more stems)
    n_old, _ = _run(plot, "subsample_10", StemConfig(density_slice_points=False))
    assert n_old <= 8


@pytest.mark.slow
def test_sparse_plot_dbh_from_thin_slices(plot: tuple) -> None:
    """Full-ring DBH RMSE at 50 / 20 % (in memory): 0.46 / 0.39 cm measured (as shipped
    0.75). The thick slices' line alone (no thin re-measure, no slice at breast height:
    ``thick_dbh_slice``, Dec 5) gives 0.89 / 1.61 cm; either rule alone brings 50 % below
    the cloud as shipped (thin re-measure 0.49, breast-height slice 0.42 cm). Asserted: 50 %
    no worse than the cloud as shipped, 20 % within the issue's 1 cm, both worse with the
    line alone."""
    n50, e50 = _run(plot, "subsample_50")
    n20, e20 = _run(plot, "subsample_20")
    assert n50 >= 16 and n20 >= 14
    assert e50 <= 0.0075
    assert e20 <= 0.01
    line = StemConfig(thin_remeasure=False, thick_dbh_slice=False)
    _, e50_off = _run(plot, "subsample_50", line)
    _, e20_off = _run(plot, "subsample_20", line)
    assert e50_off > e50 and e20_off > e20


@pytest.mark.slow
def test_a_tighter_refit_stem_is_measured_on_thin_slices(datasets_dir: Path) -> None:
    """At 50 % (seed 0: four 0.3 m slices) the 8.6 cm stem at (0.42, 8.24) m is found only by
    the tighter refits (its slices fit the clutter around it at the first tolerance). A stem
    found on thick slices is measured again on thin ones wherever it was found
    (docs/algorithms/cloud.md "Single trees: the annulus about a found stem"); before, only
    first-round stems were: 9.32 cm on the thick slices, 8.50 cm on the thin ones, against a
    full ring of 8.51 cm. Asserted: within 0.3 cm of the ring (a quarter of the thick
    error), with and without the thin re-measure (since Dec 5 the thick measurement of a
    plot takes the slice at breast height, ``thick_dbh_slice``), and the thick line no
    closer. (Since Dec 5 the RANSAC draws are those of the canonical point order,
    docs/algorithms/cloud.md "Point order": the thick line gives 0.14 cm off; its > 0.5 cm
    was a draw of the file's order.)"""
    from _cloud_refs import fixed_references, load_seeds, reference_of_each

    xyz = read_cloud(datasets_dir / "treels/pine_plot.laz").xyz
    refs = fixed_references(xyz, load_seeds()["treels_pine_plot"])
    prep = TRANSFORMS["subsample_50"](Context(xyz, None))
    assert prep is not None

    def error_at_stem_4(cfg: StemConfig) -> float:
        det = detect_stems(prep.xyz, cfg)
        hits = reference_of_each(refs, det.xy)
        (d,) = [det.diameter[j] - h[1].diameter for j, h in enumerate(hits) if h and h[0] == 4]
        return abs(float(d))

    assert refs[4] is not None and refs[4].full
    on = error_at_stem_4(StemConfig())
    assert on < 0.003
    line = StemConfig(thin_remeasure=False, thick_dbh_slice=False)
    assert error_at_stem_4(line) >= on
    assert error_at_stem_4(StemConfig(thin_remeasure=False)) < 0.003


def test_pooled_slices_never_exceed_the_band() -> None:
    cfg = StemConfig()
    assert pooled._pooled_slices_needed(cfg, 6) == cfg.min_slices + 1
    assert pooled._pooled_slices_needed(cfg, 3) == 3
