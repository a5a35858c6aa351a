"""Reference diameters from a cloud's own full rings (for benchmarks and real-data tests).

Where a trunk is seen all round (a TLS plot, a segmented single tree), a plain geometric
circle fit of the points in a thin ring at the measurement height is the best reference the
cloud itself offers; its residual RMS and arc coverage say how good a reference it is. It
shares the points with the detector but none of its machinery (clustering, slices, consensus,
tests, taper line, lean correction), so it checks them.

A single fit depends on its start circle (which points the first 30 % band keeps, and where
the trimming settles): on treels spruce the ring moves by 0.6 cm with start shifts of a few
cm. :func:`converged_ring_reference` therefore fits from several start circles about a
fixed seed and reports the median and the spread of the results; the benchmarks seed it from
a committed file (``benchmarks/_cloud_ring_seeds.json``), not from the detector they score.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from stemmap.cloud.result import BASE_SLICE, CloudStems
from stemmap.cloud.slicefit import _segment_arcs

__all__ = [
    "RingReference",
    "converged_ring_reference",
    "ring_reference",
    "stem_references",
]


@dataclass(frozen=True)
class RingReference:
    """A full-ring reference: ``diameter`` (m), its fit ``rms`` (m), ``arc_deg``, ``n``;
    ``spread`` (m) the range of the diameters fitted from ``starts`` start circles (0 and 1
    for a single fit)."""

    x: float
    y: float
    diameter: float
    rms: float
    arc_deg: float
    n: int
    spread: float = 0.0
    starts: int = 1

    @property
    def full(self) -> bool:
        """Seen all round (arc >= 300 degrees) with at least 20 points."""
        return self.arc_deg >= 300.0 and self.n >= 20


def ring_reference(
    xyz: ArrayLike,
    center: tuple[float, float],
    z: float,
    radius: float,
    *,
    half_thickness: float = 0.05,
) -> RingReference | None:
    """Geometric least-squares circle of the ring ``|z_i - z| <= half_thickness`` near a stem.

    Points within ``1.5 radius + 0.1 m`` of ``center``; start from the given circle (the
    points within 30 % of its radius), then Gauss-Newton on the orthogonal distances with
    3 x 1.4826 MAD trimming, three rounds.
    None when fewer than 10 points are in the ring, or when the fit leaves the disc its
    points were taken from (centre or radius beyond ``1.5 radius + 0.1 m``: it diverged).
    """
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(center, dtype=np.float64)
    m = (np.abs(p[:, 2] - z) <= half_thickness) & (
        np.hypot(p[:, 0] - c[0], p[:, 1] - c[1]) <= 1.5 * radius + 0.1
    )
    q = p[m, :2]
    if q.shape[0] < 10:
        return None
    cx, cy, r = float(c[0]), float(c[1]), float(radius)
    # start from the given circle: points within 30 % of r (2 cm at least) of it; a fork or
    # a branch in the ring is outside and stays out
    keep = np.abs(np.hypot(q[:, 0] - cx, q[:, 1] - cy) - r) <= max(0.3 * r, 0.02)
    if keep.sum() < 10:
        return None
    for _ in range(3):
        for _ in range(20):
            v = q[keep] - (cx, cy)
            d = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-12)
            J = np.column_stack((-v[:, 0] / d, -v[:, 1] / d, -np.ones_like(d)))
            step = np.linalg.lstsq(J, -(d - r), rcond=None)[0]
            cx, cy, r = cx + step[0], cy + step[1], r + step[2]
            if np.abs(step).max() < 1e-7:
                break
        res = np.abs(np.hypot(q[:, 0] - cx, q[:, 1] - cy) - r)
        mad = float(np.median(res[keep]))
        keep = res <= max(3 * 1.4826 * mad, 1e-3)
    if (
        not (np.isfinite(r) and 0 < r <= 1.5 * radius + 0.1)
        or np.hypot(cx - c[0], cy - c[1]) > 1.5 * radius + 0.1
    ):
        return None  # diverged (a short arc from a start off the trunk): no ring of these points
    res = np.hypot(q[keep, 0] - cx, q[keep, 1] - cy) - r
    ids = np.zeros(int(keep.sum()), dtype=np.int64)
    arc = float(_segment_arcs(q[keep], ids, 1, np.array([[cx, cy]]))[0])
    return RingReference(
        float(cx), float(cy), 2 * float(r), math.sqrt(float(np.mean(res**2))), arc, int(keep.sum())
    )


def converged_ring_reference(
    xyz: ArrayLike,
    center: tuple[float, float],
    z: float,
    radius: float,
    *,
    half_thickness: float = 0.05,
    shift: float = 0.02,
    scales: tuple[float, ...] = (0.9, 1.0, 1.1),
) -> RingReference | None:
    """:func:`ring_reference` from several start circles: the centre as given and moved by
    ``shift`` (m) along +-x and +-y, each with the radius times each of ``scales`` (15
    starts by default). Returns the fit with the median diameter of those that succeeded,
    with ``spread`` = largest - smallest diameter among them (the reference's own
    uncertainty from its start) and ``starts`` = how many succeeded. None when none did.
    """
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    cx, cy = float(center[0]), float(center[1])
    offsets = ((0.0, 0.0), (shift, 0.0), (-shift, 0.0), (0.0, shift), (0.0, -shift))
    fits = [
        f
        for dx, dy in offsets
        for s in scales
        if (
            f := ring_reference(p, (cx + dx, cy + dy), z, s * radius, half_thickness=half_thickness)
        )
        is not None
    ]
    if not fits:
        return None
    d = np.array([f.diameter for f in fits])
    mid = fits[int(np.argsort(d, kind="stable")[(d.size - 1) // 2])]
    return replace(mid, spread=float(d.max() - d.min()), starts=len(fits))


def stem_references(xyz: ArrayLike, stems: CloudStems) -> list[RingReference | None]:
    """The :func:`ring_reference` of every detected stem of ``xyz``: at the stem's breast
    height (the cloud's median z for a pre-cut slice), 5 cm half thickness (10 cm when the
    detector measured a spacing above 3 cm: a sparse cloud needs a thicker ring for 20
    points), started from the detected circle."""
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    half = 0.05 if stems.spacing < 0.03 else 0.1
    z_slice = float(np.median(p[:, 2])) if stems.base == BASE_SLICE else math.nan
    return [
        ring_reference(
            p,
            (float(stems.xy[i, 0]), float(stems.xy[i, 1])),
            float(stems.z[i]) if stems.base != BASE_SLICE else z_slice,
            float(stems.diameter[i]) / 2,
            half_thickness=half,
        )
        for i in range(len(stems))
    ]
