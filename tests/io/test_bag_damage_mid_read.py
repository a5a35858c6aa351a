"""Bags that open but are damaged further in: every bag reader ends in the project's own error
or a reported skip naming the file, the topic and the message, never a raw rosbags / mcap /
sqlite / decompressor exception, and a command that writes products writes none of them.

The laser-scan, odometry and IMU readers share :func:`stemmap.io._bag._decoded` with the
camera reader: the scan-like logs keep the messages before the damage and record one
:class:`SkippedFrame` saying where the rest was lost (a bad frame in a long log is reported
and skipped); the camera reader, whose frames must follow each other for visual odometry and
which refuses an undecodable image already, raises an InputError from the same text.

Before this change (branch base 7ad0d91) the camera reader let rosbags' exceptions through
mid-read (``OverflowError``, ``ReaderError``, ``AnyReaderError``, lz4's ``RuntimeError``,
bz2's ``OSError``), on the same kinds of damage as below.
"""

from __future__ import annotations

import re
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from _ros_bags import BagFactory
from stemmap.cli import app
from stemmap.errors import InputError
from stemmap.io import SkippedFrame
from stemmap.io._bag2_budget import mcap_chunks
from stemmap.io.camera_bag import read_camera_bag
from stemmap.io.rosbag import _records, iter_laser_scans, read_imu, read_odometry

N = 60  # frames: each with a scan, an odometry and an IMU message, two images, two CameraInfo
LEFT, RIGHT = "/cam/left/image", "/cam/right/image"
CAMERA = f"topics {LEFT} and {RIGHT}"
H, W = 120, 160  # 19 kB images: a few MB a bag, so rosbags writes MCAP chunks (1 MiB) >= 3
K = [100.0, 0.0, W / 2, 0.0, 100.0, H / 2, 0.0, 0.0, 1.0]


def _write(f: BagFactory, path: Path) -> Path:
    rng = np.random.default_rng(7)
    msgs: list[tuple[str, Any]] = []
    for i in range(N):
        t = 1.0 + 0.1 * i
        img = rng.integers(0, 256, (H, W), dtype=np.uint8)
        msgs += [
            ("/scan", f.laserscan(t, np.full(300, 3.0))),
            ("/odom", f.odometry(t, (0.1 * i, 0.0, 0.0), (0, 0, 0, 1), (1.0, 0.0, 0.0), 0.0)),
            ("/imu", f.imu(t, (0, 0, 0, 1), (0.0, 0.0, 9.8))),
            (LEFT, f.image(t, img, "mono8")),
            (RIGHT, f.image(t, np.roll(img, -2, axis=1), "mono8")),
            ("/cam/left/camera_info", f.camera_info(t, K, W, H)),
            ("/cam/right/camera_info", f.camera_info(t, K, W, H, tx=-100.0 * 0.1)),
        ]
    return f.write(path, msgs)


def _storage(p: Path) -> Path:
    return next(q for q in p.iterdir() if q.suffix in (".db3", ".mcap")) if p.is_dir() else p


def _garble(path: Path, at: int) -> None:
    """Overwrite 64 bytes of ``path`` from byte ``at`` with 0xFF."""
    data = bytearray(path.read_bytes())
    data[at : at + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))


def _garble_records(path: Path, starts: list[int]) -> None:
    """Garble the record starting at the middle of ``starts`` and every later one."""
    for at in starts[len(starts) // 2 :]:
        _garble(path, at)


def _damage_ros1(p: Path) -> None:
    """Garble the middle chunk's data from its middle message record on (uncompressed), or
    the start of its compressed stream; the chunk's and the bag's indexes stay intact."""
    view = memoryview(p.read_bytes())
    chunks = [r for r in _records(view, 13) if r[1]["op"] == b"\x05"]
    assert len(chunks) >= 3
    _, header, a, b = chunks[len(chunks) // 2]
    if header["compression"] != b"none":
        _garble(p, a)
        return
    _garble_records(p, [a + off for off, h, _, _ in _records(view[a:b], 0) if h["op"] == b"\x02"])


def _damage_mcap(p: Path) -> None:
    """Garble the records of the middle (uncompressed) chunk from its middle one on; the
    summary (chunk and message indexes) stays intact."""
    s = _storage(p)
    data = s.read_bytes()
    chunks = sorted({c.offset for c in mcap_chunks(s)})
    assert len(chunks) >= 3
    body = chunks[len(chunks) // 2] + 9  # past the opcode and the record length
    assert data[body - 9] == 0x06  # a chunk record
    u32 = int.from_bytes(data[body + 28 : body + 32], "little")  # compression name length
    pos = body + 32 + u32 + 8  # past start/end time, size, crc, compression, records length
    end = pos + int.from_bytes(data[pos - 8 : pos], "little")
    starts = []
    while pos < end:
        starts.append(pos)
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    _garble_records(s, starts)


def _damage_sqlite(p: Path) -> None:
    """Cut the payload of message 200 of 420 to 5 bytes (a sqlite blob that cannot be CDR)."""
    with sqlite3.connect(_storage(p)) as db:
        db.execute("UPDATE messages SET data = substr(data, 1, 5) WHERE id = 200")


KINDS = {
    "ros1": (BagFactory(1, chunk_bytes=200_000), _damage_ros1),
    "ros1-lz4": (BagFactory(1, chunk_bytes=200_000, compression="lz4"), _damage_ros1),
    "ros1-bz2": (BagFactory(1, chunk_bytes=200_000, compression="bz2"), _damage_ros1),
    "ros2-mcap": (BagFactory(2, storage="mcap"), _damage_mcap),
    "ros2-sqlite3": (BagFactory(2, storage="sqlite3"), _damage_sqlite),
}


@pytest.fixture(params=sorted(KINDS))
def damaged(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    factory, damage = KINDS[str(request.param)]
    p = _write(factory, tmp_path / "drive")
    assert len(list(read_camera_bag(p))) == N  # intact, every reader reads it all
    damage(p)
    return p


def test_the_camera_reader_raises_an_input_error_naming_the_bag_topics_and_message(
    damaged: Path,
) -> None:
    cb = read_camera_bag(damaged)  # the CameraInfo topics come before the damage
    frames = []
    with pytest.raises(InputError) as info:
        frames.extend(cb)
    msg = str(info.value)
    assert msg.startswith(f"ROS bag {str(damaged)!r}: "), msg
    m = re.search(rf"(after message|message) (\d+) of {re.escape(CAMERA)}", msg)
    assert m is not None, msg
    assert re.search(r"bag time \d+\.\d{3} s", msg), msg
    assert 0 < len(frames) < N  # frames before the damage came through
    assert int(m.group(2)) >= 2 * len(frames)  # two images a frame read before it broke
    assert not isinstance(info.value.__cause__, InputError)  # the raw cause is kept, chained


@pytest.mark.parametrize(
    ("topic", "read"),
    [
        ("/scan", lambda p, sk: list(iter_laser_scans(p, skipped=sk))),
        ("/odom", lambda p, sk: read_odometry(p, skipped=sk).times),
        ("/imu", lambda p, sk: read_imu(p, skipped=sk).times),
    ],
)
def test_the_log_readers_keep_what_comes_before_and_report_the_rest(
    damaged: Path, topic: str, read: Any
) -> None:
    skipped: list[SkippedFrame] = []
    got = read(damaged, skipped)
    if not skipped:  # the damage missed this topic's messages (sqlite: one message of one)
        assert len(got) == N
        return
    assert len(got) < N
    assert all(re.search(rf"message \d+ of topic {topic}\b", s.reason) for s in skipped)
    last = skipped[-1]
    assert last.frame_index >= len(got)  # reported where it broke, after what was kept


def test_a_camera_odometry_run_on_a_damaged_bag_writes_nothing(
    damaged: Path, tmp_path: Path
) -> None:
    """``stemmap odometry --camera`` stops with one ``error:`` line naming the bag; the old
    trajectory file is left as it was and no temporary or partial file stays behind."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "traj.csv"
    out.write_text("old trajectory\n")
    res = CliRunner().invoke(app, ["odometry", "--camera", str(damaged), "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "error:" in res.output and damaged.name in res.output
    assert out.read_text() == "old trajectory\n"
    assert sorted(q.name for q in out_dir.iterdir()) == ["traj.csv"]
