"""ROS 2 bags and MCAP files with compressed data, and ROS 1 bags without an index: what one
small file may make stemmap allocate (``stemmap.io._bag2_budget``, ``_bag_salvage``).

Before (branch base 7a8b9a6): rosbags decompressed every MCAP chunk (zstd, lz4), every
message of a message-compressed ROS 2 bag and every storage file of a file-compressed one
whole, whatever they announced; the salvage of an unindexed ROS 1 bag held every message of
the topic before yielding the first. The files here are small (hand-made zstd RLE frames:
benchmarks/hostile_bags.py) and the budget is set low (``STEMMAP_MAX_READ_GB=0.01``: 10 MB)
so that a few MB stand for gigabytes; tracemalloc shows what was allocated.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from _memory import traced_peak

import hostile_bags as hb  # benchmarks/ (tests/conftest.py)
import stemmap.io._bag2_budget as b2
from stemmap.errors import InputError
from stemmap.io._budget import ReadLimitError
from stemmap.io._util import SkippedFrame
from stemmap.io.rosbag import bag_summary, iter_laser_scans

BEAMS = 1_000_000  # 4 MB of float32 ranges a scan


def _refusal(fn) -> tuple[str, int]:
    def run() -> str:
        with pytest.raises(ReadLimitError) as err:
            fn()
        return str(err.value)

    msg, peak = traced_peak(run)
    return str(msg), peak


# --------------------------------------------------------------------------------------------
# MCAP chunks
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
@pytest.mark.parametrize("indexed", [False, True])
def test_an_mcap_chunk_announcing_more_than_the_budget_is_refused_before_decompressing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, compression: str, indexed: bool
) -> None:
    p = hb.mcap_bomb(tmp_path / "m.mcap", 2, BEAMS, compression=compression, indexed=indexed)
    assert p.stat().st_size < 100_000  # 8 MB of scans
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.01")
    msg, peak = _refusal(lambda: list(iter_laser_scans(p)))
    assert repr(str(p)) in msg and f"{compression}-compressed chunk" in msg
    assert "8 MB of messages" in msg and "STEMMAP_MAX_READ_GB=" in msg
    assert peak < 2_000_000  # the 8 MB chunk was never decompressed


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
@pytest.mark.parametrize("indexed", [False, True])
def test_within_the_budget_the_mcap_file_reads(
    tmp_path: Path, compression: str, indexed: bool
) -> None:
    p = hb.mcap_bomb(tmp_path / "m.mcap", 2, BEAMS, compression=compression, indexed=indexed)
    scans = list(iter_laser_scans(p))
    assert [s.time for s in scans] == [1.0, 1.0]  # the stamps (both 1 s)
    assert all(s.ranges.shape == (BEAMS,) and not s.ranges.any() for s in scans)


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_an_mcap_chunk_expanding_past_its_announcement_is_damage_not_an_allocation(
    tmp_path: Path, compression: str
) -> None:
    # indexed: read through the chunk index; the chunk's 8 MB stop after the announced 1 kB
    p = hb.mcap_bomb(
        tmp_path / "m.mcap", 2, BEAMS, compression=compression, size=1000, indexed=True
    )
    tiny = hb.mcap_bomb(tmp_path / "t.mcap", 1, 10, compression=compression, indexed=True)
    _, base = traced_peak(lambda: list(iter_laser_scans(tiny)))  # opening a bag: typestore, ...
    skipped: list[SkippedFrame] = []
    scans, peak = traced_peak(lambda: list(iter_laser_scans(p, skipped=skipped)))
    assert scans == []
    assert len(skipped) == 1 and "decompresses past the 1,000 bytes" in skipped[0].reason
    assert peak < base + 1_000_000  # not the 8 MB the data expand to
    # unindexed: rosbags scans the chunks when it opens the file
    q = hb.mcap_bomb(tmp_path / "u.mcap", 2, BEAMS, compression=compression, size=1000)
    with pytest.raises(InputError, match="decompresses past the 1,000 bytes"):
        bag_summary(q)


def test_an_index_announcing_more_than_its_chunk_is_checked_too(tmp_path: Path) -> None:
    """rosbags decompresses an indexed chunk to the size its chunk index says: the index's
    announcement is compared with the budget as well as the chunk record's."""
    p = hb.mcap_bomb(tmp_path / "m.mcap", 1, 1000, indexed=True)
    table = b2.mcap_chunks(p)
    assert len(table) == 2 and table[0] == table[1]  # chunk record + its index, agreeing
    assert table[0].compression == "zstd" and table[0].offset > 0


# --------------------------------------------------------------------------------------------
# ROS 2 zstd compression: per message, per file
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("announce", [True, False])
def test_a_message_inflating_past_the_budget_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, announce: bool
) -> None:
    p = hb.ros2_message_bomb(tmp_path / "b", 2 * BEAMS, announce=announce)  # 8 MB message
    tiny = hb.ros2_message_bomb(tmp_path / "t", 10, announce=announce)
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.01")  # messages up to 3.33 MB
    _, base = traced_peak(lambda: list(iter_laser_scans(tiny)))  # opening a bag: typestore, ...
    msg, peak = _refusal(lambda: list(iter_laser_scans(p)))
    assert repr(str(p)) in msg and "topic /scan, message 2" in msg
    assert "zstd-compressed message" in msg and "STEMMAP_MAX_READ_GB=" in msg
    assert ("announces 8 MB" in msg) == announce
    # announced: refused from the frame header; not: decompressed up to the 3.33 MB limit
    assert peak < base + (1_000_000 if announce else 4_500_000)


def test_within_the_budget_a_message_compressed_bag_reads(tmp_path: Path) -> None:
    p = hb.ros2_message_bomb(tmp_path / "b", 2 * BEAMS, announce=False)
    scans = list(iter_laser_scans(p))
    assert [len(s) for s in scans] == [90, 90, 2 * BEAMS]
    assert [s.time for s in scans] == [1.0, 2.0, 3.0]


def test_a_file_compressed_bag_is_inflated_at_most_to_the_disk_room(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    room = 2_000_000
    monkeypatch.setattr(b2, "disk_room", lambda: room)  # as if the disk had 2 MB to spare
    told = hb.ros2_file_bomb(tmp_path / "a", 0.005)  # 5 MB, announced in the frame header
    msg, peak = _refusal(lambda: bag_summary(told))
    assert "announce 5.0" in msg and "TMPDIR" in msg and repr(str(told)) in msg
    assert peak < 1_000_000  # refused from the header, nothing inflated
    quiet = hb.ros2_file_bomb(tmp_path / "b", 0.005, announce=False)
    msg, _ = _refusal(lambda: bag_summary(quiet))
    assert f"inflates past {room / 1e6:g} MB" in msg and "TMPDIR" in msg


def test_within_the_disk_room_a_file_compressed_bag_reads(tmp_path: Path) -> None:
    p = hb.ros2_file_bomb(tmp_path / "b", 0.005, announce=False)
    scans = list(iter_laser_scans(p))
    assert [len(s) for s in scans] == [90, 90, 90]


def test_an_inflated_message_over_the_budget_is_refused_before_it_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file-compressed ROS 2 bag whose inflated database holds a message of more than a
    third of the budget: rosbags would read the message whole."""
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.types import ScanBatch

    big = ScanBatch(np.zeros((2, 2 * BEAMS)), np.array([1.0, 2.0]), -math.pi, 1e-6)
    p = write_scans_bag(tmp_path / "b", big, ros=2, compression="zstd", compression_mode="file")
    assert sum(f.stat().st_size for f in p.iterdir()) < 100_000  # 16 MB of scans
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.01")
    msg, _ = _refusal(lambda: list(iter_laser_scans(p)))
    assert "largest message holds 8 MB once the bag is inflated" in msg and repr(str(p)) in msg


@pytest.mark.parametrize("mode", ["message", "file"])
def test_legitimate_compressed_bags_read_as_their_uncompressed_twin(
    tmp_path: Path, mode: str
) -> None:
    """rosbags' own writer, random ranges: the bounded decompressors return what rosbags' own
    ones return."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(3)
    ranges = rng.uniform(0.5, 20, (20, 360)).astype(np.float32)

    def write(folder: Path, compressed: bool) -> Path:
        w = Writer(folder, version=9)
        if compressed:
            w.set_compression(
                CompressionMode.MESSAGE if mode == "message" else CompressionMode.FILE,
                CompressionFormat.ZSTD,
            )
        with w:
            c = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
            for k, r in enumerate(ranges):
                msg = T["sensor_msgs/msg/LaserScan"](
                    header=T["std_msgs/msg/Header"](
                        stamp=T["builtin_interfaces/msg/Time"](sec=1 + k, nanosec=0),
                        frame_id="laser",
                    ),
                    angle_min=-1.0,
                    angle_max=-1.0 + 0.01 * 359,
                    angle_increment=0.01,
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=0.1,
                    range_max=30.0,
                    ranges=r,
                    intensities=np.zeros(0, np.float32),
                )
                w.write(c, (1 + k) * 10**9, ts.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))
        return folder

    plain = list(iter_laser_scans(write(tmp_path / "plain", False)))
    packed = list(iter_laser_scans(write(tmp_path / "packed", True)))
    assert len(plain) == len(packed) == 20
    for a, b in zip(plain, packed, strict=True):
        assert a.time == b.time and np.array_equal(a.ranges, b.ranges)


def test_the_bounded_decompressor_reads_concatenated_frames_as_zstd_does() -> None:
    zstd = b2._zstd()
    data = zstd.compress(b"abc" * 1000) + zstd.compress(b"xyz" * 10)
    assert b2.inflate_bounded("zstd", data, 3030) == zstd.decompress(data)
    assert b2.inflate_bounded("zstd", data, 3029) is None
    with pytest.raises(InputError, match="end inside a frame"):
        b2.inflate_bounded("zstd", data[:-3], 10**6)


# --------------------------------------------------------------------------------------------
# ROS 1 bag without an index: streamed
# --------------------------------------------------------------------------------------------


def test_an_unindexed_bag_is_read_one_chunk_at_a_time(tmp_path: Path) -> None:
    """A 40 MB topic in 4 MB lz4 chunks, cut at its index: the first scan comes after one
    chunk was read, not the whole topic (before: every message held, ~40 MB, first)."""
    p = hb.ros1_unindexed_bag(tmp_path / "u.bag", 0.04, beams=250_000, chunk_mb=4)

    def first() -> object:
        it = iter_laser_scans(p)
        scan = next(it)
        it.close()
        return scan

    scan, peak = traced_peak(first)
    assert len(scan) == 250_000  # type: ignore[arg-type]
    assert peak < 15_000_000
    assert sum(1 for _ in iter_laser_scans(p)) == sum(t.n_messages for t in bag_summary(p))


def test_rosbags_still_holds_the_names_the_bound_replaces() -> None:
    # install_bounded_codecs does nothing where rosbags keeps its decompressors under other
    # names; a rosbags upgrade that moves them must fail here, not silently unbound the reads.
    from rosbags.rosbag2 import reader as r2
    from rosbags.rosbag2 import storage_mcap

    from stemmap.io._bag2_budget import _BoundedZstd, install_bounded_codecs

    install_bounded_codecs()
    table = storage_mcap.DECOMPRESSORS
    assert isinstance(table, dict) and {"zstd", "lz4"} <= set(table)
    assert isinstance(r2.zstd, _BoundedZstd)
