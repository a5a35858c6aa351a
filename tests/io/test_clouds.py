"""Point-cloud readers, tested on files written by other tools (laspy, plyfile, pypcd4, numpy)
and on hand-written spec-exact headers; bad and truncated files must raise InputError."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.io.clouds import (
    count_points,
    iter_cloud_chunks,
    iter_las_chunks,
    read_cloud,
)


@pytest.fixture
def pts(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(-20, 20, size=(500, 3))


def _write_las(path: Path, xyz: np.ndarray, version: str = "1.2") -> None:
    header = laspy.LasHeader(point_format=1 if version == "1.2" else 6, version=version)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = xyz.min(axis=0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = np.arange(len(xyz), dtype=np.uint16)
    las.write(path)


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_las_round_trip_and_chunks(tmp_path: Path, pts: np.ndarray, ext: str) -> None:
    f = tmp_path / f"c{ext}"
    _write_las(f, pts)
    cloud = read_cloud(f)
    # LAS stores integers at scale 1 mm: the round trip is exact to half a unit.
    np.testing.assert_allclose(cloud.xyz, pts, atol=0.0005 + 1e-9)
    np.testing.assert_array_equal(cloud.fields["intensity"], np.arange(len(pts)))
    chunks = list(iter_las_chunks(f, chunk_size=128))
    assert [len(c) for c in chunks] == [128, 128, 128, 116]
    np.testing.assert_allclose(np.concatenate([c.xyz for c in chunks]), cloud.xyz)
    assert count_points(f) == len(pts)
    assert sum(len(c) for c in iter_cloud_chunks(f, chunk_size=200)) == len(pts)


def test_truncated_las_names_file(tmp_path: Path, pts: np.ndarray) -> None:
    f = tmp_path / "t.las"
    _write_las(f, pts)
    data = f.read_bytes()
    f.write_bytes(data[: len(data) - 28 * 100])  # drop the last ~100 point records
    with pytest.raises(InputError, match=r"t\.las"):
        read_cloud(f)


def test_garbage_las(tmp_path: Path) -> None:
    f = tmp_path / "g.laz"
    f.write_bytes(b"not a las file at all" * 10)
    with pytest.raises(InputError, match=r"g\.laz"):
        read_cloud(f)


@pytest.mark.parametrize("text", [True, False])
@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ply_written_by_plyfile(
    tmp_path: Path, pts: np.ndarray, text: bool, byte_order: str
) -> None:
    plyfile = pytest.importorskip("plyfile")
    v = np.empty(len(pts), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    v["intensity"] = np.linspace(0, 1, len(pts))
    f = tmp_path / "c.ply"
    el = plyfile.PlyElement.describe(v, "vertex")
    plyfile.PlyData([el], text=text, byte_order=byte_order).write(str(f))
    cloud = read_cloud(f)
    # ascii PLY prints floats with repr precision; binary is exact.
    np.testing.assert_allclose(cloud.xyz, pts, rtol=1e-12, atol=1e-12)
    assert "intensity" in cloud.fields


def test_ply_handwritten_ascii(tmp_path: Path) -> None:
    f = tmp_path / "h.ply"
    f.write_text(
        "ply\nformat ascii 1.0\ncomment by hand\nelement vertex 2\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n1 2 3\n4 5 6\n"
    )
    np.testing.assert_array_equal(read_cloud(f).xyz, [[1, 2, 3], [4, 5, 6]])


def test_ply_without_z_and_truncated(tmp_path: Path) -> None:
    f = tmp_path / "noz.ply"
    f.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        "end_header\n1 2\n"
    )
    with pytest.raises(InputError, match=r"noz\.ply.*z"):
        read_cloud(f)
    g = tmp_path / "trunc.ply"
    g.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + np.zeros(7, "<f4").tobytes()
    )
    with pytest.raises(InputError, match=r"trunc\.ply"):
        read_cloud(g)


@pytest.mark.parametrize("encoding", ["ASCII", "BINARY", "BINARY_COMPRESSED"])
def test_pcd_written_by_pypcd4(tmp_path: Path, pts: np.ndarray, encoding: str) -> None:
    pypcd4 = pytest.importorskip("pypcd4")
    f = tmp_path / "c.pcd"
    pypcd4.PointCloud.from_xyz_points(pts.astype(np.float32)).save(
        str(f), encoding=getattr(pypcd4.Encoding, encoding)
    )
    np.testing.assert_allclose(read_cloud(f).xyz, pts.astype(np.float32), atol=1e-5)


def test_pcd_handwritten_binary_spec(tmp_path: Path, pts: np.ndarray) -> None:
    """A PCD v0.7 binary file written byte by byte from the PCL spec (x y z intensity)."""
    pytest.importorskip("pypcd4")
    n = len(pts)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\n"
        "SIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4")])
    rec["x"], rec["y"], rec["z"] = pts.T
    rec["i"] = 7.0
    f = tmp_path / "spec.pcd"
    f.write_bytes(header.encode() + rec.tobytes())
    cloud = read_cloud(f)
    np.testing.assert_allclose(cloud.xyz, pts.astype(np.float32), atol=1e-5)
    np.testing.assert_array_equal(cloud.fields["intensity"], 7.0)
    # truncated: half the records missing
    g = tmp_path / "short.pcd"
    g.write_bytes(header.encode() + rec.tobytes()[: 8 * n])
    with pytest.raises(InputError, match=r"short\.pcd"):
        read_cloud(g)


@pytest.mark.parametrize(("delim", "header"), [(" ", ""), (",", "x,y,z,i\n"), (";", "")])
def test_xyz_text(tmp_path: Path, pts: np.ndarray, delim: str, header: str) -> None:
    f = tmp_path / "c.xyz"
    body = "\n".join(delim.join(f"{v:.6f}" for v in (*row, 1.0)) for row in pts)
    f.write_text(header + body + "\n")
    cloud = read_cloud(f)
    np.testing.assert_allclose(cloud.xyz, pts, atol=1e-6)  # printed with 6 decimals
    np.testing.assert_array_equal(cloud.fields["col3"], 1.0)


def test_xyz_bad_inputs(tmp_path: Path) -> None:
    f = tmp_path / "two.xyz"
    f.write_text("1 2\n3 4\n")
    with pytest.raises(InputError, match="at least x y z"):
        read_cloud(f)
    g = tmp_path / "ragged.txt"
    g.write_text("1 2 3\n4 5\n")
    with pytest.raises(InputError, match=r"ragged\.txt"):
        read_cloud(g)
    e = tmp_path / "empty.xyz"
    e.write_text("")
    with pytest.raises(InputError, match="empty"):
        read_cloud(e)
    h = tmp_path / "header_only.xyz"  # numpy's UserWarning used to precede the error
    h.write_text("x y z\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="holds no points"):
            read_cloud(h)


def test_missing_and_unknown(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        read_cloud(tmp_path / "nope.las")
    u = tmp_path / "c.obj"
    u.write_text("v 1 2 3\n")
    with pytest.raises(InputError, match="unknown point-cloud extension"):
        read_cloud(u)


@pytest.mark.slow
def test_real_laz_files(datasets_dir: Path) -> None:
    cloud = read_cloud(datasets_dir / "fortls_slice" / "diameters.laz")
    assert len(cloud) == 200_020  # the dataset README's count
    z = cloud.xyz[:, 2]
    assert z.min() >= 1.2 - 1e-3 and z.max() <= 1.4 + 1e-3
    dbh = read_cloud(datasets_dir / "lidr_dbh" / "dbh.laz")
    assert len(dbh) == 1369


def test_bag_of_pointcloud2(tmp_path: Path, bags: Any) -> None:
    """ROS1 / ROS2 bags (written with rosbags' own writers) through read_cloud."""
    rng = np.random.default_rng(3)
    msgs = []
    parts = []
    for k in range(2):
        a = rng.uniform(-5, 5, (50, 3)).astype("<f4")
        parts.append(a)
        fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]  # 7 = FLOAT32
        msgs.append(("/points", bags.pointcloud2(1.0 + k, a.tobytes(), fields, 12, 50)))
    path = bags.write(tmp_path / "b", msgs)
    cloud = read_cloud(path, topic="/points")
    np.testing.assert_array_equal(cloud.xyz, np.vstack(parts).astype(np.float64))
    with pytest.raises(InputError):
        read_cloud(tmp_path / "missing.bag")


def _patch_las_header(f: Path, offset: int, fmt: str, value: Any) -> None:
    import struct

    data = bytearray(f.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    f.write_bytes(bytes(data))


def test_las_point_count_half_the_file_is_an_error(tmp_path: Path, pts: np.ndarray) -> None:
    """A header announcing half the records would silently read half the cloud (issue 13)."""
    f = tmp_path / "half.las"
    _write_las(f, pts)
    # LAS 1.2 header: legacy point count (uint32) at byte 107
    _patch_las_header(f, 107, "<I", len(pts) // 2)
    with pytest.raises(InputError, match=r"half\.las.*announces 250 points.*holds 500"):
        read_cloud(f)
    with pytest.raises(InputError, match="announces"):
        list(iter_cloud_chunks(f, chunk_size=100))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_las_zero_scale_is_an_error(tmp_path: Path, pts: np.ndarray, axis: int) -> None:
    f = tmp_path / "zero.las"
    _write_las(f, pts)
    # x, y, z scale factors (float64) at bytes 131, 139, 147
    _patch_las_header(f, 131 + 8 * axis, "<d", 0.0)
    with pytest.raises(InputError, match=r"zero\.las.*scale factors.*finite non-zero"):
        read_cloud(f)


def test_a_cloud_of_only_nan_points_is_an_error_not_an_empty_plot(tmp_path):
    # the user audit (docs/cli.md): `stemmap stems nan.xyz` wrote an empty stems CSV and
    # exited 0 ("the cloud is empty"), hiding a broken export
    p = tmp_path / "nan.xyz"
    np.savetxt(p, np.full((50, 3), np.nan))
    with pytest.raises(InputError, match="no point with finite coordinates"):
        list(iter_cloud_chunks(p))
    assert read_cloud(p).xyz.shape == (0, 3)  # a frame reader still gets an empty frame
    xyz = np.full((50, 3), np.nan)
    xyz[:10] = np.arange(30.0).reshape(10, 3)
    np.savetxt(p, xyz)
    assert next(iter_cloud_chunks(p)).xyz.shape == (10, 3)  # NaN rows dropped, as before


def test_stems_cli_refuses_a_cloud_of_nan(tmp_path):
    from typer.testing import CliRunner

    from stemmap.cli import app

    p = tmp_path / "nan.xyz"
    np.savetxt(p, np.full((50, 3), np.nan))
    out = tmp_path / "s.csv"
    res = CliRunner().invoke(app, ["stems", str(p), "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "no point with finite coordinates" in res.output and not out.exists()


def test_text_clouds_announcing_more_points_than_they_hold_are_truncated(tmp_path):
    # the user audit (docs/cli.md): an ascii PLY announcing 4e9 vertices was "out of memory"
    # (np.loadtxt allocated them first) and an ascii PCD announcing more points than it holds
    # was read short without a word
    ply = tmp_path / "huge.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4000000000\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n1 2 3\n"
    )
    with pytest.raises(InputError, match="truncated"):
        read_cloud(ply)
    head = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        "WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n"
    )
    for n in (4_000_000_000, 10):
        pcd = tmp_path / f"short{n}.pcd"
        pcd.write_text(head.format(n=n) + "1.000 2.000 3.000\n" * 5)
        with pytest.raises(InputError, match="truncated"):
            read_cloud(pcd)
    pcd.write_text(head.format(n=5) + "1.000 2.000 3.000\n" * 5)
    assert read_cloud(pcd).xyz.shape == (5, 3)
