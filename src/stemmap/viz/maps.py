"""Stem-map figure: vehicle path, GPS fixes and trees drawn to scale (matplotlib, Agg)."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stemmap.io.atomic import atomic_write
from stemmap.types import StemMap, Trajectory

__all__ = ["plot_stem_map", "save_stem_map_png"]


def plot_stem_map(
    ax: Any,
    stem_map: StemMap,
    trajectory: Trajectory | None = None,
    *,
    gps_xy: ArrayLike | None = None,
    reference: Trajectory | None = None,
    truth_xy: ArrayLike | None = None,
    title: str = "",
    min_draw_diameter: float = 0.0,
) -> None:
    """Draw a stem map on a matplotlib ``ax``.

    Trees are circles with their estimated diameter in metres (to scale, equal axes; a tree
    smaller than ``min_draw_diameter`` is drawn at that size so it stays visible), the
    trajectory a line, GPS fixes dots, an optional reference trajectory (e.g. dead reckoning)
    dashed and optional true tree positions crosses.
    """
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    if reference is not None and len(reference):
        ax.plot(
            reference.xy[:, 0],
            reference.xy[:, 1],
            "--",
            color="0.6",
            lw=0.8,
            label="dead reckoning",
        )
    if gps_xy is not None:
        g = np.asarray(gps_xy, dtype=np.float64).reshape(-1, 2)
        if g.size:
            ax.plot(g[:, 0], g[:, 1], ".", color="tab:orange", ms=1.5, label="GPS (aligned)")
    if trajectory is not None and len(trajectory):
        ax.plot(
            trajectory.xy[:, 0], trajectory.xy[:, 1], "-", color="tab:blue", lw=0.8, label="path"
        )
    if len(stem_map):
        d = np.nan_to_num(stem_map.diameters, nan=0.2)
        d = np.maximum(d, min_draw_diameter)
        patches = [Circle((t.x, t.y), 0.5 * di) for t, di in zip(stem_map, d, strict=True)]
        ax.add_collection(
            PatchCollection(patches, facecolor="tab:green", edgecolor="darkgreen", lw=0.3)
        )
        ax.plot([], [], "o", color="tab:green", label=f"trees ({len(stem_map)})")
    if truth_xy is not None:
        t = np.asarray(truth_xy, dtype=np.float64).reshape(-1, 2)
        ax.plot(t[:, 0], t[:, 1], "x", color="k", ms=3, lw=0.5, label="true trees")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title)
    ax.legend(loc="best", fontsize="small")


def save_stem_map_png(
    path: str | os.PathLike[str],
    stem_map: StemMap,
    trajectory: Trajectory | None = None,
    *,
    dpi: int = 150,
    size_in: float = 8.0,
    **kwargs: Any,
) -> None:
    """Render :func:`plot_stem_map` to a PNG file, written atomically."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size_in, size_in))
    ax = fig.add_subplot(1, 1, 1)
    # a tree should stay visible on a km-wide map: at least ~1 pixel
    xy = stem_map.xy
    extent = float(np.ptp(xy, axis=0).max()) if xy.shape[0] > 1 else 10.0
    min_d = extent / (size_in * dpi) * 2 if math.isfinite(extent) else 0.0
    plot_stem_map(ax, stem_map, trajectory, min_draw_diameter=min_d, **kwargs)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=dpi)
