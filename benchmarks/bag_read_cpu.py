"""CPU time of reading legitimate bags with two stemmap source trees (e.g. a branch and its
base): the cost of the read-budget checks (``stemmap.io._bag_budget``, ``_bag2_budget``) and
whether the scans read are identical.

Every bag holds the same ``--scans`` simulated LaserScans of ``--beams`` ranges (uniform
0.5-20 m, seed 0), written by this tree's ``write_scans_bag``: ROS 1 uncompressed / bz2 /
lz4 (and lz4 in 64 kB chunks cut at 97 %: no index, the salvage path), ROS 2 sqlite3
uncompressed / zstd per message / zstd per file, MCAP uncompressed / zstd chunks. Each
(bag, tree) pair is read in a fresh subprocess (``iter_laser_scans``, all scans),
``--repeat`` times alternating the trees; the process CPU time of the read alone
(``time.process_time``, imports excluded) is reported as the minimum over the repeats, with
a SHA-256 of every scan's time and ranges.

    PYTHONPATH=src python benchmarks/bag_read_cpu.py --base /tmp/base/src --json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

_CHILD = """
import hashlib, sys, time
from stemmap.io.rosbag import iter_laser_scans
h = hashlib.sha256()
t = time.process_time()
n = 0
for s in iter_laser_scans(sys.argv[1]):
    h.update(repr(s.time).encode()); h.update(s.ranges.tobytes()); n += 1
print(time.process_time() - t, n, h.hexdigest()[:16])
"""


def _bags(d: Path, scans: int, beams: int) -> dict[str, Path]:
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.types import ScanBatch

    rng = np.random.default_rng(0)
    batch = ScanBatch(
        rng.uniform(0.5, 20.0, (scans, beams)).astype(np.float32).astype(np.float64),
        np.arange(scans) * 0.025 + 1.0,
        -np.pi / 2,
        np.pi / (beams - 1),
    )
    out: dict[str, Path] = {
        "ros1": write_scans_bag(d / "r1.bag", batch, ros=1),
        "ros1_bz2": write_scans_bag(d / "r1bz2.bag", batch, ros=1, compression="bz2"),
        "ros1_lz4": write_scans_bag(d / "r1lz4.bag", batch, ros=1, compression="lz4"),
        "ros2_sqlite3": write_scans_bag(d / "r2", batch, ros=2),
        "ros2_zstd_message": write_scans_bag(d / "r2m", batch, ros=2, compression="zstd"),
        "ros2_zstd_file": write_scans_bag(
            d / "r2f", batch, ros=2, compression="zstd", compression_mode="file"
        ),
        "mcap": write_scans_bag(d / "mc", batch, ros=2, storage="mcap"),
        "mcap_zstd": write_scans_bag(
            d / "mcz", batch, ros=2, storage="mcap", compression="zstd", compression_mode="storage"
        ),
    }
    cut = d / "r1lz4_noindex.bag"  # lz4 in 64 kB chunks without its index: the salvage
    chunked = write_scans_bag(d / "r1c.bag", batch, ros=1, compression="lz4", chunk_bytes=65536)
    data = chunked.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.97)])
    out["ros1_lz4_noindex"] = cut
    return out


def _read(bag: Path, src: Path) -> tuple[float, int, str]:
    env = dict(os.environ, PYTHONPATH=str(src))
    p = subprocess.run(
        [sys.executable, "-c", _CHILD, str(bag)], env=env, capture_output=True, text=True
    )
    if p.returncode:
        raise RuntimeError(p.stderr[-500:])
    cpu, n, digest = p.stdout.split()
    return float(cpu), int(n), digest


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", type=Path, required=True, help="the other tree's src folder")
    ap.add_argument("--src", type=Path, default=ROOT / "src")
    ap.add_argument("--scans", type=int, default=3000)
    ap.add_argument("--beams", type=int, default=361)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    res: dict[str, object] = {"scans": a.scans, "beams": a.beams, "load": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory(prefix="stemmap-bagcpu-") as tmp:
        for name, bag in _bags(Path(tmp), a.scans, a.beams).items():
            cpu: dict[str, list[float]] = {"base": [], "src": []}
            seen: dict[str, tuple[int, str]] = {}
            for _ in range(a.repeat):
                for key, src in (("base", a.base), ("src", a.src)):
                    t, n, digest = _read(bag, src)
                    cpu[key].append(t)
                    seen[key] = (n, digest)
            row = {
                "base_cpu_s": round(min(cpu["base"]), 3),
                "src_cpu_s": round(min(cpu["src"]), 3),
                "ratio": round(min(cpu["src"]) / min(cpu["base"]), 3),
                "scans": seen["src"][0],
                "identical": seen["base"] == seen["src"],
            }
            res[name] = row
            if not a.json:
                print(name, json.dumps(row), flush=True)
    res["load_end"] = os.getloadavg()[0]
    if a.json:
        print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
