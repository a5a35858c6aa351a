"""Tile catalog: inputs, header-only index, chunk grid (ownership partition, split), reads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stemmap.engine import Catalog, expand_inputs, plan_chunks, read_chunk
from stemmap.engine.staging import chunk_points, stage_tile
from stemmap.errors import ConfigError, InputError


def test_inputs_folder_glob_list_and_files(stand_tiles: tuple[Path, np.ndarray]) -> None:
    folder, _ = stand_tiles
    files = sorted(folder.glob("*.laz"))
    assert len(files) == 9
    lst = folder.parent / "tiles.txt"
    lst.write_text("# my tiles\n" + "\n".join(f"tiles/{p.name}" for p in files[:3]) + "\n\n")
    assert expand_inputs([folder]) == files
    assert expand_inputs([str(folder / "tile_0_*.laz")]) == [
        p for p in files if p.name.startswith("tile_0_")
    ]
    assert [p.resolve() for p in expand_inputs([lst])] == files[:3]
    # duplicates collapse; order is by path
    assert expand_inputs([files[1], files[0], files[1]]) == files[:2]


def test_inputs_errors_name_the_input(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nope\.laz"):
        expand_inputs([tmp_path / "nope.laz"])
    with pytest.raises(InputError, match=r"holds no \.las/\.laz"):
        expand_inputs([tmp_path])
    with pytest.raises(InputError, match="matches no file"):
        expand_inputs([str(tmp_path / "*.laz")])
    (tmp_path / "a.ply").write_text("ply")
    with pytest.raises(InputError, match="LAS/LAZ files only"):
        expand_inputs([tmp_path / "a.ply"])
    bad = tmp_path / "bad.laz"
    bad.write_bytes(b"not a las file at all")
    with pytest.raises(InputError, match="not a readable LAS/LAZ"):
        Catalog.from_inputs([bad])


def test_catalog_from_headers(stand_tiles: tuple[Path, np.ndarray]) -> None:
    folder, xyz = stand_tiles
    cat = Catalog.from_inputs([folder])
    assert cat.n_points == len(xyz)
    b = cat.bounds
    np.testing.assert_allclose(b, [*xyz[:, :2].min(0), *xyz[:, :2].max(0)], atol=1e-9)
    assert not any(t.copc for t in cat.tiles)


@pytest.mark.parametrize(("size", "buffer"), [(10.0, 2.0), (7.0, 5.0), (25.0, 0.0)])
def test_owned_areas_partition_the_plane(
    stand_tiles: tuple[Path, np.ndarray], size: float, buffer: float
) -> None:
    """Every position -- inside the catalog, on chunk edges, far outside -- belongs to exactly
    one chunk: a stem is neither lost nor doubled."""
    cat = Catalog.from_inputs([stand_tiles[0]])
    chunks = plan_chunks(cat, size, buffer)
    rng = np.random.default_rng(0)
    pts = np.concatenate(
        (
            rng.uniform(-20, 50, (5000, 2)),
            np.round(rng.uniform(-5, 35, (2000, 2)) / size) * size,  # exactly on edges
        )
    )
    owners = np.sum([c.owns(pts) for c in chunks], axis=0)
    assert np.all(owners == 1)


def test_dense_chunks_are_split(stand_tiles: tuple[Path, np.ndarray]) -> None:
    cat = Catalog.from_inputs([stand_tiles[0]])
    whole = plan_chunks(cat, 40.0, 2.0)
    assert len(whole) == 1
    budget = cat.n_points // 3
    split = plan_chunks(cat, 40.0, 2.0, max_points=budget)
    assert len(split) > 1
    assert all(c.expected_points <= budget for c in split)
    # the split chunks still partition the plane
    pts = np.random.default_rng(1).uniform(-10, 50, (3000, 2))
    assert np.all(np.sum([c.owns(pts) for c in split], axis=0) == 1)
    # automatic chunk size: multiples of 10 m within the budget
    auto = plan_chunks(cat, None, 2.0, max_points=budget)
    assert all((c.box[2] - c.box[0]) % 10 == 0 for c in auto)


def test_bad_chunk_options(stand_tiles: tuple[Path, np.ndarray]) -> None:
    cat = Catalog.from_inputs([stand_tiles[0]])
    with pytest.raises(ConfigError, match="--chunk-size"):
        plan_chunks(cat, 0.0, 1.0)
    with pytest.raises(ConfigError, match="--buffer"):
        plan_chunks(cat, 10.0, -1.0)


def test_staged_extra_fields_follow_their_points(tmp_path: Path) -> None:
    """Staging with an extra field (GPS time, for sensor positions): each chunk gets its
    points' own values, in the order of a direct read, for overlapping buffers (a point in up
    to four boxes) and several LAZ blocks a tile."""
    import laspy

    rng = np.random.default_rng(4)
    folder = tmp_path / "tiles"
    folder.mkdir()
    for i in range(2):
        for j in range(2):
            xyz = np.round(rng.uniform(0, 10, (3000, 3)) * 1000) / 1000 + [10 * i, 10 * j, 0]
            header = laspy.LasHeader(point_format=6, version="1.4")
            header.scales = np.array([0.001, 0.001, 0.001])
            header.offsets = np.floor(xyz.min(axis=0))
            las = laspy.LasData(header)
            las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            las.gps_time = rng.permutation(3000) + 10_000.0 * (2 * i + j)  # unique per point
            las.write(folder / f"t_{i}_{j}.laz")
    cat = Catalog.from_inputs([folder])
    for size, buf in ((7.0, 2.0), (5.0, 6.0)):  # buffers under and over half a chunk
        chunks = plan_chunks(cat, size, buf)
        stage = str(tmp_path / f"stage{size:g}")
        for k in range(len(cat.tiles)):
            mine = [c for c in chunks if k in c.tiles]
            stage_tile(cat, k, mine, stage, ("gps_time",), read_points=700)
        for ch in chunks:
            direct, dx = read_chunk(cat, ch, fields=("gps_time",))
            staged, sx = chunk_points(cat, ch, stage, ("gps_time",))
            np.testing.assert_array_equal(staged, direct)
            np.testing.assert_array_equal(sx["gps_time"], dx["gps_time"])


def test_read_chunk_and_staging_read_exactly_the_buffered_box(
    stand_tiles: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    folder, xyz = stand_tiles
    cat = Catalog.from_inputs([folder])
    chunks = plan_chunks(cat, 12.0, 3.0)
    stage = str(tmp_path / "stage")
    for k in range(len(cat.tiles)):
        stage_tile(cat, k, [c for c in chunks if k in c.tiles], stage, read_points=50_000)
    for ch in chunks:
        x0, y0, x1, y1 = ch.buffered
        m = (xyz[:, 0] >= x0) & (xyz[:, 0] <= x1) & (xyz[:, 1] >= y0) & (xyz[:, 1] <= y1)
        direct, _ = read_chunk(cat, ch, read_points=70_000)
        staged, _ = chunk_points(cat, ch, stage)
        # same points in the same order (tile order, then file order)
        np.testing.assert_array_equal(direct, xyz[m])
        np.testing.assert_array_equal(staged, xyz[m])


def test_staging_tolerates_a_chunk_cleared_while_a_rerun_stages_its_tile(
    stand_tiles: tuple[Path, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stage task Dask re-runs after a worker was killed can still be writing the fragments
    of a chunk that finished meanwhile and whose folder the run cleared (`clear_stage`); that
    chunk needs nothing more, so the task must not fail (it did: FileNotFoundError on the
    rename, failing every chunk that waited for the tile), and the other chunks' fragments
    must be complete."""
    import os

    from stemmap.engine import staging

    folder, _ = stand_tiles
    cat = Catalog.from_inputs([folder])
    chunks = plan_chunks(cat, 12.0, 3.0)
    stage = tmp_path / "stage"
    mine = [c for c in chunks if 0 in c.tiles]
    assert len(mine) >= 2
    done = mine[0].id
    real_replace = os.replace

    def clear_then_replace(src: str, dst: str) -> None:
        if Path(src).parent.name == done:
            staging.clear_stage(stage, done)  # the run finishing chunk `done` meanwhile
        real_replace(src, dst)

    monkeypatch.setattr(staging.os, "replace", clear_then_replace)
    staging.stage_tile(cat, 0, mine, str(stage), read_points=50_000)
    monkeypatch.setattr(staging.os, "replace", real_replace)
    assert not (stage / done).exists()
    for ch in mine[1:]:
        assert (stage / ch.id / "0.xyz").is_file()
        assert not list((stage / ch.id).glob("*.tmp*"))  # no temporary file left behind
