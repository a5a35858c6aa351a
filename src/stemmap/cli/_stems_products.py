"""Forestry products of ``stemmap stems``: stem profiles CSV, metrics JSON, labelled LAS."""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stemmap.cloud.result import CloudStems
from stemmap.io.atomic import atomic_write

if TYPE_CHECKING:
    from stemmap.io.conventions import CloudConvention

__all__ = ["write_forestry_products"]

log = logging.getLogger(__name__)

PROFILE_COLUMNS = ("tree", "height", "diameter", "diameter_std", "x", "y")


def _num(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.4f}"


def write_forestry_products(
    cloud: Path,
    stems: CloudStems,
    chunk_size: int,
    topic: str | None,
    *,
    profile: Path | None = None,
    metrics: Path | None = None,
    labels: Path | None = None,
    convention: CloudConvention | None = None,
) -> None:
    """Read the cloud's xyz once more (streamed) and write the requested products.

    ``profile``: CSV, one row per (tree, level) (:data:`PROFILE_COLUMNS`; tree = the stems
    CSV id, height in m above the stem's base). ``metrics``: JSON with the plot summary
    (:func:`~stemmap.products.forestry.plot_summary` over the occupied 1 m cells of the cloud)
    and per-tree DBH, DBH std, height and stem volume. ``labels``: LAS with a ``tree_id``
    extra dimension (:func:`~stemmap.products.forestry.tree_labels`), all other fields of a
    LAS/LAZ input kept (in the file's own coordinates). ``convention``: the cloud's units
    and up axis, as for the stems (the profiles and metrics are in metres, z up).
    """
    from stemmap.io.clouds import iter_cloud_chunks
    from stemmap.products.forestry import (
        occupied_area,
        plot_summary,
        stem_profiles,
        stem_volume,
        tree_labels,
    )

    xyz = np.concatenate(
        [c.xyz for c in iter_cloud_chunks(cloud, chunk_size, topic=topic, convention=convention)]
    )
    profs = stem_profiles(xyz, stems) if (profile or metrics) else []
    if profile is not None:
        with atomic_write(profile, "w") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(PROFILE_COLUMNS)
            for pr in profs:
                for i in range(pr.height.size):
                    w.writerow(
                        [
                            pr.tree,
                            f"{pr.height[i]:.2f}",
                            _num(float(pr.diameter[i])),
                            _num(float(pr.diameter_std[i])),
                            _num(float(pr.xy[i, 0])),
                            _num(float(pr.xy[i, 1])),
                        ]
                    )
    if metrics is not None:
        area = occupied_area(xyz[:, :2], 1.0)
        doc = plot_summary(stems, area, area_method="occupied 1 m cells of the cloud")
        trees = []
        for k, pr in enumerate(profs):
            vol, to_h = stem_volume(pr, float(stems.height[k]))

            def f(v: float, nd: int = 4) -> float | None:
                return round(float(v), nd) if math.isfinite(v) else None

            trees.append(
                {
                    "id": k,
                    "dbh_m": f(stems.diameter[k]),
                    "dbh_std_m": f(stems.diameter_std[k], 5),
                    "height_m": f(stems.height[k], 2),
                    "volume_m3": f(vol),
                    "profile_to_m": f(to_h, 2),
                }
            )
        doc["trees"] = trees
        doc["base"] = stems.base
        with atomic_write(metrics, "w") as fh:
            json.dump(doc, fh, indent=1)
    if labels is not None:
        _write_labels(cloud, xyz, tree_labels(xyz, stems), labels)


def _write_labels(cloud: Path, xyz: np.ndarray, ids: np.ndarray, path: Path) -> None:
    import laspy

    if cloud.suffix.lower() in (".las", ".laz"):
        las = laspy.read(str(cloud))
        if las.header.point_count != ids.shape[0]:  # pragma: no cover - reader mismatch
            raise RuntimeError("the labelled cloud lost points between reads")
    else:
        header = laspy.LasHeader(point_format=0, version="1.2")
        header.scales = np.array([0.001, 0.001, 0.001])
        header.offsets = np.floor(xyz.min(axis=0))
        las = laspy.LasData(header)
        las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if "tree_id" not in las.point_format.dimension_names:
        las.add_extra_dim(laspy.ExtraBytesParams(name="tree_id", type=np.uint32))
    las.tree_id = ids.astype(np.uint32)
    with atomic_write(path, "wb") as fh:
        las.write(fh, do_compress=path.suffix.lower() == ".laz")
