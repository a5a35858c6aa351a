"""Filters, clustering, shape descriptors and the ground model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.cloud.cluster import dbscan, grid_components
from stemmap.cloud.filters import pass_through, point_spacing, voxel_downsample
from stemmap.cloud.ground import GroundAccumulator, fit_ground
from stemmap.cloud.shape import (
    arc_coverage_deg,
    cluster_covariances,
    major_axis_tilt_deg,
    pca_eccentricity,
)
from stemmap.errors import ConfigError, InputError


def test_pass_through_is_strict_box() -> None:
    p = np.array([[0.0, 0, -0.2], [0.1, 0, -0.2], [0.1, 10, -0.2], [5, -9.9, -0.49], [5, 0, 0.0]])
    keep = pass_through(p, x=(0, 10), y=(-10, 10), z=(-0.5, 0))
    assert keep.tolist() == [False, True, False, True, False]
    with pytest.raises(ConfigError):
        pass_through(p, x=(1, 0))
    with pytest.raises(InputError):
        pass_through(np.zeros((3, 2)))


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 300),
    voxel=st.floats(0.005, 0.5),
    seed=st.integers(0, 2**31),
)
def test_voxel_downsample_properties(n: int, voxel: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-2, 2, (n, 3))
    out, counts = voxel_downsample(p, voxel, return_counts=True)
    assert counts.sum() == n  # every point lands in exactly one voxel
    # the weighted mean of the voxel means is the mean of all points (eq. 2 averages)
    np.testing.assert_allclose((out * counts[:, None]).sum(0) / n, p.mean(0), atol=1e-9)
    # no two outputs share a voxel, and there are at most as many outputs as inputs
    assert out.shape[0] <= n


def test_voxel_downsample_exact_means() -> None:
    p = np.array([[0.001, 0.001, 0.001], [0.009, 0.009, 0.009], [0.5, 0.5, 0.5]])
    out = voxel_downsample(p, 0.01)
    np.testing.assert_allclose(out, [[0.005, 0.005, 0.005], [0.5, 0.5, 0.5]])
    with pytest.raises(ConfigError):
        voxel_downsample(p, 0.0)


def test_point_spacing_of_a_grid() -> None:
    g = np.stack(np.meshgrid(np.arange(50), np.arange(50), [0.0]), -1).reshape(-1, 3) * 0.02
    assert point_spacing(g) == pytest.approx(0.02, rel=1e-9)
    assert np.isnan(point_spacing(np.zeros((1, 3))))


def test_cluster_covariances_and_eccentricity() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(0, [1.0, 0.25, 0.1], (4000, 3))  # variances 1, 1/16, 1/100
    b = rng.normal(0, 1.0, (4000, 3)) + 10
    p = np.vstack((a, b))
    lab = np.repeat([0, 1], 4000)
    _, cov, n = cluster_covariances(p, lab)
    assert n.tolist() == [4000, 4000]
    e = pca_eccentricity(cov)
    # 4000 samples: variance estimates within ~5 %, so the ratio 16 within ~10 %
    assert e[0] == pytest.approx(16.0, rel=0.1)
    assert e[1] == pytest.approx(1.0, rel=0.15)
    np.testing.assert_allclose(cov[0], np.cov(a.T, bias=True), atol=1e-12)


def test_major_axis_tilt() -> None:
    """Angle of the principal axis from vertical: 0 for a stem, 90 for a horizontal strip, the
    rotation angle for a stem leaning in the xz plane (sign and axis order do not matter)."""
    lean = math.radians(30.0)
    rot = np.array(
        [[math.cos(lean), 0, math.sin(lean)], [0, 1, 0], [-math.sin(lean), 0, math.cos(lean)]]
    )
    covs = np.stack(
        (
            np.diag([0.01, 0.02, 1.0]),
            np.diag([1.0, 0.02, 0.01]),
            rot @ np.diag([0.01, 0.02, 1.0]) @ rot.T,
        )
    )
    np.testing.assert_allclose(major_axis_tilt_deg(covs), [0.0, 90.0, 30.0], atol=1e-9)
    assert float(major_axis_tilt_deg(covs[1])) == pytest.approx(90.0)
    with pytest.raises(InputError):
        major_axis_tilt_deg(np.eye(2))


def test_arc_coverage() -> None:
    t = np.linspace(0, 2 * np.pi, 361)[:-1]
    ring = np.column_stack((np.cos(t), np.sin(t)))
    assert arc_coverage_deg(ring, [0, 0]) == pytest.approx(359.0)
    half = ring[(t >= 0) & (t <= np.pi)]
    assert arc_coverage_deg(half, [0, 0]) == pytest.approx(180.0)


def test_grid_components_and_dbscan() -> None:
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 0.3, (200, 2))
    b = rng.uniform(0, 0.3, (200, 2)) + np.array([2.0, 0.0])
    p = np.vstack((a, b))
    lab = grid_components(p, 0.05)
    assert len(set(lab[:200])) == 1 and len(set(lab[200:])) == 1 and lab[0] != lab[-1]
    lab3 = dbscan(np.column_stack((p, np.zeros(400))), 0.1, 5)
    assert lab3[0] != lab3[-1] and lab3.min() >= 0
    with pytest.raises(ConfigError):
        dbscan(p, 0.0, 5)


def test_ground_on_a_slope_with_objects() -> None:
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 20, (40_000, 2))
    z = 3.0 + 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + rng.normal(0, 0.01, len(xy))
    # a "trunk" and some "bushes" above the ground, and one low outlier
    trunk = np.column_stack((rng.normal(10, 0.1, (3000, 2)), rng.uniform(0, 10, 3000)))
    trunk[:, 2] += 3.0 + 0.1 * 10 - 0.05 * 10
    low = np.array([[5.5, 5.5, -20.0]])
    p = np.vstack((np.column_stack((xy, z)), trunk, low))
    g = fit_ground(p, 1.0)
    q = rng.uniform(1, 19, (500, 2))
    truth = 3.0 + 0.1 * q[:, 0] - 0.05 * q[:, 1]
    # cell minima sit ~2-3 sigma below the plane (1 cm noise) and bilinear interpolation of a
    # plane is exact: a few centimetres
    assert np.max(np.abs(g.ground_at(q) - truth)) < 0.05
    # streaming in chunks gives the same raster
    acc = GroundAccumulator(1.0)
    for part in np.array_split(p, 7):
        acc.update(part)
    np.testing.assert_allclose(acc.model().z, g.z)
    with pytest.raises(InputError):
        GroundAccumulator(1.0).model()


@pytest.mark.parametrize("stray", [False, True])
def test_cell_index_is_numpy_unique_of_the_packed_keys(stray: bool) -> None:
    """The dense-occupancy cell index (ground minima, canopy raster) gives exactly the cells
    and inverse of a sort-based ``np.unique``, also when a stray point forces the fallback."""
    from stemmap.cloud.ground import cell_index

    rng = np.random.default_rng(7)
    ij = rng.integers(-40, 60, size=(20_000, 2)).astype(np.int64)
    if stray:
        ij[5] = (3_000_000, -2_000_000)  # a bounding box of 1e13 cells: np.unique path
    keys = ((ij[:, 0] + (1 << 30)) << 32) | (ij[:, 1] + (1 << 30))
    uk, inv = np.unique(keys, return_inverse=True)
    cells, got = cell_index(ij)
    np.testing.assert_array_equal(((cells[:, 0] + (1 << 30)) << 32) | (cells[:, 1] + (1 << 30)), uk)
    np.testing.assert_array_equal(got, inv)
    assert cell_index(np.zeros((0, 2), dtype=np.int64))[0].shape == (0, 2)


@pytest.mark.parametrize("stray", [False, True])
def test_dense_grid_kernels_equal_the_numpy_reductions(stray: bool) -> None:
    """The one-pass ground-minimum and canopy-maximum kernels give exactly what the numpy
    reductions over cell_index give: the same cells in the same order, of equal minima the
    one of smallest x, then y, the same three lowest z, the same maxima -- on coordinates
    quantised to 1 cm (many exact ties, points on cell edges, negative cells); with a stray
    point far away the dense grid is refused and the numpy path runs."""
    from stemmap.cloud._grid_kernel import lowest_per_cell, max_per_cell
    from stemmap.cloud.ground import cell_index
    from stemmap.cloud.measure import _CANOPY_CELL, _canopy_update

    rng = np.random.default_rng(11)
    p = np.round(rng.uniform(-12.0, 9.0, (30_000, 3)), 2)
    p[:, 2] = np.round(rng.normal(0.0, 0.05, p.shape[0]), 2)  # ties in z
    if stray:
        p[7] = (4.0e6, -3.0e6, 0.0)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    low = lowest_per_cell(x, y, z, 1.0)
    top = max_per_cell(x, y, z, _CANOPY_CELL)
    if stray:
        assert low is None and top is None
    else:
        assert low is not None and top is not None
        cells, inv = cell_index(np.floor(p[:, :2] / 1.0).astype(np.int64))
        zmin = np.full(cells.shape[0], np.inf)
        np.minimum.at(zmin, inv, z)
        cand = np.flatnonzero(z == zmin[inv])
        cand = cand[np.lexsort((y[cand], x[cand], inv[cand]))]  # of equal minima: min x, y
        _, first = np.unique(inv[cand], return_index=True)
        o = np.lexsort((z, inv))
        grp = [z[o][inv[o] == c][:3] for c in range(cells.shape[0])]
        low3 = np.array([np.pad(v, (0, 3 - v.size), constant_values=np.inf) for v in grp])
        np.testing.assert_array_equal(low[0], cells)
        np.testing.assert_array_equal(low[1], cand[first])
        np.testing.assert_array_equal(low[2], low3)
        cells, inv = cell_index(np.floor(p[:, :2] / _CANOPY_CELL).astype(np.int64))
        hmax = np.full(cells.shape[0], -np.inf)
        np.maximum.at(hmax, inv, z)
        np.testing.assert_array_equal(top[0], cells)
        np.testing.assert_array_equal(top[1], hmax)
    # streamed in parts (the merge path), the canopy and the ground are the same as in one go
    one = _canopy_update({}, p[:, :2], z)
    parts: dict[str, np.ndarray] = {}
    acc1, acc3 = GroundAccumulator(1.0), GroundAccumulator(1.0)
    acc1.update(p)
    for part in np.array_split(np.arange(p.shape[0]), 3):
        parts = _canopy_update(parts, p[part, :2], z[part])
        acc3.update(p[part])
    np.testing.assert_array_equal(parts["keys"], one["keys"])
    np.testing.assert_array_equal(parts["h"], one["h"])
    np.testing.assert_array_equal(acc1._keys, acc3._keys)
    np.testing.assert_array_equal(acc1._low, acc3._low)
    np.testing.assert_array_equal(acc1._z3, acc3._z3)  # so the support, exactly
