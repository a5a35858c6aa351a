"""ROS bag readers, tested on ROS1 / ROS2 (sqlite3, mcap) bags written with rosbags' writers."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from _ros_bags import BagFactory
from stemmap.errors import InputError
from stemmap.io import (
    SkippedFrame,
    decode_pointcloud2,
    iter_scans,
    list_topics,
    read_imu,
    read_navsatfix,
    read_odometry,
    read_pointclouds,
    read_scans,
    read_scans_indexed,
)
from stemmap.io.rosbag import (
    PointField,
    is_bag,
    roll_pitch_from_acceleration,
    roll_pitch_from_quaternion,
)

F32, F64, U8, U16, I32 = 7, 8, 2, 4, 5


def _yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _quat_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


# ---------------------------------------------------------------- LaserScan


def test_laserscan_round_trip(tmp_path: Path, bags: BagFactory) -> None:
    rng = np.random.default_rng(1)
    ranges = rng.uniform(0.5, 20.0, size=(5, 271)).astype(np.float32)
    ranges[:, 7] = np.nan
    ranges[:, 8] = np.inf
    msgs = [
        ("/scan", bags.laserscan(1700000000.0 + 0.025 * i, ranges[i], -2.35, 0.0175, 0.05, 25.0))
        for i in range(5)
    ]
    p = bags.write(tmp_path / "scans", msgs)
    assert is_bag(p)
    b = read_scans(p)
    # float32 on the wire: ranges are exactly the float32 values promoted to float64
    np.testing.assert_array_equal(b.ranges, ranges.astype(np.float64))
    # stamps: sec + nanosec; float64 at 1.7e9 s resolves ~0.24 us
    np.testing.assert_allclose(b.times, 1700000000.0 + 0.025 * np.arange(5), atol=1e-6)
    assert b.angle_min == pytest.approx(-2.35, abs=1e-6)  # float32 field
    assert b.angle_increment == pytest.approx(0.0175, rel=1e-6)
    assert (b.range_min, b.range_max) == pytest.approx((0.05, 25.0), rel=1e-6)
    assert b.frame == "laser"
    assert len(list(iter_scans(p))) == 5
    if p.is_dir():  # a bare ROS2 storage file (metadata.yaml lost) reads the same
        (storage,) = [q for q in p.iterdir() if q.suffix in (".db3", ".mcap")]
        assert is_bag(storage)
        np.testing.assert_array_equal(read_scans(storage).ranges, b.ranges)


def test_laserscan_intensities_kept(tmp_path: Path) -> None:
    f = BagFactory(2)
    p = f.write(tmp_path / "b", [("/scan", f.laserscan(1.0, [1.0, 2.0], intensities=[5.0, 6.0]))])
    (s,) = list(iter_scans(p))
    np.testing.assert_array_equal(s.intensities, [5.0, 6.0])


def test_corrupt_message_is_skipped(tmp_path: Path, bags: BagFactory) -> None:
    msgs = [("/scan", bags.laserscan(10.0 + i, np.full(30, 3.0))) for i in range(3)]
    p = bags.write(tmp_path / "b", msgs, raw=[("/scan", "sensor_msgs/msg/LaserScan", b"\x00\x01")])
    skipped: list[SkippedFrame] = []
    b = read_scans(p, skipped=skipped)
    assert len(b) == 3 and len(skipped) == 1
    assert skipped[0].frame_index == 3 and "cannot be decoded" in skipped[0].reason


def test_mixed_geometry_keeps_dominant(tmp_path: Path, bags: BagFactory) -> None:
    msgs = [
        ("/scan", bags.laserscan(1.0 + i, np.full(40 if i != 2 else 35, 3.0))) for i in range(4)
    ]
    p = bags.write(tmp_path / "b", msgs)
    skipped: list[SkippedFrame] = []
    b = read_scans(p, skipped=skipped)
    assert b.n_beams == 40 and len(b) == 3
    assert [s.frame_index for s in skipped] == [2] and "35 beams" in skipped[0].reason
    assert read_scans_indexed(p)[1].tolist() == [0, 1, 3]


def test_zero_stamp_falls_back_to_bag_time(tmp_path: Path) -> None:
    f = BagFactory(1)
    p = f.write(tmp_path / "b", [("/scan", f.laserscan(0.0, [1.0]))])
    (s,) = list(iter_scans(p))
    assert s.time == pytest.approx(1e-9)  # the writer's receive time (1 ns)


# ---------------------------------------------------------------- topic selection


def test_topic_selection(tmp_path: Path) -> None:
    f = BagFactory(2)
    msgs = [
        ("/front/scan", f.laserscan(1.0, [1.0, 2.0])),
        ("/rear/scan", f.laserscan(1.0, [3.0, 4.0, 5.0])),
        ("/odom", f.odometry(1.0, (0, 0, 0), _yaw_quat(0), (0, 0, 0), 0)),
    ]
    p = f.write(tmp_path / "b", msgs)
    assert list_topics(p) == {
        "/front/scan": "sensor_msgs/msg/LaserScan",
        "/odom": "nav_msgs/msg/Odometry",
        "/rear/scan": "sensor_msgs/msg/LaserScan",
    }
    with pytest.raises(InputError, match=r"2 sensor_msgs/msg/LaserScan topics.*--topic"):
        read_scans(p)
    assert read_scans(p, topic="/rear/scan").n_beams == 3
    with pytest.raises(InputError, match=r"no topic '/scan'.*/front/scan \(sensor_msgs"):
        read_scans(p, topic="/scan")
    with pytest.raises(InputError, match=r"'/odom'.*carries nav_msgs/msg/Odometry"):
        read_scans(p, topic="/odom")
    with pytest.raises(InputError, match=r"no sensor_msgs/msg/Imu topic; available topics"):
        read_imu(p)
    assert len(read_odometry(p)) == 1  # the only Odometry topic is auto-selected


# ---------------------------------------------------------------- damaged / missing bags


def test_missing_and_non_bag_paths(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        read_scans(tmp_path / "x.bag")
    (tmp_path / "folder").mkdir()
    with pytest.raises(InputError, match=r"without metadata\.yaml"):
        list_topics(tmp_path / "folder")
    (tmp_path / "fake.bag").write_bytes(b"#ROSBAG V2.0\nthis is not a bag")
    with pytest.raises(InputError, match=r"cannot open ROS bag .*fake\.bag"):
        read_scans(tmp_path / "fake.bag")


def test_truncated_bag(tmp_path: Path, bags: BagFactory) -> None:
    """A bag cut in half (recording killed, copy interrupted) is refused with an InputError
    naming the file and the likely cause -- never a raw rosbags/sqlite exception. (A ROS1 bag
    cut after its first chunk starts is salvaged instead, see
    test_ros1_bag_without_index_is_salvaged; here the ROS1 bag is cut inside its header.)"""
    rng = np.random.default_rng(2)
    msgs = [("/scan", bags.laserscan(1.0 + i, rng.uniform(1, 9, 500))) for i in range(200)]
    p = bags.write(tmp_path / "b", msgs)
    if p.is_dir():  # ROS2: truncate the storage file, read it without metadata
        (storage,) = [q for q in p.iterdir() if q.suffix in (".db3", ".mcap")]
        target = tmp_path / f"cut{storage.suffix}"
        shutil.copy(storage, target)
    else:
        target = p
    data = target.read_bytes()
    target.write_bytes(data[: len(data) // 2] if p.is_dir() else data[:2000])
    with pytest.raises(
        InputError, match=rf"cannot open ROS bag '{re.escape(str(target))}'.*truncated"
    ):
        read_scans(target)


@pytest.mark.parametrize("compression", ["", "bz2", "lz4"])
def test_ros1_bag_without_index_is_salvaged(tmp_path: Path, compression: str) -> None:
    """ROS1 bags cut short (copy interrupted) keep every message of their complete chunks;
    uncompressed chunks are read up to the last complete message record."""
    f = BagFactory(1, chunk_bytes=20_000, compression=compression)
    rng = np.random.default_rng(4)
    ranges = rng.uniform(1, 9, (200, 500)).astype(np.float32)
    msgs = [("/scan", f.laserscan(1.0 + i, ranges[i])) for i in range(200)]
    p = f.write(tmp_path / "b", msgs)
    data = p.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    skipped: list[SkippedFrame] = []
    b, idx = read_scans_indexed(cut, skipped=skipped)
    n = len(b)
    assert 0 < n < 200 and idx.tolist() == list(range(n))
    np.testing.assert_array_equal(b.ranges, ranges[:n].astype(np.float64))  # intact messages
    assert len(skipped) == 1 and "lost" in skipped[0].reason and skipped[0].frame_index == n
    if not compression:  # 60 % of ~2 kB-per-message data: about 120 messages recoverable
        assert n >= 115
    assert list_topics(cut) == {"/scan": "sensor_msgs/msg/LaserScan"}


def test_ros1_killed_recording_without_chunk_size(tmp_path: Path) -> None:
    """rosbag writes a chunk's size only when closing it: a killed recording leaves the last
    chunk with data length 0 and no index. Its message records are still read."""
    f = BagFactory(1)  # one chunk holds all 30 messages
    msgs = [("/scan", f.laserscan(1.0 + i, np.full(100, float(i)))) for i in range(30)]
    p = f.write(tmp_path / "b", msgs)
    data = bytearray(p.read_bytes())
    # find the chunk record (op=0x05) after the 4096-byte bag header record and zero its
    # data length, then drop everything after the 25th message (the index and the rest)
    from stemmap.io.rosbag import _records

    recs = list(_records(memoryview(bytes(data)), 13))
    chunk = next(r for r in recs if r[1]["op"] == b"\x05")
    _, _, a, _ = chunk
    data[a - 4 : a] = (0).to_bytes(4, "little")
    inner = list(_records(memoryview(bytes(data[a:])), 0))
    msg_recs = [r for r in inner if r[1]["op"] == b"\x02"]
    end = a + msg_recs[24][3] + 10  # 10 bytes into message 26: an incomplete record
    cut = tmp_path / "killed.bag"
    cut.write_bytes(bytes(data[:end]))
    skipped: list[SkippedFrame] = []
    b = read_scans(cut, skipped=skipped)
    np.testing.assert_array_equal(b.ranges[:, 0], np.arange(25.0))
    assert "incomplete" in skipped[-1].reason


def test_not_a_bag_is_not_salvaged(tmp_path: Path) -> None:
    p = tmp_path / "x.bag"
    p.write_bytes(b"hello world, not a bag at all")
    with pytest.raises(InputError, match=r"cannot open ROS bag"):
        read_scans(p)
    q = tmp_path / "magic_only.bag"
    q.write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(InputError, match=r"recovered no message"):
        read_scans(q)


# ---------------------------------------------------------------- Odometry


def test_odometry_round_trip(tmp_path: Path, bags: BagFactory) -> None:
    n = 20
    t = 50.0 + 0.1 * np.arange(n)
    yaw = np.linspace(-3.0, 3.0, n)  # crosses +-pi region edges without wrapping issues
    cov = np.zeros((6, 6))
    cov[0, 0], cov[1, 1], cov[5, 5], cov[0, 5] = 0.01, 0.02, 0.003, 0.001
    order = np.r_[1, 0, 2:n]  # out-of-order stamps must come back sorted
    msgs = [
        ("/odom", bags.odometry(t[i], (i, -i, 0.5), _yaw_quat(yaw[i]), (1.5, 0.1, 0), 0.2, cov))
        for i in order
    ]
    o = read_odometry(bags.write(tmp_path / "b", msgs))
    np.testing.assert_allclose(o.times, t, atol=1e-6)
    np.testing.assert_allclose(o.poses[:, 0], np.arange(n))
    np.testing.assert_allclose(o.poses[:, 2], yaw, atol=1e-12)
    np.testing.assert_allclose(o.twists, np.tile([1.5, 0.1, 0.2], (n, 1)))
    np.testing.assert_allclose(o.z, 0.5)
    np.testing.assert_allclose(o.pose_cov[0], cov[np.ix_([0, 1, 5], [0, 1, 5])])
    assert (o.frame, o.child_frame) == ("odom", "base_link")
    tr = o.trajectory()
    assert len(tr) == n and tr.frame == "odom"


# ---------------------------------------------------------------- IMU


def test_imu_orientation_and_gravity(tmp_path: Path, bags: BagFactory) -> None:
    roll, pitch, yaw = 0.1, -0.2, 1.0
    q = _quat_rpy(roll, pitch, yaw)
    g = 9.81
    acc = (
        -g * math.sin(pitch),
        g * math.sin(roll) * math.cos(pitch),
        g * math.cos(roll) * math.cos(pitch),
    )
    msgs = [
        ("/imu", bags.imu(1.0, q, acc)),
        ("/imu", bags.imu(2.0, (0, 0, 0, 0), acc, has_orientation=False)),  # accel-only IMU
    ]
    log = read_imu(bags.write(tmp_path / "b", msgs))
    assert log.from_orientation.tolist() == [True, False]
    # message 0 from the quaternion (float64 on the wire: exact to rounding)
    assert (log.roll[0], log.pitch[0], log.yaw[0]) == pytest.approx((roll, pitch, yaw), abs=1e-12)
    # message 1 from gravity: same tilt, no yaw
    assert (log.roll[1], log.pitch[1]) == pytest.approx((roll, pitch), abs=1e-12)
    assert math.isnan(log.yaw[1])
    r, p = log.tilt_at([1.5])
    assert (r[0], p[0]) == pytest.approx((roll, pitch), abs=1e-12)


@settings(max_examples=50, deadline=None)
@given(
    st.floats(-1.4, 1.4),  # |roll| < 80 deg
    st.floats(-1.4, 1.4),  # |pitch| < 80 deg (away from gimbal lock)
    st.floats(-3.1, 3.1),
)
def test_roll_pitch_quaternion_and_gravity_agree(roll: float, pitch: float, yaw: float) -> None:
    q = _quat_rpy(roll, pitch, yaw)
    r_q, p_q = roll_pitch_from_quaternion([q])
    g = 9.81
    acc = [
        -g * math.sin(pitch),
        g * math.sin(roll) * math.cos(pitch),
        g * math.cos(roll) * math.cos(pitch),
    ]
    r_a, p_a = roll_pitch_from_acceleration([acc])
    # both are exact formulas; 1e-9 rad allows float rounding of the trigonometry
    assert r_q[0] == pytest.approx(roll, abs=1e-9) and p_q[0] == pytest.approx(pitch, abs=1e-9)
    assert r_a[0] == pytest.approx(roll, abs=1e-9) and p_a[0] == pytest.approx(pitch, abs=1e-9)


# ---------------------------------------------------------------- NavSatFix


def test_navsatfix_round_trip(tmp_path: Path, bags: BagFactory) -> None:
    msgs = [
        ("/fix", bags.navsatfix(1.0, 60.0, 25.0, 30.0, status=2, var=0.04)),
        ("/fix", bags.navsatfix(2.0, 60.0 + 100 / 111412.2, 25.0, 31.0, status=0)),
        ("/fix", bags.navsatfix(3.0, math.nan, math.nan, math.nan, status=-1)),
    ]
    g = read_navsatfix(bags.write(tmp_path / "b", msgs))
    np.testing.assert_array_equal(g.status, [2, 0, -1])
    assert g.valid.tolist() == [True, True, False]
    assert g.cov[0, 0, 0] == pytest.approx(0.04) and g.cov[0, 2, 2] == pytest.approx(0.16)
    xy = g.to_local()
    # 1 deg of latitude at 60 N spans 111412.2 m on WGS84 (meridian arc): 100 m north
    assert xy[1] == pytest.approx([0.0, 100.0], abs=0.01)
    assert g.frame == "gps"


# ---------------------------------------------------------------- PointCloud2


def _xyzi(
    n: int, big: bool, pad: int
) -> tuple[np.ndarray, bytes, list[tuple[str, int, int, int]], int]:
    e = ">" if big else "<"
    step = 16 + 2 + pad  # x y z intensity(f32) ring(u16) + padding
    dt = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "ring"],
            "formats": [e + "f4"] * 4 + [e + "u2"],
            "offsets": [0, 4, 8, 12, 16],
            "itemsize": step,
        }
    )
    rng = np.random.default_rng(3)
    a = np.zeros(n, dtype=dt)
    for c in ("x", "y", "z", "intensity"):
        a[c] = rng.uniform(-10, 10, n)
    a["ring"] = np.arange(n) % 16
    a["x"][5] = np.nan  # a missing return in an organised cloud
    fields = [("x", 0, F32, 1), ("y", 4, F32, 1), ("z", 8, F32, 1), ("intensity", 12, F32, 1)]
    fields.append(("ring", 16, U16, 1))
    return a, a.tobytes(), fields, step


@pytest.mark.parametrize("big", [False, True])
def test_pointcloud2_round_trip(tmp_path: Path, bags: BagFactory, big: bool) -> None:
    a, data, fields, step = _xyzi(64, big, pad=6)
    msgs = [("/points", bags.pointcloud2(5.0, data, fields, step, 64, is_bigendian=big))]
    (cloud,) = list(read_pointclouds(bags.write(tmp_path / "b", msgs)))
    keep = np.isfinite(a["x"])
    assert len(cloud) == 63 and cloud.frame == "velodyne" and cloud.time == 5.0
    np.testing.assert_array_equal(cloud.xyz[:, 1], a["y"][keep].astype(np.float64))
    np.testing.assert_array_equal(cloud.fields["ring"], a["ring"][keep])
    assert cloud.fields["ring"].dtype.isnative


def test_pointcloud2_row_padding_and_multi_count_fields() -> None:
    # 2 rows x 3 points, point_step 32 (x,y,z f64 + 2-element u8 'rgb' at 24), row_step 100
    width, height, step, row_step = 3, 2, 32, 100
    buf = np.zeros(row_step * height, dtype=np.uint8)
    expect = []
    for r in range(height):
        for c in range(width):
            off = r * row_step + c * step
            xyz = np.array([r, c, r * 10 + c], dtype="<f8")
            buf[off : off + 24] = np.frombuffer(xyz.tobytes(), np.uint8)
            buf[off + 24 : off + 26] = [r, c]
            expect.append(xyz)
    fields = [PointField("x", 0, F64), PointField("y", 8, F64), PointField("z", 16, F64)]
    fields.append(PointField("rgb", 24, U8, 2))
    fields.append(PointField("", 26, U8, 1))  # unnamed padding field: ignored
    cloud = decode_pointcloud2(
        buf[: row_step + width * step],  # last row without its trailing padding
        fields,
        point_step=step,
        width=width,
        height=height,
        row_step=row_step,
    )
    np.testing.assert_array_equal(cloud.xyz, np.array(expect))
    assert cloud.fields["rgb"].shape == (6, 2) and cloud.fields["rgb"][4].tolist() == [1, 1]


def test_pointcloud2_bad_layouts() -> None:
    xyz = [("x", 0, F32, 1), ("y", 4, F32, 1), ("z", 8, F32, 1)]
    data = bytes(12 * 4)
    with pytest.raises(InputError, match="no z field"):
        decode_pointcloud2(data, xyz[:2], point_step=12, width=4)
    with pytest.raises(InputError, match="unknown datatype 9"):
        decode_pointcloud2(data, [*xyz, ("i", 0, 9, 1)], point_step=12, width=4)
    with pytest.raises(InputError, match="does not fit in point_step 12"):
        decode_pointcloud2(data, [*xyz, ("i", 10, F32, 1)], point_step=12, width=4)
    with pytest.raises(InputError, match="needs 60"):
        decode_pointcloud2(data, xyz, point_step=12, width=5)
    with pytest.raises(InputError, match="appears twice"):
        decode_pointcloud2(data, [*xyz, ("x", 0, F32, 1)], point_step=12, width=4)
    with pytest.raises(InputError, match="row_step 10"):
        decode_pointcloud2(data, xyz, point_step=12, width=4, row_step=10)
    empty = decode_pointcloud2(b"", xyz, point_step=12, width=0)
    assert len(empty) == 0


def test_pointcloud2_keep_nans_and_int_coordinates() -> None:
    a = np.array([(1, 2, 3), (4, 5, 6)], dtype=[("x", "<i4"), ("y", "<i4"), ("z", "<i4")])
    c = decode_pointcloud2(
        a.tobytes(), [("x", 0, I32, 1), ("y", 4, I32, 1), ("z", 8, I32, 1)], point_step=12, width=2
    )
    np.testing.assert_array_equal(c.xyz, [[1, 2, 3], [4, 5, 6]])
    f = np.array([(np.nan, 0, 0)], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    fl = [("x", 0, F32, 1), ("y", 4, F32, 1), ("z", 8, F32, 1)]
    assert len(decode_pointcloud2(f.tobytes(), fl, point_step=12, width=1, skip_nans=False)) == 1


_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


@settings(max_examples=60, deadline=None)
@given(
    order=st.permutations(["x", "y", "z", "t"]),
    coord_type=st.sampled_from([7, 8, 5, 3]),
    extra_type=st.integers(1, 8),
    gaps=st.lists(st.integers(0, 5), min_size=5, max_size=5),
    big=st.booleans(),
    width=st.integers(0, 7),
    height=st.integers(1, 3),
    row_pad=st.integers(0, 9),
    seed=st.integers(0, 2**31 - 1),
)
def test_pointcloud2_any_layout(
    order: list[str],
    coord_type: int,
    extra_type: int,
    gaps: list[int],
    big: bool,
    width: int,
    height: int,
    row_pad: int,
    seed: int,
) -> None:
    """Random field order, types, gaps between fields, trailing padding, row padding and byte
    order: the decoded values equal the ones packed (exactly: no arithmetic is involved)."""
    e = ">" if big else "<"
    offsets, fields, off = {}, [], 0
    for k, name in enumerate(order):
        off += gaps[k]
        dt = coord_type if name != "t" else extra_type
        offsets[name] = off
        fields.append((name, off, dt, 1))
        off += np.dtype(_TYPES[dt]).itemsize
    step = off + gaps[4]
    dtype = np.dtype(
        {
            "names": list(order),
            "formats": [e + _TYPES[f[2]] for f in fields],
            "offsets": [offsets[n] for n in order],
            "itemsize": step,
        }
    )
    rng = np.random.default_rng(seed)
    n = width * height
    pts = np.zeros(n, dtype=dtype)
    for name, _, dt, _ in fields:
        info = np.iinfo(_TYPES[dt]) if _TYPES[dt][0] in "iu" else None
        lo, hi = (max(info.min, -100), min(info.max, 100)) if info else (-100, 100)
        pts[name] = rng.integers(lo, hi + 1, n) if info else rng.uniform(lo, hi, n)
    row_step = width * step + row_pad
    buf = np.zeros(row_step * height, dtype=np.uint8)
    raw = np.frombuffer(pts.tobytes(), np.uint8).reshape(height, width * step)
    buf.reshape(height, row_step)[:, : width * step] = raw
    c = decode_pointcloud2(
        buf.tobytes(),
        fields,
        point_step=step,
        width=width,
        height=height,
        row_step=row_step,
        is_bigendian=big,
    )
    assert len(c) == n
    for j, name in enumerate("xyz"):
        np.testing.assert_array_equal(c.xyz[:, j], pts[name].astype(np.float64))
    np.testing.assert_array_equal(c.fields["t"], pts["t"])
    assert c.fields["t"].dtype == np.dtype(_TYPES[extra_type])  # native order, same kind


def test_docstring_examples_run() -> None:
    import doctest

    import stemmap.io.rosbag as rosbag_mod

    res = doctest.testmod(rosbag_mod)
    assert res.failed == 0 and res.attempted > 0


@pytest.mark.parametrize("mode", ["FILE", "MESSAGE"])
def test_ros2_zstd_compressed_bag(tmp_path: Path, mode: str) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    f = BagFactory(2)
    w = Writer(tmp_path / "z", version=9)
    w.set_compression(CompressionMode[mode], CompressionFormat.ZSTD)
    with w:
        c = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=f.ts)
        for i in range(3):
            w.write(c, 10**9 * (i + 1), f.serialize(f.laserscan(1.0 + i, np.full(5, 2.0 + i))))
    b = read_scans(tmp_path / "z")
    np.testing.assert_array_equal(b.ranges[:, 0], [2.0, 3.0, 4.0])


def test_gnss_to_local_needs_a_fix(tmp_path: Path) -> None:
    f = BagFactory(2)
    msgs = [("/fix", f.navsatfix(1.0, math.nan, math.nan, math.nan, status=-1))]
    g = read_navsatfix(f.write(tmp_path / "b", msgs))
    with pytest.raises(InputError, match="no valid fix"):
        g.to_local()
    assert g.to_local((25.0, 60.0)).shape == (1, 2)  # explicit origin: NaN rows kept


@pytest.mark.parametrize(("ros", "storage"), [(1, "sqlite3"), (2, "sqlite3"), (2, "mcap")])
def test_write_scans_bag_round_trip(tmp_path: Path, ros: int, storage: str) -> None:
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.types import ScanBatch

    rng = np.random.default_rng(5)
    r = rng.uniform(0.5, 20, (6, 50)).astype(np.float32).astype(np.float64)
    r[0, :3] = np.nan
    b = ScanBatch(r, 1.7e9 + 0.1 * np.arange(6), -1.2, 0.05, 0.1, 30.0, frame="lms")
    p = write_scans_bag(tmp_path / "out", b, ros=ros, storage=storage)
    assert p.name == ("out.bag" if ros == 1 else "out")
    back = read_scans(p)
    np.testing.assert_array_equal(back.ranges, b.ranges)  # float32-representable: exact
    np.testing.assert_allclose(back.times, b.times, atol=1e-6)  # ns stamps, float64 at 1.7e9 s
    assert back.frame == "lms" and back.n_beams == 50
    # overwriting an existing bag replaces it whole and leaves no temp folder behind
    write_scans_bag(p, ScanBatch(r[:2], b.times[:2], -1.2, 0.05), ros=ros, storage=storage)
    assert len(read_scans(p)) == 2
    assert sorted(q.name for q in tmp_path.iterdir()) == [p.name]


def test_write_scans_bag_bad_config(tmp_path: Path) -> None:
    from stemmap.errors import ConfigError
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.types import ScanBatch

    b = ScanBatch(np.ones((1, 2)), [0.0], 0.0, 0.1)
    with pytest.raises(ConfigError, match="ros must be 1 or 2"):
        write_scans_bag(tmp_path / "x", b, ros=3)
    with pytest.raises(ConfigError, match="storage"):
        write_scans_bag(tmp_path / "x", b, ros=2, storage="csv")
