"""Reader / writer throughput: scans (NPZ, CSV, ROS1 / ROS2 bags), PointCloud2 decoding, maps,
PLY point clouds.

Prints one JSON object with --json. Every file is written to a temporary folder by stemmap's
own writers (scans, maps) or rosbags' writers (bags), then read back; the times are wall-clock
medians of ``--repeat`` runs on one core (the machine may be shared: compare ratios within one
run rather than absolute numbers across runs).

    python benchmarks/io_readers.py --json [--scans 5000] [--beams 361] [--repeat 3]
    python benchmarks/io_readers.py --json --only-ply --ply-points 15000000

The PLY sections write a binary little-endian file, and a smaller ascii one (x, y, z float32,
intensity float32, red, green, blue uchar: 19-byte vertices, then a face element as in a mesh
export; ascii floats with 9 significant digits, exact for float32) and read each
with stemmap's read_ply (our reader) and, when plyfile is installed (GPL-3, not a stemmap
dependency; the comparison is skipped without it), with read_ply as it was before, on plyfile:
the same PointCloud (xyz float64, the other properties as fields) from either. The two readers
alternate; process CPU time and wall time are reported, with the load average at the start and
end.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import statistics
import struct
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from _ros_bags import BagFactory  # writes real bags (shared with tests/io)
from stemmap.io import (
    decode_pointcloud2,
    read_scans,
    read_trees_csv,
    write_scans_csv,
    write_scans_npz,
    write_trees_csv,
    write_trees_geojson,
)
from stemmap.io.clouds import read_ply
from stemmap.types import ScanBatch, StemMap, Tree


def _median_time(fn: Callable[[], Any], repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _write_ply(path: Path, n: int, rng: np.random.Generator, text: bool = False) -> None:
    """A PLY by hand (header per the spec, then packed records or ascii lines)."""
    dt = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")]
        + [(c, "u1") for c in ("red", "green", "blue")]
    )
    n_faces = 1000
    head = (
        f"ply\nformat {'ascii' if text else 'binary_little_endian'} 1.0\n"
        f"comment stemmap benchmark\nelement vertex {n}\n"
        + "".join(f"property float {c}\n" for c in ("x", "y", "z", "intensity"))
        + "".join(f"property uchar {c}\n" for c in ("red", "green", "blue"))
        + f"element face {n_faces}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face = np.dtype([("n", "u1"), ("v", "<i4", (3,))])
    with path.open("wb") as fh:
        fh.write(head.encode())
        step = 2_000_000
        for a in range(0, n, step):
            m = min(step, n - a)
            rec = np.empty(m, dtype=dt)
            for c in ("x", "y", "z", "intensity"):
                rec[c] = rng.uniform(-50, 50, m)
            for c in ("red", "green", "blue"):
                rec[c] = rng.integers(0, 256, m)
            if text:
                cols = np.column_stack([rec[c].astype(np.float64) for c in dt.names or ()])
                np.savetxt(fh, cols, fmt=["%.9g"] * 4 + ["%d"] * 3)
            else:
                fh.write(rec.tobytes())
        faces = np.empty(n_faces, dtype=face)
        faces["n"] = 3
        faces["v"] = rng.integers(0, n, (n_faces, 3))
        if text:
            np.savetxt(fh, np.column_stack((faces["n"], faces["v"])), fmt="%d")
        else:
            fh.write(faces.tobytes())


def _read_ply_via_plyfile(path: Path) -> Any:
    """stemmap's read_ply as it was before our reader (plyfile parse, the same PointCloud)."""
    from plyfile import PlyData

    from stemmap.io.clouds import _finish

    data = PlyData.read(str(path))["vertex"].data
    names = data.dtype.names or ()
    xyz = np.column_stack([np.asarray(data[c], dtype=np.float64) for c in ("x", "y", "z")])
    fields = {k: np.asarray(data[k]) for k in names if k not in ("x", "y", "z")}
    return _finish(xyz, path, fields)


def run_ply(n_points: int, repeat: int, text: bool = False) -> dict[str, Any]:
    """Read speed of our PLY reader vs plyfile on one binary (or ascii) file, alternating."""
    try:
        import plyfile  # noqa: F401
    except ImportError:
        have_plyfile = False
    else:
        have_plyfile = True
    rng = np.random.default_rng(1)
    out: dict[str, Any] = {"n_points": n_points, "load_avg_start": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "cloud.ply"
        _write_ply(p, n_points, rng, text)
        out["file_mb"] = round(p.stat().st_size / 1e6, 1)
        readers: dict[str, Callable[[], Any]] = {"ours": lambda: read_ply(p)}
        if have_plyfile:
            readers["plyfile"] = lambda: _read_ply_via_plyfile(p)
        times: dict[str, dict[str, list[float]]] = {k: {"cpu": [], "wall": []} for k in readers}
        ref: np.ndarray | None = None
        for _ in range(repeat):
            for name, fn in readers.items():  # alternate the readers within each round
                c0, w0 = time.process_time(), time.perf_counter()
                xyz = fn().xyz
                times[name]["cpu"].append(time.process_time() - c0)
                times[name]["wall"].append(time.perf_counter() - w0)
                if ref is None:
                    ref = xyz
                elif not np.array_equal(ref, xyz):
                    raise AssertionError(f"{name} read different coordinates")
                del xyz
        for name, t in times.items():
            cpu, wall = statistics.median(t["cpu"]), statistics.median(t["wall"])
            out[name] = {
                "cpu_s": round(cpu, 3),
                "wall_s": round(wall, 3),
                "points_per_cpu_s": round(n_points / cpu),
                "points_per_wall_s": round(n_points / wall),
            }
        if have_plyfile:
            out["speedup_cpu_vs_plyfile"] = round(out["plyfile"]["cpu_s"] / out["ours"]["cpu_s"], 2)
            out["speedup_wall_vs_plyfile"] = round(
                out["plyfile"]["wall_s"] / out["ours"]["wall_s"], 2
            )
        else:
            out["plyfile"] = "not installed: comparison skipped"
    out["load_avg_end"] = os.getloadavg()[0]
    return out


def _scans(n_scans: int, n_beams: int, rng: np.random.Generator) -> ScanBatch:
    r = rng.uniform(0.3, 30.0, (n_scans, n_beams))
    r[rng.random(r.shape) < 0.1] = np.nan
    return ScanBatch(
        r, 0.025 * np.arange(n_scans), -math.pi / 2, math.pi / (n_beams - 1), 0.05, 80.0
    )


def _naive_pointcloud2(data: bytes, n: int, step: int) -> np.ndarray:
    """Per-point struct.unpack: the loop a vectorised decoder replaces (reference only)."""
    out = np.empty((n, 3))
    for i in range(n):
        out[i] = struct.unpack_from("<fff", data, i * step)
    return out


def run(
    n_scans: int, n_beams: int, n_bag: int, n_points: int, n_trees: int, repeat: int
) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    res: dict[str, Any] = {
        "scenario": {
            "n_scans": n_scans,
            "n_beams": n_beams,
            "n_bag_messages": n_bag,
            "n_pointcloud_points": n_points,
            "pointcloud_point_step_bytes": 22,
            "n_trees": n_trees,
            "no_return_fraction": 0.1,
            "repeat": repeat,
            "timing": "median wall-clock of repeat runs, one process, shared 2-core machine",
            "python": sys.version.split()[0],
            "numpy": np.__version__,
        }
    }
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        batch = _scans(n_scans, n_beams, rng)
        for kind, writer in (("npz", write_scans_npz), ("csv", write_scans_csv)):
            p = d / f"scans.{kind}"
            tw = _median_time(lambda p=p, w=writer: w(p, batch), repeat)
            tr = _median_time(lambda p=p: read_scans(p), repeat)
            res[f"scans_{kind}"] = {
                "write_s": round(tw, 4),
                "read_s": round(tr, 4),
                "read_scans_per_s": round(n_scans / tr),
                "file_mb": round(p.stat().st_size / 1e6, 2),
            }
        small = _scans(n_bag, n_beams, rng)
        for label, fac in (
            ("ros1", BagFactory(1)),
            ("ros2_sqlite3", BagFactory(2)),
            ("ros2_mcap", BagFactory(2, "mcap")),
        ):
            msgs = [
                ("/scan", fac.laserscan(1000.0 + t, r, small.angle_min, small.angle_increment))
                for t, r in zip(small.times, small.ranges, strict=True)
            ]
            p = fac.write(d / f"bag_{label}", msgs)
            tr = _median_time(lambda p=p: read_scans(p), repeat)
            res[f"bag_{label}_laserscan"] = {
                "read_s": round(tr, 4),
                "messages_per_s": round(n_bag / tr),
            }
            if label == "ros1":  # the same bag without its index (cut at 95 %): salvage path
                cut = d / "cut.bag"
                raw = p.read_bytes()
                cut.write_bytes(raw[: int(len(raw) * 0.95)])
                logging.disable(logging.WARNING)
                ts = _median_time(lambda c=cut: read_scans(c), repeat)
                n_rec = len(read_scans(cut))
                logging.disable(logging.NOTSET)
                res["bag_ros1_salvage_laserscan"] = {
                    "file_fraction_kept": 0.95,
                    "messages_recovered": n_rec,
                    "read_s": round(ts, 4),
                    "messages_per_s": round(n_rec / ts),
                }
        # PointCloud2: x y z f32, intensity f32, ring u16, 4 bytes padding -> 22-byte points
        step = 22
        dt = np.dtype(
            {
                "names": ["x", "y", "z", "intensity", "ring"],
                "formats": ["<f4", "<f4", "<f4", "<f4", "<u2"],
                "offsets": [0, 4, 8, 12, 16],
                "itemsize": step,
            }
        )
        pts = np.zeros(n_points, dtype=dt)
        for c in ("x", "y", "z", "intensity"):
            pts[c] = rng.uniform(-50, 50, n_points)
        pts["x"][rng.random(n_points) < 0.05] = np.nan
        data = pts.tobytes()
        fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 7, 1)]
        fields.append(("ring", 16, 4, 1))
        tv = _median_time(
            lambda: decode_pointcloud2(data, fields, point_step=step, width=n_points), repeat
        )
        n_naive = min(n_points, 100_000)
        tn = _median_time(lambda: _naive_pointcloud2(data, n_naive, step), 1) * n_points / n_naive
        res["pointcloud2_decode"] = {
            "vectorised_s": round(tv, 5),
            "points_per_s": round(n_points / tv),
            "naive_struct_loop_s_extrapolated": round(tn, 4),
            "speedup_vs_naive": round(tn / tv, 1),
        }
        trees = StemMap(
            tuple(
                Tree(i, *rng.uniform(-100, 100, 2), rng.uniform(0.1, 0.6), np.eye(2) * 1e-3, 5)
                for i in range(n_trees)
            )
        )
        p = d / "trees.csv"
        res["trees_csv"] = {
            "write_s": round(_median_time(lambda: write_trees_csv(p, trees), repeat), 4),
            "read_s": round(_median_time(lambda: read_trees_csv(p), repeat), 4),
        }
        g = d / "trees.geojson"
        res["trees_geojson_write_s"] = round(
            _median_time(lambda: write_trees_geojson(g, trees, origin_lonlat=(25.0, 60.0)), repeat),
            4,
        )
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--scans", type=int, default=5000)
    ap.add_argument("--beams", type=int, default=361)
    ap.add_argument("--bag-messages", type=int, default=2000)
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--trees", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--ply-points", type=int, default=2_000_000)
    ap.add_argument("--ply-ascii-points", type=int, default=500_000)
    ap.add_argument("--only-ply", action="store_true", help="run the PLY section only")
    a = ap.parse_args()
    res = {} if a.only_ply else run(a.scans, a.beams, a.bag_messages, a.points, a.trees, a.repeat)
    res["ply_read"] = run_ply(a.ply_points, a.repeat)
    res["ply_read_ascii"] = run_ply(a.ply_ascii_points, a.repeat, text=True)
    print(json.dumps(res, indent=None if a.json else 2))


if __name__ == "__main__":
    main()
