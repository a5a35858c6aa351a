"""A mapped tree's DBH fused from its detections by their own uncertainty
(stemmap.slam.uncertainty.fused_diameters, TreeFrames.diameter_std)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import TreeFrames
from stemmap.slam.uncertainty import (
    DIAMETER_FLOOR,
    diameter_standard_errors,
    fused_diameters,
)
from stemmap.types import StemObservations


def _drive_by(
    rng: np.random.Generator, n_near: int = 30, n_far: int = 15
) -> tuple[np.ndarray, np.ndarray]:
    """Diameters and fit stds of one 0.30 m trunk seen over a pass: near detections with a
    tight fit (sd 5 mm, error 5 mm), far few-return ones with a loose fit (sd 4-8 cm) and the
    far detections' shared overestimate (+6 cm, the real passes' 10-17 m bias)."""
    sd_near = np.full(n_near, 0.005)
    sd_far = rng.uniform(0.04, 0.08, n_far)
    d = np.concatenate(
        (
            0.30 + rng.normal(0.0, 0.005, n_near),
            0.36 + rng.normal(0.0, 1.0, n_far) * sd_far,
        )
    )
    return d, np.concatenate((sd_near, sd_far))


def test_far_noisy_detections_do_not_pull_the_fused_diameter(rng: np.random.Generator) -> None:
    """The plain mean moves by a third of the far detections' bias (15 of 45); the weighted
    one stays within the near detections' own error. Weights 1/(sd^2 + f^2): near 1/(0.005^2 +
    0.02^2) against at most 1/(0.04^2 + 0.02^2) far, 4.7x, so the far share of the weight is
    at most 15 / (15 + 4.7 * 30) ~ 10 % -> at most ~0.6 cm of the 6 cm bias."""
    e_plain, e_fused = [], []
    for _ in range(20):
        d, sd = _drive_by(rng)
        idx = np.zeros(d.size, dtype=np.int64)
        plain, _, _, n_plain = fused_diameters(idx, d, 1)
        fused, _, spread, n_eff = fused_diameters(idx, d, 1, diameter_std=sd)
        e_plain.append(plain[0] - 0.30)
        e_fused.append(fused[0] - 0.30)
        # bias <= 0.6 cm plus the far ones' noise at ~10 % weight (~0.1 cm) and the near ones'
        assert abs(fused[0] - 0.30) < 0.008
        assert n_plain[0] == d.size and 0 < n_eff[0] < d.size  # far ones count less
        # the weighted spread is the near detections' scatter plus the far ones' small share
        assert spread[0] < float(np.std(d, ddof=1))
    # the far ones pull the plain mean by a third of their bias (2 cm; its noise ~0.4 cm over
    # 20 passes), the weighted one by less than a third of that
    assert np.mean(e_plain) > 0.015
    assert np.mean(np.abs(e_fused)) < np.mean(np.abs(e_plain)) / 3.0


def test_far_detections_alone_still_give_a_diameter(rng: np.random.Generator) -> None:
    """A tree seen only far away is not dropped or distorted: its weighted mean is a mean of
    its own detections (weights relative within the tree)."""
    d = 0.36 + rng.normal(0.0, 0.05, 12)
    sd = rng.uniform(0.04, 0.08, 12)
    idx = np.r_[np.zeros(12, dtype=np.int64)]
    fused, se, _, _ = fused_diameters(idx, d, 1, diameter_std=sd)
    assert d.min() <= fused[0] <= d.max() and np.isfinite(se[0])


def test_equal_weights_are_the_plain_mean_and_standard_errors() -> None:
    """No per-detection std (or all NaN, or all equal): exactly the former fusion -- the plain
    mean, and ``diameter_standard_errors``' spread and standard error."""
    idx = np.array([0, 0, 0, 0, 1, 2, 2, -1])
    d = np.array([0.30, 0.32, 0.28, 0.31, 0.5, 0.2, np.nan, 9.0])
    se0, sp0, n0 = diameter_standard_errors(idx, d, 4, rho=0.5, bias=0.03)
    for sd in (None, np.full(8, np.nan), np.full(8, 0.01)):
        m, se, sp, n = fused_diameters(idx, d, 4, diameter_std=sd, rho=0.5, bias=0.03)
        assert m[0] == pytest.approx(0.3025) and m[1] == 0.5 and m[2] == 0.2
        assert math.isnan(m[3])
        np.testing.assert_allclose(se, se0, equal_nan=True)
        np.testing.assert_allclose(sp, sp0, equal_nan=True)
        np.testing.assert_allclose(n, n0)


def test_nan_std_counts_as_the_median_one() -> None:
    idx = np.zeros(3, dtype=np.int64)
    d = np.array([0.30, 0.40, 0.50])
    a = fused_diameters(idx, d, 1, diameter_std=[0.01, np.nan, 0.03])[0]
    b = fused_diameters(idx, d, 1, diameter_std=[0.01, 0.02, 0.03])[0]
    assert a[0] == pytest.approx(b[0])


def test_inverse_variance_weights() -> None:
    """Two detections: the weights are 1 / (sd^2 + floor^2)."""
    idx = np.zeros(2, dtype=np.int64)
    m = fused_diameters(idx, [0.3, 0.4], 1, diameter_std=[0.0, 0.03], floor=0.01)[0]
    w1, w2 = 1 / 0.01**2, 1 / (0.03**2 + 0.01**2)
    assert m[0] == pytest.approx((w1 * 0.3 + w2 * 0.4) / (w1 + w2))
    assert DIAMETER_FLOOR > 0


def test_bad_arguments() -> None:
    idx = np.zeros(2, dtype=np.int64)
    for bad in ({"floor": 0.0}, {"bias": -1.0}, {"rho": 2.0}, {"diameter_std": [0.1]}):
        with pytest.raises(ConfigError):
            fused_diameters(idx, [0.3, 0.4], 1, **bad)  # type: ignore[arg-type]


def test_frames_carry_the_detections_diameter_std() -> None:
    """``from_observations``: ``diameter_std = 2 sqrt(cov_rr)``, kept by frame selection."""
    covs = np.zeros((3, 3, 3))
    covs[:, 2, 2] = [1e-4, 4e-4, np.nan]
    obs = StemObservations(
        centers=[[5.0, 0.0], [6.0, 1.0], [7.0, -1.0]],
        radii=[0.1, 0.2, 0.15],
        covs=covs,
        n_points=[10, 5, 3],
        arc_deg=[90.0, 60.0, 40.0],
        widths=np.full(3, np.nan),
        quality=np.ones(3),
        index=[0, 1, 1],
        times=[0.0, 0.1, 0.1],
    )
    fr = TreeFrames.from_observations(obs, [0.0, 0.1])
    assert fr.diameter_std is not None
    np.testing.assert_allclose(fr.diameter_std, [0.02, 0.04, np.nan])
    sub = fr.select_frames(1, 2)
    assert sub.diameter_std is not None
    np.testing.assert_allclose(sub.diameter_std, [0.04, np.nan])
    with pytest.raises(InputError):
        TreeFrames([0.0], [0, 1], [5.0], [0.0], [0.3], None, [-0.1])
    plain = TreeFrames([0.0], [0, 1], [5.0], [0.0], [0.3])
    assert plain.diameter_std is None


def test_annotate_uncertainty_fuses_the_map_diameter(rng: np.random.Generator) -> None:
    """The post-step of every back-end: with per-detection stds the map's DBH is the weighted
    fusion -- far detections (> 12 m: +6 cm biased, loose fits) do not pull it -- and without
    them the back-end's own diameter is kept (as before)."""
    from tests.slam._synthetic import loop_problem

    from stemmap.slam.base import SlamResult, frame_trajectory, observation_to_world
    from stemmap.slam.uncertainty import annotate_uncertainty
    from stemmap.types import StemMap, Tree

    problem, truth, trees, diam = loop_problem(1, laps=0.5, n_trees=40, sigma_r=0.01)
    fr = problem.frames
    # which tree each detection is (nearest true tree to its true map position)
    world = observation_to_world(truth[fr.frame_index], fr.ranges, fr.bearings,
                                 problem.sensor_offset)  # fmt: skip
    tree_of = np.argmin(np.hypot(*(world[:, None, :] - trees[None, :, :]).transpose(2, 0, 1)),
                        axis=1)  # fmt: skip
    far = fr.ranges > 12.0
    sd = np.where(far, rng.uniform(0.04, 0.08, far.size), 0.005)
    d = diam[tree_of] + np.where(far, 0.06, 0.0) + rng.normal(0.0, 1.0, far.size) * sd
    frames = dataclasses.replace(fr, diameters=d, diameter_std=sd)
    problem = dataclasses.replace(problem, frames=frames)
    sm = StemMap(tuple(Tree(i, x, y, -1.0) for i, (x, y) in enumerate(trees)))
    result = SlamResult(frame_trajectory(fr.times, truth), sm)
    fused, rep = annotate_uncertainty(result, problem)
    assert rep.diameter_weighted
    got = np.array([t.diameter for t in fused])
    n = np.bincount(tree_of, minlength=len(trees))
    near_n = np.bincount(tree_of[~far], minlength=len(trees))
    mixed = (near_n >= 5) & (n - near_n >= 5)  # seen near and far
    assert mixed.sum() >= 5
    plain = np.bincount(tree_of, d, minlength=len(trees)) / np.maximum(n, 1)
    # the plain mean carries the far detections' share of the +6 cm; in the weighted one a far
    # detection counts ~1/9 of a near one (1 / (0.06^2 + 0.02^2) against 1 / (0.005^2 + 0.02^2))
    e_plain, e_got = plain[mixed] - diam[mixed], got[mixed] - diam[mixed]
    assert np.median(e_plain) > 0.02
    assert np.median(np.abs(e_got)) < np.median(e_plain) / 2
    assert np.all(np.abs(e_got) < np.abs(e_plain))
    kept, rep0 = annotate_uncertainty(
        result, dataclasses.replace(problem, frames=dataclasses.replace(frames, diameter_std=None))
    )
    assert not rep0.diameter_weighted and all(t.diameter == -1.0 for t in kept)
