"""Cross-sections of real trunks at scan height for the simulator (issue 11): smooth
out-of-roundness, cm-scale bark ridges, elliptic and leaning stems, buttress lobes.

Pure geometry: :func:`trunk_outline` returns the polygon of one trunk's outline around its
centre; :func:`stemmap.sim.stand_features.make_trunks_noncircular` places them in a stand. Used to
*test* the detectors on what real stands have and the perfect circles of the simulator lack,
never to tune them (defaults are chosen on the real slices, docs/algorithms/scan-detection.md).
"""

from __future__ import annotations

import math

import numpy as np

from stemmap.errors import ConfigError
from stemmap.types import FloatArray

__all__ = ["rough_radius", "trunk_outline"]


def rough_radius(
    n_vertices: int,
    radius: float,
    roughness: float,
    gen: np.random.Generator,
    *,
    harmonics: tuple[int, int] = (2, 8),
) -> FloatArray:
    """Radius profile ``radius (1 + roughness p(phi) / rms(p))`` with ``p`` a sum of random
    harmonics ``k`` in ``harmonics`` (inclusive) of amplitude ``N(0, 1/k)`` and random phase: a
    1/k (pink) spectrum, smooth out-of-roundness for low harmonics, bark ridges for high ones."""
    phi = 2 * np.pi * np.arange(n_vertices) / n_vertices
    prof = np.zeros(n_vertices)
    for k in range(harmonics[0], harmonics[1] + 1):
        prof += gen.normal(0.0, 1.0 / k) * np.cos(k * phi + gen.uniform(0, 2 * np.pi))
    rms = float(np.sqrt(np.mean(prof**2))) or 1.0
    return np.asarray(radius * (1.0 + roughness * prof / rms))


def trunk_outline(
    radius: float,
    gen: np.random.Generator,
    *,
    n_vertices: int = 48,
    ellipticity: float = 0.0,
    roughness: float = 0.0,
    bark_rms: float = 0.0,
    lean_deg: float = 0.0,
    buttress: float = 0.0,
    n_lobes: int = 4,
) -> FloatArray:
    """Outline (V, 2) of one trunk around its centre, metres.

    Parameters
    ----------
    radius : float, metres
        Half the DBH measured across the stem axis.
    gen : numpy Generator
        Draws only for the features that are on (a zero parameter draws nothing, so adding a
        feature keeps the other trunks' shapes).
    n_vertices : int, >= 8
        Polygon vertices (bark ridges need ~4 vertices per ridge wavelength: 180 or more).
    ellipticity : float in [0, 0.5)
        Semi-axes ``r (1 + e)``, ``r (1 - e)``, random orientation (mean caliper = DBH).
    roughness : float, >= 0
        Relative RMS of smooth out-of-roundness (harmonics 2-8, :func:`rough_radius`).
    bark_rms : float, metres, >= 0
        RMS of bark ridges: harmonics 9 to ``n_vertices // 4`` with a 1/k spectrum (ridges a
        few cm apart on a 30 cm trunk). The real slices' ring references have 3.6-22 mm of
        residual RMS about their circles (ring_rms_m of benchmarks/real_geometry.py).
    lean_deg : float, degrees in [0, 60]
        Lean of the stem from vertical, random azimuth: a horizontal slice of a stem of
        diameter D leaning by ``a`` is stretched to ``D / cos(a)`` along the lean azimuth.
    buttress : float, >= 0
        Relative height of buttress lobes (flare at the base): ``r (1 + b max(0, cos(m (phi -
        phi0)))^4)`` with ``m = n_lobes`` lobes at a random phase.
    n_lobes : int, >= 1
    """
    if not (
        n_vertices >= 8
        and 0 <= ellipticity < 0.5
        and roughness >= 0
        and bark_rms >= 0
        and 0 <= lean_deg <= 60
        and buttress >= 0
        and n_lobes >= 1
    ):
        raise ConfigError(
            "trunk_outline needs n_vertices >= 8, 0 <= ellipticity < 0.5, roughness >= 0, "
            "bark_rms >= 0, 0 <= lean_deg <= 60, buttress >= 0, n_lobes >= 1; got "
            f"{n_vertices}, {ellipticity}, {roughness}, {bark_rms}, {lean_deg}, {buttress}, "
            f"{n_lobes}."
        )
    phi = 2 * np.pi * np.arange(n_vertices) / n_vertices
    prof = rough_radius(n_vertices, 1.0, roughness, gen) if roughness > 0 else np.ones(n_vertices)
    if buttress > 0:
        phase = gen.uniform(0, 2 * np.pi)
        prof = prof * (1.0 + buttress * np.maximum(np.cos(n_lobes * (phi - phase)), 0.0) ** 4)
    k_hi = n_vertices // 4
    if bark_rms > 0 and k_hi >= 9:
        ridges = rough_radius(n_vertices, 1.0, 1.0, gen, harmonics=(9, k_hi)) - 1.0
        prof = prof + (bark_rms / radius) * ridges
    rot = gen.uniform(0, np.pi)  # drawn even for a circle: the same stream as before
    a, b = radius * (1 + ellipticity), radius * (1 - ellipticity)
    ex, ey = a * np.cos(phi) * prof, b * np.sin(phi) * prof
    c, s = math.cos(rot), math.sin(rot)
    xy = np.column_stack((c * ex - s * ey, s * ex + c * ey))
    if lean_deg > 0:
        az = gen.uniform(0, 2 * np.pi)
        u = np.array([math.cos(az), math.sin(az)])
        stretch = 1.0 / math.cos(math.radians(lean_deg)) - 1.0
        xy = xy + stretch * np.outer(xy @ u, u)
    return xy
