"""write_scans_bag's ROS1 chunk options: a compressed bag reads back the same scans, in chunks
of the asked size and compression (the fuzz targets ros1_bag_bz2 / _lz4 seed from it)."""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.io import read_scans
from stemmap.io._bag_budget import ros1_chunks
from stemmap.io.rosbag import write_scans_bag
from stemmap.types import ScanBatch


def _batch() -> ScanBatch:
    rng = np.random.default_rng(3)
    return ScanBatch(
        ranges=rng.uniform(0.5, 20.0, (12, 91)).astype(np.float32).astype(np.float64),
        times=np.arange(12) * 0.1 + 1.0,
        angle_min=-np.pi / 2,
        angle_increment=np.pi / 90,
        range_max=30.0,
    )


@pytest.mark.parametrize("compression", ["bz2", "lz4"])
def test_a_compressed_bag_reads_back_the_scans_in_small_chunks(tmp_path, compression):
    b = _batch()
    p = write_scans_bag(tmp_path / "c.bag", b, compression=compression, chunk_bytes=512)
    got = read_scans(p)
    np.testing.assert_array_equal(got.ranges, b.ranges)
    chunks = ros1_chunks(p)
    # 12 messages of ~400 bytes in chunks closed at 512 bytes: one chunk every message or two
    assert len(chunks) >= 6
    assert {c.compression for c in chunks} == {compression}


def test_chunk_options_are_refused_for_ros2_and_unknown_compression(tmp_path):
    with pytest.raises(ConfigError, match="ROS1"):
        write_scans_bag(tmp_path / "r2", _batch(), ros=2, compression="lz4")
    with pytest.raises(ConfigError, match="compression"):
        write_scans_bag(tmp_path / "x.bag", _batch(), compression="zip")
