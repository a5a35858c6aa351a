"""Slice circles refitted to the stem inside them (:func:`stemmap.cloud.slicefit.
_opaque_core_refits`; docs/algorithms/cloud.md "Single trees with noise: a trunk is opaque").

With 1 cm of Gaussian noise per axis, treels spruce.laz's stem slices fitted circles of
r 17-19 cm through the bark on one side and the branch stubs on the other (the stem is
r ~12 cm): DBH 37.6 cm against a 23.8 cm ring. Those circles hold the stem's far side inside
their disc, which a trunk (opaque) cannot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloud_robustness import TRANSFORMS, Context
from stemmap.cloud.reference import stem_references
from stemmap.cloud.slicefit import _opaque_core_refits
from stemmap.cloud.stems import StemConfig, detect_stems
from stemmap.io.clouds import read_cloud


def _ring_with_clutter(seed: int) -> np.ndarray:
    """A 12 cm stem seen all round (200 returns, 3 mm noise) and 60 clutter returns 18-26 cm
    from its centre on one side (branch stubs)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, 200)
    r = 0.12 + rng.normal(0, 0.003, a.shape[0])
    ring = np.column_stack((r * np.cos(a), r * np.sin(a)))
    b = rng.uniform(-0.6, 0.6, 60)
    d = rng.uniform(0.18, 0.26, b.shape[0])
    return np.vstack((ring, np.column_stack((d * np.cos(b), d * np.sin(b)))))


def _one_fit(cx: float, r: float, rms: float, nin: int) -> tuple[np.ndarray, ...]:
    """One segment's fit (centres, radii, RMS, ok, inliers) with its centre at (cx, 0)."""
    return np.array([[cx, 0.0]]), np.array([r]), np.array([rms]), np.array([True]), np.array([nin])


def test_a_circle_holding_the_stem_is_refitted_to_it() -> None:
    """An inflated circle (centre 6 cm towards the clutter, r 18 cm: the noisy spruce's
    fits) holds the stem's far side inside; the refit finds the 12 cm stem within 3 mm (a
    fit's error on 200 returns with 3 mm noise is < 1 mm; 3 mm leaves room for the clutter
    that touches the ring)."""
    pts = _ring_with_clutter(1)
    ids = np.zeros(pts.shape[0], dtype=np.int64)
    fit = _one_fit(0.06, 0.18, 0.02, 150)
    (c, r, rms, ok, _nin), n = _opaque_core_refits(pts, ids, fit, "ours", (0.02, 0.75), 8)
    assert n == 1 and ok[0]
    assert abs(r[0] - 0.12) < 0.003
    assert np.hypot(*c[0]) < 0.003
    assert rms[0] < 0.006


def test_a_stem_fit_is_left_alone() -> None:
    """The stem's own circle holds no returns inside: not flagged, returned unchanged."""
    pts = _ring_with_clutter(2)
    ids = np.zeros(pts.shape[0], dtype=np.int64)
    fit = _one_fit(0.0, 0.12, 0.003, 200)
    out, n = _opaque_core_refits(pts, ids, fit, "ours", (0.02, 0.75), 8)
    assert n == 0
    for a, b in zip(out, fit, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.slow
def test_noisy_spruce_keeps_its_stem_diameter(datasets_dir: Path) -> None:
    """treels spruce with 1 cm Gaussian noise per axis (the benchmark's ``noise_1cm``, seed
    0): within the issue's 1.5 cm of the ring of the cloud as shipped (measured: 0.4-0.8 cm).
    Before Dec 5 the RANSAC draws followed the file's point order and, on those draws,
    without the core refits the stem was lost or 13 cm too large; on the canonical order's
    draws (docs/algorithms/cloud.md "Point order") no slice circle holds the stem inside on
    this cloud (0.48 cm with and without the refits), so the refits are tested on the
    synthetic rings above."""
    xyz = read_cloud(datasets_dir / "treels/spruce.laz").xyz
    (ref,) = stem_references(xyz, detect_stems(xyz, StemConfig()))
    assert ref is not None and ref.full
    prep = TRANSFORMS["noise_1cm"](Context(xyz, None))
    assert prep is not None
    det = detect_stems(prep.xyz, StemConfig())
    assert len(det) == 1
    assert abs(float(det.diameter[0]) - ref.diameter) < 0.015
