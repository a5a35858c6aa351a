"""COPC tiles: a chunk's buffered box is read by a spatial query of the octree (only the
nodes meeting the box are decoded), and a COPC catalog gives the single process's stems for
any chunking. The COPC files are written by copclib (a dev dependency)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stemmap.cloud import CloudStems, StemConfig, detect_stems
from stemmap.engine import Catalog, plan_chunks, read_chunk, run_stems_catalog

pytest.importorskip("copclib")

from test_stems_engine import assert_same_stems

from _laz_tiles import write_copc


def _rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


def _read_all(path: str) -> np.ndarray:
    import laspy

    with laspy.CopcReader.open(path) as rd:
        pts = rd.query()
        return np.column_stack((pts.x, pts.y, pts.z))


@pytest.fixture(scope="module")
def copc_tiles(
    stand_tiles: tuple[Path, np.ndarray], tmp_path_factory: pytest.TempPathFactory
) -> Path:
    """The 30 x 30 m test stand as nine 10 m COPC tiles."""
    root = tmp_path_factory.mktemp("copc")
    xyz = stand_tiles[1]
    ij = np.floor(xyz[:, :2] / 10.0).astype(np.int64)
    for n, key in enumerate(np.unique(ij, axis=0)):
        m = np.all(ij == key, axis=1)
        write_copc(root / f"tile_{key[0]}_{key[1]}.copc.laz", xyz[m], depth=3, seed=n)
    return root


def test_copc_query_reads_exactly_the_buffered_box(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    xyz = np.round(rng.uniform([0, 0, 0], [20, 10, 5], size=(20_000, 3)) * 1000) / 1000
    path = tmp_path / "a.copc.laz"
    write_copc(path, xyz, depth=4)
    cat = Catalog.from_inputs([path])
    assert cat.tiles[0].copc and cat.n_points == len(xyz)
    whole = _read_all(cat.tiles[0].path)
    np.testing.assert_allclose(_rows(whole), _rows(xyz), rtol=0, atol=1e-9)
    for ch in plan_chunks(cat, 4.0, 1.0):
        got, _ = read_chunk(cat, ch)
        b = ch.buffered
        m = (whole[:, 0] >= b[0]) & (whole[:, 0] <= b[2])
        m &= (whole[:, 1] >= b[1]) & (whole[:, 1] <= b[3])
        # the points of the box, in the order of the whole file (octree node order): the
        # same relative order in every chunk, as a LAS tile's file order
        np.testing.assert_array_equal(got, whole[m])


@pytest.fixture(scope="module")
def copc_reference(copc_tiles: Path) -> CloudStems:
    """One process over the whole cloud, tiles in catalog order, each in its file order (a
    single run's anchors: the pilot is the whole catalog); shared by the chunk sizes."""
    cat = Catalog.from_inputs([copc_tiles])
    whole = np.concatenate([_read_all(t.path) for t in cat.tiles])
    return detect_stems(whole, StemConfig())


@pytest.mark.parametrize("size", [10.0, 7.0])
def test_copc_catalog_equals_single_process(
    copc_tiles: Path, copc_reference: CloudStems, client: Any, tmp_path: Path, size: float
) -> None:
    cat = Catalog.from_inputs([copc_tiles])
    assert len(cat) == 9 and all(t.copc for t in cat.tiles)
    run = run_stems_catalog(cat, StemConfig(), tmp_path, chunk_size=size, buffer=4.0, client=client)
    assert not run.failed and run.stems is not None
    assert not (tmp_path / "stage").exists()  # COPC tiles are queried, never staged
    reference = copc_reference
    assert_same_stems(reference, run.stems)
    assert isinstance(run.config, StemConfig)
    assert run.config.spacing == reference.spacing
    assert run.config.noise_floor == reference.noise_floor
