"""The ground raster of a buffered chunk equals the whole cloud's near a data edge; the
bilinear kernel equals scipy's map_coordinates bit for bit, and the one-pass heights and slice
band equal the height-then-mask computation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from stemmap.cloud._grid_kernel import bilinear_nearest
from stemmap.cloud.ground import GroundAccumulator, GroundModel, fit_ground


def _terrain(seed: int) -> np.ndarray:
    """A rough 30 x 30 m slope (ground returns, a few stems' worth of raised points) with
    its top-right part missing: an inner data edge at x = 20 for y >= 10."""
    rng = np.random.default_rng(seed)
    n = 60_000
    x, y = rng.uniform(0, 30, n), rng.uniform(0, 30, n)
    z = 0.15 * x - 0.08 * y + 0.3 * np.sin(x / 3.0) * np.cos(y / 4.0) + rng.normal(0, 0.02, n)
    up = rng.random(n) < 0.2
    z[up] += rng.uniform(0.2, 3.0, up.sum())  # vegetation above the ground
    keep = ~((x >= 20.0) & (y >= 10.0))
    return np.column_stack((x, y, z))[keep]


@pytest.mark.parametrize("seed", [0, 1])
def test_chunk_ground_equals_the_whole_clouds_near_an_inner_edge(seed: int) -> None:
    """Chunks of 7 and 10 m with a 5 m buffer: with the catalog's box as the raster extent
    the ground at the points within 1 m of a chunk's owned square is the whole cloud's (to
    rounding: the plane fits run in coordinates relative to each raster's corner); without
    it, chunks whose buffer holds no point beyond the edge clamp the ground there."""
    p = _terrain(seed)
    # the catalog's box: its header bounds, i.e. the extreme coordinates
    box = (p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max())
    acc = GroundAccumulator(1.0)
    acc.update(p)
    whole = acc.model(extent=box)
    assert whole.z.shape == (30, 30)
    worst = {True: 0.0, False: 0.0}
    for size in (7.0, 10.0):
        for i in range(5):
            for j in range(5):
                own = (i * size, j * size, (i + 1) * size, (j + 1) * size)
                buf = (own[0] - 5, own[1] - 5, own[2] + 5, own[3] + 5)
                inside = (
                    (p[:, 0] >= buf[0])
                    & (p[:, 0] <= buf[2])
                    & (p[:, 1] >= buf[1])
                    & (p[:, 1] <= buf[3])
                )
                near = (
                    (p[:, 0] >= own[0] - 1)
                    & (p[:, 0] < own[2] + 1)
                    & (p[:, 1] >= own[1] - 1)
                    & (p[:, 1] < own[3] + 1)
                )
                if not near.any():
                    continue
                a = GroundAccumulator(1.0)
                a.update(p[inside])
                window = (max(box[0], buf[0]), max(box[1], buf[1]))
                window += (min(box[2], buf[2]), min(box[3], buf[3]))
                for use in (True, False):
                    g = a.model(extent=window if use else None)
                    d = np.abs(g.ground_at(p[near, :2]) - whole.ground_at(p[near, :2])).max()
                    worst[use] = max(worst[use], float(d))
    assert worst[True] < 1e-9
    assert worst[False] > 1e-3  # the case the extent exists for does occur here


def test_extent_only_grows_the_raster() -> None:
    p = _terrain(2)
    inner = fit_ground(p)
    acc = GroundAccumulator(1.0)
    acc.update(p)
    grown = acc.model(extent=(-3.2, 1.0, 33.5, 20.0))
    assert grown.origin == (-4.0, 0.0) and grown.z.shape == (38, 30)
    assert inner.origin == (0.0, 0.0) and inner.z.shape == (30, 30)
    assert grown.observed is not None and not grown.observed[:4].any()


@pytest.mark.parametrize("seed", range(4))
def test_bilinear_kernel_is_scipys_map_coordinates(seed: int) -> None:
    """Same bits as map_coordinates(order=1, mode="nearest") inside, on cell centres and
    edges, and outside the grid (clamped), for grids down to one cell."""
    rng = np.random.default_rng(seed)
    for _ in range(50):
        nx, ny = (int(v) for v in rng.integers(1, 30, 2))
        z = rng.normal(size=(nx, ny)) * 10 ** rng.uniform(-3, 3)
        ox, oy = rng.uniform(-1e5, 1e5, 2)
        cell = float(rng.choice([0.3, 0.5, 1.0, 2.0]))
        x = ox + rng.uniform(-3, nx * cell + 3, 2000)
        y = oy + rng.uniform(-3, ny * cell + 3, 2000)
        x[:300] = ox + (rng.integers(-2, nx + 2, 300) + 0.5) * cell
        y[300:600] = oy + rng.integers(-2, ny + 2, 300) * cell
        got = bilinear_nearest(z, (ox, oy), cell, x, y)
        fi, fj = (x - ox) / cell - 0.5, (y - oy) / cell - 0.5
        want = ndimage.map_coordinates(z, [fi, fj], order=1, mode="nearest")
        assert got is not None
        np.testing.assert_array_equal(got.view(np.int64), want.view(np.int64))
    assert bilinear_nearest(z, (0.0, 0.0), 1.0, np.array([np.nan]), np.array([0.0])) is None


@pytest.mark.parametrize("seed", range(3))
def test_band_of_is_height_then_mask(seed: int) -> None:
    """``GroundModel.band_of``: the heights of ``height_of`` and the indices of
    ``(h >= lo) & (h <= hi)``, bit for bit, inside and outside the raster, on the band's
    limits, with NaN heights and on strided input; the numpy path where a coordinate is
    not finite."""
    rng = np.random.default_rng(seed)
    g = fit_ground(_terrain(seed), cell=1.0)
    xyz = np.asfortranarray(_terrain(seed + 10))  # column-major: strided rows
    xyz[:50, :2] += rng.uniform(-40, 40, (50, 2))  # outside the raster: clamped
    want_h = g.height_of(xyz)
    lo, hi = 0.5, 2.0
    xyz[50:60, 2] += lo - want_h[50:60]  # heights on the lower limit
    xyz[60:70, 2] += hi - want_h[60:70]  # and on the upper one
    xyz[70, 2] = np.nan
    want_h = g.height_of(xyz)
    h, idx = g.band_of(xyz, lo, hi)
    np.testing.assert_array_equal(h.view(np.int64), want_h.view(np.int64))
    np.testing.assert_array_equal(idx, np.flatnonzero((want_h >= lo) & (want_h <= hi)))
    assert idx.dtype == np.int64 and 70 not in idx and idx.size > 1000
    bad = np.ascontiguousarray(xyz)
    bad[3, 0] = np.inf  # not finite: scipy's interpolation, as height_of
    h2, idx2 = g.band_of(bad, lo, hi)
    want2 = g.height_of(bad)
    np.testing.assert_array_equal(h2.view(np.int64), want2.view(np.int64))
    np.testing.assert_array_equal(idx2, np.flatnonzero((want2 >= lo) & (want2 <= hi)))
    flat = GroundModel((0.0, 0.0), 1.0, np.full((1, 1), 0.25), "lowest stem points")
    h3, idx3 = flat.band_of(np.array([[5.0, 5.0, 1.0], [0.0, 0.0, 0.0]]), 0.5, 2.0)
    assert h3.tolist() == [0.75, -0.25] and idx3.tolist() == [0]


def test_nearest_cell_fill_is_local() -> None:
    """The ground fills an empty cell from its nearest observed cell (scipy's
    distance_transform_edt). A chunk's raster is a window of the whole one: a cell whose
    nearest observed cell is closer than the window's border gets the same one (also among
    ties, which integer grids have plenty of), so the fill is the whole cloud's."""
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(100):
        valid = rng.random((50, 50)) < rng.uniform(0.05, 0.6)
        if rng.random() < 0.5:
            valid[:, 25:] = False  # a data edge
        a, b = (int(v) for v in rng.integers(0, 15, 2))
        c, e = a + int(rng.integers(12, 35)), b + int(rng.integers(12, 35))
        sub = valid[a:c, b:e]
        if not valid.any() or not sub.any():
            continue
        d, (fi, fj) = ndimage.distance_transform_edt(~valid, return_indices=True)
        _, (gi, gj) = ndimage.distance_transform_edt(~sub, return_indices=True)
        ii, jj = np.indices(sub.shape)
        border = np.minimum.reduce([ii, jj, sub.shape[0] - 1 - ii, sub.shape[1] - 1 - jj])
        inner = d[a:c, b:e] < border - 0.5
        np.testing.assert_array_equal((fi[a:c, b:e] - a)[inner], gi[inner])
        np.testing.assert_array_equal((fj[a:c, b:e] - b)[inner], gj[inner])
        checked += int(inner.sum())
    assert checked > 10_000
