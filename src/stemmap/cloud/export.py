"""Writers for :class:`~stemmap.cloud.stems.CloudStems`: CSV, GeoJSON, top-view PNG (atomic)."""

from __future__ import annotations

import csv
import json
import math
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stemmap.cloud.stems import CloudStems
from stemmap.io.atomic import atomic_write

__all__ = ["STEM_CSV_COLUMNS", "plot_stems", "write_stems_csv", "write_stems_geojson"]

#: Columns of the stems CSV (metres, degrees; quality in [0, 1]; covariances in m^2).
#: ``diameter_std`` and ``cov_xx, cov_xy, cov_yy`` come from the fit covariance (empty where
#: not estimated); ``dbh_height`` (m above the base) and ``dbh_rule`` say where the DBH was
#: measured and why; ``base`` what heights are measured from (``ground``, ``lowest stem
#: points`` for a cloud without ground, ``slice heights as given``). docs/algorithms/cloud.md.
STEM_CSV_COLUMNS = (
    "id",
    "x",
    "y",
    "z",
    "diameter",
    "n_points",
    "quality",
    "arc_deg",
    "rms",
    "n_slices",
    "taper",
    "height",
    "eccentricity",
    "method",
    "diameter_std",
    "cov_xx",
    "cov_xy",
    "cov_yy",
    "dbh_height",
    "dbh_rule",
    "base",
)


def _num(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.4f}"


def _sci(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.4g}"


def write_stems_csv(path: str | os.PathLike[str], stems: CloudStems) -> None:
    """One row per stem, columns :data:`STEM_CSV_COLUMNS`; empty cells for NaN."""
    with atomic_write(path, "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(STEM_CSV_COLUMNS)
        for k in range(len(stems)):
            w.writerow(
                [
                    k,
                    _num(float(stems.xy[k, 0])),
                    _num(float(stems.xy[k, 1])),
                    _num(float(stems.z[k])),
                    _num(float(stems.diameter[k])),
                    int(stems.n_points[k]),
                    _num(float(stems.quality[k])),
                    _num(float(stems.arc_deg[k])),
                    _num(float(stems.rms[k])),
                    int(stems.n_slices[k]),
                    _num(float(stems.taper[k])),
                    _num(float(stems.height[k])),
                    _num(float(stems.eccentricity[k])),
                    stems.method,
                    _sci(float(stems.diameter_std[k])),
                    _sci(float(stems.xy_cov[k, 0, 0])),
                    _sci(float(stems.xy_cov[k, 0, 1])),
                    _sci(float(stems.xy_cov[k, 1, 1])),
                    _num(float(stems.dbh_height[k])),
                    str(stems.dbh_rule[k]),
                    stems.base,
                ]
            )


def write_stems_geojson(
    path: str | os.PathLike[str], stems: CloudStems, *, crs: str | None = None
) -> None:
    """A FeatureCollection of Points (cloud frame coordinates) with the CSV columns as properties.

    Coordinates are the cloud's own; pass ``crs`` (e.g. ``"EPSG:32633"``) only when the cloud is
    georeferenced (it is recorded as a ``crs`` member, RFC 7946 otherwise assumes WGS84).
    """
    feats: list[dict[str, Any]] = []
    for k in range(len(stems)):

        def f(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        feats.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "Point",
                    "coordinates": [float(stems.xy[k, 0]), float(stems.xy[k, 1])],
                },
                "properties": {
                    "id": k,
                    "z": f(stems.z[k]),
                    "diameter": f(stems.diameter[k]),
                    "n_points": int(stems.n_points[k]),
                    "quality": f(stems.quality[k]),
                    "arc_deg": f(stems.arc_deg[k]),
                    "rms": f(stems.rms[k]),
                    "height": f(stems.height[k]),
                    "method": stems.method,
                },
            }
        )
    doc: dict[str, Any] = {"type": "FeatureCollection", "features": feats}
    if crs:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    with atomic_write(path, "w") as fh:
        json.dump(doc, fh, indent=1)


def plot_stems(
    path: str | os.PathLike[str],
    stems: CloudStems,
    *,
    background_xy: ArrayLike | None = None,
    title: str = "",
) -> None:
    """Top view: stems as circles of their diameter (scaled up x5 for visibility, labelled with
    DBH in cm) over an optional subsample of the cloud's xy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    fig, ax = plt.subplots(figsize=(8, 8))
    if background_xy is not None:
        b = np.asarray(background_xy, dtype=np.float64).reshape(-1, 2)
        ax.scatter(b[:, 0], b[:, 1], s=0.2, c="0.7", lw=0, rasterized=True)
    for k in range(len(stems)):
        x, y = stems.xy[k]
        ax.add_patch(
            Circle((x, y), 2.5 * stems.diameter[k], fc="none", ec=plt.cm.viridis(stems.quality[k]))
        )
        ax.annotate(f"{100 * stems.diameter[k]:.0f}", (x, y), fontsize=7, ha="center")
    if len(stems):
        ax.scatter(stems.xy[:, 0], stems.xy[:, 1], s=4, c="k")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{len(stems)} stems ({stems.method}); circles 5x DBH, labels DBH cm")
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=120)
    plt.close(fig)
