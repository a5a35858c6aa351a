"""Peak memory of ``stemmap`` on hostile inputs: small files that announce huge data.

Each case writes one file (or folder) that is small on disk but announces -- honestly or not --
a huge allocation, then runs the stemmap command that reads it in a subprocess under an
address-space limit (``--max-memory-gb``, so a bomb cannot take the shared machine down) and
records its exit code, peak RSS (``ru_maxrss`` of the child, from ``os.wait4``), CPU time and
the last line of its stderr. The expected result is a refusal (exit 2, one ``error:`` line)
at a peak close to the ~0.2 GB the command's imports take.

Usage::

    PYTHONPATH=src python benchmarks/hostile_inputs.py --json            # every case
    PYTHONPATH=src python benchmarks/hostile_inputs.py --cases las_2e9 npz_bomb --bomb-gb 20
    python benchmarks/hostile_inputs.py --src /path/to/other/src           # another checkout

Cases: ``npz_bomb`` (scan NPZ, ``--bomb-gb`` of deflated ranges), ``tiff_frame`` /
``pgm_frame`` (a camera frame announcing 30000 x 30000), ``las_2e9`` / ``laz_2e9`` (a 1 kB
LAS/LAZ whose header announces 2e9 points), ``ply_4e9`` (binary PLY announcing 4e9
vertices), ``xyz_one_line`` / ``odometry_one_line`` (``--text-mb`` of numbers without a
newline), ``odometry_short_lines`` (``--text-mb`` of ``0,0,0`` lines), ``bag_huge_scan``
(a ROS 1 bag whose LaserScan announces 2^30 ranges); since Dec 6: ``bag_lz4_chunk`` (a ROS 1
bag whose one lz4 chunk holds ``--bag-gb`` of LaserScans, ~4 MB a GB on disk),
``bag_bz2_chunk`` (the same in bz2, ~1 kB a GB: python-lz4 gives up near 1 GB on its own),
``bag_lz4_lying`` (the same chunk, its header announcing 1 MB), ``tiff_cut`` (a camera TIFF
frame whose strip runs past the end of the file), ``yolo_polygons`` (``segment --train`` on a
real 16 Mpx mangrove photo with a label file of ``--yolo-lines`` polygons). ROS 2 / MCAP
(benchmarks/hostile_bags.py): ``mcap_zstd_chunk`` (an MCAP file without summary whose one
zstd chunk holds ``--bag-gb`` of LaserScans, 32 kB a GB), ``mcap_lz4_chunk`` (the same in lz4,
with a summary), ``mcap_zstd_lying`` (the zstd chunk, indexed, its header and index announcing
1 MB), ``ros2_zstd_message`` / ``ros2_zstd_message_unannounced`` (a message-compressed sqlite3
bag whose last message inflates to ``--bag-gb``, its zstd frame announcing the size or not),
``ros2_zstd_file`` (a file-compressed bag inflating to ``--bag-gb``, size not announced: rosbags
writes it to the temporary folder), ``ros2_zstd_file_huge`` (the same, its frame header
announcing 1 PB), ``bag_unindexed_topic`` (library: ``iter_laser_scans`` over a ROS 1 bag cut
at its index whose topic holds ``--topic-gb`` in 64 MB lz4 chunks; the one case run as
``python -c``, not a command); since Dec 6 (branch ``budgetroom``) ``bag_topic_detect``
(``detect`` on that bag: ``read_scans`` holds the whole topic).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

import hostile_bags as hb  # benchmarks/

ROOT = Path(__file__).resolve().parents[1]
BEAMS = 361


def _scan_npz(path: Path, rows: int, bomb: bool = True) -> Path:
    """A valid scan NPZ of ``rows`` x 361 ranges of 5 m, deflated (written in chunks)."""
    from numpy.lib import format as npy_format

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, value in (("angle_min", -math.pi / 2), ("angle_increment", math.pi / 360)):
            with zf.open(f"{name}.npy", "w") as fh:
                npy_format.write_array(fh, np.array(value))
        with zf.open("time.npy", "w", force_zip64=True) as fh:
            npy_format.write_array(fh, np.arange(rows) * 0.025)
        with zf.open("ranges.npy", "w", force_zip64=True) as fh:
            npy_format.write_array_header_2_0(
                fh, {"descr": "<f8", "fortran_order": False, "shape": (rows, BEAMS)}
            )
            block = np.full((4096, BEAMS), 5.0).tobytes()
            left = rows
            while left > 0:
                n = min(left, 4096)
                fh.write(block[: n * BEAMS * 8])
                left -= n
    return path


def _camera_folder(root: Path, frame: bytes, suffix: str) -> Path:
    """An RGB-D frames folder (64 x 48) whose second rgb frame is ``frame``."""
    import cv2

    from stemmap.io.camera_frames import write_camera_frames
    from stemmap.odometry.visual import StereoCalibration, VisualFrame

    rng = np.random.default_rng(0)
    frames = [
        VisualFrame(
            0.1 * k,
            rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
            depth=rng.uniform(1, 5, (48, 64)),
        )
        for k in range(3)
    ]
    write_camera_frames(root, frames, StereoCalibration(50.0, 50.0, 31.5, 23.5, 64, 48))
    for k, p in enumerate(sorted((root / "rgb").iterdir())):
        p.unlink()
        if k == 1:
            data = frame
        else:
            ok, buf = cv2.imencode(suffix, rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
            assert ok
            data = buf.tobytes()
        (root / "rgb" / f"{k:06d}{suffix}").write_bytes(data)
    return root


def _tiff(w: int, h: int) -> bytes:
    """An RGB TIFF of w x h black pixels in one deflated strip (~1 kB per Mpx on disk): the
    TIFF counterpart of a PNG bomb (libtiff inflates it in full)."""
    comp = zlib.compressobj(9)
    row = bytes(3 * w)
    strip = b"".join(comp.compress(row) for _ in range(h)) + comp.flush()
    entries = [(256, 4, w), (257, 4, h), (258, 3, 8), (259, 3, 8), (262, 3, 2), (273, 4, 0)]
    entries += [(277, 3, 3), (278, 4, h), (279, 4, len(strip))]
    offset = 8 + 2 + 12 * len(entries) + 4
    ifd = struct.pack("<H", len(entries))
    for tag, ftype, value in entries:
        value = offset if tag == 273 else value
        ifd += struct.pack("<HHI", tag, ftype, 1)
        ifd += struct.pack("<H" if ftype == 3 else "<I", value).ljust(4, b"\0")
    return b"II*\0" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0) + strip


def las_announcing(path: Path, count: int) -> Path:
    """A 10-point LAS/LAZ (by suffix) whose header then announces ``count`` points."""
    import laspy

    hdr = laspy.LasHeader(point_format=0, version="1.4")
    hdr.scales = np.array([0.01, 0.01, 0.01])
    las = laspy.LasData(hdr)
    xyz = np.random.default_rng(0).uniform(0, 10, (10, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(str(path))
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 107, count if count < 2**32 else 0)  # legacy count
    struct.pack_into("<Q", data, 247, count)  # LAS 1.4 64-bit count
    path.write_bytes(bytes(data))
    return path


def _ply(path: Path, count: int) -> Path:
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {count}\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n"
    )
    path.write_bytes(head.encode() + np.zeros((10, 3), "<f4").tobytes())
    return path


def _text(path: Path, mb: float, unit: bytes) -> Path:
    n = int(mb * 1e6) // len(unit)
    block = unit * max(1, min(n, 1 << 16))
    with path.open("wb") as fh:
        left = n
        while left > 0:
            k = min(left, 1 << 16)
            fh.write(block[: k * len(unit)])
            left -= k
    return path


def _bag_huge_scan(path: Path) -> Path:
    """A ROS 1 bag of LaserScans whose last message's ranges length field says 2^30."""
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.types import ScanBatch

    a = np.linspace(-math.pi / 2, math.pi / 2, BEAMS)
    write_scans_bag(
        path, ScanBatch(np.full((3, BEAMS), 5.0), np.arange(3) * 0.1, a[0], a[1] - a[0]), ros=1
    )
    data = bytearray(path.read_bytes())
    marker = struct.pack("<I", BEAMS)  # the ranges array length (uint32) of each message
    at = data.rfind(marker)
    assert at > 0, "ranges length field not found"
    struct.pack_into("<I", data, at, 1 << 30)
    path.write_bytes(bytes(data))
    return path


class _CompressingSink:
    """What rosbags' ROS 1 writer sees as a chunk's BytesIO, compressing as it is written, so
    a multi-GB chunk never sits in memory (``getvalue`` returns the compressed bytes)."""

    def __init__(self, compression: str) -> None:
        import bz2

        from lz4.frame import LZ4FrameCompressor

        self._c = LZ4FrameCompressor() if compression == "lz4" else bz2.BZ2Compressor(9)
        self._parts = [self._c.begin()] if compression == "lz4" else []
        self._n = 0

    def write(self, data: bytes | memoryview) -> int:
        self._n += len(data)
        self._parts.append(self._c.compress(bytes(data)))
        return len(data)

    def tell(self) -> int:
        return self._n

    def getvalue(self) -> bytes:
        return b"".join(self._parts) + self._c.flush()

    def close(self) -> None:
        self._parts = []


def ros1_compressed_bag(
    path: Path,
    n_scans: int,
    beams: int,
    *,
    compression: str = "lz4",
    size: int | None = None,
    range_m: float = 5.0,
) -> Path:
    """A ROS 1 bag of ``n_scans`` LaserScans of ``beams`` ranges of ``range_m`` (0: bytes of
    zeros, which bz2 compresses ~10x faster than a 4-byte pattern) in ONE chunk compressed
    with ``compression`` (``"lz4"`` or ``"bz2"``): an honest bomb, 4 x n_scans x beams bytes
    once decompressed (the chunk's ``size`` field, a uint32, allows up to 4.29 GB), written
    through a compressing sink in ~1 message of memory (lz4: ~4 MB on disk per GB).
    ``size``: overwrite the chunk header's uncompressed ``size`` field with this value (a
    header announcing less than the data expand to)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    writer = Writer(path)
    writer.set_compression(
        Writer.CompressionFormat.LZ4 if compression == "lz4" else Writer.CompressionFormat.BZ2
    )
    writer.chunk_threshold = 1 << 62  # one chunk, written on close
    with writer:
        writer.compressor = lambda data: data  # the sink has compressed it already
        writer.chunks[-1].data = _CompressingSink(compression)  # type: ignore[assignment]
        conn = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        msg = hb.laserscan_message(T, beams, np.full(beams, range_m, np.float32))
        ser = ts.serialize_ros1(msg, "sensor_msgs/msg/LaserScan")
        for k in range(n_scans):  # the same message at 1 s steps (its stamp says 1 s)
            writer.write(conn, (1 + k) * 1_000_000_000, ser)
    if size is not None:
        with path.open("r+b") as fh:
            head = fh.read(8192)
            at = head.find(b"size=", len(b"#ROSBAG V2.0\n") + 4096)  # the chunk header's
            assert at > 0, "chunk size field not found"
            fh.seek(at + 5)
            fh.write(struct.pack("<I", size))
    return path


BAG_BEAMS = 4_000_000  # 16 MB of float32 ranges a LaserScan


def _bag_bomb(path: Path, gb: float, size: int | None = None, compression: str = "lz4") -> Path:
    """``ros1_compressed_bag`` of ``gb`` GB in one chunk (at most the uint32 size field's
    4.29 GB), of ranges 0 (the fastest to compress); ``size`` makes the header lie."""
    n = max(1, min(int(gb * 1e9 / (4 * BAG_BEAMS)), (2**32 - 1) // (4 * BAG_BEAMS + 200)))
    return ros1_compressed_bag(path, n, BAG_BEAMS, compression=compression, size=size, range_m=0.0)


MANGROVE = Path("/work/shared/datasets/mangrove/images")


def _yolo_training(d: Path, lines: int) -> list[str]:
    """``segment --train`` on one real 4608 x 3456 mangrove photo (read in place) with a label
    file of ``lines`` small class-0 squares (~60 B a line)."""
    photo = sorted(MANGROVE.glob("*.jpg"))[0]
    rng = np.random.default_rng(0)
    rows = []
    for x, y in rng.uniform(0.05, 0.9, (lines, 2)):
        rows.append(f"0 {x:.4f} {y:.4f} {x + 0.02:.4f} {y:.4f} {x + 0.02:.4f} {y + 0.05:.4f}")
    (d / f"{photo.stem}.txt").write_text("\n".join(rows) + "\n")
    return [
        "segment",
        "--train",
        str(photo),
        "--labels",
        str(d / f"{photo.stem}.txt"),
        "--model-out",
        str(d / "m.npz"),
        "--augment",
        "0",
    ]


def _map_with_odometry(d: Path, odometry: Path) -> list[str]:
    """``stemmap map`` of a small scan NPZ with ``odometry`` as its wheel odometry CSV."""
    scans = _scan_npz(d / "s.npz", 40)
    return ["map", str(scans), "--odometry", str(odometry), "--out", str(d / "m")]


# name -> (builder(tmp, args) -> argv after "stemmap")
CASES: dict[str, Callable[[Path, argparse.Namespace], list[str]]] = {
    "npz_bomb": lambda d, a: [
        "detect",
        str(_scan_npz(d / "bomb.npz", int(a.bomb_gb * 1e9 / (BEAMS * 8)))),
        "--out",
        str(d / "o.csv"),
        "-q",
    ],
    "tiff_frame": lambda d, a: [
        "odometry",
        "--camera",
        str(_camera_folder(d / "f", _tiff(30000, 30000), ".tif")),
        "--out",
        str(d / "t.csv"),
    ],
    "pgm_frame": lambda d, a: [
        "odometry",
        "--camera",
        str(_camera_folder(d / "f", b"P6\n30000 30000\n255\n" + bytes(64), ".ppm")),
        "--out",
        str(d / "t.csv"),
    ],
    "las_2e9": lambda d, a: [
        "stems",
        str(las_announcing(d / "c.las", 2 * 10**9)),
        "--out",
        str(d / "s.csv"),
    ],
    "laz_2e9": lambda d, a: [
        "stems",
        str(las_announcing(d / "c.laz", 2 * 10**9)),
        "--out",
        str(d / "s.csv"),
    ],
    "ply_4e9": lambda d, a: ["stems", str(_ply(d / "c.ply", 4 * 10**9)), "--out", str(d / "s.csv")],
    "xyz_one_line": lambda d, a: [
        "stems",
        str(_text(d / "c.xyz", a.text_mb, b"1 ")),
        "--out",
        str(d / "s.csv"),
    ],
    "odometry_one_line": lambda d, a: _map_with_odometry(d, _text(d / "o.csv", a.text_mb, b"1,")),
    "odometry_short_lines": lambda d, a: _map_with_odometry(
        d, _text(d / "o.csv", a.text_mb, b"0,0,0\n")
    ),
    "bag_huge_scan": lambda d, a: [
        "detect",
        str(_bag_huge_scan(d / "b.bag")),
        "--out",
        str(d / "o.csv"),
        "-q",
    ],
    "bag_lz4_chunk": lambda d, a: [
        "detect",
        str(_bag_bomb(d / "b.bag", a.bag_gb)),
        "--out",
        str(d / "o.csv"),
        "-q",
    ],
    "bag_bz2_chunk": lambda d, a: [
        "detect",
        str(_bag_bomb(d / "b.bag", a.bag_gb, compression="bz2")),
        "--out",
        str(d / "o.csv"),
        "-q",
    ],
    "bag_lz4_lying": lambda d, a: [
        "detect",
        str(_bag_bomb(d / "b.bag", a.bag_gb, size=10**6)),
        "--out",
        str(d / "o.csv"),
        "-q",
    ],
    "tiff_cut": lambda d, a: [
        "odometry",
        "--camera",
        str(_camera_folder(d / "f", _tiff(64, 48)[:-10], ".tif")),
        "--out",
        str(d / "t.csv"),
    ],
    "yolo_polygons": lambda d, a: _yolo_training(d, a.yolo_lines),
    "mcap_zstd_chunk": lambda d, a: _detect(
        hb.mcap_bomb(d / "m.mcap", _n_scans(a.bag_gb), BAG_BEAMS, compression="zstd"), d
    ),
    "mcap_lz4_chunk": lambda d, a: _detect(
        hb.mcap_bomb(d / "m.mcap", _n_scans(a.bag_gb), BAG_BEAMS, compression="lz4", indexed=True),
        d,
    ),
    "mcap_zstd_lying": lambda d, a: _detect(
        hb.mcap_bomb(d / "m.mcap", _n_scans(a.bag_gb), BAG_BEAMS, size=10**6, indexed=True), d
    ),
    "ros2_zstd_message": lambda d, a: _detect(
        hb.ros2_message_bomb(d / "b", int(a.bag_gb * 1e9 / 4)), d
    ),
    "ros2_zstd_message_unannounced": lambda d, a: _detect(
        hb.ros2_message_bomb(d / "b", int(a.bag_gb * 1e9 / 4), announce=False), d
    ),
    "ros2_zstd_file": lambda d, a: _detect(hb.ros2_file_bomb(d / "b", a.bag_gb, announce=False), d),
    "ros2_zstd_file_huge": lambda d, a: _detect(
        hb.ros2_file_bomb(d / "b", a.bag_gb, announce=False, content_size=10**15), d
    ),
    "bag_topic_detect": lambda d, a: _detect(hb.ros1_unindexed_bag(d / "u.bag", a.topic_gb), d),
    "bag_unindexed_topic": lambda d, a: [
        "-c",
        "import sys; from stemmap.io.rosbag import iter_laser_scans; "
        "print(sum(1 for _ in iter_laser_scans(sys.argv[1])), 'scans')",
        str(hb.ros1_unindexed_bag(d / "u.bag", a.topic_gb)),
    ],
}


def _n_scans(gb: float) -> int:
    return max(1, int(gb * 1e9 / (4 * BAG_BEAMS)))


def _detect(bag: Path, d: Path) -> list[str]:
    return ["detect", str(bag), "--out", str(d / "o.csv"), "-q"]


def _run(argv: list[str], src: Path, limit_gb: float, timeout: float) -> dict[str, object]:
    env = dict(os.environ, PYTHONPATH=str(src))
    limit = int(limit_gb * 2**30)

    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as err:
        p = subprocess.Popen(
            [sys.executable, *argv]
            if argv[0] == "-c"
            else [sys.executable, "-m", "stemmap", *argv],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=err,
            preexec_fn=preexec,
        )
        deadline = time.monotonic() + timeout
        while True:
            pid, status, usage = os.wait4(p.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() > deadline:
                p.kill()
                pid, status, usage = os.wait4(p.pid, 0)
                break
            time.sleep(0.05)
        p.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        lines = [ln for ln in err.read().splitlines() if ln.strip()]
    return {
        "exit": p.returncode,
        "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
        "wall_s": round(time.perf_counter() - t0, 2),
        "stderr_last": lines[-1][:400] if lines else "",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--src", type=Path, default=ROOT / "src", help="stemmap source tree to run")
    ap.add_argument("--bomb-gb", type=float, default=20.0, help="npz_bomb decompressed size")
    ap.add_argument("--text-mb", type=float, default=300.0, help="size of the text cases")
    ap.add_argument("--bag-gb", type=float, default=2.0, help="bag_lz4_* chunk size (<= 4.29)")
    ap.add_argument("--topic-gb", type=float, default=3.0, help="bag_unindexed_topic size")
    ap.add_argument("--yolo-lines", type=int, default=200, help="yolo_polygons label lines")
    ap.add_argument("--max-memory-gb", type=float, default=8.0, help="address-space limit")
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args()
    out: dict[str, object] = {"src": str(args.src), "max_memory_gb": args.max_memory_gb}
    with tempfile.TemporaryDirectory(prefix="stemmap-hostile-") as tmp:
        for name in args.cases:
            d = Path(tmp) / name
            d.mkdir()
            argv = CASES[name](d, args)
            size = sum(f.stat().st_size for f in d.rglob("*") if f.is_file())
            res = {"input_bytes": size, **_run(argv, args.src, args.max_memory_gb, args.timeout)}
            out[name] = res
            if not args.json:
                print(name, json.dumps(res), flush=True)
    if args.json:
        print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
