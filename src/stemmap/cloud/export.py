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
from stemmap.io.geo import GeoLayer, array_fields, georeference_features, write_gpkg

__all__ = [
    "STEM_CSV_COLUMNS",
    "plot_stems",
    "write_stems_csv",
    "write_stems_geojson",
    "write_stems_gpkg",
]

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

    With ``crs`` (the cloud's CRS, e.g. ``"EPSG:32633"``) the geometry is WGS84 lon/lat per RFC
    7946 and the cloud coordinates stay in properties ``x``, ``y``; without it the geometry is
    in cloud metres, declared a local frame (:func:`stemmap.io.geo.georeference_features`).
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
    georeference_features(doc, stems.xy, crs, stems.frame)  # RFC 7946 lon/lat or local metres
    with atomic_write(path, "w") as fh:
        json.dump(doc, fh, indent=1)


def write_stems_gpkg(
    path: str | os.PathLike[str], stems: CloudStems, *, crs: str | None = None
) -> None:
    """A GeoPackage (layer ``stems``, Points in the native ``crs`` or the local frame) whose
    fields are the CSV's columns except ``id``, ``x``, ``y`` (the geometry): numbers, the text
    columns ``method``, ``dbh_rule``, ``base``, and ``cov_xx``, ``cov_xy``, ``cov_yy``."""
    fields = array_fields(stems, len(stems), skip=("xy",), constants=("method", "base"))
    write_gpkg(path, [GeoLayer("stems", stems.xy, fields)], crs, stems.frame)


def plot_stems(
    path: str | os.PathLike[str],
    stems: CloudStems,
    *,
    background_xy: ArrayLike | None = None,
    title: str = "",
) -> None:
    """Top view to scale: each stem a circle of its DBH (equal axes, scale bar), a centre dot of
    fixed screen size coloured by fit quality (colour bar) so that thin stems stay visible on
    a large plot, and the DBH in cm beside it; over an optional subsample of the cloud's xy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    from stemmap.viz.maps import add_scale_bar

    fig, ax = plt.subplots(figsize=(8, 8))
    if background_xy is not None:
        b = np.asarray(background_xy, dtype=np.float64).reshape(-1, 2)
        ax.scatter(b[:, 0], b[:, 1], s=0.2, c="0.75", lw=0, rasterized=True, label="cloud")
    n = len(stems)
    if n:
        d = np.nan_to_num(stems.diameter, nan=0.0)
        circles = [Circle((x, y), 0.5 * di) for (x, y), di in zip(stems.xy, d, strict=True)]
        ax.add_collection(PatchCollection(circles, fc="none", ec="k", lw=0.8))
        sc = ax.scatter(
            stems.xy[:, 0], stems.xy[:, 1], s=12, c=stems.quality, cmap="viridis",
            vmin=0, vmax=1, zorder=3, label=f"stem centre ({n})",
        )  # fmt: skip
        fig.colorbar(sc, ax=ax, shrink=0.7, label="fit quality (0-1)")
        for (x, y), di in zip(stems.xy, d, strict=True):
            ax.annotate(f"{100 * di:.0f}", (x, y), xytext=(4, 4), textcoords="offset points",
                        fontsize=7)  # fmt: skip
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    pts = stems.xy if background_xy is None else np.asarray(background_xy).reshape(-1, 2)
    extent = float(np.ptp(pts, axis=0).max()) if len(pts) > 1 else 10.0
    add_scale_bar(ax, extent)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    med = f", median DBH {100 * float(np.nanmedian(stems.diameter)):.1f} cm" if n else ""
    head = f"{n} stems ({stems.method}){med}"
    ax.set_title(f"{title}\n{head}" if title else head, fontsize="medium")
    ax.text(0.01, 0.01, "circles: DBH to scale; labels: DBH (cm)", transform=ax.transAxes,
            fontsize="x-small", color="0.3")  # fmt: skip
    if n or background_xy is not None:
        ax.legend(loc="upper left", fontsize="x-small", markerscale=2)
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=120)
    plt.close(fig)
