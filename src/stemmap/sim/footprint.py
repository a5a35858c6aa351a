"""The range a footprint-averaging (SICK LMS-class) pulsed scanner reports for one beam.

One model, used by both virtual scanners of the project: the simulator
(:func:`stemmap.sim.scanner.simulate_scans`, exact sub-beams against circles and segments) and
the real-geometry benchmark (:func:`stemmap.eval.real_slices.virtual_scans`, sub-cells of real
point clouds). Each samples a beam's footprint by ``K`` sub-rays (sub-beams) and hands their
first-hit ranges to :func:`footprint_ranges`.

**The model** (docs/algorithms/sim-eval.md, "Mixed pixels: one footprint model"). A beam whose
footprint is split between surfaces at ranges ``r_j`` returns, when the surfaces lie within the
pulse's range resolution of each other, one merged echo; its range is the mean of the
``r_j`` weighted by the power each part sends back,

    ``r = sum_j (w_j rho_j / r_j^2) r_j / sum_j (w_j rho_j / r_j^2)``,

``w_j`` the share of the beam's radiant power that falls on part ``j`` (the profile weight of
its sub-ray), ``rho_j`` its reflectance (equal for every surface here: a model without
per-surface reflectance) and ``1 / r_j^2`` the received power of a diffuse (Lambertian)
target that intercepts a given share of the beam (the lidar equation for an extended target).
This is what :func:`stemmap.scan.features.mixed_fraction` inverts. Sources: Hebert & Krotkov
(1992, Image Vis. Comput. 10(3)) and Tuley, Vandapel & Hebert (2005, ICRA, "Analysis and removal
of artifacts in 3-D LADAR data"): a beam on two objects closer in range than the instrument's
range resolution gives one echo read as a single point between them (mixed pixel); Sanz-Cortiella
et al. (2011, Sensors 11(3) 2751-2772) on a SICK LMS200 with partial beam blockage: "the
distance value given by the sensor depends more on the blocked radiant power than on the
blocked surface area" (so a power weighting, not the plain area mean), and only a second
target within 1.5-2.5 m behind the first moves the reading; SICK's LMS5xx / LRS4000 manuals:
the part of the beam that misses a small object "can be reflected by a larger object in the
background ... this can lead to a corruption of the measured value".

**Return threshold.** The beam returns when the share of its power that hits something,
``sum_{hit} w_j / sum_j w_j``, is at least ``min_share`` (and > 0): an energy threshold on
the covered share (docs/algorithms/scan-detection.md, "Averaging scanners: the return
threshold (Dec 4)"). ``0`` returns when any sub-ray hits.

**Not modelled.** Surfaces farther apart than the range resolution give two echoes and a
single-echo scanner reports one of them (the first strong enough), not a blend; the simulator
and the benchmark blend at any separation (the detector's mixed-pixel prior assumes the same).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from stemmap.errors import InputError
from stemmap.types import FloatArray

__all__ = ["beam_range", "footprint_ranges", "sub_ray_offsets"]


@njit(cache=True, inline="always")
def beam_range(
    sub_r: FloatArray, weight: FloatArray, min_share: float
) -> float:  # pragma: no cover - numba
    """Range of one beam from the first-hit ranges ``sub_r`` (K,) of its sub-rays (``inf`` =
    no hit) and their power shares ``weight`` (K,, > 0): the ``weight / r^2``-weighted mean
    of the hits (module docstring), or ``inf`` when the hit share of ``weight`` is 0 or below
    ``min_share``."""
    w_all = 0.0
    w_hit = 0.0
    num = 0.0
    den = 0.0
    for j in range(sub_r.shape[0]):
        w = weight[j]
        w_all += w
        r = sub_r[j]
        if r < np.inf:
            w_hit += w
            p = w / (r * r)  # received power of this part (equal reflectance)
            num += p * r
            den += p
    if not w_hit > 0.0 or w_hit < min_share * w_all - 1e-9 * w_all:
        return np.inf
    return num / den


@njit(cache=True)
def _ranges_kernel(
    sub_r: FloatArray, weight: FloatArray, min_share: float, out: FloatArray
) -> None:  # pragma: no cover - numba
    for i in range(sub_r.shape[0]):
        out[i] = beam_range(sub_r[i], weight, min_share)


def footprint_ranges(
    sub_r: ArrayLike, weight: ArrayLike | None = None, min_share: float = 0.0
) -> FloatArray:
    """Ranges of beams from their sub-rays (the model of the module docstring).

    Parameters
    ----------
    sub_r : array_like of shape (..., K), metres
        First-hit range of each sub-ray of each beam; ``inf`` (or NaN) where it hit nothing.
    weight : array_like of shape (K,), > 0, optional
        Share of the beam's radiant power carried by each sub-ray (the beam profile sampled at
        the sub-rays; need not sum to 1). Default: uniform.
    min_share : float in [0, 1]
        Return threshold: the share of ``weight`` that must hit for the beam to return.

    Returns
    -------
    ndarray of shape (...,), metres
        ``sum w r^-1 / sum w r^-2`` over the sub-rays that hit (the ``w / r^2`` power-weighted
        mean range), ``inf`` where the beam does not return.

    Examples
    --------
    Half the footprint on a trunk at 5 m, half on a wall at 10 m: the trunk sends back four
    times the power, so the reading lies at 4/5 of the way to the trunk, not half way.

    >>> float(footprint_ranges([[5.0, 5.0, 10.0, 10.0]])[0])
    6.0
    >>> float(footprint_ranges([[5.0, np.inf, np.inf, np.inf]], min_share=0.5)[0])
    inf
    """
    r = np.asarray(sub_r, dtype=np.float64)
    if r.ndim < 1 or r.shape[-1] < 1:
        raise InputError(f"sub_r must have a last axis of sub-rays, got shape {r.shape}.")
    k = r.shape[-1]
    w = np.ones(k) if weight is None else np.asarray(weight, dtype=np.float64).reshape(-1)
    if w.shape[0] != k or not np.all(np.isfinite(w) & (w > 0)):
        raise InputError(f"weight must be {k} finite values > 0, got {w!r}.")
    if not 0.0 <= min_share <= 1.0:
        raise InputError(f"min_share must be in [0, 1], got {min_share!r}.")
    flat = np.ascontiguousarray(np.where(np.isnan(r), np.inf, r).reshape(-1, k))
    out = np.empty(flat.shape[0])
    _ranges_kernel(flat, np.ascontiguousarray(w), float(min_share), out)
    return out.reshape(r.shape[:-1])


def sub_ray_offsets(width: float, k: int) -> FloatArray:
    """Offsets (same unit as ``width``) of ``k`` sub-rays that sample a footprint of full
    width ``width``: the centres of ``k`` equal cells tiling it (midpoint rule), so each
    sub-ray stands for ``1 / k`` of the footprint. ``k = 1``: the beam axis.

    With thin sub-rays the outermost ones sit ``width / (2 k)`` inside the footprint's
    edges: the sampled footprint is ``width (1 - 1/k)`` wide and the gap between the
    footprints of neighbouring beams ``step - width + width / k``, not ``step - width``.
    ``k`` odd puts a sub-ray on the beam axis (a half-footprint threshold is then exactly
    "the axis ray hits")."""
    if k < 1:
        raise InputError(f"k must be >= 1, got {k}.")
    return np.asarray(width * ((np.arange(k) + 0.5) / k - 0.5), dtype=np.float64)
