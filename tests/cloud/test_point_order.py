"""The same cloud in another point order gives the same stems, bit for bit.

Before (main at 3c67552) TreeLS spruce gave a DBH of 23.57-23.81 cm over 10 random
permutations of its points (file order 23.56) and pine_plot stems moved by up to 10 mm:
the ground took the first of equal cell minima in point order, and the spacing sample, the
RANSAC draws, the fits' sums and the KD-tree tie-breaks followed the band's order. Now the
ground breaks ties by coordinates and the band is put in a canonical order
(:mod:`stemmap.cloud.canonical`) before any step reads it, so every floating-point operation
runs on the same numbers in the same order: the tolerance is exact equality (NaN equal to
NaN), not a rounding bound. docs/algorithms/cloud.md "Point order".
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import laspy
import numpy as np
import pytest

from stemmap.cloud import StemConfig, detect_stems, detect_stems_file
from stemmap.cloud._grid_kernel import lowest_per_cell
from stemmap.cloud.canonical import canonical_order
from stemmap.cloud.ground import _SUPPORT, GroundAccumulator
from stemmap.cloud.result import CloudStems
from stemmap.io.clouds import read_cloud
from stemmap.products.forestry import stem_profiles
from stemmap.sim.lidar import lidar_preset, random_stand3d, simulate_tls


def _identical(a: CloudStems, b: CloudStems) -> None:
    """Every column and attribute of the two results equal (arrays exactly, NaN == NaN)."""
    assert len(a) == len(b) > 0
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            if va.dtype == object:
                assert list(va) == list(vb), f.name
            else:
                np.testing.assert_array_equal(va, vb, err_msg=f.name)
        elif isinstance(va, float):
            assert va == vb or (np.isnan(va) and np.isnan(vb)), f.name
        else:
            assert va == vb, f.name


def _write_las(path: Path, xyz: np.ndarray) -> Path:
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(str(path))
    return path


@pytest.fixture(scope="module")
def sim_plot() -> np.ndarray:
    """A single-scan simulated plot on a LAS file's 1 mm grid (ties in x, y and z)."""
    stand = random_stand3d(10, (14.0, 14.0), dbh_min=0.12, n_shrubs=4, rng=3)
    xyz = simulate_tls(stand, [[7.0, 7.0]], lidar_preset("tls_coarse"), rng=4).xyz
    return np.round(xyz * 1000.0) / 1000.0


def test_permuted_simulated_plot(sim_plot: np.ndarray, tmp_path: Path) -> None:
    """In memory and streamed (a LAS written in another order, read in chunks of 20 000
    points, so the ground is merged across chunks): the file order's stems."""
    cfg = StemConfig(estimate_height=True)
    ref = detect_stems(sim_plot, cfg)
    assert len(ref) >= 8
    for seed in range(3):
        perm = np.random.default_rng(seed).permutation(sim_plot.shape[0])
        _identical(detect_stems(sim_plot[perm], cfg), ref)
    path = _write_las(tmp_path / "permuted.las", sim_plot[perm])
    base = detect_stems_file(_write_las(tmp_path / "ordered.las", sim_plot), cfg)
    _identical(detect_stems_file(path, cfg, chunk_size=20_000), base)


@pytest.mark.parametrize("name", ["treels/spruce.laz", "treels/pine_plot.laz"])
def test_permuted_real_cloud(datasets_dir: Path, name: str) -> None:
    """TreeLS spruce (23.57-23.81 cm over 10 orders before) and pine_plot (16 stems, up to
    10 mm apart before): three random orders give the file order's stems and stem profiles."""
    xyz = read_cloud(datasets_dir / name).xyz
    cfg = StemConfig(estimate_height=True)
    ref = detect_stems(xyz, cfg)
    prof = stem_profiles(xyz, ref)
    for seed in range(3):
        perm = np.random.default_rng(seed).permutation(xyz.shape[0])
        got = detect_stems(xyz[perm], cfg)
        _identical(got, ref)
        for a, b in zip(stem_profiles(xyz[perm], got), prof, strict=True):
            np.testing.assert_array_equal(a.height, b.height)
            np.testing.assert_array_equal(a.diameter, b.diameter)


def test_ground_minima_break_ties_by_coordinates() -> None:
    """Equal minima in a cell: the point of smallest x, then y, in the compiled kernel, in
    numpy's fallback (a stray point makes the grid sparse) and across chunks; its support
    (points within 0.1 m above, up to 3) exact across chunks (main added the chunks' own
    counts, which depended on how the points fell into chunks)."""
    rng = np.random.default_rng(0)
    n = 4000
    xyz = np.column_stack(
        (rng.integers(0, 400, n) / 100, rng.integers(0, 400, n) / 100, rng.integers(0, 3, n) / 100)
    )
    far = np.array([[5e6, 5e6, 10.0]])  # forces the numpy path (a sparse bounding box)

    def minima(p: np.ndarray, chunks: int) -> np.ndarray:
        acc = GroundAccumulator(1.0)
        for part in np.array_split(p, chunks):
            acc.update(part)
        return np.column_stack((acc._low, acc._sup))

    # expected: per cell the lexicographically smallest (z, x, y)
    ij = np.floor(xyz[:, :2]).astype(np.int64)
    o = np.lexsort((xyz[:, 1], xyz[:, 0], xyz[:, 2], ij[:, 1], ij[:, 0]))
    first = np.ones(n, dtype=bool)
    first[1:] = np.any(np.diff(ij[o], axis=0) != 0, axis=1)
    want = xyz[o][first]
    # support: the cell's points within 0.1 m above its minimum, counted up to 3
    cell_of = np.cumsum(first) - 1
    zs = xyz[o, 2]
    sup = np.bincount(cell_of, zs <= want[cell_of, 2] + _SUPPORT)
    want_sup = np.column_stack((want, np.minimum(sup, 3)))
    for seed in range(3):
        p = xyz[np.random.default_rng(seed).permutation(n)]
        low = lowest_per_cell(p[:, 0], p[:, 1], p[:, 2], 1.0)
        assert low is not None
        np.testing.assert_array_equal(p[low[1]], want)
        np.testing.assert_array_equal(minima(p, 1), want_sup)
        np.testing.assert_array_equal(minima(p, 7), want_sup)
        np.testing.assert_array_equal(minima(np.vstack((p, far)), 1)[:-1], want_sup)


def test_canonical_order_is_lexsort() -> None:
    """canonical_order sorts like np.lexsort of the keys (the points equal in every key are
    the same point), on a 1 mm grid with many ties, with runs of equal x and equal (x, y)."""
    rng = np.random.default_rng(1)
    for q in (1.0, 0.01, 0.001):
        k = np.round(rng.uniform(0, 3, (20_000, 3)) / q) * q
        o = canonical_order(k[:, 0], k[:, 1], k[:, 2])
        np.testing.assert_array_equal(k[o], k[np.lexsort((k[:, 2], k[:, 1], k[:, 0]))])
    assert canonical_order(np.zeros(0)).size == 0


def test_munjer2025_is_order_free(datasets_dir: Path) -> None:
    """Preset munjer2025 (EB-LiDAR): voxel points, DBSCAN labels and stems bit-identical over
    three orders. Before (main at 837827b) the voxel grid summed each voxel's points in
    input order (means up to 6e-14 m apart on the lidR slice) and the ground-relative box
    took the first of equal cell minima: on virtual VLP-16 frames of pine_plot on a 2 mm
    grid, 18 of 39 frames kept other points in the box in another order
    (`benchmarks/cloud_point_order.py --munjer`). DBSCAN then reads the voxels in voxel-key
    order, so its border points go to the same cluster in any input order."""
    import math

    from munjer2025_real_frames import virtual_frame
    from stemmap.cloud.munjer import MunjerConfig, munjer_clusters

    plot = read_cloud(datasets_dir / "treels" / "pine_plot.laz").xyz
    frames = [
        np.round(virtual_frame(plot, np.array([4.9, y, math.pi / 2])) / 0.002) * 0.002
        for y in np.arange(-8.0, 18.0, 2.0)
    ]
    cases = [(f, MunjerConfig(ground_relative=True)) for f in frames]
    slice_ = read_cloud(datasets_dir / "lidr_dbh" / "dbh.laz").xyz
    cases.append((slice_, MunjerConfig(box_x=None, box_y=None, box_z=None)))
    n_stems = 0
    for xyz, cfg in cases:
        ref = munjer_clusters(xyz, cfg)
        n_stems += len(ref.stems())
        for seed in range(3):
            got = munjer_clusters(xyz[np.random.default_rng(seed).permutation(len(xyz))], cfg)
            np.testing.assert_array_equal(got.points, ref.points)
            np.testing.assert_array_equal(got.labels, ref.labels)
            a, b = got.stems(), ref.stems()
            assert len(a) == len(b)
            np.testing.assert_array_equal(a.xy, b.xy)
            np.testing.assert_array_equal(a.diameter, b.diameter)
    assert n_stems > 0  # the frames hold trunks EB-LiDAR accepts
