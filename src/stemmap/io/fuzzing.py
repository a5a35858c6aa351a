"""Fuzzing the file readers: valid seed files, mutations, and the "clean error or data" oracle.

Used by ``tests/io/test_fuzz_readers.py`` (hypothesis, bounded time in CI) and by
``benchmarks/fuzz.py`` (a long random campaign). Every reader of a user file must either
return data or raise a :class:`~stemmap.errors.StemmapError` (InputError/ConfigError, which
the CLI prints as one ``error:`` line); any other exception (IndexError, struct.error,
MemoryError, ...) is a bug that would reach the user as a traceback.

Mutations (each a tuple ``(kind, position in [0, 1), value)`` so hypothesis can shrink them):
bit flip, byte set, truncation, deletion of a span, duplication of a span (splice), insertion
of bytes, an integer header field overwritten with an extreme value (0, -1, 2^31-1, 2^32-1,
2^63-1 in 1, 2, 4 or 8 bytes), a float field set to NaN/inf/0/-1e300, and for text files a
numeric token replaced with ``nan``, ``inf``, ``-1``, ``1e308``, an empty string or garbage.
"""

from __future__ import annotations

import json
import re
import struct
import tempfile
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import StemmapError

__all__ = ["MUTATION_KINDS", "TARGETS", "FuzzTarget", "check_input", "mutate", "write_seeds"]

#: Mutation kinds, in the order of the first tuple element.
MUTATION_KINDS = (
    "bitflip",
    "setbyte",
    "truncate",
    "delete",
    "splice",
    "insert",
    "intfield",
    "floatfield",
    "token",
)

_INTS = (0, -1, 1, 2**31 - 1, 2**32 - 1, 2**63 - 1, -(2**31), 255, 65535)
_FLOATS = (float("nan"), float("inf"), float("-inf"), 0.0, -1e300, 1e300, 5e-324)
_TOKENS = (b"nan", b"inf", b"-inf", b"-1", b"1e308", b"", b"0", b"x", b"1,2", b"-0", b"99999999")
_NUM = re.compile(rb"-?\d+(\.\d+)?([eE][-+]?\d+)?")

Mutation = tuple[int, float, int]


def mutate(data: bytes, ops: Sequence[Mutation]) -> bytes:
    """Apply mutations ``(kind, position in [0, 1), value)`` to ``data`` in order."""
    b = bytearray(data)
    for kind, pos, val in ops:
        n = len(b)
        i = min(int(pos * n), max(n - 1, 0))
        k = MUTATION_KINDS[kind % len(MUTATION_KINDS)]
        if n == 0 and k not in ("insert",):
            continue
        if k == "bitflip":
            b[i] ^= 1 << (val % 8)
        elif k == "setbyte":
            b[i] = val % 256
        elif k == "truncate":
            del b[i:]
        elif k == "delete":
            del b[i : i + 1 + val % 64]
        elif k == "splice":
            j = (i + 1 + val * 7919) % max(n, 1)
            b[j:j] = b[i : i + 1 + val % 256]
        elif k == "insert":
            b[i:i] = bytes([(val * 31 + t) % 256 for t in range(1 + val % 16)])
        elif k == "intfield":
            width = (1, 2, 4, 8)[val % 4]
            v = _INTS[(val // 4) % len(_INTS)]
            raw = (v % (1 << (8 * width))).to_bytes(width, "little")
            b[i : i + width] = raw
        elif k == "floatfield":
            fv = _FLOATS[(val // 2) % len(_FLOATS)]
            with np.errstate(over="ignore"):  # 1e300 -> float32 inf is intended
                raw = struct.pack("<d", fv) if val % 2 else np.float32(fv).tobytes()
            b[i : i + len(raw)] = raw
        else:  # token: replace the numeric token nearest to the position
            m = _NUM.search(bytes(b), i) or _NUM.search(bytes(b))
            if m:
                b[m.start() : m.end()] = _TOKENS[val % len(_TOKENS)]
    return bytes(b)


# ------------------------------------------------------------------------------ seed files


def _scans() -> Any:
    from stemmap.types import ScanBatch

    a = np.radians(np.arange(-30.0, 30.01, 2.0))
    r = 4.0 + 0.2 * np.sin(np.arange(3)[:, None] + a[None, :])
    r[1, 5] = np.inf
    return ScanBatch(r, np.array([0.0, 0.1, 0.2]), float(a[0]), float(a[1] - a[0]), 0.05, 30.0)


def _seed_npz(p: Path) -> None:
    from stemmap.io.scans import write_scans_npz

    write_scans_npz(p, _scans(), compress=False)


def _seed_npz_compressed(p: Path) -> None:
    from stemmap.io.scans import write_scans_npz

    write_scans_npz(p, _scans(), compress=True)


def _seed_scans_csv(p: Path) -> None:
    from stemmap.io.scans import write_scans_csv

    write_scans_csv(p, _scans())


def _seed_obs(p: Path) -> None:
    from stemmap.io.maps import write_observations_csv
    from stemmap.scan.detect import ScanTrunkDetector

    write_observations_csv(p, ScanTrunkDetector().detect_batch(_sim_scans()))


def _sim_scans() -> Any:
    from stemmap.sim.forest import Stand
    from stemmap.sim.scanner import cast_rays
    from stemmap.types import ScanBatch

    a = np.radians(np.arange(-90.0, 90.01, 1.0))
    stand = Stand(np.array([[3.0, 0.0], [2.0, 2.0]]), np.array([0.3, 0.2]))
    r, _ = cast_rays(np.zeros(2), a, stand, 30.0)
    return ScanBatch(np.tile(r, (2, 1)), np.array([0.0, 0.1]), float(a[0]), float(a[1] - a[0]))


def _stem_map() -> Any:
    from stemmap.types import StemMap, Tree

    return StemMap(
        (
            Tree(1, 2.0, 3.0, 0.31, cov=np.diag([0.01, 0.02]), n_obs=4),
            Tree(2, -1.5, 7.25, 0.22, cov=np.diag([0.03, 0.01]), n_obs=2),
        )
    )


def _seed_trees_csv(p: Path) -> None:
    from stemmap.io.maps import write_trees_csv

    write_trees_csv(p, _stem_map())


def _seed_trees_geojson(p: Path) -> None:
    from stemmap.io.maps import write_trees_geojson

    write_trees_geojson(p, _stem_map())


def _traj() -> Any:
    from stemmap.types import Trajectory

    t = np.arange(5, dtype=np.float64) * 0.5
    poses = np.column_stack((t, 0.5 * t, 0.1 * t)).astype(np.float64)
    return Trajectory(t, poses)


def _seed_traj_csv(p: Path) -> None:
    from stemmap.io.trajectory import write_trajectory_csv

    write_trajectory_csv(p, _traj())


def _seed_traj_tum(p: Path) -> None:
    from stemmap.io.trajectory import write_trajectory_tum

    write_trajectory_tum(p, _traj())


def _xyz() -> np.ndarray:
    g = np.random.default_rng(7)
    return g.uniform(-5, 5, (40, 3))


def _seed_las(p: Path) -> None:
    import laspy

    xyz = _xyz()
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = xyz.min(axis=0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(p)


def _seed_ply_ascii(p: Path) -> None:
    xyz = _xyz()
    head = (
        "ply\nformat ascii 1.0\ncomment fuzz seed\n"
        f"element vertex {len(xyz)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar intensity\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )
    rows = "".join(f"{x:.4f} {y:.4f} {z:.4f} {k % 200}\n" for k, (x, y, z) in enumerate(xyz))
    p.write_text(head + rows + "3 0 1 2\n")


def _seed_ply_binary(p: Path) -> None:
    xyz = _xyz()
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(xyz)}\nproperty double x\nproperty double y\nproperty double z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    face = struct.pack("<B3i", 3, 0, 1, 2)
    p.write_bytes(head + xyz.astype("<f8").tobytes() + face)


def _pcd_header(n: int, data: str) -> str:
    return (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
        "SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    )


def _seed_pcd_ascii(p: Path) -> None:
    xyz = _xyz()
    rows = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in xyz)
    p.write_text(_pcd_header(len(xyz), "ascii") + rows)


def _seed_pcd_binary(p: Path) -> None:
    xyz = _xyz()
    p.write_bytes(_pcd_header(len(xyz), "binary").encode() + xyz.astype("<f4").tobytes())


def _seed_xyz(p: Path) -> None:
    xyz = _xyz()
    p.write_text("x y z\n" + "".join(f"{x:.3f} {y:.3f} {z:.3f}\n" for x, y, z in xyz))


def _seed_bag(p: Path) -> None:
    from stemmap.io.rosbag import write_scans_bag

    write_scans_bag(p, _scans(), ros=1)


def _seed_bag_compressed(p: Path, compression: str) -> None:
    """The scans of :func:`_seed_bag` in a ROS 1 bag whose chunks are bz2 / lz4 compressed
    (a chunk every ~0.5 kB, so a mutation hits a chunk header, its data or the index)."""
    from stemmap.io.rosbag import write_scans_bag

    write_scans_bag(p, _scans(), ros=1, compression=compression, chunk_bytes=512)


def _seed_ros2(p: Path, storage: str) -> None:
    import shutil

    from stemmap.io.rosbag import write_scans_bag

    folder = p.with_name(p.stem + "_bag")
    write_scans_bag(folder, _scans(), ros=2, storage=storage)
    inner = next(f for f in folder.iterdir() if f.suffix == p.suffix)
    shutil.copyfile(inner, p)
    shutil.rmtree(folder)


def _ros2_zstd_folder(folder: Path, mode: str, storage: str = "sqlite3") -> Path:
    """The scans of :func:`_seed_bag` in a ROS2 bag compressed with zstd per ``mode``; returns
    the file a fuzz input replaces (the storage file, ``.zstd`` in file mode)."""
    from stemmap.io.rosbag import write_scans_bag

    write_scans_bag(
        folder, _scans(), ros=2, storage=storage, compression="zstd", compression_mode=mode
    )
    return next(f for f in folder.iterdir() if f.name != "metadata.yaml")


def _seed_ros2_zstd(p: Path, mode: str) -> None:
    """The storage file of a zstd-compressed ROS2 bag (per message: the sqlite3 file; per
    file: the zstd file; per MCAP chunk: the .mcap file, read alone)."""
    import shutil

    folder = p.with_name(p.stem + "_bag")
    storage = "mcap" if mode == "storage" else "sqlite3"
    shutil.copyfile(_ros2_zstd_folder(folder, mode, storage), p)
    shutil.rmtree(folder)


def _read_ros2_zstd(p: Path, mode: str) -> Any:
    """A zstd-compressed ROS2 bag whose storage file is ``p``: the seed's bag folder (its
    metadata.yaml names the compression) with ``p`` in place of its storage file."""
    import shutil

    folder = p.with_name(p.stem + "_bag")
    shutil.copyfile(p, _ros2_zstd_folder(folder, mode))
    return _read_scans(folder)


def _seed_png(p: Path) -> None:
    import cv2

    img = np.zeros((24, 32, 3), np.uint8)
    img[:, 10:16] = (40, 70, 90)  # a dark vertical "trunk" on a bright background
    img[:, :10] = img[:, 16:] = (180, 200, 170)
    ok, buf = cv2.imencode(p.suffix, img)
    assert ok
    p.write_bytes(buf.tobytes())


def _seed_calibration(p: Path) -> None:
    doc = {
        "G": [[500.0, -1.0, 640.0], [2.0, 480.0, 360.0], [0.001, 0.0, 1.0]],
        "method": "dlt_refined",
        "rms_px": 0.5,
        "camera": {"K": [[800, 0, 640], [0, 800, 360], [0, 0, 1]], "width": 1280, "height": 720},
        "laser_to_camera": {"R": np.eye(3).tolist(), "t": [0.1, 0.0, 0.2]},
    }
    p.write_text(json.dumps(doc, indent=1))


def _seed_pairs(p: Path) -> None:
    p.write_text(
        "# pairs\nx,y,u,v\n" + "".join(f"{k},{k % 3},{10 * k},{5 + k}\n" for k in range(8))
    )


# ------------------------------------------------------------------------------ readers


def _read_scans(p: Path) -> Any:
    from stemmap.io.scans import read_scans

    return read_scans(p, skipped=[])


def _read_obs(p: Path) -> Any:
    from stemmap.io.maps import read_observations_csv

    return read_observations_csv(p)


def _read_trees_csv(p: Path) -> Any:
    from stemmap.io.maps import read_trees_csv

    return read_trees_csv(p)


def _read_trees_geojson(p: Path) -> Any:
    from stemmap.io.maps import read_trees_geojson

    return read_trees_geojson(p)


def _read_traj_csv(p: Path) -> Any:
    from stemmap.io.trajectory import read_trajectory_csv

    return read_trajectory_csv(p)


def _read_traj_tum(p: Path) -> Any:
    from stemmap.io.trajectory import read_trajectory_tum

    return read_trajectory_tum(p)


def _read_cloud(p: Path) -> Any:
    from stemmap.io.clouds import count_points, iter_cloud_chunks, read_cloud

    count_points(p)
    for _ in iter_cloud_chunks(p, chunk_size=16):
        pass
    return read_cloud(p)


def _read_calibration(p: Path) -> Any:
    from stemmap.cli._vision import read_calibration

    return read_calibration(p)


def _read_pairs(p: Path) -> Any:
    from stemmap.cli._vision import _read_table

    return _read_table(p, ["x", "y", "u", "v"], ["z"])


def _read_image_cli(p: Path) -> Any:
    """The image path of the CLI (``stemmap segment``): exit 0 or a clean exit 2."""
    from typer.testing import CliRunner

    from stemmap.cli import app

    out = p.with_name(p.stem + "_mask.png")
    res = CliRunner().invoke(app, ["segment", str(p), "--out", str(out)])
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    if res.exit_code not in (0, 2):
        raise RuntimeError(f"segment exited {res.exit_code}: {res.output[-300:]}")
    if "Traceback" in res.output:
        raise RuntimeError(f"segment printed a traceback: {res.output[-300:]}")
    return res.exit_code


_FRAME_SIZE = (32, 24)  # (width, height) of the camera frame seeds


def _seed_frame(p: Path) -> None:
    """A camera frame (TIFF or PPM by suffix) of the size :func:`_read_frame` expects."""
    import cv2

    w, h = _FRAME_SIZE
    img = np.random.default_rng(0).integers(0, 255, (h, w, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(p.suffix, img)
    assert ok
    p.write_bytes(buf.tobytes())


def _read_frame(p: Path) -> Any:
    """A camera frames folder's decode path (header checked against camera.json's size)."""
    from stemmap.io.camera_frames import _read_image

    return _read_image(p, _FRAME_SIZE)


@dataclass(frozen=True)
class FuzzTarget:
    """A reader under test, its file suffix and a writer of one valid seed file."""

    name: str
    suffix: str
    seed: Callable[[Path], None]
    read: Callable[[Path], Any]


TARGETS: dict[str, FuzzTarget] = {
    t.name: t
    for t in (
        FuzzTarget("scans_npz", ".npz", _seed_npz, _read_scans),
        FuzzTarget("scans_npz_compressed", ".npz", _seed_npz_compressed, _read_scans),
        FuzzTarget("scans_csv", ".csv", _seed_scans_csv, _read_scans),
        FuzzTarget("observations_csv", ".csv", _seed_obs, _read_obs),
        FuzzTarget("trees_csv", ".csv", _seed_trees_csv, _read_trees_csv),
        FuzzTarget("trees_geojson", ".geojson", _seed_trees_geojson, _read_trees_geojson),
        FuzzTarget("trajectory_csv", ".csv", _seed_traj_csv, _read_traj_csv),
        FuzzTarget("trajectory_tum", ".txt", _seed_traj_tum, _read_traj_tum),
        FuzzTarget("las", ".las", _seed_las, _read_cloud),
        FuzzTarget("ply_ascii", ".ply", _seed_ply_ascii, _read_cloud),
        FuzzTarget("ply_binary", ".ply", _seed_ply_binary, _read_cloud),
        FuzzTarget("pcd_ascii", ".pcd", _seed_pcd_ascii, _read_cloud),
        FuzzTarget("pcd_binary", ".pcd", _seed_pcd_binary, _read_cloud),
        FuzzTarget("xyz", ".xyz", _seed_xyz, _read_cloud),
        FuzzTarget("ros1_bag", ".bag", _seed_bag, _read_scans),
        FuzzTarget("ros1_bag_bz2", ".bag", lambda p: _seed_bag_compressed(p, "bz2"), _read_scans),
        FuzzTarget("ros1_bag_lz4", ".bag", lambda p: _seed_bag_compressed(p, "lz4"), _read_scans),
        FuzzTarget("ros2_db3", ".db3", lambda p: _seed_ros2(p, "sqlite3"), _read_scans),
        FuzzTarget("ros2_mcap", ".mcap", lambda p: _seed_ros2(p, "mcap"), _read_scans),
        FuzzTarget("ros2_mcap_zstd", ".mcap", lambda p: _seed_ros2_zstd(p, "storage"), _read_scans),
        FuzzTarget(
            "ros2_zstd_message",
            ".db3",
            lambda p: _seed_ros2_zstd(p, "message"),
            lambda p: _read_ros2_zstd(p, "message"),
        ),
        FuzzTarget(
            "ros2_zstd_file",
            ".zstd",
            lambda p: _seed_ros2_zstd(p, "file"),
            lambda p: _read_ros2_zstd(p, "file"),
        ),
        FuzzTarget("calibration_json", ".json", _seed_calibration, _read_calibration),
        FuzzTarget("pairs_csv", ".csv", _seed_pairs, _read_pairs),
        FuzzTarget("image_png", ".png", _seed_png, _read_image_cli),
        FuzzTarget("image_jpg", ".jpg", _seed_png, _read_image_cli),
        FuzzTarget("frame_tiff", ".tif", _seed_frame, _read_frame),
        FuzzTarget("frame_ppm", ".ppm", _seed_frame, _read_frame),
    )
}


def write_seeds(folder: Path, names: Sequence[str] | None = None) -> dict[str, bytes]:
    """Write one valid seed per target into ``folder``; return the seed bytes by target."""
    seeds: dict[str, bytes] = {}
    for name in names or TARGETS:
        t = TARGETS[name]
        p = folder / f"seed_{name}{t.suffix}"
        t.seed(p)
        seeds[name] = p.read_bytes()
    return seeds


def check_input(name: str, data: bytes, workdir: Path | None = None) -> str | None:
    """Run target ``name``'s reader on ``data``: None if it returned or raised a
    StemmapError, else the traceback text (a reader bug)."""
    t = TARGETS[name]
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        p = Path(d) / f"fuzz{t.suffix}"
        p.write_bytes(data)
        try:
            t.read(p)
        except StemmapError:
            return None
        except Exception:  # the oracle: anything else is a bug
            return traceback.format_exc()
    return None
