"""Helpers for tests/engine and benchmarks/catalog.py: a simulated TLS stand cut into square
LAZ tiles (tests import it through tests/conftest.py's sys.path)."""

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


def write_copc(path: Path, xyz: np.ndarray, depth: int = 3, seed: int = 0) -> None:
    """A COPC file (LAS 1.4 point format 6, 1 mm scale) of ``xyz`` written by copclib.

    Octree over the cube around the points: each point goes to a level drawn at random
    (seeded) and to the node of that level holding it; a node whose descendants hold points
    but which drew none gets one point from a descendant (a COPC reader walks the hierarchy
    from the root). Points keep their input order within a node.
    """
    import copclib
    import laspy

    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    center = (lo + hi) / 2
    half = float(np.max(hi - lo)) / 2 + 1e-3
    origin = center - half
    rng = np.random.default_rng(seed)
    level = rng.integers(0, depth + 1, size=len(xyz))

    keys = np.zeros((len(xyz), 4), dtype=np.int64)
    for lev in range(depth + 1):
        m = level == lev
        cell = 2 * half / 2**lev
        keys[m, 0] = lev
        keys[m, 1:] = np.clip(np.floor((xyz[m] - origin) / cell), 0, 2**lev - 1)
    nodes: dict[tuple[int, ...], list[int]] = {}
    for i, k in enumerate(map(tuple, keys.tolist())):
        nodes.setdefault(k, []).append(i)
    for lev in range(depth, 0, -1):  # every ancestor of a node must hold a point
        for key in [k for k in nodes if k[0] == lev]:
            d, x, y, z = key
            parent = (d - 1, x // 2, y // 2, z // 2)
            if parent not in nodes:
                donor = nodes[key]
                nodes[parent] = [donor.pop(0)]
                if not donor:
                    del nodes[key]
    scale = np.full(3, 0.001)
    offset = np.floor(lo)
    cfg = copclib.CopcConfigWriter(6, copclib.Vector3(*scale), copclib.Vector3(*offset))
    cfg.las_header.min = copclib.Vector3(*lo)
    cfg.las_header.max = copclib.Vector3(*hi)
    cfg.copc_info.center_x, cfg.copc_info.center_y, cfg.copc_info.center_z = center
    cfg.copc_info.halfsize = half
    cfg.copc_info.spacing = 2 * half / 128
    writer = copclib.FileWriter(str(path), cfg)
    fmt = laspy.PointFormat(6)
    for key in sorted(nodes):
        idx = np.array(nodes[key])
        rec = laspy.ScaleAwarePointRecord.zeros(
            len(idx), point_format=fmt, scales=scale, offsets=offset
        )
        rec.x, rec.y, rec.z = xyz[idx, 0], xyz[idx, 1], xyz[idx, 2]
        writer.AddNode(
            copclib.VoxelKey(*key), copclib.VectorChar(rec.array.view(np.int8).reshape(-1))
        )
    writer.Close()
