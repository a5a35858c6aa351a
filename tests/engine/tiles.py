"""Test and benchmark helpers: a simulated TLS stand cut into square LAZ tiles."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np

from stemmap.sim.lidar import lidar_preset, random_stand3d, simulate_tls


def write_laz(path: Path, xyz: np.ndarray) -> None:
    """LAS 1.4 point format 6, 1 mm scale, LAZ-compressed when ``path`` ends in .laz."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(path)


def quantize(xyz: np.ndarray) -> np.ndarray:
    """The coordinates a 1 mm LAS file stores (what a reader gets back)."""
    return np.round(xyz * 1000.0) / 1000.0


def stand_cloud(
    size: float = 40.0, n_trees: int = 40, seed: int = 3, stations: int = 3
) -> np.ndarray:
    """A coarse TLS cloud of a ``size`` x ``size`` m stand scanned from ``stations`` x
    ``stations`` positions, cropped to the stand, on the 1 mm grid of a LAS file."""
    stand = random_stand3d(n_trees, (size, size), rng=seed, n_shrubs=6)
    g = np.linspace(size / (2 * stations), size * (1 - 1 / (2 * stations)), stations)
    pos = [(x, y) for x in g for y in g]
    pc = simulate_tls(stand, pos, lidar_preset("tls_coarse", range_max=30.0), rng=seed + 1)
    xyz = quantize(pc.xyz)
    keep = (xyz[:, 0] >= 0) & (xyz[:, 0] < size) & (xyz[:, 1] >= 0) & (xyz[:, 1] < size)
    return xyz[keep]


def write_tiles(folder: Path, xyz: np.ndarray, tile: float, ext: str = ".laz") -> list[Path]:
    """Cut ``xyz`` into ``tile`` x ``tile`` m tiles (half-open squares), one file each."""
    folder.mkdir(parents=True, exist_ok=True)
    ij = np.floor(xyz[:, :2] / tile).astype(np.int64)
    out = []
    for key in np.unique(ij, axis=0):
        m = np.all(ij == key, axis=1)
        p = folder / f"tile_{key[0]}_{key[1]}{ext}"
        write_laz(p, xyz[m])
        out.append(p)
    return out
