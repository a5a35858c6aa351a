"""Stems over a tile catalog: equal to one process over the whole cloud, for any chunking;
manifest, resume, and a failing tile reported while the rest finish."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stemmap.cloud import CloudStems, StemConfig, detect_stems
from stemmap.engine import Catalog, Manifest, run_stems_catalog

# Tolerances of the chunked result against one process over the whole cloud. The detector's
# clustering and vertical-filter grids are anchored at the minimum of the points it is given,
# and its point spacing and slice noise floor are measured on them, so the same stem fitted in
# a buffered chunk sees a few points assigned differently: measured differences are up to
# 2.5 mm in position and diameter on this two-station stand, 1.1 / 1.8 mm on a nine-station
# one (exactly 0 with grids anchored at multiples of the cell and a fixed spacing, see
# docs/algorithms/engine.md) -- well below the detector's ~1 cm DBH error on such clouds.
POS_TOL = 0.005
DBH_TOL = 0.005


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    from distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
        ) as cluster,
        Client(cluster) as cl,
    ):
        yield cl


@pytest.fixture(scope="module")
def reference(stand_tiles: tuple[Path, np.ndarray]) -> CloudStems:
    """One process over the whole cloud, points in the catalog's order."""
    return detect_stems(stand_tiles[1], StemConfig())


def assert_same_stems(a: CloudStems, b: CloudStems) -> None:
    assert len(a) == len(b) > 0
    d, i = cKDTree(b.xy).query(a.xy)
    assert np.unique(i).size == len(a)  # one-to-one
    assert d.max() < POS_TOL
    np.testing.assert_allclose(b.diameter[i], a.diameter, atol=DBH_TOL)
    np.testing.assert_array_equal(b.n_slices[i], a.n_slices)


@pytest.mark.parametrize(("size", "buffer"), [(10.0, 4.0), (7.0, 5.0), (None, 5.0)])
def test_chunked_equals_single_process(
    stand_tiles: tuple[Path, np.ndarray],
    reference: CloudStems,
    client: Any,
    tmp_path: Path,
    size: float | None,
    buffer: float,
) -> None:
    cat = Catalog.from_inputs([stand_tiles[0]])
    run = run_stems_catalog(
        cat, StemConfig(), tmp_path, chunk_size=size, buffer=buffer, client=client
    )
    assert not run.failed and run.stems is not None
    assert_same_stems(reference, run.stems)
    # merged output is sorted by x, then y, whatever the chunking
    assert np.all(np.diff(run.stems.xy[:, 0]) >= 0)
    lines = Manifest(tmp_path).entries()
    assert set(lines) == {c.id for c in run.chunks}
    assert all(r["status"] == "done" for r in lines.values())
    assert sum(r["n_stems"] for r in lines.values()) == len(run.stems)
    assert not (tmp_path / "stage").exists()  # staged fragments are removed


def test_resume_redoes_only_missing_or_changed_chunks(
    stand_tiles: tuple[Path, np.ndarray], client: Any, tmp_path: Path
) -> None:
    tiles = tmp_path / "tiles"
    shutil.copytree(stand_tiles[0], tiles)
    cat = Catalog.from_inputs([tiles])
    work = tmp_path / "work"
    first = run_stems_catalog(cat, StemConfig(), work, chunk_size=10.0, client=client)
    n = len(first.chunks)
    assert len(first.computed) == n
    again = run_stems_catalog(cat, StemConfig(), work, chunk_size=10.0, resume=True, client=client)
    assert again.computed == [] and len(again.skipped) == n
    assert_same_stems(first.stems, again.stems)  # type: ignore[arg-type]
    # a chunk whose line is missing (killed before it finished) is redone, only it
    man = Manifest(work)
    lines = man.path.read_text().splitlines()
    dropped = json.loads(lines[3])["chunk"]
    man.path.write_text("\n".join(lines[:3] + lines[4:]) + "\n")
    third = run_stems_catalog(cat, StemConfig(), work, chunk_size=10.0, resume=True, client=client)
    assert third.computed == [dropped]
    # a changed tile invalidates exactly the chunks whose buffered box reads it
    changed = cat.tiles[4]
    Path(changed.path).write_bytes(Path(changed.path).read_bytes())  # same bytes: still done
    assert (
        run_stems_catalog(
            cat, StemConfig(), work, chunk_size=10.0, resume=True, client=client
        ).computed
        == []
    )
    # other parameters: everything is redone
    fourth = run_stems_catalog(
        cat, StemConfig(min_slices=4), work, chunk_size=10.0, resume=True, client=client
    )
    assert len(fourth.computed) == n


def test_failed_tile_is_reported_and_the_rest_finish(
    stand_tiles: tuple[Path, np.ndarray], client: Any, tmp_path: Path
) -> None:
    tiles = tmp_path / "tiles"
    shutil.copytree(stand_tiles[0], tiles)
    cat = Catalog.from_inputs([tiles])
    # truncate one tile after indexing (a copy cut short): its header still reads
    bad = Path(cat.tiles[0].path)
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])
    run = run_stems_catalog(
        cat, StemConfig(), tmp_path / "w", chunk_size=10.0, client=client, retries=0
    )
    users = {c.id for c in run.chunks if 0 in c.tiles}
    assert set(run.failed) == users
    assert run.stems is None  # no merged product with a hole in it
    assert len(run.computed) == len(run.chunks) - len(users)
    lines = Manifest(tmp_path / "w").entries()
    assert all("tile_0_0" in lines[c]["error"] for c in users)
    assert all(lines[c]["status"] == "failed" for c in users)
