"""ROS 1 bags with compressed chunks (bz2, lz4): a chunk is decompressed whole before its first
message is read, so a small file can ask for gigabytes -- honestly (the chunk header's
``size`` field announces it: up to 4.29 GB per chunk) or not (the header announces less than
the data expands to).

Before: rosbags decompressed every chunk whole, whatever it announced: the 60 MB chunk below
(0.26 MB on disk) was allocated, copied per message and decoded; a header lying about the
size made no difference. Now (``stemmap.io._bag_budget``):

* every chunk's announced size is checked against the read budget (``STEMMAP_MAX_READ_GB``)
  before the first message is read, in the indexed and in the salvage (no index) path;
* a chunk is decompressed to at most the size its header announces: one that expands past it
  is damaged, reported as the rest of the topic lost, without allocating the rest.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from _memory import traced_peak

from hostile_inputs import ros1_compressed_bag  # benchmarks/ (tests/conftest.py)
from stemmap.errors import InputError
from stemmap.io._util import SkippedFrame
from stemmap.io.rosbag import iter_laser_scans

N, BEAMS = 60, 250_000  # one chunk of 60 scans x 1 MB of float32 ranges: 60 MB


@pytest.mark.parametrize("compression", ["lz4", "bz2"])
def test_a_chunk_announcing_more_than_the_budget_is_refused_before_it_is_decompressed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, compression: str
) -> None:
    bag = ros1_compressed_bag(tmp_path / "b.bag", N, BEAMS, compression=compression, range_m=0)
    assert bag.stat().st_size < 2_000_000  # 60 MB of ranges in < 2 MB
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.1")  # 100 MB: below ~3 x 60 MB to read it

    def read() -> object:
        with pytest.raises(InputError) as err:
            next(iter_laser_scans(bag))
        return str(err.value)

    msg, peak = traced_peak(read)
    assert "b.bag" in str(msg) and f"{compression}-compressed chunk" in str(msg)
    assert "60 MB" in str(msg) and "STEMMAP_MAX_READ_GB=" in str(msg)
    assert peak < 20e6, f"peak {peak / 1e6:.0f} MB"  # the chunk (60 MB) was never decompressed


def test_within_the_budget_the_bag_reads_as_before(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bag = ros1_compressed_bag(tmp_path / "b.bag", 5, 1000)
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.1")
    scans = list(iter_laser_scans(bag))
    assert len(scans) == 5 and all(float(s.ranges.mean()) == 5.0 for s in scans)


@pytest.mark.parametrize("compression", ["lz4", "bz2"])
def test_a_chunk_expanding_past_its_announced_size_is_damage_not_an_allocation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, compression: str
) -> None:
    # the header says 1 MB, the data expand to 60 MB: the budget check passes, so the bound
    # must hold while decompressing
    bag = ros1_compressed_bag(
        tmp_path / "b.bag", N, BEAMS, compression=compression, size=10**6, range_m=0
    )
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0")  # no budget: only the size bound acts
    skipped: list[SkippedFrame] = []
    scans, peak = traced_peak(lambda: list(iter_laser_scans(bag, skipped=skipped)))
    assert scans == []
    assert len(skipped) == 1 and "past the 1,000,000 bytes its header announces" in (
        skipped[0].reason
    )
    assert peak < 20e6, f"peak {peak / 1e6:.0f} MB"  # before: >= 60 MB


def test_the_salvage_path_checks_the_chunks_too(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the same bag with its index cut off (a killed recording) is read chunk by chunk by
    # stemmap's own salvage: the same refusal, before the chunk is decompressed
    bag = ros1_compressed_bag(tmp_path / "b.bag", N, BEAMS)
    data = bag.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: data.rfind(b"op=\x04")])  # drop the index data and what follows
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.1")

    def read() -> None:
        with pytest.raises(
            InputError, match=r"cut\.bag.*lz4-compressed chunk.*STEMMAP_MAX_READ_GB"
        ):
            next(iter_laser_scans(cut))

    _, peak = traced_peak(read)
    assert peak < 20e6, f"peak {peak / 1e6:.0f} MB"


def test_every_reader_of_a_bag_gets_the_check(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # open_bag itself checks: the camera Image-bag reader and the topic listing use it
    # directly, not through the message iterator
    from stemmap.io.camera_bag import read_camera_bag
    from stemmap.io.rosbag import bag_summary, open_bag

    bag = ros1_compressed_bag(tmp_path / "b.bag", N, BEAMS, range_m=0)
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.1")
    for call in (open_bag(bag).__enter__, lambda: bag_summary(bag), lambda: read_camera_bag(bag)):
        with pytest.raises(InputError, match=r"b\.bag.*lz4-compressed chunk at byte"):
            call()
