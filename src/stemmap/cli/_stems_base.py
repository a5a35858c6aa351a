"""What ``stemmap stems`` says about where its heights came from, and why a run found nothing.

The detector measures heights from a ground model, or -- for a cloud without ground, one tree
exported by 3DFin, TreeQSM or ITSMe -- from the cloud's lowest stem points
(:meth:`stemmap.cloud.ground.GroundAccumulator.stem_base`). That choice decides the band the
stems are cut in, so the summary states it like the units and the up axis; a warning follows
only where the result contradicts it. An empty result names the causes the run has evidence
for (docs/cli.md, stems).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stemmap.cloud.ground import BASE_GROUND, BASE_STEM
from stemmap.cloud.result import BASE_SLICE

__all__ = ["base_warning", "empty_result_notes", "height_payload", "height_reference"]

#: What each base is called in the summary, and why it was taken.
_SAID = {
    BASE_GROUND: ("ground model", "the cloud's lowest points per cell"),
    BASE_STEM: ("lowest stem points", "no ground found: one tree exported without ground"),
    BASE_SLICE: ("z as given", "a slice under 1 m tall: heights not normalised"),
}


def height_reference(result: Any) -> tuple[str, str] | None:
    """(value, note) of the summary's "heights from" row, or None when the method has no
    base (munjer2025: one lidar frame). A flat base gives its z (cloud frame, metres)."""
    base = str(getattr(result, "base", "") or "")
    if not base:
        return None
    value, note = _SAID.get(base, (base, "per chunk of the tile catalog"))
    z = float(getattr(result, "base_z", math.nan))
    if base == BASE_STEM and math.isfinite(z):
        value = f"{value}, z = {z:.2f} m"
    return value, note


def height_payload(result: Any) -> dict[str, Any]:
    """The --json keys of the height reference: ``height_reference`` (the CSV's ``base``)
    and ``base_z_m`` (the flat base's z, null for a ground model or a slice)."""
    z = float(getattr(result, "base_z", math.nan))
    return {
        "height_reference": str(getattr(result, "base", "") or "") or None,
        "base_z_m": z if math.isfinite(z) else None,
    }


def base_warning(result: Any) -> str | None:
    """A warning when a cloud taken for one tree without ground gave several stems: the
    verdict means its lowest points fit inside one stem, so two or more stems say it is a
    plot whose ground was missed, and their heights (and DBH heights) are measured from the
    wrong base. The real segmented trees (archi Tree_1, Tree_2) give one stem each."""
    if getattr(result, "base", "") != BASE_STEM or len(result) < 2:
        return None
    z = float(getattr(result, "base_z", math.nan))
    return (
        f"no ground was found (the cloud's lowest points fit inside one stem), so heights "
        f"were measured from z = {z:.2f} m as for one tree exported without ground, but "
        f"{len(result)} stems were found: if this is a plot, its ground is missing or too "
        "sparse and the DBH heights may be wrong (detect_stems(ground=...) takes a ground "
        "model)."
    )


def empty_result_notes(
    sample: Any, up_axis_hint: str | None, *, catalog: bool = False
) -> tuple[list[str], list[str]]:
    """(warnings, notes) for a run without stems whose --units / --up-axis were not given.

    A warning names --up-axis only when the cloud's shape says so (``up_axis_hint``, from
    :func:`stemmap.io.conventions.up_axis_hint`). Otherwise the convention is one possible
    cause among others (a sparse plot, the base: :attr:`CloudStems.reason`), stated as a
    note with the measured evidence: the size of the cloud read as metres, z up, which the
    user can compare with the real one (a cloud in mm reads 1000 x too large, in ft 3.28 x;
    treels pine_plot written Y up, which the shape check misses, reads 10 x 20.3 m across
    and 10 m tall for a 10 x 10 m plot of 20 m trees). For a tile ``catalog`` (which takes
    no --up-axis) the note says to turn the tiles instead.
    """
    warnings = [] if up_axis_hint is None else [up_axis_hint]
    notes: list[str] = []
    a = None if sample is None else np.asarray(sample, dtype=np.float64)
    if a is not None and a.ndim == 2 and a.shape[0] > 0:
        a = a[np.all(np.isfinite(a), axis=1)]
    if a is not None and a.ndim == 2 and a.shape[0] > 0:
        span = np.ptp(a, axis=0)
        size = (
            f"read as metres with z up, the cloud is {span[0]:.1f} x {span[1]:.1f} m across "
            f"and {span[2]:.1f} m tall"
        )
        if up_axis_hint is None:  # the shape check saw nothing: the user judges the size
            axis = "turn the tiles z up" if catalog else "pass --up-axis (y, x)"
            notes.append(
                f"{size} (the shape check saw nothing amiss); if that is not its size or "
                f"its up axis, pass --units (mm, cm, ft) or {axis}."
            )
        else:
            notes.append(f"{size}; if that is not its size, pass --units (mm, cm, ft).")
    return warnings, notes
