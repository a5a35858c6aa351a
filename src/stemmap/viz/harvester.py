"""Top-view figure of a simulated trunk capture."""

from __future__ import annotations

import os

import numpy as np

from stemmap.harvester.kinematics import ForestryCrane
from stemmap.harvester.simulate import CaptureResult
from stemmap.io.atomic import atomic_write
from stemmap.sim.forest import Stand

__all__ = ["plot_capture"]


def plot_capture(
    path: str | os.PathLike[str], stand: Stand, result: CaptureResult, crane: ForestryCrane
) -> None:
    """Write a PNG: trees to scale, the crane's reach, the head's path and the captured trunk."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    for k, (xy, d) in enumerate(zip(stand.trees_xy, stand.diameters, strict=True)):
        target = k == result.target_tree
        ax.add_patch(Circle(tuple(xy), d / 2, color="tab:red" if target else "tab:brown",
                            alpha=0.9 if target else 0.6))  # fmt: skip
    reach = crane.max_reach()
    ax.add_patch(Circle((0, 0), reach, fill=False, ls="--", color="grey", lw=0.8))
    ax.plot(0, 0, "ks", ms=8, label="crane base")
    hp = result.head_path
    if hp.shape[0]:
        ax.plot(hp[:, 0], hp[:, 1], "-", color="tab:blue", lw=1.2, label="head path")
        ax.plot(hp[-1, 0], hp[-1, 1], "o", color="tab:blue", ms=5)
    status = "captured" if result.success else f"failed: {result.reason}"
    err = (
        f", final error {result.final_error * 100:.1f} cm"
        if np.isfinite(result.final_error)
        else ""
    )
    ax.set_title(f"Simulated capture: {status}{err}, {result.cycles} cycles", fontsize=10)
    lim = reach + 1.0
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="lower left", fontsize=8)
    ax.grid(alpha=0.3)
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", bbox_inches="tight")
    plt.close(fig)
