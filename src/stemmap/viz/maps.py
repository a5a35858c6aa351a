"""Stem-map figure: vehicle path, GPS fixes and trees drawn to scale (matplotlib, Agg)."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stemmap.io.atomic import atomic_write
from stemmap.types import StemMap, Trajectory

__all__ = ["add_scale_bar", "nice_length", "plot_stem_map", "save_stem_map_png"]


def nice_length(extent: float) -> float:
    """A round scale-bar length (1, 2 or 5 x 10^k m) near a fifth of ``extent``."""
    target = max(extent, 1e-3) / 5.0
    k = math.floor(math.log10(target))
    for m in (5.0, 2.0, 1.0):
        if m * 10**k <= target:
            return m * 10**k
    return 10.0**k


def add_scale_bar(ax: Any, extent: float, *, loc: str = "lower right") -> float:
    """Draw a metric scale bar (:func:`nice_length`) on an equal-aspect ``ax``; return it."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    length = nice_length(extent)
    label = f"{length:g} m" if length >= 1 else f"{100 * length:g} cm"
    ax.add_artist(
        AnchoredSizeBar(
            ax.transData, length, label, loc, pad=0.4, sep=3, frameon=True, size_vertical=0
        )
    )
    return length


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
    gate: float = 1.0,
) -> None:
    """Draw a stem map on a matplotlib ``ax``, to scale, with a scale bar and a legend.

    Trees are circles of their estimated diameter (equal axes; a tree smaller than
    ``min_draw_diameter`` is drawn at that size so it stays visible on a large map) with a
    centre dot of fixed screen size, so that every tree is visible at any map extent. The
    trajectory is a line, GPS fixes dots, an optional reference trajectory (dead reckoning)
    dashed. Without truth the centre dots are coloured by ``confidence`` (colour bar). With
    ``truth_xy`` the map is matched to the truth (one-to-one, within ``gate``
    metres): matched trees green, spurious mapped trees red, missed true trees as black
    crosses; matched true positions are small open grey rings drawn *under* the mapped trees.
    """
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    if reference is not None and len(reference):
        ax.plot(*reference.xy.T, "--", color="0.6", lw=0.8, label="dead reckoning", zorder=1)
    if gps_xy is not None:
        g = np.asarray(gps_xy, dtype=np.float64).reshape(-1, 2)
        if g.size:
            ax.plot(*g.T, ".", color="tab:orange", ms=1.5, label="GPS (aligned)", zorder=1)
    if trajectory is not None and len(trajectory):
        ax.plot(*trajectory.xy.T, "-", color="tab:blue", lw=0.8, label="path", zorder=2)
    n = len(stem_map)
    xy = stem_map.xy
    matched = np.zeros(n, dtype=bool)
    t_xy = None if truth_xy is None else np.asarray(truth_xy, dtype=np.float64).reshape(-1, 2)
    t_hit = np.zeros(0 if t_xy is None else t_xy.shape[0], dtype=bool)
    if t_xy is not None:
        from stemmap.eval.matching import match_points

        m = match_points(xy, t_xy, gate)
        if m.pairs.size:
            matched[m.pairs[:, 0]] = True
            t_hit[m.pairs[:, 1]] = True
        if t_hit.any():
            ax.plot(*t_xy[t_hit].T, "o", mfc="none", mec="0.5", ms=5, mew=0.6, zorder=3,
                    label=f"true position of a matched tree ({int(t_hit.sum())})")  # fmt: skip
        if (~t_hit).any():
            ax.plot(*t_xy[~t_hit].T, "x", color="k", ms=5, mew=1.0, zorder=3,
                    label=f"missed true tree ({int((~t_hit).sum())})")  # fmt: skip
    if n:
        d = np.maximum(np.nan_to_num(stem_map.diameters, nan=0.2), min_draw_diameter)
        colour = np.where(matched | (t_xy is None), "tab:green", "tab:red")
        patches = [Circle((x, y), 0.5 * di) for (x, y), di in zip(xy, d, strict=True)]
        ax.add_collection(
            PatchCollection(patches, facecolor=colour, edgecolor="k", lw=0.3, alpha=0.7, zorder=4)
        )
        if t_xy is None:
            conf = np.array([t.confidence for t in stem_map], dtype=np.float64)
            sc = ax.scatter(*xy.T, s=9, c=conf, cmap="RdYlGn", vmin=0, vmax=1, zorder=5,
                            edgecolors="k", linewidths=0.2, label=f"mapped tree ({n})")  # fmt: skip
            ax.figure.colorbar(sc, ax=ax, shrink=0.6, pad=0.02, label="confidence (real tree)")
        else:
            if matched.any():
                ax.plot(*xy[matched].T, "o", color="darkgreen", ms=2.5, zorder=5,
                        label=f"mapped, matched ({int(matched.sum())})")  # fmt: skip
            if (~matched).any():
                ax.plot(*xy[~matched].T, "o", color="tab:red", ms=3, zorder=5,
                        label=f"mapped, spurious ({int((~matched).sum())})")  # fmt: skip
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    pts = [xy] + ([trajectory.xy] if trajectory is not None and len(trajectory) else [])
    allp = np.vstack(pts) if sum(p.shape[0] for p in pts) else np.zeros((1, 2))
    extent = float(np.ptp(allp, axis=0).max()) if allp.shape[0] > 1 else 10.0
    add_scale_bar(ax, extent)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title, fontsize="medium")
    ax.legend(loc="upper left", fontsize="x-small", framealpha=0.8)


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
    # trees at least 2 px wide on a km-wide map (the centre dots keep them visible anyway)
    xy = stem_map.xy
    extent = float(np.ptp(xy, axis=0).max()) if xy.shape[0] > 1 else 10.0
    min_d = extent / (size_in * dpi) * 2 if math.isfinite(extent) else 0.0
    plot_stem_map(ax, stem_map, trajectory, min_draw_diameter=min_d, **kwargs)
    ax.text(
        0.01, 0.01, "circles: DBH to scale"
        + (f" (at least {100 * min_d:.0f} cm wide)" if min_d > 0.05 else ""),
        transform=ax.transAxes, ha="left", va="bottom", fontsize="x-small", color="0.3",
    )  # fmt: skip
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=dpi)
